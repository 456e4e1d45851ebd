"""IMU preintegration on the manifold (Forster, Carlone, Dellaert, Scaramuzza, TRO 2017).

Between two times ``i`` and ``j`` the bias-corrected IMU samples are summarised as

    delta_R = prod_k Exp((w_k - b_g) dt_k)
    delta_v = sum_k delta_R_ik (a_k - b_a) dt_k
    delta_p = sum_k delta_v_ik dt_k + 1/2 delta_R_ik (a_k - b_a) dt_k^2

(Forster eq. 33-35), each sample held constant over its interval (zero-order hold, the
convention of the paper and of GTSAM). The covariance of the preintegration error
``(delta_phi, delta_v, delta_p)`` is propagated sample by sample with the discrete-time model of
Forster eq. 62-63, the continuous white-noise densities turned into discrete standard
deviations ``sigma_d = density / sqrt(dt)``. Optionally the bias random walk over the interval
is propagated too (a 15-state error ``(phi, v, p, b_g, b_a)`` whose bias part starts at zero),
which is what GTSAM's CombinedImuFactor does; :attr:`Preintegrated.covariance` is always the
9x9 marginal of the measurement part.

The bias Jacobians of Forster Appendix B (``d delta / d b``) come out of the same propagation,
so a back-end can correct the summary to first order when its bias estimate changes.

Gravity in the world is ``(0, 0, -GRAVITY)`` (world z up); see :func:`predict`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import GRAVITY, skew
from autonomy.options import option, validate


#: ICM-42688-P (the IMU of the Pixhawk 6C / 6X) gyroscope rate noise density, datasheet
#: DS-000347 rev. 1.7: 0.0028 deg/s/sqrt(Hz), in rad/s/sqrt(Hz).
ICM42688P_GYRO_NOISE_DENSITY = math.radians(0.0028)
#: ICM-42688-P accelerometer noise density, 70 ug/sqrt(Hz), in m/s^2/sqrt(Hz).
ICM42688P_ACCEL_NOISE_DENSITY = 70e-6 * GRAVITY


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise model (Kalibr / EuRoC ``sensor.yaml`` names and units).

    Defaults are the EuRoC ADIS16448 values of ``mav0/imu0/sensor.yaml``; the flight's
    ``[vins_imu]`` table defaults to :meth:`icm42688p`.
    """

    gyro_noise_density: float = option(1.6968e-4, ge=0.0, le=1.0,
                                       doc="gyroscope white noise, rad/s/sqrt(Hz)")
    accel_noise_density: float = option(2.0e-3, ge=0.0, le=10.0,
                                        doc="accelerometer white noise, m/s^2/sqrt(Hz)")
    gyro_random_walk: float = option(1.9393e-5, ge=0.0, le=1.0,
                                     doc="gyroscope bias random walk, rad/s^2/sqrt(Hz)")
    accel_random_walk: float = option(3.0e-3, ge=0.0, le=10.0,
                                      doc="accelerometer bias random walk, m/s^3/sqrt(Hz)")

    def __post_init__(self) -> None:
        validate(self)

    @classmethod
    def icm42688p(cls) -> "ImuNoise":
        """The flight controller's IMU of the Pixhawk 6C / 6X: the ICM-42688-P's datasheet
        white-noise densities; datasheets give no bias random walk, so EuRoC's (the figures
        VIO pipelines are most often tuned with) stand in."""
        return cls(ICM42688P_GYRO_NOISE_DENSITY, ICM42688P_ACCEL_NOISE_DENSITY)


