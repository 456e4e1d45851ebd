"""Trajectory comparison: alignment of an estimated path onto ground truth, and its error.

An odometry estimate lives in its own world frame (fixed at initialisation, yaw free), so
before it can be compared with ground truth it is aligned onto it by the rigid (or, for a
monocular estimate, similarity) transform that fits best in least squares; the absolute
trajectory error (ATE) is what remains (Sturm et al., "A benchmark for the evaluation of
RGB-D SLAM systems", IROS 2012; Zhang and Scaramuzza, "A tutorial on quantitative trajectory
evaluation for visual(-inertial) odometry", IROS 2018).

Whether the estimator's covariance is honest is the normalised estimation error squared
(NEES, Bar-Shalom, Li and Kirubarajan, "Estimation with Applications to Tracking and
Navigation", 2001, §5.4): ``e^T P^-1 e`` for an error ``e`` of ``d`` dimensions and its
reported covariance ``P`` averages ``d`` when ``P`` is the error's true covariance, more when
the estimator is overconfident and less when it is too cautious.

Unaligned, where the estimate is tied to the truth at the start (a flight's local frame), the
error at the end of a path splits into the path's scale and bearing (``split_displacement``):
the estimated horizontal displacement over the true one as one complex ratio, whose modulus
is the scale a monocular estimator can lose and whose argument is the heading it can drift.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import hamilton_product, quat_exp, quat_log, so3_log

#: Relative size below which the second singular value of the cross-covariance counts as zero:
#: the points are then collinear (or coincide) and the rotation about their line is free.
RANK_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Alignment:
    """The transform ``target ≈ s R source + t``: rotation ``R`` (3x3), translation ``t`` (3,),
    scale ``s`` (1.0 for a rigid alignment)."""

    R: np.ndarray
    t: np.ndarray
    s: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``s R p + t`` for each row ``p`` of ``points`` (N, 3)."""
        return self.s * np.asarray(points, dtype=float) @ self.R.T + self.t


def align_umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> Alignment:
    """The least-squares similarity (``with_scale``) or rigid transform taking ``source`` onto
    ``target``, both (N, 3) with row ``i`` of one matching row ``i`` of the other.

    Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE TPAMI 13(4), 1991, minimises ``(1/N) sum_i |y_i - (s R x_i + t)|^2`` in
    closed form. With means ``mu_x``, ``mu_y``, source variance
    ``sigma_x^2 = (1/N) sum |x_i - mu_x|^2`` and cross-covariance
    ``Sigma = (1/N) sum (y_i - mu_y)(x_i - mu_x)^T = U D V^T`` (SVD):
    ``R = U S V^T`` with ``S = diag(1, 1, det(U) det(V))`` (a rotation, never a reflection),
    ``s = tr(D S) / sigma_x^2`` (or 1 when rigid), ``t = mu_y - s R mu_x``.

    The rotation is unique only when ``Sigma`` has rank >= 2. Points that all coincide or all
    lie on one line leave the rotation about that line undetermined, so they raise
    ``ValueError`` rather than return one arbitrary rotation of many; so do fewer than three
    points, mismatched shapes and non-finite values.
    """
    x, y = _paired_points(source, target)
    mu_x, mu_y = x.mean(axis=0), y.mean(axis=0)
    dx, dy = x - mu_x, y - mu_y
    U, D, Vt = np.linalg.svd(dy.T @ dx / len(x))
    if D[1] <= RANK_TOLERANCE * max(D[0], np.finfo(float).tiny):
        raise ValueError("the points coincide or are collinear: the rotation is undetermined")
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    s = float(D @ np.diag(S) / np.mean(np.sum(dx * dx, axis=1))) if with_scale else 1.0
    return Alignment(R, mu_y - s * R @ mu_x, s)


