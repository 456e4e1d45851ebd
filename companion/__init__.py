"""The application: the flight process (``flight/``), what runs it (``launch/``), the tools
around it (``tools/``), the config and the command line (``cli/``).

OpenBLAS runs one thread here unless the environment says otherwise. The stack's linear
algebra is 3x3 to N x 3, far below where BLAS threads pay, and OpenBLAS's idle threads spin:
with its default pool a simulated flight burned twice the CPU for the same result and time
(docs/benchmarks.md), a core taken from the stages' own worker threads on the vehicle.

On an x86-64 CPU with AVX2 and FMA, OpenBLAS also runs its Haswell kernels unless the
environment names others (``OPENBLAS_CORETYPE``). numpy's OpenBLAS picks its kernels by the
CPU it finds, and kernels round differently; a closed-loop flight grows the last bit into
another flight: the realistic dome's pair 5 seed 1 on true depth navigates 44.6 s on the
Haswell kernels and 44.9 s on the Sandybridge ones (docs/simulator.md, "Reproducible
flights"). Pinned, a simulated flight, an evaluation's trial or a replay is the same on every
such machine (Intel since 2013, AMD since 2015); the AVX-512 kernels a newer CPU would pick
gain nothing on matrices this small. Elsewhere (the Orin's ARM) OpenBLAS chooses as before.

Both must be set before numpy is first imported, so they are the package's first statements.
"""

import os
import platform


def cpu_runs_haswell_kernels() -> bool:
    """Is this an x86-64 CPU with AVX2 and FMA (its ``/proc/cpuinfo`` flags)?"""
    if platform.machine() not in ("x86_64", "AMD64"):
        return False
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as cpuinfo:
            flags = next((line for line in cpuinfo if line.startswith("flags")), "")
    except OSError:
        return False
    return {"avx2", "fma"} <= set(flags.partition(":")[2].split())


os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if cpu_runs_haswell_kernels():
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

from importlib.metadata import PackageNotFoundError, version  # noqa: E402

try:
    __version__ = version("companion")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
