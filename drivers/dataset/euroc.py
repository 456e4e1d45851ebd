"""Read and write datasets in the EuRoC MAV / ASL folder layout, plus a ``depth0`` stream.

    mav0/cam0/data/<t_ns>.png, cam0/data.csv, cam0/sensor.yaml      camera images
    mav0/depth0/data/<t_ns>.png, depth0/data.csv, depth0/sensor.yaml  ground-truth depth,
                                                  uint16 millimetres, 0 = invalid, cam0's times
    mav0/imu0/data.csv, imu0/sensor.yaml             gyro (rad/s) then accel (m/s^2), body frame
    mav0/state_groundtruth_estimate0/data.csv        p, q (w first), v, gyro bias, accel bias
    mav0/cam0/truth.csv, cam0/truth.yaml             the simulator's only: each frame's true
                                                  exposure time, the camera's true mounting

Timestamps are integer nanoseconds. The body frame is the IMU's; each ``sensor.yaml`` holds
``T_BS``, the sensor's pose in the body frame, as in the original dataset (Burri et al., "The
EuRoC micro aerial vehicle datasets", IJRR 2016). The same reader serves real recordings and
the simulator's, so evaluation code cannot tell them apart, except by the camera's truth
(``cam0/truth.*``): what a real camera hides (its stamps' offset and jitter, its mounting's
calibration error), which only a simulator knows. It is kept apart from the calibration the
estimator is given, and only the evaluation reads it.
"""

from __future__ import annotations

import csv
import math
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.vins.preintegration import ImuNoise

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GROUNDTRUTH_HEADER = "#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz"
FRAMES_HEADER = "#timestamp [ns],filename"
CAMERA_TRUTH_HEADER = "#timestamp [ns],exposure middle [ns]"
#: ``imu0/sensor.yaml`` keys and the :class:`ImuNoise` fields they fill.
IMU_NOISE_KEYS = {
    "gyroscope_noise_density": "gyro_noise_density",
    "gyroscope_random_walk": "gyro_random_walk",
    "accelerometer_noise_density": "accel_noise_density",
    "accelerometer_random_walk": "accel_random_walk",
}
MAX_DEPTH_MM = 65535


class DatasetError(ValueError):
    """A dataset folder that cannot be read, naming the file and what is wrong with it."""


@dataclass(frozen=True)
class ImuTable:
    """IMU samples: times (N,) int64 ns, gyro (N, 3) rad/s and accel (N, 3) m/s^2, body frame."""

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray


@dataclass(frozen=True)
class GroundTruthTable:
    """Body poses in the world frame with velocity and the IMU's true biases, (N, k) arrays."""

    t_ns: np.ndarray
    position: np.ndarray
    q_W_B: np.ndarray
    velocity: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


@dataclass(frozen=True)
class CameraStream:
    """One image stream: times (N,) int64 ns, image paths, intrinsics and mounting."""

    t_ns: np.ndarray
    paths: tuple[Path, ...]
    camera: PinholeCamera
    distortion: tuple[float, ...]
    T_B_C: np.ndarray
    rate_hz: float


@dataclass(frozen=True)
class CameraTruth:
    """A simulated camera's truth: ``exposed_ns``, each frame's true middle of exposure (int64
    ns, a rolling shutter's middle row's, in the order of the camera stream's stamps), and
    ``T_B_C``, its true mounting."""

    exposed_ns: np.ndarray
    T_B_C: np.ndarray


# ---------------------------------------------------------------- depth PNG convention


def depth_to_millimetres(depth_m: np.ndarray) -> np.ndarray:
    """Float metres (NaN = unknown) as uint16 millimetres, 0 where unknown, non-positive or
    beyond the 65.535 m the format can hold."""
    depth = np.asarray(depth_m, dtype=np.float64)
    mm = np.rint(depth * 1000.0)
    valid = np.isfinite(mm) & (mm > 0) & (mm <= MAX_DEPTH_MM)
    return np.where(valid, mm, 0).astype(np.uint16)


