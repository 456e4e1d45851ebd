"""Rotor drag as a speedometer (autonomy/vins/drag.py)."""

import math

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, V, X

from autonomy.geometry import GRAVITY, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.vins import VinsOptions
from autonomy.vins.backend import KeyframeState, PriorSigmas, SlidingWindowSmoother
from autonomy.vins.drag import drag_factor, drag_residual, mean_specific_force

from test_vins_smoother import IMU_DT, NOISE

DRAG = 0.3  # 1/s, the simulated vehicle's ([vehicle] drag)


def steady_cruise(yaw: float, velocity_W) -> np.ndarray:
    """The attitude ``R_W_B`` of a body cruising at ``velocity_W`` in still air: its thrust,
    along body z, balances gravity and the drag ``-DRAG v``, so body z is along
    ``g e_z + DRAG v``."""
    z = np.array([0.0, 0.0, GRAVITY]) + DRAG * np.asarray(velocity_W, dtype=float)
    z /= np.linalg.norm(z)
    x = np.cross(rot_z(yaw)[:, 1], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def cruise_preintegration(R_W_B, bias_a, seconds=0.1, bias_hat=np.zeros(3)):
    """A preintegration of a body at attitude ``R_W_B`` flying at a constant velocity: the
    accelerometer reads ``R^T g e_z`` (the thrust and the drag together) plus ``bias_a``."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY)
    pim = gtsam.PreintegratedCombinedMeasurements(
        params, gtsam.imuBias.ConstantBias(np.asarray(bias_hat, float), np.zeros(3)))
    force_B = R_W_B.T @ np.array([0.0, 0.0, GRAVITY]) + np.asarray(bias_a, dtype=float)
    for _ in range(int(round(seconds / IMU_DT))):
        pim.integrateMeasurement(force_B, np.zeros(3), IMU_DT)
    return pim


def test_mean_specific_force_is_the_reading_whatever_bias_was_assumed():
    R, bias = steady_cruise(0.7, [1.0, 0.5, 0.0]), np.array([0.02, -0.01, 0.03])
    pim = cruise_preintegration(R, bias, bias_hat=np.array([0.1, 0.2, -0.1]))
    assert np.allclose(mean_specific_force(pim), R.T @ [0.0, 0.0, GRAVITY] + bias, atol=1e-9)


def test_the_residual_vanishes_at_the_true_speed_and_grows_with_the_speed_error():
    v, bias = np.array([0.8, -0.6, 0.1]), np.array([0.03, 0.01, 0.0])
    R = steady_cruise(-1.2, v)
    force = mean_specific_force(cruise_preintegration(R, bias))  # no turn: the middle's
    assert np.allclose(drag_residual(force, DRAG, R, v, v, bias), 0.0, atol=1e-9)
    slower = drag_residual(force, DRAG, R, 0.9 * v, 0.9 * v, bias)
    assert np.linalg.norm(slower) == pytest.approx(
        DRAG * 0.1 * np.linalg.norm((R.T @ v)[:2]), rel=1e-6)


def test_the_factor_jacobians_match_finite_differences():
    pim = gtsam.PreintegratedCombinedMeasurements(  # turning: the middle's frame is not i's
        gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY))
    for _ in range(20):
        pim.integrateMeasurement(np.array([-0.3, 0.1, GRAVITY]), np.array([0.2, -0.1, 0.4]),
                                 IMU_DT)
    factor = drag_factor((X(0), V(0), V(1), B(0)), pim, DRAG, 0.02, 1e9)  # Huber's weight 1
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3(so3_exp(np.array([0.1, 0.2, 1.0]))),
                                    np.array([1.0, 2.0, 3.0])))
    values.insert(V(0), np.array([1.0, 0.5, 0.1]))
    values.insert(V(1), np.array([1.1, 0.4, 0.0]))
    values.insert(B(0), gtsam.imuBias.ConstantBias(np.array([0.05, -0.02, 0.01]), np.zeros(3)))
    dims = ((X(0), 6), (V(0), 3), (V(1), 3), (B(0), 6))
    analytic, _ = factor.linearize(values).jacobian()
    sigma = 0.02 / math.sqrt(pim.deltaTij())  # the analytic Jacobian is whitened
    error = factor.unwhitenedError(values)
    numeric = []
    for key, dim in dims:
        for d in range(dim):
            step = gtsam.VectorValues()
            for other, other_dim in dims:
                step.insert(other, np.eye(other_dim)[d] * 1e-6 if other == key
                            else np.zeros(other_dim))
            numeric.append((factor.unwhitenedError(values.retract(step)) - error) / 1e-6)
    assert np.allclose(analytic * sigma, np.array(numeric).T, atol=1e-5)


def cruise_without_landmarks(options: VinsOptions, bias_x: float, seconds: float = 8.0):
    """A smoother fed only IMU keyframes (every 0.1 s) of a level cruise at 1 m/s along x,
    whose accelerometer has a bias ``bias_x`` along x that the smoother starts without. Blind,
    it integrates the bias into its speed; nothing but the drag says how fast it goes.
    Returns the last velocity."""
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    velocity = np.array([1.0, 0.0, 0.0])
    R = steady_cruise(0.0, velocity)
    smoother.start(KeyframeState(0, 0.0, make_pose(R, np.zeros(3)), velocity, np.zeros(3),
                                 np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.01), 0.01, 0.02))
    rng = np.random.default_rng(3)
    force = mean_specific_force(cruise_preintegration(R, [bias_x, 0.0, 0.0]))
    for k in range(1, int(round(seconds / 0.1)) + 1):
        pim = smoother.preintegration()
        for _ in range(int(round(0.1 / IMU_DT))):
            noise = rng.normal(0.0, 6.9e-4 / math.sqrt(IMU_DT), 3)
            pim.integrateMeasurement(force + noise, np.zeros(3), IMU_DT)
        smoother.add_keyframe(k * 0.1, pim, [], None, airborne=True)
    return smoother.latest.velocity


def test_with_drag_a_cruise_keeps_its_speed_through_an_unknown_bias():
    """The IMU factors constrain only velocity changes, and an accelerometer bias the
    smoother does not know yet changes the velocity; the drag factor pins the speed, and so
    the bias."""
    options = dict(keyframe_prior_position_sigma=0.1, keyframe_prior_rotation_sigma=0.05)
    blind = cruise_without_landmarks(VinsOptions(**options), 0.03)
    with_drag = cruise_without_landmarks(VinsOptions(**options, drag_coefficient=DRAG), 0.03)
    assert abs(blind[0] - 1.0) > 0.1  # the bias integrated: 0.03 m/s^2 over 8 s
    assert abs(with_drag[0] - 1.0) < 0.03


def drag_factors_of(still: bool, airborne: bool, seconds: float = 0.1) -> int:
    """How many drag factors a smoother gives a keyframe interval of ``seconds`` on a floor
    tilted by 3 degrees (gravity leaks into the horizontal axes)."""
    options = VinsOptions(drag_coefficient=DRAG)
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    smoother.start(KeyframeState(0, 0.0, np.eye(4), np.zeros(3), np.zeros(3), np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.01), 0.01, 0.02))
    pim = smoother.preintegration()
    for _ in range(int(round(seconds / IMU_DT))):
        pim.integrateMeasurement(so3_exp(np.radians([3.0, 0.0, 0.0])).T @ [0, 0, GRAVITY],
                                 np.zeros(3), IMU_DT)
    keyframe = smoother._keyframe(1, seconds, [], None, airborne=airborne)
    graph, *_ = smoother._imu_step(keyframe, pim, still)
    return sum(isinstance(graph.at(i), gtsam.CustomFactor) for i in range(graph.size()))


def test_only_an_airborne_keyframe_gets_the_drag_factor():
    """On the ground contact forces, not the air, hold the body: standing still, or on the
    ground and not still (armed, or before the stillness window has filled), no factor; an
    interval longer than a gap's limit neither."""
    assert drag_factors_of(still=False, airborne=True) == 1
    assert drag_factors_of(still=True, airborne=False) == 0
    assert drag_factors_of(still=False, airborne=False) == 0
    assert drag_factors_of(still=False, airborne=True, seconds=1.0) == 0


def test_a_roll_during_the_interval_leaks_no_thrust_into_the_speed():
    """Rolling at 0.3 rad/s with the thrust along body z and no drag (at rest in the air's
    frame): in the interval's first frame the thrust leans 0.14 m/s^2 into the horizontal;
    taken at the interval's middle it does not, so the factor reads no speed."""
    pim = gtsam.PreintegratedCombinedMeasurements(
        gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY))
    for _ in range(20):
        pim.integrateMeasurement(np.array([0.0, 0.0, GRAVITY]), np.array([0.3, 0.0, 0.0]),
                                 IMU_DT)
    assert abs(mean_specific_force(pim)[1]) > 0.1  # the leak, in the first frame
    factor = drag_factor((X(0), V(0), V(1), B(0)), pim, DRAG, 0.02, 1e9)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3())
    values.insert(V(0), np.zeros(3))
    values.insert(V(1), np.zeros(3))
    values.insert(B(0), gtsam.imuBias.ConstantBias())
    # what is left is the preintegration's hold of each sample's attitude (half a sample: 7 mm/s^2)
    assert np.abs(factor.unwhitenedError(values)).max() < 0.01
