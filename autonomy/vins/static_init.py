"""Static initialisation: gravity direction and gyro bias from an IMU window at rest.

On the ground before take-off the mean specific force is ``-g`` expressed in the body, i.e. it
points along world ``+z`` (world z up), and the mean gyro reading is the gyro bias. A window is
accepted only while it is still. Rotors spinning on the ground vibrate the IMU far above its
white-noise floor (EuRoC V1_01: 0.05-0.08 rad/s gyro std per sample), so stillness is judged on
short block averages (``average_s``, 50 ms by default), which remove the zero-mean vibration but
keep real motion: the standard deviations of the norms of the block-averaged gyro and accel must
stay below ``max_gyro_norm_std`` / ``max_accel_norm_std``, and the mean accel norm must be
within ``accel_norm_tolerance`` of ``gravity``. Thresholds can be set explicitly or derived
from a white-noise model with :meth:`StaticInitOptions.from_noise`.

The world yaw is unobservable from a static IMU: :func:`static_initialise` returns the
gravity-aligned ``R_W_B`` with zero yaw (``geometry.yaw_of(R_W_B) == 0``: the body x axis
projects onto world +x); it is the tilt-only rotation when the body x axis is vertical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from autonomy.geometry import GRAVITY, rot_z, so3_exp, yaw_of
from autonomy.options import option, validate


@dataclass(frozen=True)
class StaticInitOptions:
    """How a static window is chosen and judged still."""

    window_s: float = option(1.5, gt=0.0, le=60.0, doc="length of the static window, seconds "
                             "(the latest samples given are used)")
    min_samples: int = option(20, ge=2, doc="fewest IMU samples the window must hold")
    average_s: float = option(0.05, ge=0.0, le=1.0, doc="block-average length before the "
                              "stillness statistics, seconds (0: raw samples); removes rotor "
                              "vibration")
    max_gyro_norm_std: float = option(0.02, gt=0.0, doc="largest std of the block-averaged "
                                      "gyro norm, rad/s")
    max_accel_norm_std: float = option(0.15, gt=0.0, doc="largest std of the block-averaged "
                                       "accel norm, m/s^2")
    accel_norm_tolerance: float = option(0.5, gt=0.0, doc="largest |mean accel norm - gravity|,"
                                         " m/s^2 (accel bias and scale error included)")
    gravity: float = option(GRAVITY, gt=0.0, doc="local gravity magnitude, m/s^2")

    def __post_init__(self) -> None:
        validate(self)

    @classmethod
    def from_noise(cls, gyro_noise_density: float, accel_noise_density: float,
                   factor: float = 5.0, **kwargs) -> "StaticInitOptions":
        """Thresholds ``factor`` x the white-noise std of one block average
        (``density / sqrt(average_s)``, or ``density * sqrt(rate)`` when ``average_s`` is 0
        and ``rate_hz`` is given). Only right for an IMU without vibration."""
        rate_hz = kwargs.pop("rate_hz", None)
        base = cls(**kwargs)
        if base.average_s > 0.0:
            scale = 1.0 / math.sqrt(base.average_s)
        elif rate_hz is not None and rate_hz > 0:
            scale = math.sqrt(rate_hz)
        else:
            raise ValueError("from_noise: average_s is 0, give rate_hz")
        return replace(base, max_gyro_norm_std=factor * gyro_noise_density * scale,
                       max_accel_norm_std=factor * accel_noise_density * scale)


@dataclass(frozen=True)
class StaticInit:
    """A successful static initialisation.

    ``R_W_B``: body orientation, gravity-aligned world (z up), zero yaw. ``gyro_bias``: mean
    gyro, rad/s. ``gravity_B``: unit vector of world +z in the body (mean specific force
    direction). ``accel_norm``: mean accel norm, m/s^2. ``t_start``/``t_end``: the window used;
    ``samples``: its sample count; ``gyro_norm_std``/``accel_norm_std``: its stillness statistics.
    """

    R_W_B: np.ndarray
    gyro_bias: np.ndarray
    gravity_B: np.ndarray
    accel_norm: float
    t_start: float
    t_end: float
    samples: int
    gyro_norm_std: float
    accel_norm_std: float


@dataclass(frozen=True)
class NotStill:
    """The window was not usable (motion, too short, implausible gravity); wait and retry."""

    reason: str
    t_start: float
    t_end: float
    gyro_norm_std: float = float("nan")
    accel_norm_std: float = float("nan")


def gravity_aligned_rotation(up_B: np.ndarray) -> np.ndarray:
    """``R_W_B`` with ``R_W_B @ up_B == e_z`` and zero yaw (body x toward world +x)."""
    u = np.asarray(up_B, dtype=float)
    u = u / np.linalg.norm(u)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, ez)
    s = float(np.linalg.norm(axis))
    c = float(np.dot(u, ez))
    if s < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R = so3_exp(axis / s * math.atan2(s, c))
    if math.hypot(R[0, 0], R[1, 0]) > 1e-9:
        R = rot_z(-yaw_of(R)) @ R
    return R


def _block_mean(x: np.ndarray, t: np.ndarray, average_s: float) -> np.ndarray:
    if average_s <= 0.0:
        return x
    idx = np.floor((t - t[0]) / average_s).astype(np.int64)
    counts = np.bincount(idx)
    sums = np.stack([np.bincount(idx, weights=x[:, i]) for i in range(3)], axis=1)
    keep = counts > 0
    return sums[keep] / counts[keep, None]


def static_initialise(t, gyro, accel, options: StaticInitOptions | None = None
                      ) -> StaticInit | NotStill:
    """Initialise from the latest ``options.window_s`` seconds of IMU samples.

    ``t`` (N,) seconds, increasing; ``gyro`` (N, 3) rad/s; ``accel`` (N, 3) m/s^2, body frame.
    Returns :class:`StaticInit`, or :class:`NotStill` with a reason when the window is too short
    or not still (the caller waits for more samples). Raises ``ValueError`` on malformed input:
    mismatched shapes, NaN/inf, or non-increasing times.
    """
    o = StaticInitOptions() if options is None else options
    t = np.asarray(t, dtype=float).reshape(-1) if np.ndim(t) <= 1 else np.asarray(t, float)
    gyro = np.asarray(gyro, dtype=float)
    accel = np.asarray(accel, dtype=float)
    if t.ndim != 1:
        raise ValueError(f"t: expected a 1-D array, got shape {t.shape}")
    for name, a in (("gyro", gyro), ("accel", accel)):
        if a.ndim != 2 or a.shape != (t.shape[0], 3):
            raise ValueError(f"{name}: expected shape ({t.shape[0]}, 3), got {a.shape}")
    for name, a in (("t", t), ("gyro", gyro), ("accel", accel)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: contains NaN or infinite values")
    if t.shape[0] < 2:
        raise ValueError(f"t: need at least 2 samples, got {t.shape[0]}")
    if np.any(np.diff(t) <= 0.0):
        raise ValueError("t: times must be strictly increasing")

    t_end = float(t[-1])
    # each sample holds until the next (zero-order hold), the last one for a typical period
    covered = t_end - float(t[0]) + float(np.median(np.diff(t)))
    if covered < o.window_s * (1.0 - 1e-6):
        return NotStill(f"only {covered:.3f} s of IMU, need {o.window_s:.3f} s",
                        float(t[0]), t_end)
    m = t >= t_end - o.window_s * (1.0 + 1e-9)
    tw, gw, aw = t[m], gyro[m], accel[m]
    t_start = float(tw[0])
    if tw.shape[0] < o.min_samples:
        return NotStill(f"{tw.shape[0]} samples in the window, need {o.min_samples}",
                        t_start, t_end)
    gb = _block_mean(gw, tw, o.average_s)
    ab = _block_mean(aw, tw, o.average_s)
    g_std = float(np.std(np.linalg.norm(gb, axis=1)))
    a_std = float(np.std(np.linalg.norm(ab, axis=1)))
    if g_std > o.max_gyro_norm_std:
        return NotStill(f"rotating: gyro norm std {g_std:.4f} rad/s > {o.max_gyro_norm_std:g}",
                        t_start, t_end, g_std, a_std)
    if a_std > o.max_accel_norm_std:
        return NotStill(f"accelerating: accel norm std {a_std:.4f} m/s^2 > "
                        f"{o.max_accel_norm_std:g}", t_start, t_end, g_std, a_std)
    mean_a = aw.mean(axis=0)
    norm = float(np.linalg.norm(mean_a))
    if abs(norm - o.gravity) > o.accel_norm_tolerance:
        return NotStill(f"mean accel norm {norm:.3f} m/s^2 is not gravity ({o.gravity:.3f})",
                        t_start, t_end, g_std, a_std)
    up = mean_a / norm
    return StaticInit(gravity_aligned_rotation(up), gw.mean(axis=0), up, norm, t_start, t_end,
                      int(tw.shape[0]), g_std, a_std)