def _paired_points(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise ValueError(f"expected two (N, 3) arrays of matching points, got shapes "
                         f"{x.shape} and {y.shape}")
    if len(x) < 3:
        raise ValueError(f"alignment needs at least 3 points, got {len(x)}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("the points contain NaN or infinite values")
    return x, y


def ate_rmse(estimated: np.ndarray, truth: np.ndarray, with_scale: bool = False) -> float:
    """Absolute trajectory error: ``sqrt((1/N) sum_i |p_i - (s R e_i + t)|^2)`` for estimated
    positions ``e_i`` and true positions ``p_i`` (both (N, 3)), after
    :func:`align_umeyama` of the estimate onto the truth."""
    alignment = align_umeyama(estimated, truth, with_scale)
    residual = np.asarray(truth, dtype=float) - alignment.apply(estimated)
    return float(np.sqrt(np.mean(np.sum(residual * residual, axis=1))))


def path_length(positions: np.ndarray) -> float:
    """Length of the polyline through ``positions`` (N, 3): ``sum_i |p_{i+1} - p_i|``."""
    steps = np.diff(np.asarray(positions, dtype=float), axis=0)
    return float(np.sum(np.linalg.norm(steps, axis=1)))


def interpolate_poses(t_query, t: np.ndarray, positions: np.ndarray,
                      quaternions_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at times ``t_query`` (M,) from poses at strictly increasing times ``t`` (N,):
    positions (M, 3) and unit quaternions ``(w, x, y, z)`` (M, 4).

    Between samples ``k`` and ``k+1``, at ``a = (t_q - t_k) / (t_{k+1} - t_k)``, the position
    is ``(1 - a) p_k + a p_{k+1}`` and the rotation is the slerp
    ``q_k Exp(a Log(q_k^-1 q_{k+1}))`` of the normalised quaternions, the short way round. A
    query outside ``[t_0, t_N-1]`` raises ``ValueError``: extrapolated ground truth would be a
    silent guess.
    """
    t = np.asarray(t, dtype=float)
    query = np.atleast_1d(np.asarray(t_query, dtype=float))
    if len(t) < 2 or np.any(np.diff(t) <= 0.0):
        raise ValueError("interpolation needs at least 2 samples at strictly increasing times")
    outside = (query < t[0]) | (query > t[-1]) | ~np.isfinite(query)
    if np.any(outside):
        raise ValueError(f"query time {query[outside][0]} is outside the samples' span "
                         f"[{t[0]}, {t[-1]}]")
    k = np.clip(np.searchsorted(t, query, side="right") - 1, 0, len(t) - 2)
    a = (query - t[k]) / (t[k + 1] - t[k])
    p = np.asarray(positions, dtype=float)
    q = np.asarray(quaternions_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    position = (1.0 - a)[:, None] * p[k] + a[:, None] * p[k + 1]
    rotation = np.array([_slerp(q[i], q[i + 1], alpha) for i, alpha in zip(k, a)])
    return position, rotation.reshape(-1, 4)


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> tuple[float, float, float, float]:
    """``q0 Exp(a Log(q0^-1 q1))`` for unit quaternions ``(w, x, y, z)``."""
    q0_inverse = (q0[0], -q0[1], -q0[2], -q0[3])
    phi = np.array(quat_log(hamilton_product(q0_inverse, q1)))
    return hamilton_product(q0, quat_exp(a * phi))


def pose_error_body(T_estimated: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """The error of a pose estimate in its body frame, rotation first (the order and frame of
    GTSAM's ``Pose3`` tangent, so of the smoother's marginal covariances):
    ``[Log(R_e^T R_t), R_e^T (p_t - p_e)]``, to first order ``Log(T_e^-1 T_t)``."""
    R_e, p_e = T_estimated[:3, :3], T_estimated[:3, 3]
    R_t, p_t = T_true[:3, :3], T_true[:3, 3]
    return np.r_[so3_log(R_e.T @ R_t), R_e.T @ (p_t - p_e)]


def nees(error: np.ndarray, covariance: np.ndarray) -> float:
    """``e^T P^-1 e`` (module docstring). A non-finite or singular ``covariance`` raises
    ``ValueError``: it cannot say how large an error should be."""
    error = np.asarray(error, dtype=float)
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape != (len(error), len(error)) or not np.isfinite(covariance).all():
        raise ValueError(f"covariance of shape {covariance.shape} for an error of "
                         f"{len(error)} is unusable (wrong shape or not finite)")
    try:
        return float(error @ np.linalg.solve(covariance, error))
    except np.linalg.LinAlgError:
        raise ValueError("singular covariance") from None


#: The least horizontal distance flown over which :func:`split_displacement` splits an error
#: into the path's scale and bearing, metres (shorter, both are noise).
DISPLACEMENT_MIN_M = 1.0


@dataclass(frozen=True)
class DisplacementSplit:
    """An estimator's position error at the end of a path, taken apart against the
    horizontal path flown: the true horizontal displacement ``D`` (``distance_m`` long) and the
    estimate's ``E``, as the complex ratio ``E / D = scale * exp(i bearing)``; the error
    ``E - D`` along ``D`` (``along_m``, negative: the estimate fell short) and across it
    (``across_m``, positive: to the left), the height error gathered over the path
    (``height_m``), and the error at its start (``start_m``, 3-D). The horizontal error at the
    end is exactly the start's plus ``along_m`` and ``across_m`` in D's frame: a scale error
    shows along, a heading error across."""

    distance_m: float
    scale: float
    bearing_deg: float
    along_m: float
    across_m: float
    height_m: float
    start_m: float


def split_displacement(true_start, true_end, estimated_start, estimated_end,
                       least_m: float = DISPLACEMENT_MIN_M) -> DisplacementSplit | None:
    """The error at ``estimated_end`` against ``true_end`` split over the path from the
    starts (positions, metres, z up; :class:`DisplacementSplit`); None when the true path
    ends within ``least_m`` of its start horizontally."""
    true_start, true_end, estimated_start, estimated_end = (
        np.asarray(p, dtype=float) for p in (true_start, true_end, estimated_start,
                                             estimated_end))
    true_step, estimated_step = true_end - true_start, estimated_end - estimated_start
    flown, estimated = complex(*true_step[:2]), complex(*estimated_step[:2])
    if abs(flown) < least_m:
        return None
    ratio = estimated / flown
    in_path_frame = (estimated - flown) * flown.conjugate() / abs(flown)
    return DisplacementSplit(
        distance_m=abs(flown), scale=abs(ratio), bearing_deg=math.degrees(cmath.phase(ratio)),
        along_m=in_path_frame.real, across_m=in_path_frame.imag,
        height_m=float(estimated_step[2] - true_step[2]),
        start_m=float(np.linalg.norm(estimated_start - true_start)))
