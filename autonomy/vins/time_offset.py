"""Online camera-IMU time offset: the camera's rotation between frames against the gyro's.

A camera that is not synchronised with the IMU stamps each frame late by an unknown offset
``td``: the frame stamped ``s`` was exposed at ``s - td`` on the IMU's clock (5-30 ms on a USB
camera). An estimator that takes the stamp as the exposure time fits every image to the pose
``td`` too late, and the IMU and the camera disagree whenever the motion changes. VINS-Mono
estimates ``td`` inside its optimisation, shifting every feature by ``td`` times its image
velocity (Qin & Shen, "Online Temporal Calibration for Monocular Visual-Inertial Systems",
IROS 2018). Here it is estimated beside the smoother instead, as a one-dimensional problem on
rotations alone, in the spirit of the rotation-alignment calibrations (Kelly & Sukhatme,
"A General Framework for Temporal Calibration of Multiple Proprioceptive and Exteroceptive
Sensors", ISER 2010), and the smoother is simply given corrected frame times.

**The pair measurement.** Frame ``j`` is paired with an earlier frame ``i`` about
``time_offset_pair_s`` before it that shares at least ``time_offset_min_features`` tracks. From
the two frames' undistorted bearings ``u`` (in ``i``) and ``w`` (in ``j``) alone,
:func:`fit_rotation` finds the camera's rotation ``R_ij`` (``p_i = R_ij p_j + t_ij``) with the
translation's direction as a nuisance: Gauss-Newton on the angular epipolar errors
``u . (t x R w) / |t x R w|`` under a Huber loss, from the gyro's prediction. Its information
``Lambda_ij`` is the rotation block of the Gauss-Newton Hessian with the translation
marginalised (a Schur complement) and the noise taken from the residuals (their MAD). When the
translation's effect is below the noise (hovering, turning in place), the rotation-only fit
``u ~ R w`` is kept instead: it is then unbiased and better conditioned.

**The gyro's side.** The gyro, less the smoother's bias estimate, is integrated into an
orientation ``R(t)`` at IMU rate, zero-order hold as in the preintegration (:class:`GyroTrack`).
For an offset ``td`` the gyro predicts the camera's rotation over the pair as

    R_C(td) = R_C_B R(s_i - td)^T R(s_j - td) R_B_C.

Shifting both ends by ``-delta``, ``R(t - delta) ~ R(t) Exp(-omega(t) delta)``, so

    R_C(td + delta) ~ R_C(td) Exp(J delta),   J = R_C_B (R_g^T omega_i - omega_j),

with ``R_g = R(a)^T R(b)`` the body's rotation over the pair and ``omega`` the body rates at its
ends. A pair carries information on ``td`` only as far as the angular velocity differs between
its ends: in steady flight, or a steady turn, none; at the start and end of a turn, or when the
vehicle pitches to accelerate, a lot.

Each end's ``omega`` is the mean rate over :data:`RATE_SPAN_S` around it, the secant
``Log(R(t - h)^T R(t + h)) / 2h``, not the one gyro sample at ``t``. A sample carries the rotors'
vibration, which the camera does not see (in the realistic profile 0.145 rad/s at 122.5 Hz,
aliased by the 200 Hz sampling to about 0.08 rad/s at 77.5 Hz: docs/simulator.md), as large as
the change of rate a turn makes. Taken for motion it added to ``H`` information the pairs do not
hold, so windows claimed sigmas of 0.3-0.9 ms while up to 12 ms off, and it shortened every
Gauss-Newton step by the same factor, so a window's solution stayed near its starting point,
the previous estimate (docs/vins.md, "The time offset's windows and the rotors' vibration").

**The window.** The residual of pair ``k`` is ``r_k(td) = Log(R_C(td)^T R_ij)`` and the estimate
minimises ``sum_k rho(r_k^T Lambda_k r_k)`` over the pairs of the last
``time_offset_window_s`` (Huber ``rho``, so a bad pair cannot pull it far): Gauss-Newton on the
scalar ``td`` with ``r_k(td + delta) ~ r_k(td) - J_k delta``,

    delta = sum_k J_k^T Lambda_k r_k / H,   H = sum_k J_k^T Lambda_k J_k,   sigma = 1 / sqrt(H),

re-evaluating the rotations exactly at each iterate. ``H`` is the window's rotational
excitation. Consecutive pairs overlap (a pair spans ``time_offset_pair_s``, a new one starts
every frame), so each pair's information is scaled by the frame interval over the pair's
interval, and each pair's covariance has a floor (:data:`ROTATION_SIGMA_FLOOR`) for what the
pixels' scatter does not show. Measured on four simulated 40 s flights of the ideal profile with
offsets of -15, 0 and 15 ms, the windows with ``sigma`` under 1 ms were off by under
``1.8 sigma`` in 95 % of cases and ``2.8 sigma`` at worst; on twelve realistic recordings (the
gyro's and the mounting's errors, which the model leaves out) by ``1.4-5.3 sigma`` (docs/vins.md).

**The estimate in use.** A window becomes the *target* when its ``sigma`` is below
``time_offset_max_sigma_s`` (the motion showed the offset), its solution within
``max_time_offset_s``, and its ``sigma`` below the target's, which grows by
:data:`DRIFT_PER_SQRT_S` with the time since (a camera's offset wanders with its clock and its
exposure, so a newer window of nearly the same quality takes over). The offset in use steps
towards the target by at most ``time_offset_max_step_s`` per frame, so the frame times stay
increasing and a sudden change does not shake the smoother. Its reported sigma is the target's,
combined with the distance still to go. Until a first window is excited enough the offset stays
at ``time_offset_s`` and its sigma is None.

Why not VINS-Mono's way: ``td`` as a variable of the smoother would be connected to every
projection factor, so iSAM2 would re-eliminate it with the whole window at every keyframe, and
each factor's derivative in ``td`` would be a Python callback (GTSAM's ``CustomFactor``) for
hundreds of factors per keyframe; the back-end's 15 ms budget allows neither. Decoupled, the
estimate costs about a millisecond per frame, does not depend on the smoother being healthy,
and reads as what it is: the time shift that lines the camera's rotation up with the gyro's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import so3_exp
from autonomy.vins.options import VinsOptions

#: Huber threshold of the pair fit, in robust sigmas of the angular residuals.
PAIR_HUBER_K = 1.345
#: Huber threshold of the window fit, on a pair's Mahalanobis distance ``sqrt(r^T Lambda r)``.
WINDOW_HUBER_K = 3.0
#: Gauss-Newton iterations of the pair fit and of the window fit.
PAIR_ITERATIONS = 3
WINDOW_ITERATIONS = 4
#: The translation's share of the residuals is negligible (the rotation-only fit is kept) when
#: the rotation-only fit's median residual is below this many pixels.
ROTATION_ONLY_PX = 0.5
#: Bearings within this angle of the epipole weigh as if at this angle (their epipolar plane
#: is ill-defined), radians.
EPIPOLE_FLOOR_RAD = math.radians(2.0)
#: A noise floor on the pair rotation, radians: what neither the pixels' scatter nor the model
#: shows (the gyro's noise over the pair, the calibration of the camera's mounting).
ROTATION_SIGMA_FLOOR = 3e-4
#: How fast the reported sigma grows while nothing updates the estimate, seconds per sqrt(s).
DRIFT_PER_SQRT_S = 1e-4
#: The span the rates at a pair's ends are averaged over, seconds: about three cycles of the
#: rotors' vibration as the 200 Hz gyro aliases it (77.5 Hz at hover), a tenth of a turn's
#: onset.
RATE_SPAN_S = 0.04
#: The gyro history kept beyond the window, seconds (the shifted times reach outside it).
GYRO_MARGIN_S = 0.5


@dataclass(frozen=True)
class TimeOffset:
    """The camera-IMU time offset in use: frames are exposed ``seconds`` before their stamp.

    ``sigma``: its one-sigma uncertainty, seconds (None while nothing has shown the offset, and
    when it is fixed by the options). ``estimating``: estimated online. ``updates``: frames on
    which the estimate moved. ``window_sigma``: the sigma of the last window's own solution,
    seconds: how well the recent motion shows the offset (infinite while the angular velocity
    does not change; None before the first window).
    """

    seconds: float = 0.0
    sigma: float | None = None
    estimating: bool = False
    updates: int = 0
    window_sigma: float | None = None


@dataclass(frozen=True)
class RotationFit:
    """A camera rotation ``R`` (``R_ij``: ``p_i = R p_j + t``) from two frames' bearings, its
    ``information`` (3x3, 1/rad^2), the ``features`` it used and whether the translation was
    modelled (``translation``) or negligible."""

    R: np.ndarray
    information: np.ndarray
    features: int
    translation: bool
    residual_px: float


@dataclass(frozen=True)
class _Pair:
    """Frames stamped ``s_i`` < ``s_j`` and the camera rotation between them."""

    s_i: float
    s_j: float
    R: np.ndarray
    information: np.ndarray
    overlap: float
    R_gyro: np.ndarray  # the body's rotation by the gyro, at the offset in use when paired


@dataclass(frozen=True)
class PairRotations:
    """A frame pair in the body frame (the camera's through its configured mounting): the
    body's rotation over the pair by the gyro (``R_gyro``, at the offset in use when the pair
    was made) and by the camera (``R_camera``), and the camera rotation's ``information``
    (3x3, 1/rad^2), already scaled by ``overlap``: the share of the pair's interval no earlier
    pair covered. :mod:`autonomy.vins.gyro_alignment` fits the gyro's misalignment to them."""

    R_gyro: np.ndarray
    R_camera: np.ndarray
    information: np.ndarray
    overlap: float


