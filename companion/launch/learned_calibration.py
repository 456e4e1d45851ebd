"""The calibrations a flight learned, kept for the next flight of the same camera.

Two of the VINS's calibrations are estimated in flight and are worth more from the start of the
next one than learned again in it (docs/vins.md):

- **the camera-IMU time offset.** With ``[vins] estimate_time_offset`` the VINS estimates it
  online from ``[vins] time_offset_s``, and the estimate moves only once the camera has turned
  enough: a flight that starts from the configured value flies its first turns on the wrong
  one. With ``[camera] learned_time_offset_file`` set, ``companion fly`` writes there the
  offset a flight ended with, when the estimate moved (its sigma is known), and the next flight
  starts from it (``time_offset_s``).
- **the gyro's response to the yaw rate** (its cross-axis error with the camera's mounting), or
  with ``[vins] gyro_alignment_rates = "all"`` its whole misalignment (nine numbers, kept when
  the flight has shown every one of them, else its yaw column).
  The estimate (``[vins] estimate_gyro_alignment``) learns it in the first corner, after that
  corner's false tilt is in the smoother; carried from an earlier flight, the correction holds
  from the first sample. With ``[camera] learned_gyro_alignment_file`` set, a flight with no
  column kept yet is a calibration flight: it estimates the column (when it estimates the time
  offset, whose frame pairs it needs) and writes it there once the flight has shown it (its
  sigma at most :data:`KEEP_ALIGNMENT_SHARE` of the prior's). Every later flight is corrected
  by it from the first sample (``[vins] gyro_alignment``; fixed, or the estimate's prior mean
  when ``estimate_gyro_alignment`` is set). On the simulator's 36 realistic recordings the
  online estimate was better than none on 26, the carried column on 25 (docs/vins.md, "The
  gyro's yaw response with the gate", "The sensor noise's bank").

Each file names the camera (:func:`camera_identity`), so a different camera, or the same one in
another mode, starts from the configuration again. A file that cannot be read, or holds a value
the options refuse, is named in a warning and ignored: the flight then starts as configured, and
learns both calibrations again as a flight with no file does, replacing the file. Files are
replaced atomically, so a reader sees the old file or the new one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
from datetime import datetime, timezone
from pathlib import Path

log = logging.getLogger(__name__)

#: The files' layout; another is ignored with a warning.
FORMAT = 1

#: A gyro alignment is kept only when its sigma is at most this share of the prior's
#: (``[vins] gyro_cross_axis_sigma``): a flight with too few corners has not shown it, and a
#: column kept is used fixed by every later flight.
KEEP_ALIGNMENT_SHARE = 0.5

#: The device field that names one camera among several of its driver.
_DEVICE_FIELDS = {"v4l2": ("v4l2", "device"), "realsense": ("realsense", "serial"),
                  "oak": ("oak", "device_id")}


def camera_identity(config) -> str:
    """The camera and mode a calibration belongs to: driver, device (as configured, "" for the
    only one connected), size and rate, and an OAK's socket."""
    camera = config.camera
    section, field = _DEVICE_FIELDS[camera.driver]
    device = getattr(getattr(config, section), field)
    socket = f" {config.oak.socket}" if camera.driver == "oak" else ""
    return (f"{camera.driver} {device!r}{socket} {camera.width}x{camera.height} at "
            f"{camera.rate_hz:g} Hz")


def learned_offset_path(config) -> Path | None:
    """``[camera] learned_time_offset_file``, None when offsets are not kept (it is empty, or
    the VINS does not estimate the offset)."""
    name = config.camera.learned_time_offset_file
    if not name or not config.vins.estimate_time_offset:
        return None
    return Path(name)


def learned_alignment_path(config) -> Path | None:
    """``[camera] learned_gyro_alignment_file``, None when it is empty. Read whether or not the
    flight estimates the alignment (a calibration flight learns it, later flights use it)."""
    name = config.camera.learned_gyro_alignment_file
    return Path(name) if name else None


def start_from_learned(config):
    """``config`` with ``[vins] time_offset_s`` and ``gyro_alignment`` set to what was learned
    for this camera, each left as configured where nothing is kept, or the file is ignored
    (logged). With no column kept for this camera, the flight estimates it when it can
    (``estimate_gyro_alignment``, which needs ``estimate_time_offset``)."""
    offset = _learned(config, learned_offset_path(config), "camera-IMU time offset",
                      "time_offset_s", _offset_from)
    if offset is not None:
        config = dataclasses.replace(config, vins=offset)
        log.info("starting from the camera-IMU time offset learned before: %.1f ms (%s)",
                 1e3 * offset.time_offset_s, learned_offset_path(config))
    path = learned_alignment_path(config)
    alignment = _learned(config, path, "gyro alignment", "gyro_alignment", _column_from)
    if alignment is not None:
        config = dataclasses.replace(config, vins=alignment)
        log.info("correcting the gyro by the %s learned before (%s)",
                 _alignment_text(alignment.gyro_alignment), path)
    elif path is not None and config.vins.estimate_time_offset:
        # None kept for this camera (no file, or one ignored above): a calibration flight, so
        # that a broken file or another camera's is replaced, as the time offset's is
        config = dataclasses.replace(config, vins=dataclasses.replace(
            config.vins, estimate_gyro_alignment=True))
        log.info("no gyro yaw response kept for this camera (%s): this flight estimates it",
                 path)
    return config


