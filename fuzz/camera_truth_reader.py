#!/usr/bin/env python3
"""Fuzz the reader of a simulated camera's truth (``read_camera_truth`` of
drivers/dataset/euroc.py) with hostile files.

    python fuzz/camera_truth_reader.py [libFuzzer options] [CORPUS_DIR ...]

A harness of its own rather than more files of fuzz/euroc_reader.py, whose inputs pick their
file by their first byte modulo the number of files: more files there would move every kept
input of that harness onto another file. Each input here is one file of a small, otherwise
valid simulated camera (the ``cam0`` of fuzz/euroc_reader.py and its truth): the first byte
picks which (``cam0/truth.csv``, ``cam0/truth.yaml``, ``cam0/data.csv``: its low seven bits,
modulo 3), the rest is that file's bytes; its high bit leaves out the truth's files it does
not pick (so half a truth, or none at all, is an input too). ``read_camera`` then reads the
stream and ``read_camera_truth`` its truth.

The invariant: a :class:`~drivers.dataset.euroc.DatasetError` naming the file; or None, and
only when neither truth file is there; or a truth whose exposures are int64 nanoseconds
strictly increasing (the reader reads them as timestamps), one per frame of the stream, and
whose mounting is a finite 4x4 rigid transform (a rotation and the last row 0 0 0 1).
Anything else escaping is a finding.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from fuzz import harness  # noqa: E402

if __name__ == "__main__":
    harness.require_atheris()

with harness.instrumented(__name__ == "__main__"):
    from drivers.dataset.euroc import DatasetError, read_camera, read_camera_truth
    from fuzz import euroc_reader

TARGET = "camera_truth_reader"
TRUTH = ("mav0/cam0/truth.csv", "mav0/cam0/truth.yaml")
#: What an input's first byte picks (its low seven bits, modulo 3) to hold the rest of it.
FILES = [*TRUTH, "mav0/cam0/data.csv"]
#: The first byte's bit that leaves out the truth's files it does not pick.
LEAVE_OUT = 0x80
_SENSOR_YAML = euroc_reader.VALID["mav0/cam0/sensor.yaml"]
#: A valid camera, the one of fuzz/euroc_reader.py, exposed 15 us before its stamps and
#: mounted at a quarter turn about z and 10 cm from the configured mounting (the identity).
VALID = {
    "mav0/cam0/truth.csv": "#timestamp [ns],exposure middle [ns]\n"
                           "1000000,985000\n2000000,1985000\n",
    "mav0/cam0/truth.yaml": _SENSOR_YAML.replace(
        "data: [1, 0, 0, 0, 0, 1, 0, 0,", "data: [0, -1, 0, 0.1, 1, 0, 0, 0,"),
    "mav0/cam0/data.csv": euroc_reader.VALID["mav0/cam0/data.csv"],
    "mav0/cam0/sensor.yaml": _SENSOR_YAML,
}
#: Where each input's camera is written (one per process, reused).
_ROOT = harness.scratch(TARGET)


def write(data: bytes) -> None:
    """The camera of one input under _ROOT (module docstring)."""
    chosen = FILES[(data[0] & ~LEAVE_OUT) % len(FILES)] if data else None
    euroc_reader.write_dataset(_ROOT, VALID, chosen, data[1:])
    if data and data[0] & LEAVE_OUT:
        for name in TRUTH:
            if name != chosen:
                (_ROOT / name).unlink()


def run(data: bytes) -> list[str]:
    """Read the camera of one input and its truth, checking the invariant (module
    docstring); what the readers said: their DatasetError, its path relative to the camera's
    dataset, or "no truth" for None."""
    write(data)
    try:
        stream = read_camera(_ROOT)
        truth = read_camera_truth(_ROOT, stream)
    except DatasetError as error:
        return [euroc_reader.named(error, _ROOT)]
    if truth is None:
        assert not any((_ROOT / name).exists() for name in TRUTH), "None beside a truth file"
        return ["no truth"]
    euroc_reader.check_times(truth.exposed_ns)
    assert truth.exposed_ns.shape == stream.t_ns.shape, (truth.exposed_ns, stream.t_ns)
    euroc_reader.check_mounting(truth.T_B_C)
    return []


def test_one_input(data: bytes) -> None:
    """libFuzzer's entry point: :func:`run`."""
    run(data)


if __name__ == "__main__":
    harness.fuzz(test_one_input)
