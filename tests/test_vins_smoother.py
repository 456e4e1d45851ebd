"""The sliding-window smoother and its resets. Position and yaw are unobservable; in a window
with no landmark the biases are known only from their priors too, and once the window's
information on them is about 1e8 times weaker than its strongest, GTSAM's Cholesky calls the
system indeterminate (a reset) in each elimination order tried (tests/test_vins_fixed_lag.py
for windows with landmarks). The gauge hold (``hold_gauge``, the default) keeps it, and so do
the loose keyframe priors (``keyframe_prior_position_sigma``, off by default: docs/vins.md). A
rebuild, and each move of the hold, pins a keyframe, and its uncertainty is carried on
(``GaugeAnchor``)."""

import math

import numpy as np
import pytest
from gtsam.symbol_shorthand import V, X

from autonomy.geometry import GRAVITY, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.trajectory import pose_error_body
from autonomy.vins import ImuNoise, VinsOptions
from autonomy.vins.preintegration import about_vertical, gyro_axes_density
from autonomy.vins.backend import (
    GaugeAnchor, KeyframeState, PriorSigmas, SlidingWindowSmoother, imu_params,
    released_covariance,
)

#: The estimator's noise model of the simulated vehicle's IMU (config/sim.toml [vins_imu]).
NOISE = ImuNoise(4.8869e-05, 6.865e-04, 1.9393e-05, 3e-3)
IMU_DT = 0.005


def turning_in_place_unseeing(options: VinsOptions, seconds: float = 20.0,
                              keyframe_interval: float = 0.05, seed: int = 0,
                              gauge_sigmas: tuple[float, float] = (0.005, 0.01),
                              gap: tuple[float, float] | None = None):
    """A smoother fed keyframes with no landmark while the IMU turns in place at 0.5 rad/s,
    as over a corner: the keyframes come fast (the front-end's parallax is the rotation's) and
    nothing but the IMU joins them. It starts with the yaw and position sigmas
    ``gauge_sigmas``; no keyframe comes inside ``gap`` = (a, b) seconds, the IMU integrated
    across it (a camera that stalls). Yields the smoother after each keyframe."""
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    yaw_sigma, position_sigma = gauge_sigmas
    smoother.start(KeyframeState(0, 0.0, np.eye(4), np.zeros(3), np.zeros(3), np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, yaw_sigma),
                                                position_sigma, 0.02))
    rng = np.random.default_rng(seed)
    steps = int(round(keyframe_interval / IMU_DT))
    pim = smoother.preintegration()
    for k in range(1, int(round(seconds / keyframe_interval)) + 1):
        for _ in range(steps):
            gyro = np.array([0.0, 0.0, 0.5]) + rng.normal(0.0, 4.9e-5 / math.sqrt(IMU_DT), 3)
            accel = np.array([0.0, 0.0, GRAVITY]) + rng.normal(0.0, 6.9e-4 / math.sqrt(IMU_DT),
                                                               3)
            pim.integrateMeasurement(accel, gyro, IMU_DT)
        t = k * keyframe_interval
        if gap is not None and gap[0] < t < gap[1]:
            continue
        smoother.add_keyframe(t, pim, [], None)
        pim = smoother.preintegration()
        yield smoother


def resets_turning_in_place_unseeing(options: VinsOptions) -> int:
    for smoother in turning_in_place_unseeing(options):
        pass
    return smoother.resets


#: Only the first keyframe's prior holds the gauge, fading (the smoother before the hold).
UNHELD = VinsOptions(hold_gauge=False)


def test_a_window_without_landmarks_stays_well_posed_with_the_hold_or_the_loose_priors():
    assert resets_turning_in_place_unseeing(VinsOptions()) == 0
    assert resets_turning_in_place_unseeing(VinsOptions(
        hold_gauge=False, keyframe_prior_position_sigma=0.1,
        keyframe_prior_rotation_sigma=0.05)) == 0


def test_without_either_the_same_window_is_rebuilt():
    """What they are for: the same IMU-only window meets an indeterminate linear system
    within 20 s when nothing refreshes its absolute pose information."""
    assert resets_turning_in_place_unseeing(UNHELD) >= 1


