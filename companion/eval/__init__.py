"""Accuracy evaluations behind ``companion eval``: library functions, one module per command
(:mod:`companion.eval.vio`, :mod:`companion.eval.depth`); the CLI is a thin shell over them."""
