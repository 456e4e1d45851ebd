"""What every fuzz harness shares: atheris (optional), its coverage instrumentation, the
libFuzzer entry point, the seed corpora, and the deterministic mutations the test suite runs
each harness on (fuzz/README.md).

A harness module defines ``test_one_input(data: bytes)``, which raises (an AssertionError
saying which invariant broke, or the exception that escaped) on a finding and returns
otherwise. Run as a script it is a libFuzzer target; imported, it is a plain function the
tests call on the seed corpus and its mutations.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import random
import shutil
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Callable, Iterator

try:
    import atheris
except ImportError:  # the [fuzz] extra is optional outside the tests
    atheris = None

FUZZ = Path(__file__).resolve().parent
#: The project's own packages: what atheris instruments for coverage (and pymavlink, whose
#: parser is the first thing hostile bytes meet).
INSTRUMENTED = ("autonomy", "drivers", "companion", "pymavlink", "mcap", "mcap_protobuf")
MISSING = ("atheris is not installed; it comes with the project's [fuzz] extra: "
           "pip install -e '.[fuzz]'")


def require_atheris() -> None:
    """Exit with one line naming the extra when atheris is missing."""
    if atheris is None:
        print(MISSING, file=sys.stderr)
        raise SystemExit(2)


def instrumented(enabled: bool) -> contextlib.AbstractContextManager:
    """Around a harness's imports: atheris's coverage instrumentation of the project's
    modules when ``enabled`` (run as a fuzzer), nothing when imported by the tests."""
    if not enabled:
        return contextlib.nullcontext()
    return atheris.instrument_imports(include=list(INSTRUMENTED))


def fuzz(test_one_input: Callable[[bytes], None]) -> None:
    """Hand ``test_one_input`` to libFuzzer with the command line's arguments. The project's
    log goes nowhere (a handler on the root logger keeps Python's last-resort one quiet; a
    harness may still watch a logger), and numpy's overflow warnings are not printed."""
    logging.getLogger().addHandler(logging.NullHandler())
    warnings.simplefilter("ignore", RuntimeWarning)
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


def scratch(target: str) -> Path:
    """A folder for the files a harness writes its inputs to, removed when the process ends."""
    folder = Path(tempfile.mkdtemp(prefix=f"fuzz-{target}-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return folder


def corpus(target: str) -> list[bytes]:
    """The seed corpus of ``target`` (``fuzz/corpus/<target>/``), in file-name order."""
    return [path.read_bytes() for path in sorted((FUZZ / "corpus" / target).iterdir())]


def regressions(target: str) -> list[Path]:
    """The saved findings of ``target`` (``fuzz/regressions/<target>/``)."""
    folder = FUZZ / "regressions" / target
    return sorted(folder.iterdir()) if folder.is_dir() else []


def mutations(seeds: list[bytes], count: int, seed: int) -> Iterator[bytes]:
    """``count`` inputs made from ``seeds`` by a seeded RNG, as libFuzzer mutates: bytes
    flipped, set to an edge value, inserted, erased, a run repeated, two seeds spliced. The
    same arguments give the same inputs on every machine."""
    rng = random.Random(seed)
    for _ in range(count):
        data = bytearray(rng.choice(seeds))
        for _ in range(rng.randint(1, 4)):
            data = _mutate(rng, data, seeds)
        yield bytes(data)


def _mutate(rng: random.Random, data: bytearray, seeds: list[bytes]) -> bytearray:
    """One libFuzzer-like mutation of ``data``."""
    at = rng.randrange(len(data) + 1)
    kind = rng.randrange(6)
    if kind == 0 and data:
        data[min(at, len(data) - 1)] ^= 1 << rng.randrange(8)
    elif kind == 1 and data:
        data[min(at, len(data) - 1)] = rng.choice((0, 1, 0x7F, 0x80, 0xFF))
    elif kind == 2:
        data[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
    elif kind == 3:
        del data[at:at + rng.randint(1, 16)]
    elif kind == 4:
        data[at:at] = data[at:at + rng.randint(1, 32)] * rng.randint(2, 64)
    else:
        other = rng.choice(seeds)
        data = data[:at] + other[rng.randrange(len(other) + 1):]
    return data