def held_joint(information: np.ndarray, prior_covariance: np.ndarray) -> np.ndarray:
    """The covariance of ``(x, y)`` with information ``information`` and a prior on ``y``
    (the last ``len(prior_covariance)`` dimensions)."""
    held = information.copy()
    m = len(prior_covariance)
    held[-m:, -m:] += np.linalg.inv(prior_covariance)
    return np.linalg.inv(held)


def test_a_prior_taken_back_out_leaves_the_covariance_without_it():
    """Woodbury's identity: a 3-dimensional ``x`` and a 6-dimensional ``y`` weakly held (their
    information 1e-2 to 10 against the prior's 1e4 to 1e6): the covariance of ``x`` with the
    prior, released, is the one without it."""
    rng = np.random.default_rng(3)
    root = rng.normal(size=(9, 9)) * np.r_[[3.0] * 3, [0.1] * 6]
    information = root @ root.T + 1e-2 * np.eye(9)
    prior = np.diag([1.0, 1.0, 0.005 ** 2, 0.01 ** 2, 0.01 ** 2, 0.01 ** 2])
    released = released_covariance(held_joint(information, prior), prior)
    expected = np.linalg.inv(information)[:3, :3]
    np.testing.assert_allclose(released, expected, rtol=1e-6)
    assert np.all(np.diag(held_joint(information, prior))[:3] < 0.5 * np.diag(expected))


def test_a_prior_on_what_nothing_else_holds_cannot_be_taken_out():
    """Without the prior the problem has no bound in ``y``: the covariance is unknown (NaN),
    never the held one nor a negative one."""
    information = np.zeros((9, 9))
    information[:3, :3] = np.eye(3)
    prior = np.diag([1.0, 1.0, 0.005 ** 2, 0.01 ** 2, 0.01 ** 2, 0.01 ** 2])
    assert np.isnan(released_covariance(held_joint(information, prior), prior)).all()


def assert_same_covariance(actual: np.ndarray, expected: np.ndarray, tolerance: float = 1e-3):
    """Equal to ``tolerance`` of each entry's scale ``sqrt(P_ii P_jj)``."""
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    np.testing.assert_allclose(actual / scale, expected / scale, atol=tolerance)


def test_the_held_window_reports_the_covariance_of_the_window_without_the_hold():
    """The hold changes the covariance the window computes (every pose a millimetre from the
    held one), not the one it reports: taken out again, the blind window's pose and velocity
    covariances are those of the same window held by its fading first prior alone, metres
    after 5 s of its accelerometer bias, through some fifty moves of the hold."""
    held, unheld = (turning_in_place_unseeing(options, seconds=5.0)
                    for options in (VinsOptions(), UNHELD))
    holds = set()
    for a, b in zip(held, unheld):
        holds.add(a.gauge_keyframe)
        assert a.resets == b.resets == 0
        assert_same_covariance(a.pose_covariance(), b.pose_covariance())
        assert_same_covariance(a.velocity_covariance(), b.velocity_covariance())
    assert len(holds) > 40  # a move with (nearly) every keyframe once the window is full
    assert np.all(np.sqrt(np.diag(a.pose_covariance())[3:]) > 1.0)


def test_the_pose_and_velocity_covariances_are_the_marginals_of_each_alone():
    """Both come from one joint marginal (the velocity's at no cost beside the pose's): each
    block is the marginal iSAM2 computes for its variable alone, in the unheld window."""
    for smoother in turning_in_place_unseeing(UNHELD, seconds=2.0):
        k, isam = smoother.latest.index, smoother._smoother
        assert_same_covariance(smoother.pose_covariance(), isam.marginalCovariance(X(k)), 1e-6)
        assert_same_covariance(smoother.velocity_covariance(), isam.marginalCovariance(V(k)),
                               1e-6)
    assert smoother.resets == 0


