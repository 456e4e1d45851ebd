"""The vehicle's rotor drag coefficient fitted from a recorded flight: ``eval vio``'s
``drag_fit``, the value for ``[vins] drag_coefficient`` (autonomy/vins/drag.py).

In still air the accelerometer's horizontal body axes read ``f_xy = -k v_xy + c``, ``v`` the
body's velocity in its own axes and ``c`` a constant (the bias, and the cross-axis share of the
thrust). Between consecutive keyframes ``i`` and ``j`` of the VINS's own estimate the mean
reading is regressed on the mean body velocity ``R_i^T (v_i + v_j) / 2``, both axes together
with one offset each, by least squares: ``k`` is minus the slope. It needs no ground truth, so
a field engineer fits it on any recorded flight. It inherits the estimate's scale error: a
VINS whose speeds are 6 % short fits a ``k`` 6 % large (check ``eval vio``'s ``scale`` where
there is a truth). The flight must have flown at varied speeds along each axis (a cruise at
one speed cannot tell ``k`` from the offset), which ``speed_spread`` reports; with less than
:data:`MIN_SPEED_SPREAD` there is no fit. Intervals slower than :data:`MIN_SPEED` are left
out (standing on the ground, contact forces hold the body, not the air), and so are those
longer than :data:`MAX_INTERVAL_S` (a gap) or with a sample that is not finite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from autonomy.vins.drag import MAX_INTERVAL_S

#: Intervals whose mean speed is below this (m/s) are not fitted (on the ground, hovering).
MIN_SPEED = 0.2

#: Fewest intervals for a fit.
MIN_INTERVALS = 20

#: Least spread of the body-axis speeds about their means (m/s, the smaller axis's) for a fit.
MIN_SPEED_SPREAD = 0.1


@dataclass(frozen=True)
class DragFit:
    """``coefficient`` (1/s), ``offset_xy`` (m/s^2), the residuals' standard deviation
    (m/s^2) over ``intervals`` keyframe intervals, and ``speed_spread``, the standard
    deviation of the body-axis speeds about their own means (m/s), the smaller axis's."""

    coefficient: float
    offset_xy: tuple[float, float]
    residual_std: float
    intervals: int
    speed_spread: float

    def as_dict(self) -> dict:
        return {"coefficient_per_s": self.coefficient, "offset_xy": list(self.offset_xy),
                "residual_std": self.residual_std, "intervals": self.intervals,
                "speed_spread": self.speed_spread}


def fit_drag(keyframe_t, R_W_B, velocity_W, imu_t, accel) -> DragFit | None:
    """Fit the drag coefficient (module docstring) from keyframes at times ``keyframe_t``
    (seconds, increasing) with attitudes ``R_W_B`` (K, 3, 3) and velocities ``velocity_W``
    (K, 3), and the accelerometer's samples ``accel`` (N, 3) at ``imu_t`` (seconds, the same
    clock; each sample the mean over the period it closes). None with fewer than
    :data:`MIN_INTERVALS` usable intervals or too little spread of speeds."""
    forces, velocities = _interval_means(np.asarray(keyframe_t, float), np.asarray(R_W_B, float),
                                         np.asarray(velocity_W, float), np.asarray(imu_t, float),
                                         np.asarray(accel, float))
    if len(forces) < MIN_INTERVALS:
        return None
    spread = float(np.std(velocities, axis=0).min())
    if spread < MIN_SPEED_SPREAD:
        return None
    force, velocity = forces.reshape(-1), velocities.reshape(-1)
    axis = np.tile([0, 1], len(forces))
    design = np.column_stack([velocity, axis == 0, axis == 1]).astype(float)
    solution, *_ = np.linalg.lstsq(design, force, rcond=None)
    residual = force - design @ solution
    return DragFit(float(-solution[0]), (float(solution[1]), float(solution[2])),
                   float(np.std(residual)), len(forces), spread)


def _interval_means(keyframe_t, R_W_B, velocity_W, imu_t, accel):
    """The mean horizontal reading and mean body velocity of each usable keyframe interval
    (module docstring): two (M, 2) arrays."""
    first = np.searchsorted(imu_t, keyframe_t, side="right")  # samples in (t_i, t_i+1]
    forces, velocities = [], []
    for i in range(len(keyframe_t) - 1):
        samples = accel[first[i]:first[i + 1], :2]
        velocity_B = R_W_B[i].T @ (0.5 * (velocity_W[i] + velocity_W[i + 1]))
        if (len(samples) and np.isfinite(samples).all() and np.isfinite(velocity_B).all()
                and keyframe_t[i + 1] - keyframe_t[i] <= MAX_INTERVAL_S
                and np.linalg.norm(velocity_B) >= MIN_SPEED):
            forces.append(samples.mean(axis=0))
            velocities.append(velocity_B[:2])
    return np.reshape(forces, (-1, 2)), np.reshape(velocities, (-1, 2))
