"""What made an evaluation's records: the code's revision, the config's hash and the versions
of the libraries a flight's numbers depend on.

Records flown in parts, or resumed after an interruption, are one evaluation only if the same
code flew them with the same config on the same libraries; each record carries all three so
that merging can check (:func:`companion.tools.eval.nav.merge_records`). The libraries are
kept since one commit and config flew other flights on this machine a day after their record,
its environment built again in between from the same pyproject ranges (docs/vins.md, "The
offset swing"); which difference did it is not known.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import platform
import subprocess
from pathlib import Path

from companion.config import Config, dump_toml

#: The revision of code that is not a git checkout (an installed wheel), or when git is missing.
UNKNOWN = "unknown"
#: The checkout this package runs from: companion/tools/eval/ is three folders below it.
CHECKOUT = Path(__file__).resolve().parents[3]
#: The modules whose versions a flight's numbers depend on: the arithmetic, the tracker, the
#: smoother, the depth network and the renderer. Each is named by the distribution that
#: installed it, whichever that is (opencv-python or its headless build, onnxruntime-gpu).
FLIGHT_MODULES = ("numpy", "scipy", "cv2", "gtsam", "onnxruntime", "moderngl")


def code_revision(checkout: Path = CHECKOUT) -> str:
    """The git commit ``checkout`` is at; with ``+dirty.<hash>`` when tracked files differ from
    it, the hash of that difference (``git diff HEAD``), so two different edits of one commit
    are two revisions. :data:`UNKNOWN` outside a git checkout or without git."""
    if not (checkout / ".git").exists():
        return UNKNOWN
    try:
        head = _git(checkout, "rev-parse", "HEAD").strip()
        difference = _git(checkout, "diff", "HEAD", "--no-ext-diff", "--binary")
    except (OSError, subprocess.SubprocessError):
        return UNKNOWN
    if not difference:
        return head
    return f"{head}+dirty.{hashlib.sha256(difference.encode()).hexdigest()[:12]}"


def config_hash(config: Config) -> str:
    """SHA-256 (first 16 hex digits) of the effective config as TOML (:func:`dump_toml`): equal
    for equal configs, however they were written (file, overrides, defaults)."""
    return hashlib.sha256(dump_toml(config).encode()).hexdigest()[:16]


def library_versions() -> str:
    """The interpreter's version and, for each of :data:`FLIGHT_MODULES`, the version of every
    distribution that installed it, as ``"python 3.12.3; numpy 2.4.6; ..."`` (the module's
    name and "not installed" for one no distribution provides). The GL driver the renderer
    draws with is not among them."""
    providers = importlib.metadata.packages_distributions()
    versions = [f"python {platform.python_version()}"]
    for module in FLIGHT_MODULES:
        names = sorted(set(providers.get(module, ())))
        versions += ([f"{name} {importlib.metadata.version(name)}" for name in names]
                     or [f"{module} not installed"])
    return "; ".join(versions)


def stamp(config: Config) -> dict[str, str]:
    """What each record of a run flown with ``config`` carries: ``revision``, ``config_hash``
    and ``libraries`` (:func:`library_versions`)."""
    return {"revision": code_revision(), "config_hash": config_hash(config),
            "libraries": library_versions()}


def _git(checkout: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(checkout), *args], capture_output=True, text=True,
                          timeout=30, check=True).stdout