@dataclass(frozen=True)
class Preintegrated:
    """A preintegrated IMU summary between two times, in the frame of the body at the first.

    ``covariance`` is the 9x9 covariance of the error ``(delta_phi, delta_v, delta_p)`` with
    ``delta_R_true = delta_R Exp(delta_phi)`` (right perturbation, Forster eq. 42).
    ``covariance_full`` is the 15x15 covariance including the bias random walk over the
    interval (zero bias blocks when it was not propagated). The ``d_*_d_b*`` fields are the
    bias Jacobians (Forster eq. 69-70) at the biases the summary was made with.
    """

    delta_R: np.ndarray
    delta_v: np.ndarray
    delta_p: np.ndarray
    dt_total: float
    covariance: np.ndarray
    covariance_full: np.ndarray
    bias_g: np.ndarray
    bias_a: np.ndarray
    d_R_d_bg: np.ndarray
    d_v_d_bg: np.ndarray
    d_v_d_ba: np.ndarray
    d_p_d_bg: np.ndarray
    d_p_d_ba: np.ndarray


def exp_and_right_jacobian(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp(phi_k)`` and ``J_r(phi_k)`` for every row of ``phi`` (N, 3), vectorised
    (``Exp(phi + d) ~ Exp(phi) Exp(J_r(phi) d)``)."""
    n = phi.shape[0]
    theta = np.linalg.norm(phi, axis=1)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    K2 = K @ K
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    eye = np.eye(3)[None]
    exp = eye + a[:, None, None] * K + b[:, None, None] * K2
    jr = eye - b[:, None, None] * K + c[:, None, None] * K2
    return exp, jr


def _as_samples(name: str, x, n: int | None = None) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N, 3) array, got shape {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name}: expected {n} rows, got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def _as_vec3(name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected a finite 3-vector, got {x!r}")
    return a


def gyro_axes_density(rotation, duration: float, scale_sigma: float,
                      cross_axis_sigma: float) -> np.ndarray:
    """The gyro's scale and cross-axis errors over one interval, as the white-noise density
    (squared, per axis, rad^2/s) that carries them: a weight, not an estimate.

    A gyro reads ``(I + M) omega``, ``M``'s diagonal (scale errors) of sigma ``s_s`` and its
    off-diagonal (cross-axis responses) of sigma ``s_c``. Over an interval of ``duration`` T
    whose rotation is ``theta = int omega dt`` the preintegrated rotation is off by ``M theta``
    (to first order), of variance per axis

        var_i = s_s^2 theta_i^2 + s_c^2 (|theta|^2 - theta_i^2),

    and white noise of density ``q`` integrates to ``q T`` over it, so ``q_i = var_i / T``.
    Errors of a few tenths of a percent are nothing at hover and, at a cruise's roll and pitch
    rates, about as large as the white noise or larger: docs/vins.md, "The gyro's axes as
    noise". ``M`` is one matrix for the whole flight, which the intervals' independent noise
    does not say; the smoother only learns to trust the camera's rotation over the gyro's
    where they turn.
    """
    theta = np.asarray(rotation, dtype=float).reshape(3)
    if not (duration > 0.0 and np.isfinite(theta).all()):
        raise ValueError(f"a rotation needs a positive duration and finite components, got "
                         f"{theta.tolist()} over {duration} s")
    squares = theta**2
    return (scale_sigma**2 * squares
            + cross_axis_sigma**2 * (squares.sum() - squares)) / duration


def about_vertical(density, up) -> np.ndarray:
    """The part about the vertical of a gyro noise ``density`` (per body axis, independent:
    :func:`gyro_axes_density`), as the 3x3 density ``(u^T diag(q) u) u u^T``, ``u`` = ``up``,
    the world's z in body axes (unit).

    The preintegrated rotation's error ``dtheta`` enters the velocity's as ``-R [f]x dtheta
    dt`` (Forster eq. 62), ``f`` the specific force, near ``g u`` in flight short of a hard
    acceleration. About the vertical, ``u x u = 0``: the heading's error leaves the velocity
    as it is. About a horizontal axis it tilts gravity into the velocity, so a gyro weighed
    less there weighs the interval's velocity and position less, and the scale goes free
    (docs/vins.md, "The gyro's axes about the vertical"); the tilt is held by gravity anyway,
    the heading by the gyro and the camera alone.
    """
    u = np.asarray(up, dtype=float).reshape(3)
    return float(u**2 @ np.asarray(density, dtype=float)) * np.outer(u, u)


def preintegrate(gyro, accel, dt, bias_g, bias_a, noise: ImuNoise | None = None, *,
                 bias_random_walk: bool = True) -> Preintegrated:
    """Preintegrate ``N`` IMU samples held over the intervals ``dt`` (seconds).

    ``gyro`` (N, 3) rad/s and ``accel`` (N, 3) m/s^2 are body-frame measurements; ``dt`` is a
    scalar (the same for every sample) or an (N,) array of positive intervals, sample ``k``
    being held for ``dt[k]``. ``bias_g``/``bias_a`` are subtracted from every sample.
    ``noise`` defaults to :class:`ImuNoise` (EuRoC). With ``bias_random_walk`` the bias drift
    over the interval is propagated into ``covariance_full`` and hence into ``covariance``.
    Raises ``ValueError`` on malformed or non-finite input.
    """
    noise = ImuNoise() if noise is None else noise
    gyro = _as_samples("gyro", gyro)
    n = gyro.shape[0]
    accel = _as_samples("accel", accel, n)
    if n == 0:
        raise ValueError("gyro: no samples to preintegrate")
    dts = np.asarray(dt, dtype=float)
    dts = np.full(n, float(dts)) if dts.ndim == 0 else dts.reshape(-1)
    if dts.shape != (n,) or not np.all(np.isfinite(dts)) or np.any(dts <= 0.0):
        raise ValueError(f"dt: expected a positive scalar or {n} positive intervals")
    bg = _as_vec3("bias_g", bias_g)
    ba = _as_vec3("bias_a", bias_a)

    I3 = np.eye(3)
    dR = np.eye(3)
    dv = np.zeros(3)
    dp = np.zeros(3)
    P = np.zeros((15, 15))
    # Jacobians of (phi, v, p) with respect to (b_g, b_a): Forster Appendix B.
    dR_dbg = np.zeros((3, 3))
    dv_dbg = np.zeros((3, 3))
    dv_dba = np.zeros((3, 3))
    dp_dbg = np.zeros((3, 3))
    dp_dba = np.zeros((3, 3))
    sg2 = noise.gyro_noise_density**2
    sa2 = noise.accel_noise_density**2
    swg2 = noise.gyro_random_walk**2 if bias_random_walk else 0.0
    swa2 = noise.accel_random_walk**2 if bias_random_walk else 0.0
    A = np.eye(15)
    steps, jacobians = exp_and_right_jacobian((gyro - bg) * dts[:, None])
    acc = accel - ba
    for k in range(n):
        h = dts[k]
        a = acc[k]
        step = steps[k]
        Jr = jacobians[k]
        Ra = dR @ skew(a)
        # Error-state transition (Forster eq. 62-63), extended by the bias states.
        A[0:3, 0:3] = step.T
        A[3:6, 0:3] = -Ra * h
        A[6:9, 0:3] = -0.5 * Ra * h * h
        A[6:9, 3:6] = I3 * h
        A[0:3, 9:12] = -Jr * h
        A[3:6, 12:15] = -dR * h
        A[6:9, 12:15] = -0.5 * dR * h * h
        P = A @ P @ A.T
        # White noise: sigma_d^2 = density^2 / h, entering through B (Forster eq. 63), so each
        # block is density^2 * h * (...) ; bias random walk: density^2 * h.
        P[0:3, 0:3] += sg2 * h * (Jr @ Jr.T)
        Rt = dR @ dR.T
        P[3:6, 3:6] += sa2 * h * Rt
        P[3:6, 6:9] += sa2 * 0.5 * h**2 * Rt
        P[6:9, 3:6] += sa2 * 0.5 * h**2 * Rt
        P[6:9, 6:9] += sa2 * 0.25 * h**3 * Rt
        P[9:12, 9:12] += swg2 * h * I3
        P[12:15, 12:15] += swa2 * h * I3
        # Bias Jacobians (before dR, dv are updated).
        dp_dba = dp_dba + dv_dba * h - 0.5 * dR * h * h
        dp_dbg = dp_dbg + dv_dbg * h - 0.5 * Ra @ dR_dbg * h * h
        dv_dba = dv_dba - dR * h
        dv_dbg = dv_dbg - Ra @ dR_dbg * h
        dR_dbg = step.T @ dR_dbg - Jr * h
        # The summary itself (Forster eq. 33-35, zero-order hold).
        acc_W = dR @ a
        dp = dp + dv * h + 0.5 * acc_W * h * h
        dv = dv + acc_W * h
        dR = dR @ step
    # Keep delta_R orthonormal after many products.
    u, _, vt = np.linalg.svd(dR)
    dR = u @ vt
    P = 0.5 * (P + P.T)
    return Preintegrated(dR, dv, dp, float(np.sum(dts)), P[0:9, 0:9].copy(), P, bg, ba,
                         dR_dbg, dv_dbg, dv_dba, dp_dbg, dp_dba)


def predict(state, pre: Preintegrated, gravity=GRAVITY
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body state at the end of ``pre`` from ``state = (R_W_B, v_W, p_W)`` at its start.

    ``gravity`` is the magnitude of world gravity ``(0, 0, -gravity)`` (world z up), or a
    3-vector taken as the world gravity vector itself (for a reference frame that is not
    exactly gravity-aligned, such as a motion-capture frame). Forster eq. 44:
    ``R_j = R_i dR``, ``v_j = v_i + g T + R_i dv``, ``p_j = p_i + v_i T + g T^2/2 + R_i dp``.
    """
    R, v, p = state
    R = np.asarray(R, dtype=float)
    v = _as_vec3("v", v)
    p = _as_vec3("p", p)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R: expected a finite 3x3 rotation")
    g = np.asarray(gravity, dtype=float)
    g = np.array([0.0, 0.0, -float(g)]) if g.ndim == 0 else _as_vec3("gravity", g)
    T = pre.dt_total
    return (R @ pre.delta_R,
            v + g * T + R @ pre.delta_v,
            p + v * T + 0.5 * g * T * T + R @ pre.delta_p)


def prediction_covariance(state, pre: Preintegrated, initial_covariance=None) -> np.ndarray:
    """9x9 covariance of the predicted ``(phi_j, v_j, p_j)`` errors, rotation error right-
    perturbed (``R_true = R Exp(phi)``) and v, p errors in the world frame.

    It is the preintegration covariance rotated into the world, plus, where given, the
    9x9 covariance ``initial_covariance`` of the start state's ``(phi_i, v_i, p_i)`` errors
    (same conventions) carried through :func:`predict` to first order.
    """
    R, _, _ = state
    R = np.asarray(R, dtype=float)
    T = pre.dt_total
    M = np.zeros((9, 9))
    M[0:3, 0:3] = np.eye(3)
    M[3:6, 3:6] = R
    M[6:9, 6:9] = R
    P = M @ pre.covariance @ M.T
    if initial_covariance is not None:
        S = np.asarray(initial_covariance, dtype=float)
        if S.shape != (9, 9):
            raise ValueError("initial_covariance: expected 9x9")
        F = np.zeros((9, 9))
        F[0:3, 0:3] = pre.delta_R.T
        F[3:6, 0:3] = -R @ skew(pre.delta_v)
        F[3:6, 3:6] = np.eye(3)
        F[6:9, 0:3] = -R @ skew(pre.delta_p)
        F[6:9, 3:6] = np.eye(3) * T
        F[6:9, 6:9] = np.eye(3)
        P = P + F @ S @ F.T
    return 0.5 * (P + P.T)
