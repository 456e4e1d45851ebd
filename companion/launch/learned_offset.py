"""The camera-IMU time offset a flight learned, kept for the next flight of the same camera.

With ``[vins] estimate_time_offset`` the VINS estimates the offset online from
``[vins] time_offset_s``, and the estimate moves only once the camera has turned enough
(docs/vins.md): a flight that starts from the configured value flies its first turns on the
wrong one. With ``[camera] learned_time_offset_file`` set, ``companion fly`` writes there the
offset a flight ended with, when the estimate moved (its sigma is known), and the next flight
of the same camera starts from it. The file names the camera (:func:`camera_identity`), so a
different camera, or the same one in another mode, starts from the configuration again. A file
that cannot be read, or holds an offset the options refuse, is named in a warning and ignored:
the flight then starts as configured.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from datetime import datetime, timezone
from pathlib import Path

log = logging.getLogger(__name__)

#: The file's layout; another is ignored with a warning.
FORMAT = 1

#: The device field that names one camera among several of its driver.
_DEVICE_FIELDS = {"v4l2": ("v4l2", "device"), "realsense": ("realsense", "serial"),
                  "oak": ("oak", "device_id")}


def camera_identity(config) -> str:
    """The camera and mode an offset belongs to: driver, device (as configured, "" for the
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


def start_from_learned(config):
    """``config`` with ``[vins] time_offset_s`` set to the offset kept for this camera, or
    unchanged (no file, or one that is ignored: logged)."""
    path = learned_offset_path(config)
    if path is None or not path.exists():
        return config
    try:
        offset_s = _read(path, camera_identity(config))
        vins = dataclasses.replace(config.vins, time_offset_s=offset_s)
    except (OSError, ValueError) as error:  # OptionError is a ValueError
        log.warning("ignoring the learned camera-IMU time offset in %s: %s; starting from "
                    "[vins] time_offset_s = %s s", path, error, config.vins.time_offset_s)
        return config
    log.info("starting from the camera-IMU time offset learned before: %.1f ms (%s)",
             1e3 * offset_s, path)
    return dataclasses.replace(config, vins=vins)


def keep_learned(config, summary: dict, now: datetime | None = None) -> Path | None:
    """Write the offset the flight of ``summary`` ended with (its ``vins_time_offset``) for
    this camera, atomically; the path, or None when there is nothing to keep (offsets not
    kept, or the estimate never moved)."""
    path = learned_offset_path(config)
    offset = summary.get("vins_time_offset")
    if path is None or offset is None or not offset["estimated"] or offset["sigma_s"] is None:
        return None
    record = {"format": FORMAT, "camera": camera_identity(config),
              "offset_s": offset["seconds"], "sigma_s": offset["sigma_s"],
              "saved": (now or datetime.now(timezone.utc)).isoformat(timespec="seconds")}
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(partial, path)  # a reader sees the old file or the new one, never half of one
    log.info("kept the camera-IMU time offset %.1f ms for the next flight (%s)",
             1e3 * offset["seconds"], path)
    return path


def _read(path: Path, camera: str) -> float:
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"not JSON ({error})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise ValueError(f"not a format-{FORMAT} offset file")
    if record.get("camera") != camera:
        raise ValueError(f"it was learned with another camera, {record.get('camera')}; this "
                         f"one is {camera}")
    offset_s = record.get("offset_s")
    if isinstance(offset_s, bool) or not isinstance(offset_s, (int, float)) \
            or not math.isfinite(offset_s):
        raise ValueError(f"offset_s is {offset_s!r}, not a finite number")
    return float(offset_s)