def millimetres_to_depth(mm: np.ndarray, *, invalid: tuple[int, ...] = (0,)) -> np.ndarray:
    """uint16 millimetres as float32 metres, NaN at the ``invalid`` codes."""
    depth = mm.astype(np.float32) / 1000.0
    depth[np.isin(mm, invalid)] = np.nan
    return depth


def read_depth_png(path: Path) -> np.ndarray:
    """A depth PNG (uint16 mm, 0 = invalid) as float32 metres with NaN where invalid."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: not a readable image")
    if image.dtype != np.uint16 or image.ndim != 2:
        raise DatasetError(f"{path}: depth must be one-channel uint16, got {image.dtype} "
                           f"with shape {image.shape}")
    return millimetres_to_depth(image)


# ---------------------------------------------------------------- writing


PNG_SETTINGS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]
"""How the writer encodes its PNGs: zlib's fastest level, each row filtered by its left
neighbour (benchmarks/euroc_png.py, docs/benchmarks.md)."""


class EurocWriter:
    """Writes a dataset sample by sample; use as a context manager so the CSVs are closed.

    The camera and depth streams share timestamps (the depth is aligned with the image, through
    the same radial-tangential ``distortion``); the writer creates the folder tree and the
    ``sensor.yaml`` files up front from the sensors' descriptions.
    """

    def __init__(self, root: Path, camera: PinholeCamera, T_B_C: np.ndarray, camera_rate_hz: float,
                 imu_yaml: dict[str, float],
                 distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)):
        self.mav0 = Path(root) / "mav0"
        for name in ("cam0", "depth0"):
            (self.mav0 / name / "data").mkdir(parents=True, exist_ok=True)
            comment = "rendered colour image" if name == "cam0" else "ground-truth z-depth, uint16 mm, 0 = invalid"
            _write_camera_yaml(self.mav0 / name / "sensor.yaml", camera, T_B_C, camera_rate_hz,
                               comment, distortion)
        (self.mav0 / "imu0").mkdir(parents=True, exist_ok=True)
        (self.mav0 / "state_groundtruth_estimate0").mkdir(parents=True, exist_ok=True)
        _write_imu_yaml(self.mav0 / "imu0" / "sensor.yaml", imu_yaml)
        self._files = {
            "cam0": self._open("cam0/data.csv", FRAMES_HEADER),
            "depth0": self._open("depth0/data.csv", FRAMES_HEADER),
            "imu0": self._open("imu0/data.csv", IMU_HEADER),
            "gt": self._open("state_groundtruth_estimate0/data.csv", GROUNDTRUTH_HEADER),
        }
        self._camera, self._camera_rate_hz, self._distortion = camera, camera_rate_hz, distortion

    def _open(self, relative: str, header: str):
        handle = open(self.mav0 / relative, "w", encoding="ascii", newline="\n")
        handle.write(header + "\n")
        return handle

    def add_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None:
        self._files["imu0"].write(_row(t_ns, gyro, accel))

    def add_groundtruth(self, t_ns: int, position, q_W_B, velocity, gyro_bias, accel_bias) -> None:
        self._files["gt"].write(_row(t_ns, position, q_W_B, velocity, gyro_bias, accel_bias))

    def add_frame(self, t_ns: int, rgb: np.ndarray, depth_m: np.ndarray,
                  exposed_ns: int | None = None) -> None:
        """One camera frame (RGB uint8) and its ground-truth depth (float metres, NaN unknown);
        ``exposed_ns``, a simulator's: the true middle of its exposure (``cam0/truth.csv``)."""
        name = f"{t_ns}.png"
        if not cv2.imwrite(str(self.mav0 / "cam0" / "data" / name),
                           cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), PNG_SETTINGS):
            raise OSError(f"could not write {self.mav0 / 'cam0' / 'data' / name}")
        if not cv2.imwrite(str(self.mav0 / "depth0" / "data" / name),
                           depth_to_millimetres(depth_m), PNG_SETTINGS):
            raise OSError(f"could not write {self.mav0 / 'depth0' / 'data' / name}")
        self._files["cam0"].write(f"{t_ns},{name}\n")
        self._files["depth0"].write(f"{t_ns},{name}\n")
        if exposed_ns is not None:
            if "truth" not in self._files:
                self._files["truth"] = self._open("cam0/truth.csv", CAMERA_TRUTH_HEADER)
            self._files["truth"].write(f"{t_ns},{int(exposed_ns)}\n")

    def add_camera_truth(self, T_B_C: np.ndarray) -> None:
        """A simulator's true camera mounting (``cam0/truth.yaml``), beside the configured one
        of ``sensor.yaml`` that the estimator is given."""
        _write_camera_yaml(self.mav0 / "cam0" / "truth.yaml", self._camera, T_B_C,
                           self._camera_rate_hz, "true mounting of the simulated camera, for "
                           "evaluation only", self._distortion)

    def close(self) -> None:
        for handle in self._files.values():
            handle.close()

    def __enter__(self) -> "EurocWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _row(t_ns: int, *vectors) -> str:
    values = np.concatenate([np.asarray(v, dtype=float).ravel() for v in vectors])
    return f"{t_ns}," + ",".join(f"{x:.9g}" for x in values) + "\n"


