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


def quat_to_rotvec(q) -> np.ndarray:
    """Rotation vector of a unit quaternion, taking the short way round (``|phi| <= pi``)."""
    return np.array(quat_log(q))


# Plain-float forms of the quaternion maps, for inner loops (the simulator steps the vehicle
# every 5 ms and a numpy call costs microseconds); the array forms above and below wrap them.


def quat_log(q) -> tuple[float, float, float]:
    """``Log`` of SO(3) on a unit quaternion: its rotation vector, the short way round."""
    w, x, y, z = (float(c) for c in q)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return (2.0 * x, 2.0 * y, 2.0 * z)
    k = 2.0 * math.atan2(s, w) / s
    return (k * x, k * y, k * z)


def quat_exp(phi) -> tuple[float, float, float, float]:
    """``Exp`` of SO(3) as a unit quaternion: ``(cos(|phi|/2), sin(|phi|/2) phi/|phi|)``."""
    x, y, z = (float(c) for c in phi)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return (1.0, 0.5 * x, 0.5 * y, 0.5 * z)
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), s * x, s * y, s * z)


def hamilton_product(a, b) -> tuple[float, float, float, float]:
    """Hamilton product ``a * b`` of quaternions ``(w, x, y, z)``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_from_axes(x, y, z) -> tuple[float, float, float, float]:
    """Unit quaternion of the rotation whose matrix has columns ``x, y, z`` (Shepperd's
    method: divide by the largest of the four squared components, for accuracy)."""
    r00, r10, r20 = x
    r01, r11, r21 = y
    r02, r12, r22 = z
    trace = r00 + r11 + r22
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


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
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    q = np.array(quat_from_axes(R[:, 0], R[:, 1], R[:, 2]))
    return -q if q[0] < 0.0 else q


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product ``a * b``: ``quat_to_rot(a * b) == quat_to_rot(a) @ quat_to_rot(b)``."""
    return np.array(hamilton_product(a, b))


def rot_z(yaw: float) -> np.ndarray:
    """Rotation about the world z axis by ``yaw`` radians (counter-clockwise seen from above)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(R: np.ndarray) -> float:
    """Heading of the body x axis in the world's horizontal plane, radians in (-pi, pi]."""
    return math.atan2(R[1, 0], R[0, 0])


def yaw_alignment(T_L_B: np.ndarray, T_W_B: np.ndarray) -> np.ndarray:
    """``T_L_W`` from one body pose in both frames, both gravity-aligned (z up): the rotation
    about z by the yaw difference, and the translation that maps the body's position in ``W``
    onto its position in ``L``. Roll and pitch agree in both frames up to the estimators'
    tilt errors, which are left out so that ``L`` and ``W`` share their vertical."""
    R = rot_z(yaw_of(T_L_B[:3, :3]) - yaw_of(T_W_B[:3, :3]))
    return make_pose(R, T_L_B[:3, 3] - R @ T_W_B[:3, 3])


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


# ---------------------------------------------------------------- lens distortion
#
# The radial-tangential ("plumb bob") model of OpenCV and the EuRoC/Kalibr ``radtan`` model,
# coefficients in OpenCV's order ``(k1, k2, p1, p2[, k3])``. A point with normalised image
# coordinates ``(x, y) = (X/Z, Y/Z)`` appears at the distorted normalised coordinates
#
#     r^2 = x^2 + y^2,   a = 1 + k1 r^2 + k2 r^4 + k3 r^6
#     x_d = a x + 2 p1 x y + p2 (r^2 + 2 x^2)
#     y_d = a y + p1 (r^2 + 2 y^2) + 2 p2 x y
#
# and its pixel is ``(fx x_d + cx, fy y_d + cy)``. Undistortion inverts this map numerically.


def _distortion_coefficients(distortion) -> tuple[float, float, float, float, float]:
    """``(k1, k2, p1, p2, k3)`` of 0, 4 or 5 OpenCV-order coefficients (missing ones are 0)."""
    coefficients = tuple(float(c) for c in np.asarray(distortion, dtype=float).ravel())
    if len(coefficients) not in (0, 4, 5):
        raise ValueError("radial-tangential distortion takes 0, 4 or 5 coefficients "
                         f"(k1, k2, p1, p2[, k3]), got {len(coefficients)}")
    if not all(math.isfinite(c) for c in coefficients):
        raise ValueError(f"distortion coefficients must be finite, got {coefficients}")
    return (coefficients + (0.0,) * 5)[:5]  # type: ignore[return-value]


def _as_points(points, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {p.shape}")
    return p


def distort_normalised(distortion, normalised) -> np.ndarray:
    """Distorted normalised coordinates ``(N, 2)`` of undistorted ones ``(N, 2)`` (model above)."""
    k1, k2, p1, p2, k3 = _distortion_coefficients(distortion)
    xy = _as_points(normalised, "normalised coordinates")
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.stack([a * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                     a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y], axis=1)


def distort_points(camera: PinholeCamera, distortion, normalised) -> np.ndarray:
    """Pixels ``(N, 2)`` at which a distorting lens images normalised coordinates ``(N, 2)``."""
    d = distort_normalised(distortion, normalised)
    return np.stack([camera.fx * d[:, 0] + camera.cx, camera.fy * d[:, 1] + camera.cy], axis=1)


def undistort_normalised(distortion, distorted, *, iterations: int = 20,
                         tolerance: float = 1e-12) -> np.ndarray:
    """Invert :func:`distort_normalised` by Newton's method on the 2x2 Jacobian.

    Starts from the distorted point itself and stops once every point moves less than
    ``tolerance``; for the moderate distortion of real lenses (EuRoC: k1 = -0.28) it converges
    in about five steps to machine precision inside the image. Points where the model folds
    over (Jacobian singular, far outside any real image) come back as NaN.
    """
    k1, k2, p1, p2, k3 = _distortion_coefficients(distortion)
    target = _as_points(distorted, "distorted coordinates")
    if not (k1 or k2 or p1 or p2 or k3) or len(target) == 0:
        return target.copy()
    x, y = target[:, 0].copy(), target[:, 1].copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d a / d r^2
        ex = a * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - target[:, 0]
        ey = a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - target[:, 1]
        jxx = a + 2.0 * x * x * da + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = 2.0 * x * y * da + 2.0 * p1 * x + 2.0 * p2 * y
        jyx = 2.0 * x * y * da + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = a + 2.0 * y * y * da + 6.0 * p1 * y + 2.0 * p2 * x
        det = jxx * jyy - jxy * jyx
        with np.errstate(divide="ignore", invalid="ignore"):
            step_x = (jyy * ex - jxy * ey) / det
            step_y = (jxx * ey - jyx * ex) / det
        x -= step_x
        y -= step_y
        if not np.any(np.abs(step_x) + np.abs(step_y) > tolerance):
            break
    out = np.stack([x, y], axis=1)
    residual = distort_normalised((k1, k2, p1, p2, k3), out) - target
    out[~(np.abs(residual).max(axis=1) < 1e-9)] = np.nan
    return out


def undistort_points(camera: PinholeCamera, distortion, pixels) -> np.ndarray:
    """Undistorted normalised image coordinates ``(N, 2)`` (``X/Z, Y/Z``) of distorted pixels
    ``(N, 2)`` seen through ``camera`` with radial-tangential ``distortion`` (model above);
    NaN where the model cannot be inverted."""
    uv = _as_points(pixels, "pixels")
    distorted = np.stack([(uv[:, 0] - camera.cx) / camera.fx,
                          (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    return undistort_normalised(distortion, distorted)