def test_a_keyframe_gap_longer_than_the_window_lets_the_hold_go_and_takes_it_up_again():
    """A camera that stalls for 2 s, longer than the 1.5 s window: the keyframe after it
    marginalises the whole window, the held keyframe with it. The hold's prior goes before
    (no marginal may keep it), the next keyframe takes the hold up again, and nothing is
    rebuilt. The covariance is the unheld window's up to the gap (measured: 1.59 m at 4 s);
    the unheld window is rebuilt at the next keyframe, while the held one's goes on growing
    (2.5 m horizontally at 5 s)."""
    held, unheld = (turning_in_place_unseeing(options, seconds=5.0, gap=(2.0, 4.0))
                    for options in (VinsOptions(), UNHELD))
    holds, sigmas = [], []
    for a, b in zip(held, unheld):
        holds.append(a.gauge_keyframe)
        sigmas.append(np.sqrt(np.diag(a.pose_covariance())[3:]))
        assert a.resets == 0
        if b.resets == 0:
            assert_same_covariance(a.pose_covariance(), b.pose_covariance())
    assert b.resets == 1
    after_gap = holds.index(None) + 1  # let go at the keyframe after the gap
    assert all(hold is not None for hold in holds[after_gap:])
    assert np.all(np.diff(np.array(sigmas), axis=0) > -1e-6) and np.all(sigmas[-1][:2] > 2.0)


def first_rebuild_s(gauge_sigmas: tuple[float, float]) -> float | None:
    for smoother in turning_in_place_unseeing(UNHELD, seconds=10.0,
                                              gauge_sigmas=gauge_sigmas):
        if smoother.resets:
            return smoother.latest.t
    return None


def test_the_weaker_the_gauge_the_sooner_the_rebuild():
    """Why an IMU-only window is rebuilt (docs/vins.md, the resets): not a window gone wrong,
    but the gauge's information, position and yaw, too weak beside the rest for GTSAM's
    Cholesky (tests/test_vins_fixed_lag.py). Started at 1 cm the window lasts 6 s; started
    at 10 cm, not one keyframe."""
    tight, loose = first_rebuild_s((0.005, 0.01)), first_rebuild_s((0.01, 0.1))
    assert tight is not None and tight > 5.0
    assert loose is not None and loose < 0.5


def test_a_rebuild_keeps_the_uncertainty_of_the_keyframe_it_starts_from():
    """The rebuilt window pins the last good keyframe to 1 cm, but its position was known to
    metres after seconds blind: the reported covariance must not shrink to the pin's."""
    position_sigma = []
    for smoother in turning_in_place_unseeing(UNHELD):
        sigma = np.sqrt(np.diag(smoother.pose_covariance())[3:])
        if smoother.resets:
            break
        position_sigma.append(sigma)
    assert smoother.resets == 1
    assert np.all(sigma >= position_sigma[-1]), (sigma, position_sigma[-1])
    assert np.all(position_sigma[-1] > 0.1)



def test_a_covariance_kept_for_a_period_is_refreshed_when_it_ages_and_after_a_rebuild():
    """The odometry's covariance (``covariance_period_s``): kept from keyframe to keyframe
    until it is that old, then the new keyframe's own, and never the old window's after a
    rebuild, whose covariance has just grown by the anchor's."""
    period, kept, kept_since, resets, refreshes = 0.5, None, None, 0, 0
    for smoother in turning_in_place_unseeing(UNHELD, seconds=10.0):
        before, kept = kept, smoother.pose_covariance(period)
        t = smoother.latest.t
        if smoother.resets != resets or kept_since is None or t - kept_since >= period - 1e-9:
            assert kept is not before
            kept_since, resets, refreshes = t, smoother.resets, refreshes + 1
        else:
            assert kept is before
    assert resets >= 1  # a rebuild was met (blind, it comes within seconds)
    assert refreshes < 0.3 * 10.0 / 0.05  # 200 keyframes, refreshed at most every 0.5 s or reset