def _yaml_matrix(T: np.ndarray) -> str:
    rows = [", ".join(f"{x:.12g}" for x in row) for row in np.asarray(T, dtype=float)]
    return "  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def _write_camera_yaml(path: Path, camera: PinholeCamera, T_B_C: np.ndarray, rate_hz: float,
                       comment: str, distortion: tuple[float, ...]) -> None:
    path.write_text(
        "%YAML:1.0\n"
        "sensor_type: camera\n"
        f"comment: {comment}\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n" + _yaml_matrix(T_B_C) +
        f"rate_hz: {rate_hz:g}\n"
        f"resolution: [{camera.width}, {camera.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{camera.fx:.12g}, {camera.fy:.12g}, {camera.cx:.12g}, {camera.cy:.12g}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(f'{c:.12g}' for c in distortion)}]\n",
        encoding="ascii",
    )


def _write_imu_yaml(path: Path, noise: dict[str, float]) -> None:
    lines = "".join(f"{key}: {noise[key]:.6g}\n" for key in IMU_NOISE_KEYS)
    path.write_text(
        "%YAML:1.0\nsensor_type: imu\ncomment: simulated IMU, body frame\n"
        "T_BS:\n" + _yaml_matrix(np.eye(4)) + f"rate_hz: {noise['rate_hz']:g}\n" + lines,
        encoding="ascii",
    )


# ---------------------------------------------------------------- reading


def read_imu(root: Path) -> ImuTable:
    """``mav0/imu0/data.csv`` of the dataset at ``root``."""
    t_ns, values = _read_table(Path(root) / "mav0" / "imu0" / "data.csv", 6)
    return ImuTable(t_ns, values[:, 0:3], values[:, 3:6])


def read_groundtruth(root: Path) -> GroundTruthTable:
    """``mav0/state_groundtruth_estimate0/data.csv`` of the dataset at ``root``."""
    t_ns, v = _read_table(Path(root) / "mav0" / "state_groundtruth_estimate0" / "data.csv", 16)
    return GroundTruthTable(t_ns, v[:, 0:3], v[:, 3:7], v[:, 7:10], v[:, 10:13], v[:, 13:16])


def read_camera(root: Path, name: str = "cam0") -> CameraStream:
    """The image stream ``mav0/<name>``: its timestamps, file paths and ``sensor.yaml``."""
    folder = Path(root) / "mav0" / name
    rows = _read_rows(folder / "data.csv", 2, "frame")
    t_ns = _timestamps(folder / "data.csv", rows)
    paths = tuple(folder / "data" / row[1].strip() for row in rows)
    camera, distortion, T_B_C, rate = _read_camera_yaml(folder / "sensor.yaml")
    return CameraStream(t_ns, paths, camera, distortion, T_B_C, rate)


