"""Read a Kalibr ``camchain-imucam.yaml``: what camera-IMU calibration produces on a vehicle.

Kalibr (ethz-asl/kalibr, ``kalibr_calibrate_imu_camera``) writes one entry per camera::

    cam0:
      T_cam_imu: [[r, r, r, t], [r, r, r, t], [r, r, r, t], [0, 0, 0, 1]]
      camera_model: pinhole
      intrinsics: [fu, fv, pu, pv]
      distortion_model: radtan          # or equidistant
      distortion_coeffs: [k1, k2, p1, p2]
      resolution: [width, height]
      timeshift_cam_imu: 0.004          # t_imu = t_cam + shift

``T_cam_imu`` takes a point from the IMU's frame into the camera's, so the camera sits in
the body frame at ``T_B_C = T_B_I inv(T_cam_imu)``, where ``T_B_I`` turns the axes of the IMU
Kalibr was given into the body's FLU: the identity for FLU data (MAVROS's ``imu/data_raw``),
``diag(1, -1, -1)`` for PX4's own FRD body frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from autonomy.geometry import PinholeCamera, invert_pose
from autonomy.lens import CameraModel

#: The IMU axes Kalibr may have seen -> their rotation into the body's FLU axes.
R_BODY_IMU = {"flu": np.eye(3), "frd": np.diag([1.0, -1.0, -1.0])}


class KalibrError(ValueError):
    """The file cannot be used; the message names the file and the entry."""


@dataclass(frozen=True)
class KalibrCamera:
    """One camera of a camchain: its lens, its pose in the body frame, and the time offset
    that puts its frame times on the IMU's clock."""

    model: CameraModel
    T_B_C: np.ndarray
    time_offset_s: float


def read_camchain(path: str | Path, camera: str = "cam0", imu_frame: str = "flu") -> KalibrCamera:
    """The entry ``camera`` of the camchain at ``path``; :class:`KalibrError` when the file is
    missing, is not a camchain, or describes what the stack cannot use."""
    if imu_frame not in R_BODY_IMU:
        raise KalibrError(f"IMU frame must be one of {', '.join(R_BODY_IMU)}, got {imu_frame!r}")
    where = f"{path}: {camera}"
    entry = _entry(path, camera)
    model = _lens(entry, where)
    T_cam_imu = _matrix(entry, "T_cam_imu", where)
    T_B_I = np.eye(4)
    T_B_I[:3, :3] = R_BODY_IMU[imu_frame]
    shift = _number(entry.get("timeshift_cam_imu", 0.0), "timeshift_cam_imu", where)
    return KalibrCamera(model, T_B_I @ invert_pose(T_cam_imu), shift)


def _entry(path: str | Path, camera: str) -> dict:
    try:
        document = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as error:
        raise KalibrError(f"{path}: cannot read it: {error.strerror or error}") from None
    except UnicodeDecodeError as error:  # e.g. Kalibr's report-imucam.pdf given by mistake
        raise KalibrError(f"{path}: not YAML: not UTF-8 text ({error.reason} at byte "
                          f"{error.start})") from None
    except yaml.YAMLError as error:
        raise KalibrError(f"{path}: not YAML: {error}") from None
    if not isinstance(document, dict) or not document:
        raise KalibrError(f"{path}: not a Kalibr camchain (expected cam0: ... entries)")
    if camera not in document or not isinstance(document[camera], dict):
        raise KalibrError(f"{path}: no camera {camera!r}; it has {', '.join(map(str, document))}")
    return document[camera]


def _lens(entry: dict, where: str) -> CameraModel:
    if entry.get("camera_model", "pinhole") != "pinhole":
        raise KalibrError(f"{where}: camera_model {entry['camera_model']!r} is not supported; "
                          "calibrate with the pinhole model (radtan or equidistant)")
    fu, fv, pu, pv = _numbers(entry, "intrinsics", 4, where)
    width, height = (int(v) for v in _numbers(entry, "resolution", 2, where))
    distortion = entry.get("distortion_model", "none")
    coefficients = entry.get("distortion_coeffs", [])
    if not isinstance(coefficients, list):
        raise KalibrError(f"{where}: distortion_coeffs must be a list of numbers, got "
                          f"{coefficients!r}")
    numbers = tuple(_number(c, "distortion_coeffs", where) for c in coefficients)
    try:
        return CameraModel(PinholeCamera(width, height, fu, fv, pu, pv), distortion, numbers)
    except (ValueError, TypeError) as error:
        raise KalibrError(f"{where}: {error}") from None


def _matrix(entry: dict, key: str, where: str) -> np.ndarray:
    rows = entry.get(key)
    try:
        T = np.array(rows, dtype=float)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise KalibrError(f"{where}: {key} must be a 4x4 matrix of numbers")
    R = T[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0.0
            and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise KalibrError(f"{where}: {key} is not a rigid transform (rotation part not "
                          "orthonormal, or last row not 0 0 0 1)")
    return T


def _numbers(entry: dict, key: str, count: int, where: str) -> list[float]:
    values = entry.get(key)
    if not isinstance(values, list) or len(values) != count:
        raise KalibrError(f"{where}: {key} must be a list of {count} numbers, got {values!r}")
    return [_number(v, key, where) for v in values]


def _number(value, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise KalibrError(f"{where}: {key} must hold finite numbers, got {value!r}")
    return float(value)