def test_the_anchor_covariance_is_that_of_the_rigid_motion_it_stands_for():
    """Yaw and position errors of the anchor drawn from its covariance, applied as the rigid
    motion about it that they are, move a keyframe 12 m away by the covariance it reports
    (the yaw's lever arm included)."""
    rng = np.random.default_rng(1)
    anchor_pose = make_pose(so3_exp(np.array([0.05, -0.03, 2.0])), np.array([1.0, 2.0, 1.5]))
    root = np.r_[[0.01] * 3, [0.2] * 3][:, None] * rng.normal(size=(6, 6))
    anchor = GaugeAnchor.at(anchor_pose, root @ root.T)
    keyframe = make_pose(so3_exp(np.array([-0.04, 0.02, -1.0])), np.array([9.0, -7.0, 2.0]))
    p_g = anchor.position_W
    errors = []
    for dpsi, *dp in rng.multivariate_normal(np.zeros(4), anchor.covariance, size=20000):
        moved = make_pose(rot_z(dpsi) @ keyframe[:3, :3],
                          p_g + rot_z(dpsi) @ (keyframe[:3, 3] - p_g) + dp)
        errors.append(pose_error_body(keyframe, moved))
    expected = anchor.pose_covariance(keyframe)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected))) + 1e-12
    assert np.allclose(np.cov(np.array(errors).T) / scale, expected / scale, atol=0.05)


def test_the_white_noise_and_the_bias_walk_are_scaled_apart():
    """``imu_noise_scale`` widens the white noise the rotors add to, ``gyro_noise_scale`` the
    gyro's on top of it, ``imu_bias_walk_scale`` the bias walk (docs/vins.md, "The bias walk
    at its datasheet value", "The gyro's weight"); the smoother's
    preintegration takes all three, by default the densities twice."""
    params = imu_params(NOISE, 2.0, 1.0)
    eye = np.eye(3)
    assert np.allclose(params.getAccelerometerCovariance(), (2.0 * 6.865e-4) ** 2 * eye)
    assert np.allclose(params.getGyroscopeCovariance(), (2.0 * 4.8869e-05) ** 2 * eye)
    assert np.allclose(params.getBiasAccCovariance(), 3e-3 ** 2 * eye)
    assert np.allclose(params.getBiasOmegaCovariance(), 1.9393e-05 ** 2 * eye)
    smoother = SlidingWindowSmoother(
        PinholeCamera(640, 480, 400.0, 400.0, 320.0, 240.0), np.eye(4), NOISE,
        VinsOptions(imu_noise_scale=3.0, imu_bias_walk_scale=0.5, gyro_noise_scale=4.0))
    assert np.allclose(smoother.params.getAccelerometerCovariance(), (3.0 * 6.865e-4) ** 2 * eye)
    assert np.allclose(smoother.params.getGyroscopeCovariance(), (12.0 * 4.8869e-05) ** 2 * eye)
    assert np.allclose(smoother.params.getBiasAccCovariance(), (0.5 * 3e-3) ** 2 * eye)
    default = SlidingWindowSmoother(
        PinholeCamera(640, 480, 400.0, 400.0, 320.0, 240.0), np.eye(4), NOISE, VinsOptions())
    assert np.allclose(default.params.getBiasAccCovariance(), (2.0 * 3e-3) ** 2 * eye)
    assert np.allclose(default.params.getAccelerometerCovariance(), (2.0 * 6.865e-4) ** 2 * eye)
    assert np.allclose(default.params.getGyroscopeCovariance(), (2.0 * 4.8869e-05) ** 2 * eye)


def started_smoother(options: VinsOptions) -> SlidingWindowSmoother:
    """A smoother started level at the origin, at rest, with ``options``."""
    smoother = SlidingWindowSmoother(PinholeCamera(640, 480, 400.0, 400.0, 320.0, 240.0),
                                     np.eye(4), NOISE, options)
    smoother.start(KeyframeState(0, 0.0, np.eye(4), np.zeros(3), np.zeros(3), np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.005), 0.01, 0.02))
    return smoother


def turn_covariance(smoother: SlidingWindowSmoother, rate) -> np.ndarray:
    """The preintegrated covariance (rotation, position, velocity) of 0.1 s turning at
    ``rate`` (rad/s, body axes) with the accelerometer reading gravity's reaction."""
    gyro, dt = np.tile(rate, (20, 1)), np.full(20, IMU_DT)
    pim = smoother.preintegration(gyro, dt)
    for sample, step in zip(gyro, dt):
        pim.integrateMeasurement(np.array([0.0, 0.0, GRAVITY]), sample, step)
    return pim.preintMeasCov()[:9, :9]


