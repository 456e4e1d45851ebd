"""The application: the flight process (``flight/``), what runs it (``launch/``), the tools
around it (``tools/``), the config and the command line (``cli/``).

OpenBLAS runs one thread here unless the environment says otherwise. The stack's linear
algebra is 3x3 to N x 3, far below where BLAS threads pay, and OpenBLAS's idle threads spin:
with its default pool a simulated flight burned twice the CPU for the same result and time
(docs/benchmarks.md), a core taken from the stages' own worker threads on the vehicle. It must
be set before numpy is first imported, so it is the package's first statement.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from importlib.metadata import PackageNotFoundError, version  # noqa: E402

try:
    __version__ = version("companion")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
