#!/usr/bin/env python3
"""Fuzz the EuRoC/ASL dataset reader (drivers/dataset/euroc.py) with hostile files.

    python fuzz/euroc_reader.py [libFuzzer options] [CORPUS_DIR ...]

Each input is one file of a small, otherwise valid dataset: its first byte picks which
(``imu0/data.csv``, ``state_groundtruth_estimate0/data.csv``, ``cam0/data.csv``,
``cam0/sensor.yaml``, ``imu0/sensor.yaml``), the rest is that file's bytes. The other files
are the valid ones of :data:`VALID`. Every reader then reads the dataset: ``read_imu``,
``read_groundtruth``, ``read_camera``, ``read_imu_noise``. (The camera's truth, ``cam0/truth.*``,
has a harness of its own, fuzz/camera_truth_reader.py, so that these inputs keep their files.)

The invariant: each reader either raises :class:`~drivers.dataset.euroc.DatasetError` naming
the file, or returns what its docstring promises: int64 nanosecond times strictly increasing,
values finite, in arrays of the documented shapes,
and a camera with a positive size and finite intrinsics, a finite 4x4 rigid mounting and a
positive rate. Anything else escaping (a UnicodeDecodeError, an OverflowError, a ValueError
from the camera model...) is a finding; so is a NaN or a timestamp out of order let through.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from fuzz import harness  # noqa: E402

if __name__ == "__main__":
    harness.require_atheris()

with harness.instrumented(__name__ == "__main__"):
    import numpy as np

    from drivers.dataset.euroc import (ROTATION_TOLERANCE, DatasetError, read_camera,
                                       read_groundtruth, read_imu, read_imu_noise)

TARGET = "euroc_reader"
_T_BS = "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n"
#: A valid two-sample dataset, by file (the first byte of an input picks one of them).
VALID = {
    "mav0/imu0/data.csv": "#timestamp [ns],wx,wy,wz,ax,ay,az\n"
                          "1000000,0.1,0.2,0.3,0.0,0.0,9.81\n2000000,0.1,0.2,0.3,0.0,0.0,9.81\n",
    "mav0/state_groundtruth_estimate0/data.csv":
        "#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz\n"
        "1000000,0,0,1,1,0,0,0,0,0,0,0,0,0,0,0,0\n2000000,0,0,1,1,0,0,0,0,0,0,0,0,0,0,0,0\n",
    "mav0/cam0/data.csv": "#timestamp [ns],filename\n1000000,1000000.png\n2000000,2000000.png\n",
    "mav0/cam0/sensor.yaml": "%YAML:1.0\nsensor_type: camera\n" + _T_BS + "rate_hz: 20\n"
                             "resolution: [64, 48]\ncamera_model: pinhole\n"
                             "intrinsics: [40.0, 40.0, 31.5, 23.5]\n"
                             "distortion_model: radial-tangential\n"
                             "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n",
    "mav0/imu0/sensor.yaml": "%YAML:1.0\nsensor_type: imu\n" + _T_BS + "rate_hz: 200\n"
                             "gyroscope_noise_density: 0.0001\ngyroscope_random_walk: 1e-05\n"
                             "accelerometer_noise_density: 0.001\n"
                             "accelerometer_random_walk: 0.0001\n",
}
FILES = list(VALID)
#: Where each input's dataset is written (one per process, reused).
_ROOT = harness.scratch(TARGET)


def write(data: bytes) -> None:
    """The dataset of one input under _ROOT (module docstring)."""
    write_dataset(_ROOT, VALID, FILES[data[0] % len(FILES)] if data else None, data[1:])


def write_dataset(root: Path, valid: dict[str, str], chosen: str | None, data: bytes) -> None:
    """The files of ``valid`` under ``root``, ``chosen`` holding ``data`` instead (shared with
    fuzz/camera_truth_reader.py)."""
    for name, text in valid.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data if name == chosen else text.encode())


def run(data: bytes) -> list[str]:
    """Read the dataset of one input with every reader, checking the invariant (module
    docstring); what the readers said: their DatasetErrors, paths relative to the dataset."""
    write(data)
    said = []
    for read, check in ((read_imu, _check_imu), (read_groundtruth, _check_groundtruth),
                        (read_camera, _check_camera), (read_imu_noise, _check_noise)):
        try:
            result = read(_ROOT)
        except DatasetError as error:
            said.append(named(error, _ROOT))
            continue
        check(result)
    return said


def test_one_input(data: bytes) -> None:
    """libFuzzer's entry point: :func:`run`."""
    run(data)


def named(error: DatasetError, root: Path) -> str:
    """What ``error`` says, its path relative to ``root``; the invariant: it names a file of
    the dataset."""
    assert str(error).startswith(str(root)), f"names no file: {error}"
    return str(error)[len(str(root)) + 1:]


def check_times(t_ns: np.ndarray) -> None:
    """Times as the readers promise them: int64 nanoseconds, at least one, strictly
    increasing."""
    assert t_ns.dtype == np.int64 and t_ns.ndim == 1 and len(t_ns) > 0, t_ns
    assert (np.diff(t_ns) > 0).all(), f"timestamps not increasing: {t_ns}"


def _check_rows(t_ns: np.ndarray, *arrays: np.ndarray) -> None:
    check_times(t_ns)
    for array, columns in arrays:
        assert array.shape == (len(t_ns), columns), array.shape
        assert np.isfinite(array).all(), f"non-finite values: {array}"


def _check_imu(table) -> None:
    _check_rows(table.t_ns, (table.gyro, 3), (table.accel, 3))


def _check_groundtruth(table) -> None:
    _check_rows(table.t_ns, (table.position, 3), (table.q_W_B, 4), (table.velocity, 3),
                (table.gyro_bias, 3), (table.accel_bias, 3))


def _check_camera(stream) -> None:
    check_times(stream.t_ns)
    assert len(stream.paths) == len(stream.t_ns)
    camera = stream.camera
    assert camera.width >= 1 and camera.height >= 1, camera
    assert all(math.isfinite(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy)), camera
    assert all(math.isfinite(c) for c in stream.distortion), stream.distortion
    check_mounting(stream.T_B_C)
    assert math.isfinite(stream.rate_hz) and stream.rate_hz > 0.0, stream.rate_hz


def check_mounting(T: np.ndarray) -> None:
    """A finite 4x4 rigid transform: a rotation (to the reader's ``ROTATION_TOLERANCE``) and
    the last row 0 0 0 1."""
    assert T.shape == (4, 4) and np.isfinite(T).all(), T
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=ROTATION_TOLERANCE) and np.linalg.det(R) > 0.0, T
    assert T[3].tolist() == [0.0, 0.0, 0.0, 1.0], T


def _check_noise(noise) -> None:
    assert noise is not None


if __name__ == "__main__":
    harness.fuzz(test_one_input)
