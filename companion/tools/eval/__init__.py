"""Accuracy evaluations behind ``companion eval``: library functions, one module per command
(:mod:`companion.tools.eval.vio`, :mod:`companion.tools.eval.depth`); the CLI is a thin shell
over them."""