def test_gyro_axes_noise_weighs_only_the_turning_intervals_gyro_less():
    """With ``gyro_axes_noise`` the preintegration of an interval that turns carries the
    axes' errors over that turn in its rotation's covariance, on top of the white noise; one
    that does not turn, and every interval without the option, is weighed as before."""
    on = started_smoother(VinsOptions(gyro_axes_noise=True))
    off = started_smoother(VinsOptions())

    def rotation_variance(smoother, rate):
        return np.diag(turn_covariance(smoother, rate))[:3]

    white = rotation_variance(off, np.zeros(3))
    turn = np.array([0.0, 1.0, 2.0])  # rad/s: a pitch and a yaw over 0.1 s
    added = gyro_axes_density(turn * 0.1, 0.1, 0.005, 0.014) * 0.1
    assert added[0] > 1e3 * white[0]  # the turn's part outweighs the white noise
    np.testing.assert_allclose(rotation_variance(on, turn), white + added, rtol=0.02)
    np.testing.assert_allclose(rotation_variance(on, np.zeros(3)), white, rtol=1e-9)
    np.testing.assert_allclose(rotation_variance(off, turn), white, rtol=0.02)


def test_gyro_axes_noise_about_the_vertical_weighs_the_heading_and_leaves_the_velocity():
    """About the vertical (``gyro_axes_noise_axes = "vertical"``), a level yaw's interval
    carries the axes' errors in its heading's variance alone, and its velocity and position
    are weighed as without the option: gravity's reaction along the vertical crosses a
    heading error to nothing. About the body's three axes the cross-axis errors tilt gravity
    into the velocity, whose variance grows many times: the scale's weight lost
    (docs/vins.md, "The gyro's axes about the vertical")."""
    yaw = np.array([0.0, 0.0, 2.0])
    white = turn_covariance(started_smoother(VinsOptions()), yaw)
    vertical = turn_covariance(started_smoother(VinsOptions(
        gyro_axes_noise=True, gyro_axes_noise_axes="vertical")), yaw)
    body = turn_covariance(started_smoother(VinsOptions(gyro_axes_noise=True)), yaw)
    heading = (0.005 * 0.2) ** 2  # the gyro's scale error over the 0.2 rad turned
    assert vertical[2, 2] == pytest.approx(white[2, 2] + heading, rel=0.02)
    np.testing.assert_allclose(vertical[:2, :2], white[:2, :2], rtol=1e-6)
    np.testing.assert_allclose(vertical[3:, 3:], white[3:, 3:], rtol=1e-6)
    horizontal_velocity = np.diag(white)[6:8]
    assert (np.diag(body)[6:8] > 10.0 * horizontal_velocity).all()


def test_gyro_axes_noise_about_the_vertical_follows_the_tilt():
    """The vertical in body axes is the latest keyframe's: tilted, the density lies along
    its world z, and its variance there is each axis' weighed by the vertical's share."""
    density = np.array([1.0, 4.0, 9.0])
    up = np.array([0.0, math.sin(0.3), math.cos(0.3)])
    matrix = about_vertical(density, up)
    assert up @ matrix @ up == pytest.approx(4.0 * math.sin(0.3) ** 2 + 9.0 * math.cos(0.3) ** 2)
    np.testing.assert_allclose(matrix @ np.cross(up, [1.0, 0.0, 0.0]), 0.0, atol=1e-12)
    np.testing.assert_allclose(about_vertical(density, [0.0, 0.0, 1.0]), np.diag([0, 0, 9.0]))


def swaying_smoother(times: np.ndarray, options: VinsOptions) -> SlidingWindowSmoother:
    """A smoother with keyframes at ``times``, each interval's IMU preintegrated from a
    body that sways along x (``a = sin(2 pi t)`` m/s^2, level, no turn) over exactly that
    interval, from rest at ``times[0]``."""
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    smoother.start(KeyframeState(0, float(times[0]), np.eye(4), np.zeros(3), np.zeros(3),
                                 np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.005), 0.01, 0.02))
    for t0, t1 in zip(times, times[1:]):
        smoother.add_keyframe(float(t1), swaying_pim(smoother, t0, t1), [], None)
    return smoother


