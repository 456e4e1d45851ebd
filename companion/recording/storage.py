"""Where recordings go: one file per flight in ``[recorder] directory``, named by its start
time, the oldest deleted to keep the directory under its quota (docs/recording.md, "Files" and
"Quota").

:func:`prepare` runs before arming, so a recording that cannot be made (a directory that cannot
be created or written, a disk already below the reserve) is a clear :class:`RecordingError`
while the vehicle is on the ground, never a surprise in flight.
"""

from __future__ import annotations

import logging
import re
import shutil
from datetime import datetime, timezone
from pathlib import Path

from companion.recording.options import RecorderOptions

log = logging.getLogger(__name__)

MB = 1_000_000

#: ``flight-20261125-101500.mcap``, or ``-2``, ``-3``... for a second flight in the same second.
_FLIGHT_NAME = re.compile(r"flight-(\d{8}-\d{6})(?:-(\d+))?\.mcap")


class RecordingError(Exception):
    """A recording cannot be made or written; the message names the path and what to do."""


def free_bytes_at(directory: Path) -> int:
    """Free bytes for an unprivileged writer on the file system holding ``directory``."""
    return shutil.disk_usage(directory).free


def prepare(options: RecorderOptions, *, now: datetime | None = None) -> Path:
    """Create (empty) and return the next flight's file, ``flight-YYYYmmdd-HHMMSS.mcap`` in
    UTC (so names sort in time order whatever the time zone or daylight saving), after deleting
    the oldest flights beyond ``quota_mb``. Raises :class:`RecordingError` when the directory
    cannot be made or written, or when its disk has less than ``reserve_mb`` free."""
    directory = Path(options.directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise RecordingError(f"cannot create the recordings directory {directory}: "
                             f"{error.strerror or error}") from None
    enforce_quota(directory, int(options.quota_mb * MB))
    free = free_bytes_at(directory)
    if free < options.reserve_mb * MB:
        raise RecordingError(f"only {free / MB:.0f} MB free for recordings in {directory}; "
                             f"[recorder] reserve_mb needs {options.reserve_mb:.0f} MB: delete "
                             "old flights or lower [recorder] quota_mb")
    stamp = (now or datetime.now(timezone.utc)).strftime("%Y%m%d-%H%M%S")
    return _create(directory, f"flight-{stamp}")


def _create(directory: Path, stem: str) -> Path:
    """The first of ``stem.mcap``, ``stem-2.mcap``, ... that does not exist, created
    exclusively, so two flights starting in the same second get two files."""
    for attempt in range(1, 1000):
        path = directory / (f"{stem}.mcap" if attempt == 1 else f"{stem}-{attempt}.mcap")
        try:
            path.open("xb").close()
            return path
        except FileExistsError:
            continue
        except OSError as error:
            raise RecordingError(f"cannot write recordings in {directory}: "
                                 f"{error.strerror or error}") from None
    raise RecordingError(f"{directory} already has 999 flights named {stem}*.mcap")


def flights(directory: Path) -> list[Path]:
    """The flight recordings in ``directory``, oldest first (their names are their start
    times); other files are not the recorder's and are left alone."""
    def start(path: Path) -> tuple[str, int]:
        match = _FLIGHT_NAME.fullmatch(path.name)
        return match[1], int(match[2] or 1)

    found = [path for path in directory.glob("flight-*.mcap")
             if _FLIGHT_NAME.fullmatch(path.name) and path.is_file()]
    return sorted(found, key=start)


def enforce_quota(directory: Path, quota_bytes: int, *, keep: Path | None = None) -> list[Path]:
    """Delete the oldest flights in ``directory`` until the flights total at most
    ``quota_bytes``; never ``keep`` (the flight being recorded). Returns the deleted files."""
    recorded = [(path, path.stat().st_size) for path in flights(Path(directory))]
    total = sum(size for _, size in recorded)
    removed = []
    for path, size in recorded:
        if total <= quota_bytes:
            break
        if keep is not None and path.resolve() == Path(keep).resolve():
            continue
        try:
            path.unlink(missing_ok=True)  # gone meanwhile: it takes no room either
        except OSError as error:  # the reserve check still stops a full disk
            log.warning("cannot delete the old recording %s: %s", path, error.strerror)
            continue
        total -= size
        removed.append(path)
        log.info("deleted the recording %s (%.0f MB) to keep %s under its quota", path,
                 size / MB, directory)
    return removed