# ---------------------------------------------------------------------- small vector algebra


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula on (..., 3) rotation vectors: (..., 3, 3) rotations."""
    phi = np.asarray(phi, dtype=float)
    angle = np.sqrt(np.sum(phi * phi, axis=-1))[..., None, None]
    K = _skew(phi)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """The rotation vectors (..., 3) of (..., 3, 3) rotations of angle below pi."""
    R = np.asarray(R, dtype=float)
    cos = np.clip((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5, -1.0, 1.0)
    angle = np.arccos(cos)
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                    R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    small = angle < 1e-6
    scale = np.where(small, 0.5 + angle ** 2 / 12.0,
                     angle / (2.0 * np.sin(np.where(small, 1.0, angle))))
    return vee * scale[..., None]


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` of (..., 3) vectors: (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (n, 3) or (3,) arrays (``np.cross`` costs more on small
    arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


# ---------------------------------------------------------------------- the gyro's side


class GyroTrack:
    """The gyro integrated into an orientation ``R(t)`` (zero-order hold: a sample holds from its
    time to the next), bias-corrected with the bias current when each sample arrives; samples
    older than ``span_s`` behind the newest are dropped."""

    def __init__(self, span_s: float):
        self.span_s = float(span_s)
        self._t = np.zeros(0)
        self._w = np.zeros((0, 3))
        self._R = np.zeros((0, 3, 3))
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def last_time(self) -> float | None:
        return float(self._t[self._count - 1]) if self._count else None

    def add(self, t: float, gyro: np.ndarray, bias: np.ndarray) -> None:
        """Append a sample (times strictly increasing: the caller's buffer checked them)."""
        n = self._count
        w = np.asarray(gyro, dtype=float) - np.asarray(bias, dtype=float)
        if n == 0:
            R = np.eye(3)
        else:
            R = self._R[n - 1] @ so3_exp(self._w[n - 1] * (t - self._t[n - 1]))
        if n == len(self._t):
            self._grow()
            n = self._count
        self._t[n], self._w[n], self._R[n] = t, w, R
        self._count = n + 1

    def _grow(self) -> None:
        """Drop what is older than the span, then make room."""
        n = self._count
        keep = 0
        if n:
            keep = int(np.searchsorted(self._t[:n], self._t[n - 1] - self.span_s, side="left"))
            keep = max(0, min(keep, n - 2))
        t, w, R = self._t[keep:n], self._w[keep:n], self._R[keep:n]
        size = max(256, 2 * len(t))
        self._t, self._w, self._R = np.zeros(size), np.zeros((size, 3)), np.zeros((size, 3, 3))
        self._t[:len(t)], self._w[:len(t)], self._R[:len(t)] = t, w, R
        self._count = len(t)

    def covers(self, t0: float, t1: float) -> bool:
        """Whether the samples span ``[t0, t1]`` (the newest may hold a little past its time)."""
        return self._count >= 2 and self._t[0] <= t0 and t1 <= self._t[self._count - 1] + 0.05

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Orientations (n, 3, 3) and bias-corrected rates (n, 3) at ``times`` (inside the span)."""
        t, n = self._t[:self._count], self._count
        k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, n - 1)
        w = self._w[k]
        return self._R[k] @ exp_so3(w * (times - t[k])[:, None]), w

    def orientations_and_mean_rates(self, times: np.ndarray,
                                    span_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`at`'s orientations (n, 3, 3) at ``times``, and the body rates (n, 3)
        averaged over ``span_s`` centred on each: the secant ``Log(R(t - h)^T R(t + h)) / 2h``,
        ``h = span_s / 2`` (an end past the newest sample is held at its rate, as :meth:`at`
        holds it). One look-up for the three instants of every time: the window's fit asks
        for them at each of its iterations, and on a few hundred times numpy's per-call cost
        is most of the work."""
        half, n = 0.5 * span_s, len(times)
        R, _ = self.at(np.concatenate([times, times - half, times + half]))
        return R[:n], log_so3(np.swapaxes(R[n:2 * n], 1, 2) @ R[2 * n:]) / span_s


# ---------------------------------------------------------------------- the camera's side


def fit_rotation(u: np.ndarray, w: np.ndarray, R0: np.ndarray,
                 focal_px: float) -> RotationFit | None:
    """The rotation ``R`` with ``p_i = R p_j + t`` from bearings ``u`` (frame ``i``) and ``w``
    (frame ``j``), (n, 3) unit vectors of the same points, started at ``R0`` (module
    docstring). None when the points are too few or the fit is degenerate."""
    if len(u) < 8:
        return None
    fitted = _fit_rotation_only(u, w, ROTATION_ONLY_PX / focal_px)
    if fitted is not None:
        R, information, residual = fitted
        return RotationFit(R, information, len(u), False, focal_px * residual)
    fitted = _fit_with_translation(u, w, R0)
    if fitted is None:
        return None
    R, information, residual = fitted
    return RotationFit(R, information, len(u), True, focal_px * residual)


def _huber(a: np.ndarray, k: float) -> np.ndarray:
    """Huber weights of residuals ``a`` already divided by their scale."""
    a = np.abs(a)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


#: Floor under a robust residual scale, radians (a hundredth of a pixel at f = 500 px).
_SCALE_FLOOR = 2e-5


def _fit_rotation_only(u, w, max_residual: float):
    """``u ~ R w``: Kabsch's solution, reweighted (Huber) twice: ``R``, its information
    ``sum_k (I - w_k w_k^T) / sigma^2`` (each bearing fixes the two axes across it), and the
    median residual angle. None (at once) when the first solution's median residual exceeds
    ``max_residual``: the translation shows."""
    weight = np.ones(len(u))
    for iteration in range(3):
        try:
            U, _, Vt = np.linalg.svd((u * weight[:, None]).T @ w)
        except np.linalg.LinAlgError:
            return None
        D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
        R = U @ D @ Vt
        angle = np.sqrt(np.sum((u - w @ R.T) ** 2, axis=1))
        median = float(np.median(angle))
        if iteration == 0 and not median < max_residual:
            return None
        # |r| of a 2-D Gaussian residual has median sigma sqrt(2 ln 2)
        scale = max(median / 1.1774, _SCALE_FLOOR)
        weight = _huber(angle / scale, PAIR_HUBER_K)
    information = (weight.sum() * np.eye(3) - (w * weight[:, None]).T @ w) / scale ** 2
    return R, information, median


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """Two unit vectors (3, 2) orthogonal to the unit vector ``t`` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(t)))]
    b1 = _cross(t, helper)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, _cross(t, b1)], axis=1)


def _fit_with_translation(u, w, R0):
    """Gauss-Newton on ``R`` and the translation's direction ``t`` with the angular epipolar
    errors ``u . (t x R w) / |t x R w|``, Huber-weighted: ``R``, its information with ``t``
    marginalised (Schur complement), and the median residual angle; None if degenerate."""
    R = np.array(R0, dtype=float)
    a = _cross(w @ R.T, u)  # e = t . a
    _, vectors = np.linalg.eigh(a.T @ a)
    t = vectors[:, 0]
    floor = math.sin(EPIPOLE_FLOOR_RAD)
    for iteration in range(PAIR_ITERATIONS + 1):
        Rw = w @ R.T
        a = _cross(Rw, u)
        # the angle of u off the epipolar plane of R w: e / |t x R w|
        d = np.maximum(np.sqrt(np.sum(_cross(t, Rw) ** 2, axis=1)), floor)
        r = (a @ t) / d
        # d e / d theta = (R^T (t x u)) x w, d e / d beta = a . B (t <- t + B beta)
        c = _cross(t, u) @ R
        B = _tangent_basis(t)
        J = np.concatenate([_cross(c, w), a @ B], axis=1) / d[:, None]  # (n, 5)
        scale = max(1.4826 * float(np.median(np.abs(r))), _SCALE_FLOOR)
        weight = _huber(r / scale, PAIR_HUBER_K)
        Jw = J * weight[:, None]
        H = Jw.T @ J
        if iteration == PAIR_ITERATIONS:
            break
        try:
            step = -np.linalg.solve(H, Jw.T @ r)
        except np.linalg.LinAlgError:
            return None
        R = R @ so3_exp(step[:3])
        t = t + B @ step[3:]
        t /= np.linalg.norm(t)
        if float(step @ step) < 1e-12:  # a microradian
            break
    H = H / scale ** 2
    try:
        information = H[:3, :3] - H[:3, 3:] @ np.linalg.solve(H[3:, 3:], H[3:, :3])
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(information).all():
        return None
    return R, information, float(np.median(np.abs(r)))


# ---------------------------------------------------------------------- the estimator


class TimeOffsetEstimator:
    """The camera-IMU time offset, estimated online from frame pairs (module docstring).

    Feed every IMU sample (:meth:`add_imu`, with the gyro bias to remove) and every frame's
    stamp and features (:meth:`add_frame`); :attr:`offset` is the offset to subtract from the
    next frame's stamp.
    """

    def __init__(self, T_B_C: np.ndarray, focal_px: float, options: VinsOptions):
        self.options = options
        R_B_C = np.asarray(T_B_C, dtype=float)[:3, :3]
        self._R_B_C, self._R_C_B = R_B_C, R_B_C.T
        self.focal_px = float(focal_px)
        o = options
        self._gyro = GyroTrack(o.time_offset_window_s + o.time_offset_pair_s
                               + o.max_time_offset_s + GYRO_MARGIN_S)
        self._frames: deque = deque()  # (stamp, ids, bearings), newest last
        self._pairs: deque = deque()
        self._td = float(o.time_offset_s)  # in use
        self._target: tuple[float, float, float] | None = None  # best window: td, sigma, when
        self._stamp: float | None = None
        self._updates = 0
        self.window_offset: float | None = None  # the last window's own solution
        self.window_sigma: float | None = None
        #: The pair the last :meth:`add_frame` made, in the body frame (None if none).
        self.latest_pair: PairRotations | None = None

    @property
    def offset(self) -> TimeOffset:
        """The offset in use; its sigma combines the target's with how far the offset in use
        still is from the target."""
        target_sigma = self._target_sigma()
        sigma = None if target_sigma is None else math.hypot(target_sigma,
                                                             self._td - self._target[0])
        return TimeOffset(self._td, sigma, True, self._updates, self.window_sigma)

    def _target_sigma(self) -> float | None:
        """The best window's sigma, grown by the drift since."""
        if self._target is None:
            return None
        _, sigma, since = self._target
        return math.sqrt(sigma ** 2 + DRIFT_PER_SQRT_S ** 2 * max(0.0, self._stamp - since))

    def add_imu(self, t: float, gyro: np.ndarray, bias_g: np.ndarray) -> None:
        """One gyro sample (times strictly increasing), less the current bias estimate."""
        self._gyro.add(float(t), gyro, bias_g)

    def add_frame(self, stamp: float, ids: np.ndarray, normalised: np.ndarray) -> None:
        """One frame's stamp (the caller's, uncorrected) and its tracked features; pairs it with
        an earlier frame and refits the window."""
        o = self.options
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        xy = np.asarray(normalised, dtype=float).reshape(-1, 2)
        finite = np.isfinite(xy).all(axis=1)
        ids, xy = ids[finite], xy[finite]
        bearings = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        bearings /= np.linalg.norm(bearings, axis=1, keepdims=True)
        order = np.argsort(ids)
        frame = (float(stamp), ids[order], bearings[order])
        self._stamp = float(stamp)
        while self._frames and self._frames[0][0] < stamp - o.time_offset_pair_s - 1e-9:
            self._frames.popleft()
        pair = self._pair(frame)
        self._frames.append(frame)
        self.latest_pair = None
        if pair is not None:
            self._pairs.append(pair)
            self.latest_pair = self._in_body_frame(pair)
        while self._pairs and self._pairs[0].s_i < stamp - o.time_offset_window_s:
            self._pairs.popleft()
        if pair is not None:
            self._refit(stamp)
        self._step()

    def _pair(self, frame) -> _Pair | None:
        """The new frame against the oldest kept frame (at most ``time_offset_pair_s`` back)
        that shares enough features, and at least half that interval back."""
        o = self.options
        stamp, ids, bearings = frame
        for s_i, ids_i, bearings_i in self._frames:
            if stamp - s_i < 0.5 * o.time_offset_pair_s:
                return None
            common, here, there = np.intersect1d(ids, ids_i, assume_unique=True,
                                                 return_indices=True)
            if len(common) < o.time_offset_min_features:
                continue
            a, b = s_i - self._td, stamp - self._td
            if not self._gyro.covers(a - o.max_time_offset_s, b):
                return None
            (R_a, R_b), _ = self._gyro.at(np.array([a, b]))
            R_gyro = R_a.T @ R_b
            R0 = self._R_C_B @ R_gyro @ self._R_B_C
            fit = fit_rotation(bearings_i[there], bearings[here], R0, self.focal_px)
            if fit is None:
                return None
            covariance = np.linalg.pinv(fit.information) + ROTATION_SIGMA_FLOOR ** 2 * np.eye(3)
            # consecutive pairs overlap: count each stretch of time once
            overlap = min(1.0, (stamp - self._frames[-1][0]) / (stamp - s_i))
            return _Pair(s_i, stamp, fit.R, overlap * np.linalg.inv(covariance), overlap,
                         R_gyro)
        return None

    def _in_body_frame(self, pair: _Pair) -> PairRotations:
        """``pair``'s camera side in the body frame."""
        return PairRotations(pair.R_gyro, self._R_B_C @ pair.R @ self._R_C_B,
                             self._R_B_C @ pair.information @ self._R_C_B, pair.overlap)

    def solve(self, td: float) -> tuple[float, float]:
        """The window's offset and its sigma by Gauss-Newton from ``td`` (module docstring)."""
        pairs = list(self._pairs)
        s_i = np.array([p.s_i for p in pairs])
        s_j = np.array([p.s_j for p in pairs])
        R_vis = np.stack([p.R for p in pairs])
        Lam = np.stack([p.information for p in pairs])
        bound = self.options.max_time_offset_s
        H = 0.0
        for _ in range(WINDOW_ITERATIONS):
            R, w = self._gyro.orientations_and_mean_rates(np.concatenate([s_i - td, s_j - td]),
                                                          RATE_SPAN_S)
            (R_a, R_b), (w_a, w_b) = np.split(R, 2), np.split(w, 2)
            R_g = np.swapaxes(R_a, 1, 2) @ R_b
            R_c = self._R_C_B @ R_g @ self._R_B_C
            r = log_so3(np.swapaxes(R_c, 1, 2) @ R_vis)
            J = (np.einsum("nji,nj->ni", R_g, w_a) - w_b) @ self._R_C_B.T
            Lr = np.einsum("nij,nj->ni", Lam, r)
            LJ = np.einsum("nij,nj->ni", Lam, J)
            chi = np.sqrt(np.maximum(np.einsum("ni,ni->n", r, Lr), 0.0))
            weight = np.where(chi <= WINDOW_HUBER_K, 1.0, WINDOW_HUBER_K / np.maximum(chi, 1e-12))
            H = float(np.sum(weight * np.einsum("ni,ni->n", J, LJ)))
            g = float(np.sum(weight * np.einsum("ni,ni->n", J, Lr)))
            if H <= 0.0:
                return td, math.inf
            step = g / H
            td = float(np.clip(td + step, -2.0 * bound, 2.0 * bound))
            if abs(step) < 1e-5:  # 10 microseconds
                break
        return td, 1.0 / math.sqrt(H)

    def _refit(self, stamp: float) -> None:
        """Refit the window; it becomes the target when it is excited enough and better
        determined than the target (whose sigma grows with time)."""
        o = self.options
        start = self._td if self._target is None else self._target[0]
        td, sigma = self.solve(start)
        self.window_offset, self.window_sigma = td, sigma
        target_sigma = self._target_sigma()
        if (sigma <= o.time_offset_max_sigma_s and abs(td) <= o.max_time_offset_s
                and (target_sigma is None or sigma <= target_sigma)):
            self._target = (td, sigma, stamp)

    def _step(self) -> None:
        """The offset in use steps towards the target, by at most ``time_offset_max_step_s``."""
        if self._target is None:
            return
        bound = self.options.time_offset_max_step_s
        step = float(np.clip(self._target[0] - self._td, -bound, bound))
        if step != 0.0:
            self._td += step
            self._updates += 1