def swaying_pim(smoother: SlidingWindowSmoother, t0: float, t1: float):
    """The swaying body's IMU from ``t0`` to ``t1``, sampled at the middle of each step."""
    pim = smoother.preintegration()
    edges = np.linspace(t0, t1, max(2, int(round((t1 - t0) / IMU_DT)) + 1))
    for a, b in zip(edges, edges[1:]):
        middle = 0.5 * (a + b)
        pim.integrateMeasurement([math.sin(2 * math.pi * middle), 0.0, GRAVITY], np.zeros(3),
                                 b - a)
    return pim


def test_a_retimed_window_is_the_window_filed_at_the_new_times():
    """A camera time offset that moves: keyframes filed 18 ms late, then moved to their true
    times with the IMU preintegrated again over the new intervals (``retime``), give the
    window that was filed at the true times from the start; then the window goes on."""
    true_times = np.arange(8) * 0.1
    filed = swaying_smoother(true_times + 0.018, VinsOptions())
    right = swaying_smoother(true_times, VinsOptions())
    pims = [swaying_pim(filed, t0, t1) for t0, t1 in zip(true_times, true_times[1:])]
    assert filed.retime(true_times, pims)
    assert [t for _, t in filed.window_keyframes] == pytest.approx(true_times.tolist())
    assert filed.latest.t == pytest.approx(true_times[-1])
    np.testing.assert_allclose(filed.latest.velocity, right.latest.velocity, atol=1e-4)
    np.testing.assert_allclose(filed.latest.T_W_B, right.latest.T_W_B, atol=1e-4)
    speed = (1.0 - math.cos(2 * math.pi * true_times[-1])) / (2 * math.pi)  # from rest
    assert filed.latest.velocity[0] == pytest.approx(speed, abs=1e-3)
    t = true_times[-1] + 0.1
    assert filed.add_keyframe(t, swaying_pim(filed, true_times[-1], t), [], None)
    assert filed.resets == 0


def test_a_kept_window_keeps_every_keyframe_through_a_retime():
    """Kept open from its first keyframe (``keep_window_from``, the take-off's window), a
    window of 2.4 s keeps all of its keyframes when a retime moves them 18 ms earlier than
    the time it was kept from, the gauge hold on one of them; let go, it is the lag's again."""
    true_times = np.arange(25) * 0.1
    filed_times = true_times + 0.018
    smoother = swaying_smoother(filed_times[:1], VinsOptions())
    smoother.keep_window_from(filed_times[0])
    for t0, t1 in zip(filed_times, filed_times[1:]):
        assert smoother.add_keyframe(float(t1), swaying_pim(smoother, t0, t1), [], None)
    assert len(smoother.window_keyframes) == len(true_times)
    pims = [swaying_pim(smoother, t0, t1) for t0, t1 in zip(true_times, true_times[1:])]
    assert smoother.retime(true_times, pims)
    assert [t for _, t in smoother.window_keyframes] == pytest.approx(true_times.tolist())
    assert smoother.gauge_keyframe in [index for index, _ in smoother.window_keyframes]
    smoother.keep_window_from(None)
    t = true_times[-1] + 0.1
    assert smoother.add_keyframe(t, swaying_pim(smoother, true_times[-1], t), [], None)
    lag = VinsOptions().smoother_lag_s
    assert t - lag - 1e-9 <= smoother.window_keyframes[0][1] < t - lag + 0.1
    assert smoother.resets == 0


def test_a_retime_that_does_not_fit_the_window_is_refused():
    smoother = swaying_smoother(np.arange(4) * 0.1, VinsOptions())
    with pytest.raises(ValueError, match="4 keyframes needs as many times"):
        smoother.retime([0.0, 0.1, 0.2], [])
    with pytest.raises(ValueError, match="increasing time order"):
        smoother.retime([0.0, 0.2, 0.1, 0.3],
                        [swaying_pim(smoother, 0.0, 0.1)] * 3)
