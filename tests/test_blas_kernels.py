"""OpenBLAS's kernels are pinned where they can be, so that a simulated flight is the same on
every x86-64 machine with AVX2 (companion/__init__.py): checked in a fresh interpreter, since
the setting must precede numpy's first import."""

import os
import subprocess
import sys

import pytest

from companion import cpu_runs_haswell_kernels


def _env_after_import(**env) -> dict:
    base = {k: v for k, v in os.environ.items()
            if k not in ("OPENBLAS_CORETYPE", "OPENBLAS_NUM_THREADS")}
    script = ("import os, companion, numpy; print(os.environ.get('OPENBLAS_CORETYPE')); "
              "print(os.environ.get('OPENBLAS_NUM_THREADS'))")
    out = subprocess.run([sys.executable, "-c", script], env={**base, **env}, check=True,
                         capture_output=True, text=True).stdout.split()
    return {"OPENBLAS_CORETYPE": out[0], "OPENBLAS_NUM_THREADS": out[1]}


@pytest.mark.skipif(not cpu_runs_haswell_kernels(),
                    reason="the pin applies to x86-64 CPUs with AVX2 and FMA only")
def test_an_x86_cpu_with_avx2_runs_openblas_haswell_kernels_on_one_thread():
    assert _env_after_import() == {"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_NUM_THREADS": "1"}


def test_the_environment_s_own_choice_is_kept():
    assert _env_after_import(OPENBLAS_CORETYPE="Sandybridge", OPENBLAS_NUM_THREADS="2") == {
        "OPENBLAS_CORETYPE": "Sandybridge", "OPENBLAS_NUM_THREADS": "2"}
