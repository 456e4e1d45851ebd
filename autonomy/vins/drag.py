"""Rotor drag: the accelerometer as a speedometer, a factor that keeps the scale from drifting.

A multirotor's rotors tilt their thrust against the air they move through: in free flight the
body's specific force is the thrust along body z plus a drag against its air-relative
velocity, to first order linear in it (the rotor "momentum drag": Leishman, Macdonald, Beard
and McLain, "Quadrotors and accelerometers: state estimation with an improved dynamic model",
IEEE Control Systems 34(1), 2014; PX4's EKF2 fuses the same signal,
``src/modules/ekf2/EKF/aid_sources/drag/drag_fusion.cpp``, with ``EKF2_MCOEF``). So the
accelerometer's two horizontal body axes read, in still air,

    f_xy = -k P R^T v + b_a,xy + n,      P = [[1, 0, 0], [0, 1, 0]],

with ``k`` the drag per unit mass (1/s), ``R`` and ``v`` the body's attitude and world
velocity, ``b_a`` the accelerometer bias. The IMU factors constrain only velocity *changes*;
in a cruise at constant speed the accelerations say nothing of the speed, and the scale of
the visual map (which sets it) may wander (docs/vins.md, the mine's scale). This reading pins
the speed itself, at every keyframe.

Between keyframes ``i`` and ``j`` (``dt`` apart), the mean specific force in body frame
``i`` is ``delta_v_ij / dt`` of the preintegration plus the bias it was integrated with. The
body turns by ``Delta R_ij`` meanwhile, and in frame ``i`` the thrust (g along body z) would
lean into the horizontal axes by ``g`` times half that turn, 0.14 m/s^2 at 0.3 rad/s over
0.1 s: so force and attitude are both taken at the interval's middle, ``D = Exp(Log(Delta
R_ij) / 2)``, ``f_m = D^T f_i``, ``R_m = R_i D``. The factor's residual on ``X(i), V(i),
V(j), B(i)`` uses the mean velocity ``(v_i + v_j) / 2``:

    e = P f_m + k P R_m^T (v_i + v_j) / 2 - P b_a,i.

Its noise: the accelerometer's white noise and what remains of the rotors' vibration after
averaging over ``dt``, ``sigma = noise / sqrt(dt)`` with ``noise`` the option
``drag_noise`` (m/s^2 sqrt(s)), under a Huber loss (a gust, a touch of a wall). The model
holds in free flight only: on the ground the contact forces, not the air, hold the body (on a
3° slope the accelerometer's 0.5 m/s^2 would read as 1.7 m/s), so the smoother adds the
factor only to keyframes the estimator calls airborne (:mod:`autonomy.vins.estimator`).
Intervals longer than :data:`MAX_INTERVAL_S` (after a gap) get none: the endpoints' mean is
then no longer the interval's velocity.
"""

from __future__ import annotations

import math
from functools import partial

import gtsam
import numpy as np

from autonomy.geometry import skew, so3_exp, so3_log

#: Selects the body's horizontal axes (x forward, y to the side) from a 3-vector.
HORIZONTAL = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

#: Longest keyframe interval given a drag factor, seconds.
MAX_INTERVAL_S = 0.5


def mean_specific_force(pim: gtsam.PreintegratedCombinedMeasurements) -> np.ndarray:
    """The mean specific force over a preintegration, in the body frame at its start (module
    docstring), m/s^2, the bias it was integrated with added back."""
    return np.asarray(pim.deltaVij()) / pim.deltaTij() + \
        np.asarray(pim.biasHat().accelerometer())


def half_turn(pim: gtsam.PreintegratedCombinedMeasurements) -> np.ndarray:
    """``D = Exp(Log(Delta R_ij) / 2)``: the body's rotation from the interval's start to its
    middle, by the gyro."""
    return so3_exp(0.5 * so3_log(pim.deltaRij().matrix()))


def drag_residual(force_m: np.ndarray, k: float, R_m: np.ndarray, v_i: np.ndarray,
                  v_j: np.ndarray, bias_a: np.ndarray) -> np.ndarray:
    """``e`` of the module docstring, (2,): ``force_m`` and ``R_m`` at the interval's middle."""
    velocity_B = R_m.T @ (0.5 * (v_i + v_j))
    return HORIZONTAL @ force_m + k * (HORIZONTAL @ velocity_B) - HORIZONTAL @ bias_a


def drag_factor(keys: tuple[int, int, int, int], pim: gtsam.PreintegratedCombinedMeasurements,
                k: float, noise: float, huber_k: float) -> gtsam.CustomFactor:
    """The drag factor on ``keys = (X(i), V(i), V(j), B(i))`` for the preintegration ``pim``
    between keyframes ``i`` and ``j`` (module docstring)."""
    D = half_turn(pim)
    force_m = D.T @ mean_specific_force(pim)
    sigma = noise / math.sqrt(pim.deltaTij())
    model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
                                           gtsam.noiseModel.Isotropic.Sigma(2, sigma))
    return gtsam.CustomFactor(model, list(keys), partial(_evaluate, force_m, D, k))


def _evaluate(force_m: np.ndarray, D: np.ndarray, k: float, factor: gtsam.CustomFactor,
              values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
    """The residual and, when asked, its Jacobians in GTSAM's tangent spaces: Pose3 retracts
    as ``R Exp(w)`` (rotation first), so ``d(D^T R^T v)/dw = D^T [R^T v]_x``; ConstantBias's
    tangent is accelerometer then gyroscope."""
    keys = factor.keys()
    R_i = values.atPose3(keys[0]).rotation().matrix()
    v_i, v_j = values.atVector(keys[1]), values.atVector(keys[2])
    bias_a = values.atConstantBias(keys[3]).accelerometer()
    if jacobians is not None:
        velocity_i = R_i.T @ (0.5 * (v_i + v_j))
        jacobians[0] = np.hstack([k * HORIZONTAL @ D.T @ skew(velocity_i), np.zeros((2, 3))])
        jacobians[1] = jacobians[2] = 0.5 * k * HORIZONTAL @ D.T @ R_i.T
        jacobians[3] = np.hstack([-HORIZONTAL, np.zeros((2, 3))])
    return drag_residual(force_m, k, R_i @ D, v_i, v_j, bias_a)