def read_camera_truth(root: Path, stream: CameraStream) -> CameraTruth | None:
    """The simulator's truth of ``root``'s camera ``cam0`` (:class:`CameraTruth`), checked
    against its ``stream``'s stamps; None for a recording without it (a real one, or the
    simulator's before 2026-12-07); DatasetError when half of it is there or it does not name
    the stream's frames."""
    folder = Path(root) / "mav0" / "cam0"
    table, mounting = folder / "truth.csv", folder / "truth.yaml"
    if not table.exists() and not mounting.exists():
        return None
    rows = _read_rows(table, 2, "frame")
    stamps = _timestamps(table, rows)
    if not np.array_equal(stamps, stream.t_ns):
        first = min(len(stamps), len(stream.t_ns))  # the first frame that differs
        if first and not np.array_equal(stamps[:first], stream.t_ns[:first]):
            first = int(np.flatnonzero(stamps[:first] != stream.t_ns[:first])[0])
        raise DatasetError(f"{table}: its stamps are not those of {folder / 'data.csv'} "
                           f"({len(stamps)} and {len(stream.t_ns)} frames; frame {first + 1} "
                           "differs)")
    try:  # the exposures, read as timestamps: int64 nanoseconds, in order
        exposed_ns = _timestamps(table, [row[1:] for row in rows])
    except DatasetError as error:  # which column: the stamps have passed the same check
        raise DatasetError(f"{error} (the exposures, column 2)") from None
    return CameraTruth(exposed_ns, _read_camera_yaml(mounting)[2])


def _read_rows(path: Path, columns: int, row_name: str) -> list[list[str]]:
    """The rows of an ASCII CSV file, comment lines left out, each of ``columns`` columns
    (a row being a ``row_name``); DatasetError when there are none or the file is not that."""
    try:
        with open(path, newline="", encoding="ascii") as handle:
            rows = [row for row in csv.reader(handle) if row and not row[0].startswith("#")]
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except UnicodeDecodeError as error:
        raise DatasetError(f"{path}: not ASCII text (byte {error.start})") from None
    except csv.Error as error:
        raise DatasetError(f"{path}: not CSV ({error})") from None
    if not rows:
        raise DatasetError(f"{path}: no {row_name}s")
    bad = next((i for i, row in enumerate(rows) if len(row) != columns), None)
    if bad is not None:
        raise DatasetError(f"{path}: {row_name} {bad + 1} has {len(rows[bad])} columns, "
                           f"expected {columns}")
    return rows


def _timestamps(path: Path, rows: list[list[str]]) -> np.ndarray:
    """The rows' first column: int64 nanoseconds, strictly increasing (else DatasetError)."""
    try:
        t_ns = np.array([int(row[0]) for row in rows], dtype=np.int64)
    except ValueError as error:
        raise DatasetError(f"{path}: bad timestamp ({error})") from None
    except OverflowError:
        raise DatasetError(f"{path}: a timestamp beyond 64-bit nanoseconds") from None
    if np.any(np.diff(t_ns) <= 0):
        raise DatasetError(f"{path}: timestamps are not strictly increasing")
    return t_ns


