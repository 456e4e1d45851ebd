"""Rotations, poses and the pinhole camera, in the project's frame conventions (DESIGN.md).

Frames: world ``W`` gravity-aligned, z up; body ``B`` x forward, y left, z up (FLU); camera
``C`` the optical frame (x right, y down, z forward). A pose ``T_A_B`` is a 4x4 homogeneous
matrix taking points from frame B to frame A: ``p_A = T_A_B @ p_B``.

Quaternions are Hamilton, scalar first, ``q = (w, x, y, z)``, and ``q_A_B`` rotates vectors
from B into A, so ``quat_to_rot(q_A_B) == R_A_B``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Rotation of the optical camera frame in the FLU body frame, for a camera looking along
#: body x: the camera's x (right) is body -y, its y (down) is body -z, its z (forward) body x.
R_BODY_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

GRAVITY = 9.80665
"""Standard gravity, m/s^2; the world's gravity vector is ``(0, 0, -GRAVITY)``."""


def skew(v: np.ndarray) -> np.ndarray:
    """The matrix ``[v]x`` with ``[v]x @ u == cross(v, u)``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation by angle ``|phi|`` about axis ``phi / |phi|``."""
    angle = float(np.linalg.norm(phi))
    K = skew(phi)
    if angle < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return (
        np.eye(3)
        + (math.sin(angle) / angle) * K
        + ((1.0 - math.cos(angle)) / angle**2) * K @ K
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """The rotation vector ``phi`` with ``so3_exp(phi) == R`` and ``|phi| <= pi``."""
    return quat_to_rotvec(rot_to_quat(R))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion, taking the short way round (``|phi| <= pi``)."""
    w, v = float(q[0]), np.asarray(q[1:], dtype=float)
    if w < 0.0:
        w, v = -w, -v
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return 2.0 * v
    return (2.0 * math.atan2(s, w) / s) * v


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (Shepperd's method)."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0.0 else q


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b``: ``quat_to_rot(a * b) == quat_to_rot(a) @ quat_to_rot(b)``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def rot_z(yaw: float) -> np.ndarray:
    """Rotation about the world z axis by ``yaw`` radians (counter-clockwise seen from above)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(R: np.ndarray) -> float:
    """Heading of the body x axis in the world's horizontal plane, radians in (-pi, pi]."""
    return math.atan2(R[1, 0], R[0, 0])


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 pose ``[[R, t], [0, 1]]``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """``T^-1`` for a rigid pose, without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


@dataclass(frozen=True)
class PinholeCamera:
    """An undistorted pinhole camera: pixel ``(u, v) = (fx x/z + cx, fy y/z + cy)``.

    Pixel centres sit at integer coordinates, so the image spans ``u`` in
    ``[-0.5, width - 0.5]``, the OpenCV convention.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0.0 and self.fy > 0.0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov: float) -> "PinholeCamera":
        """Square pixels, principal point at the image centre, horizontal field of view ``hfov``
        radians across the full image width."""
        if not 0.0 < hfov < math.pi:
            raise ValueError(f"horizontal field of view must be in (0, pi) radians, got {hfov}")
        f = (width / 2.0) / math.tan(hfov / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points_C: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)``; points behind the camera give
        non-finite or meaningless pixels, so callers keep ``z > 0`` themselves."""
        p = np.asarray(points_C, dtype=float)
        return np.stack(
            [self.fx * p[:, 0] / p[:, 2] + self.cx, self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1
        )

    def rays(self) -> np.ndarray:
        """``(height, width, 3)`` camera-frame directions with z = 1 through every pixel centre,
        so ``depth[..., None] * rays()`` are the pixels' 3-D points."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)