def keep_learned(config, summary: dict, now: datetime | None = None) -> list[Path]:
    """Write what the flight of ``summary`` learned for this camera: the offset it ended with
    (``vins_time_offset``, when estimated and moved) and the gyro alignment it estimated
    (``vins_gyro_alignment``, when frame pairs have shown it: :data:`KEEP_ALIGNMENT_SHARE`).
    The paths written."""
    saved = (now or datetime.now(timezone.utc)).isoformat(timespec="seconds")
    kept = (_keep_offset(config, summary.get("vins_time_offset"), saved),
            _keep_alignment(config, summary.get("vins_gyro_alignment"), saved))
    return [path for path in kept if path is not None]


def _keep_offset(config, offset: dict | None, saved: str) -> Path | None:
    path = learned_offset_path(config)
    if path is None or offset is None or not offset["estimated"] or offset["sigma_s"] is None:
        return None
    if not _write(path, config, {"offset_s": offset["seconds"], "sigma_s": offset["sigma_s"]},
                  saved):
        return None
    log.info("kept the camera-IMU time offset %.1f ms for the next flight (%s)",
             1e3 * offset["seconds"], path)
    return path


def _keep_alignment(config, alignment: dict | None, saved: str) -> Path | None:
    """The whole matrix (by rows) when the flight estimated it and has shown every element,
    else the yaw column when it has shown that (:data:`KEEP_ALIGNMENT_SHARE`)."""
    path = learned_alignment_path(config)
    if path is None or alignment is None or not alignment["pairs"]:
        return None
    limit = KEEP_ALIGNMENT_SHARE * config.vins.gyro_cross_axis_sigma
    values, sigma = alignment["column"], alignment["sigma"]
    if alignment.get("matrix_sigma") is not None and max(_flat(alignment["matrix_sigma"])) <= limit:
        values, sigma = _flat(alignment["matrix"]), _flat(alignment["matrix_sigma"])
    if max(sigma) > limit:
        return None
    if not _write(path, config, {"gyro_alignment": list(values), "sigma": list(sigma),
                                 "pairs": alignment["pairs"]}, saved):
        return None
    log.info("kept the gyro's %s for the next flight (%s)", _alignment_text(values), path)
    return path


def _flat(rows) -> list[float]:
    return [v for row in rows for v in row]


def _alignment_text(values) -> str:
    """Three numbers, the yaw response, or nine, the whole misalignment by rows."""
    what = "yaw response" if len(values) == 3 else "misalignment (rows)"
    return f"{what} [" + ", ".join(f"{c:.4f}" for c in values) + "]"


def _learned(config, path: Path | None, what: str, field: str, value_from):
    """``config.vins`` with ``field`` set from the file at ``path``; None when there is no file
    or it is ignored (a warning names it and says why)."""
    if path is None or not path.exists():
        return None
    try:
        record = _read(path, camera_identity(config))
        return dataclasses.replace(config.vins, **{field: value_from(record)})
    except (OSError, ValueError) as error:  # OptionError is a ValueError
        log.warning("ignoring the learned %s in %s: %s; starting from [vins] %s = %s",
                    what, path, error, field, getattr(config.vins, field))
        return None


def _write(path: Path, config, values: dict, saved: str) -> bool:
    """Replace the file at ``path`` with ``values``; False, with a warning, when it cannot be
    written (a directory there, a read-only disk): the flight's summary still comes."""
    record = {"format": FORMAT, "camera": camera_identity(config), **values, "saved": saved}
    partial = path.with_name(path.name + ".partial")
    try:
        partial.write_text(json.dumps(record, indent=1) + "\n")
        os.replace(partial, path)  # a reader sees the old file or the new one, never half of one
    except OSError as error:
        log.warning("could not keep the learned calibration in %s: %s", path, error)
        with contextlib.suppress(OSError):
            partial.unlink(missing_ok=True)
        return False
    return True


def _read(path: Path, camera: str) -> dict:
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"not JSON ({error})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise ValueError(f"not a format-{FORMAT} file of learned calibration")
    if record.get("camera") != camera:
        raise ValueError(f"it was learned with another camera, {record.get('camera')}; this "
                         f"one is {camera}")
    return record


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value)


def _offset_from(record: dict) -> float:
    offset_s = record.get("offset_s")
    if not _finite(offset_s):
        raise ValueError(f"offset_s is {offset_s!r}, not a finite number")
    return float(offset_s)


def _column_from(record: dict) -> tuple[float, ...]:
    """The yaw column (three numbers) or the whole matrix by rows (nine)."""
    column = record.get("gyro_alignment")
    if not (isinstance(column, list) and len(column) in (3, 9) and all(map(_finite, column))):
        raise ValueError(f"gyro_alignment is {column!r}, not three or nine finite numbers")
    return tuple(float(c) for c in column)