def _read_table(path: Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """A sensor table: timestamps and ``columns`` finite numbers a sample."""
    rows = _read_rows(path, columns + 1, "sample")
    t_ns = _timestamps(path, rows)
    try:
        values = np.array([[float(x) for x in row[1:]] for row in rows])
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from None
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise DatasetError(f"{path}: sample {bad[0] + 1} holds a value that is not a finite "
                           "number")
    return t_ns, values


def read_imu_noise(root: Path) -> ImuNoise:
    """The IMU noise model of ``mav0/imu0/sensor.yaml`` (Kalibr's continuous-time densities)."""
    path = Path(root) / "mav0" / "imu0" / "sensor.yaml"
    with _yaml(path) as storage:
        values = {field: _number(storage, path, key) for key, field in IMU_NOISE_KEYS.items()}
    try:
        return ImuNoise(**values)
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from None


#: How far ``R^T R`` of a sensor's ``T_BS`` may be from the identity, in any entry: a rotation
#: written to four decimals (as calibration files by hand often are) is within 2e-4; a scaled
#: or sheared matrix, which would distort every bearing through it, is refused.
ROTATION_TOLERANCE = 1e-3


def _read_camera_yaml(path: Path):
    """The camera model, distortion, mounting ``T_BS`` and rate of a camera's sensor.yaml;
    DatasetError for anything missing or not a number where one is expected, and for a
    ``T_BS`` that is no pose (the estimator and the evaluation take it for one: a scaled or
    sheared "rotation" would distort every bearing through it, silently)."""
    with _yaml(path) as storage:
        fu, fv, cu, cv = _numbers(storage, path, "intrinsics", 4)
        width, height = _numbers(storage, path, "resolution", 2)
        T_B_C = np.array(_numbers(storage, path, "T_BS", 16)).reshape(4, 4)
        distortion = tuple(_numbers(storage, path, "distortion_coefficients"))
        rate = _number(storage, path, "rate_hz")
    if not (width.is_integer() and height.is_integer()):
        raise DatasetError(f"{path}: resolution must be whole pixels, got {width}x{height}")
    if not (math.isfinite(rate) and rate > 0.0):
        raise DatasetError(f"{path}: rate_hz must be a positive number, got {rate}")
    R = T_B_C[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: no rotation either
        rotation = (np.allclose(R.T @ R, np.eye(3), atol=ROTATION_TOLERANCE)
                    and np.linalg.det(R) > 0.0)
    if not (rotation and T_B_C[3].tolist() == [0.0, 0.0, 0.0, 1.0]):
        raise DatasetError(f"{path}: T_BS is not a rigid transform (a rotation, and the last "
                           "row 0 0 0 1)")
    # the nearest rotation (Procrustes): a mounting written to a few decimals is a rotation
    # to within ROTATION_TOLERANCE, and the estimator takes it for an exact one
    U, _, Vt = np.linalg.svd(R)
    T_B_C[:3, :3] = U @ Vt
    try:
        camera = PinholeCamera(int(width), int(height), fu, fv, cu, cv)
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from None
    return camera, distortion, T_B_C, rate


@contextmanager
def _yaml(path: Path):
    """An OpenCV ``FileStorage`` on the YAML file ``path``, released on leaving; its top
    level must be a map of keys (OpenCV asserts as much when a key is looked up)."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV's parse error surfaces as either
        raise DatasetError(f"{path}: not readable as YAML") from None
    try:
        if not storage.root().isMap():
            raise DatasetError(f"{path}: not a YAML map of keys")
        yield storage
    finally:
        storage.release()


def _node(storage: cv2.FileStorage, path: Path, key: str) -> cv2.FileNode:
    node = storage.getNode(key)
    if node.empty():
        raise DatasetError(f"{path}: missing {key}")
    return node


def _numbers(storage: cv2.FileStorage, path: Path, key: str,
             count: int | None = None) -> list[float]:
    """The list ``key`` (for a matrix, its ``data``) as finite numbers, ``count`` of them when
    given; DatasetError otherwise."""
    node = _node(storage, path, key)
    if node.isMap():
        node = node.getNode("data")
    items = [node.at(i) for i in range(node.size())] if node.isSeq() else None
    if items is None or not all(item.isReal() or item.isInt() for item in items):
        raise DatasetError(f"{path}: {key} is not a list of numbers")
    values = [item.real() for item in items]
    if count is not None and len(values) != count:
        raise DatasetError(f"{path}: {key} has {len(values)} numbers, expected {count}")
    if not all(math.isfinite(value) for value in values):
        raise DatasetError(f"{path}: {key} holds a number that is not finite")
    return values


def _number(storage: cv2.FileStorage, path: Path, key: str) -> float:
    node = _node(storage, path, key)
    if not (node.isReal() or node.isInt()):
        raise DatasetError(f"{path}: {key} is not a number")
    return node.real()
