"""Issue 23: the camera-IMU time offset, estimated online and corrected.

An unsynchronised camera stamps its frames late by an unknown offset ``td``. With
``[vins] estimate_time_offset`` the VINS estimates it from the camera's rotation between frames
against the gyro's (autonomy/vins/time_offset.py, docs/vins.md) and runs on the corrected times.

First the parts on synthetic data (exact geometry, no renderer): the rotation fit, and the
estimator on a camera whose turn starts at a known time. Then the whole VINS on the simulated
flight of tests/test_vins_estimator.py (world "mine", seed 0, 8 s: the take-off, then the
vehicle pitches to set off along the route at 5.5 s) with its camera stamps shifted by a hidden
``td`` (tests/time_offset_runs.py).
"""

import math

import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, make_pose, so3_exp
from autonomy.options import OptionError
from autonomy.vins import VinsOptions
from autonomy.vins.estimator import RETIME_TOLERANCE_S
from autonomy.vins.time_offset import (
    TimeOffset, TimeOffsetEstimator, exp_so3, fit_rotation, log_so3,
)
from tests.time_offset_runs import run_vins_offset, shift_recording, window_statistics

SECONDS = 8.0  # the recording tests/test_vins_estimator.py flies (shared within a session)
GOAL_S = 0.002  # issue 23: the offset recovered to within 2 ms
# Measured on this recording (mine, seed 0, 8 s): with td = +15 / -15 ms the estimate is within
# 2 ms from 5.97 / 5.89 s (0.4-0.5 s after the vehicle pitches) and ends 0.1 / 0.7 ms off; with
# td = 0 it never leaves 0.9 ms. The largest position error over the flight, against the truth
# at the exposure times: 10 mm with td = 0 estimated (11 mm without the estimator); 44 / 47 mm
# with td = +15 / -15 ms estimated (63 mm with +15 ms not corrected), most of it made in the
# climb, before the first rotation shows the offset.
MAX_POSITION_ERROR_M = 0.03
MAX_ERROR_WITH_OFFSET_M = 0.08
CONVERGED_BY_S = 7.0
MOVED_BY_FRAME = 130  # 6.5 s: the offset known half a second since, the window 1.5 s long


# ------------------------------------------------------------------ options


@pytest.mark.parametrize("changes, key", [
    ({"time_offset_s": 0.06}, "time_offset_s"),  # beyond max_time_offset_s (0.05)
    ({"time_offset_s": -0.2}, "time_offset_s"),
    ({"time_offset_s": math.nan}, "time_offset_s"),
    ({"max_time_offset_s": 0.0}, "max_time_offset_s"),
    ({"max_time_offset_s": 0.5}, "max_time_offset_s"),
    ({"max_time_offset_s": 0.01, "time_offset_s": 0.02}, "time_offset_s"),
    ({"estimate_time_offset": "yes"}, "estimate_time_offset"),
    ({"estimate_time_offset": 1}, "estimate_time_offset"),
    ({"time_offset_window_s": 0.1}, "time_offset_window_s"),
    ({"time_offset_pair_s": 0.0}, "time_offset_pair_s"),
    ({"time_offset_pair_s": 1.0, "time_offset_window_s": 1.0}, "time_offset_pair_s"),
    ({"time_offset_min_features": 3}, "time_offset_min_features"),
    ({"time_offset_max_sigma_s": -0.001}, "time_offset_max_sigma_s"),
    ({"time_offset_max_step_s": 0.0}, "time_offset_max_step_s"),
    ({"time_offset_max_step_s": math.inf}, "time_offset_max_step_s"),
    ({"retime_window": True}, "retime_window"),  # without estimate_time_offset
    ({"retime_window": "yes", "estimate_time_offset": True}, "retime_window"),
    ({"takeoff_window_s": 8.0, "estimate_time_offset": True}, "takeoff_window_s"),  # no retiming
    ({"takeoff_window_s": 1.0, "estimate_time_offset": True, "retime_window": True},
     "takeoff_window_s"),  # shorter than the lag
    ({"takeoff_window_s": -1.0}, "takeoff_window_s"),
    ({"takeoff_window_s": math.nan}, "takeoff_window_s"),
])
def test_bad_time_offset_options_are_refused_with_their_name(changes, key):
    with pytest.raises(OptionError) as error:
        VinsOptions(**changes)
    assert error.value.key == key


def test_the_offset_options_default_to_off_and_within_bounds():
    o = VinsOptions()
    assert o.estimate_time_offset is False and o.time_offset_s == 0.0
    assert o.max_time_offset_s == 0.05
    VinsOptions(estimate_time_offset=True, time_offset_s=-0.05)  # the bound itself is allowed


# ------------------------------------------------------------------ the rotation fit


def test_batched_exp_and_log_invert_each_other():
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(50, 3)) * 0.5
    phi[0] = 0.0
    phi[1] = 1e-9
    R = exp_so3(phi)
    np.testing.assert_allclose(R[5], so3_exp(phi[5]), atol=1e-12)
    np.testing.assert_allclose(log_so3(R), phi, atol=1e-9)


def _two_views(R_ij, t_ij, n=80, seed=0, noise_rad=0.0):
    """Bearings ``u`` (camera i) and ``w`` (camera j) of ``n`` points 2-12 m in front of j,
    with ``p_i = R_ij p_j + t_ij``."""
    rng = np.random.default_rng(seed)
    p_j = np.c_[rng.uniform(-0.8, 0.8, (n, 2)), np.ones(n)] * rng.uniform(2, 12, (n, 1))
    p_i = p_j @ R_ij.T + t_ij
    u = p_i / np.linalg.norm(p_i, axis=1, keepdims=True)
    w = p_j / np.linalg.norm(p_j, axis=1, keepdims=True)
    if noise_rad:
        u = u + rng.normal(0, noise_rad, u.shape)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, w


@pytest.mark.parametrize("translation", [np.array([0.05, -0.02, 0.3]), np.zeros(3)])
def test_the_rotation_between_two_views_is_found_with_or_without_translation(translation):
    R_true = so3_exp(np.array([0.02, -0.15, 0.01]))
    u, w = _two_views(R_true, translation, noise_rad=0.3 / 320)
    start = so3_exp(np.array([0.0, -0.12, 0.0]))  # the gyro's guess, 30 mrad off
    fit = fit_rotation(u, w, start, 320.0)
    error = np.linalg.norm(log_so3(fit.R.T @ R_true))
    sigma = np.sqrt(np.trace(np.linalg.inv(fit.information)))
    assert fit.translation == bool(np.any(translation))
    assert error < 3 * sigma + 1e-5
    assert sigma < 1e-3  # 80 points at 0.3 px: well under a milliradian
    assert np.all(np.linalg.eigvalsh(fit.information) > 0)


def test_too_few_points_give_no_rotation():
    u, w = _two_views(np.eye(3), np.array([0.0, 0.0, 0.2]), n=6)
    assert fit_rotation(u, w, np.eye(3), 320.0) is None


# ------------------------------------------------------------------ the estimator, synthetic


def _synthetic_flight(td, options, *, turn_at=3.0, duration=6.5, yaw_rate=0.6, seed=1,
                      gyro_matrix=np.eye(3), vibration=0.0, on_frame=None):
    """A camera (mounted as the simulator's, looking along body x) flying forward at 1 m/s
    through random points; its body starts to yaw and pitch at ``turn_at``. The gyro holds
    each 200 Hz sample over its interval, as the estimator assumes, and reads ``gyro_matrix``
    times the true rate, plus the rotors' ``vibration`` (rad/s on each axis, as the realistic
    profile's 122.5 Hz aliases to 77.5 Hz; the camera does not see it); 20 Hz frames are stamped
    ``td`` late, their bearings 0.3 px noisy.
    ``on_frame(estimator)`` is called after each frame. Returns the estimator and, per frame,
    its offset."""
    rng = np.random.default_rng(seed)
    T_B_C = make_pose(R_BODY_CAMERA, np.array([0.1, 0.0, 0.05]))
    estimator = TimeOffsetEstimator(T_B_C, 320.0, options)
    dt, n = 0.005, int(round(duration / 0.005))
    imu_t = np.arange(n + 1) * dt
    omega = np.zeros((n + 1, 3))
    omega[imu_t >= turn_at] = [0.0, 0.2, yaw_rate]
    shaking = vibration * np.sin(2 * np.pi * 77.5 * imu_t[:, None] + rng.uniform(0, 2 * np.pi, 3))
    R = [np.eye(3)]
    for k in range(n):
        R.append(R[-1] @ so3_exp(omega[k] * dt))
    directions = rng.normal(size=(4000, 3))
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * rng.uniform(
        3, 12, (4000, 1))
    offsets, fed = [], 0
    for frame in range(int(duration * 20) - 1):
        t = frame * 0.05  # true exposure time
        stamp = t + td
        k = min(int(t / dt), n - 1)
        R_W_B = R[k] @ so3_exp(omega[k] * (t - imu_t[k]))
        R_W_C = R_W_B @ T_B_C[:3, :3]
        centre = np.array([t, 0.0, 0.0]) + R_W_B @ T_B_C[:3, 3]
        p_C = (points - centre) @ R_W_C
        z = p_C[:, 2]
        seen = (z > 0.5) & (np.abs(p_C[:, 0]) < z) & (np.abs(p_C[:, 1]) < 0.75 * z)  # 90x74 deg
        ids = np.flatnonzero(seen)
        xy = p_C[seen, :2] / p_C[seen, 2:] + rng.normal(0, 0.3 / 320, (len(ids), 2))
        while fed <= n and imu_t[fed] <= stamp:
            estimator.add_imu(imu_t[fed], gyro_matrix @ omega[fed] + shaking[fed], np.zeros(3))
            fed += 1
        estimator.add_frame(stamp, ids, xy)
        if on_frame is not None:
            on_frame(estimator)
        offsets.append(estimator.offset)
    return estimator, offsets


OPTIONS_ON = VinsOptions(estimate_time_offset=True)


@pytest.mark.parametrize("td", [0.015, -0.015, 0.03, 0.0])
def test_the_offset_is_found_once_the_camera_turns(td):
    estimator, offsets = _synthetic_flight(td, OPTIONS_ON)
    before = [o for k, o in enumerate(offsets) if k * 0.05 < 2.9]
    # steady flight: no information, the estimate does not move from its start
    assert all(o.seconds == 0.0 and o.sigma is None for o in before)
    assert all(o.estimating for o in offsets)
    final = offsets[-1]
    assert abs(final.seconds - td) < 0.0005, final
    assert final.sigma is not None and final.sigma < 0.001
    assert abs(final.seconds - td) < 3 * final.sigma + 1e-4  # the sigma is honest


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_the_rotors_vibration_neither_biases_the_offset_nor_makes_it_overconfident(td):
    """A gyro vibration the camera does not see (0.15 rad/s at 77.5 Hz, the realistic profile's
    rotors as the 200 Hz gyro aliases them, twice over for margin). Taken from one gyro sample
    as the rate at a pair's ends it passed for motion: 1.6-16 ms off with sigmas of 0.4-0.5 ms
    here, and realistic recordings' windows up to 12 ms off (docs/vins.md). Averaged over
    RATE_SPAN_S, a clear turn still gives the offset, and a gentle one gives no false claim."""
    _, offsets = _synthetic_flight(td, OPTIONS_ON, vibration=0.15)
    final = offsets[-1]
    assert abs(final.seconds - td) < 0.0005, final
    assert abs(final.seconds - td) < 3 * final.sigma + 1e-4, final  # the sigma is honest
    _, offsets = _synthetic_flight(td, OPTIONS_ON, vibration=0.15, yaw_rate=0.2)
    for offset in offsets:
        assert offset.sigma is None or abs(offset.seconds - td) < 3 * offset.sigma + 1e-4, offset


def test_the_offset_moves_by_bounded_steps_within_its_bounds():
    options = VinsOptions(estimate_time_offset=True, time_offset_max_step_s=0.001,
                          max_time_offset_s=0.02)
    _, offsets = _synthetic_flight(0.03, options)  # beyond the bound
    values = np.array([o.seconds for o in offsets])
    assert np.all(np.abs(np.diff(values)) <= 0.001 + 1e-12)
    assert np.all(np.abs(values) <= 0.02 + 1e-12)


def test_the_estimate_starts_from_the_configured_offset():
    options = VinsOptions(estimate_time_offset=True, time_offset_s=0.01)
    _, offsets = _synthetic_flight(0.015, options)
    assert offsets[0].seconds == 0.01
    assert abs(offsets[-1].seconds - 0.015) < 0.0005


# ------------------------------------------------------------------ the VINS on a simulated flight


@pytest.fixture(scope="module")
def flights(record_flight, tmp_path_factory):
    """The recording, and copies of it with the camera stamps late by +15 and -15 ms."""
    root = record_flight("mine", SECONDS)
    folder = tmp_path_factory.mktemp("time_offset")
    return {0.0: root, **{td: shift_recording(root, folder / f"td{td * 1e3:+.0f}ms", td)
                          for td in (0.015, -0.015)}}


@pytest.fixture(scope="module")
def runs(flights):
    """The VINS over each: the offset estimated (on) for every offset, not (off) without one."""
    on = VinsOptions(estimate_time_offset=True)
    result = {(td, "on"): run_vins_offset(root, on) for td, root in flights.items()}
    result[(0.0, "off")] = run_vins_offset(flights[0.0], VinsOptions())
    return result


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_a_hidden_offset_is_recovered_within_two_milliseconds(runs, td):
    run = runs[(td, "on")]
    stamps, offsets = np.array(run.stamps), np.array(run.offsets)
    assert abs(offsets[-1] - td) < GOAL_S, offsets[-1]
    late = stamps >= CONVERGED_BY_S
    assert np.all(np.abs(offsets[late] - td) < GOAL_S)
    assert run.sigmas[-1] < GOAL_S
    # the stamps are the recording's, the poses are at the corrected times
    np.testing.assert_allclose(np.array(run.exposures), stamps - offsets, atol=1e-12)


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_the_windows_are_centred_on_the_hidden_offset(runs, td):
    """Each excited window's own solution (one that may become the estimate's target) against
    the hidden offset: their median within half the 2 ms goal. Their sigmas are not yet
    honest: on this flight the median |z| is about 1.4 where 0.67 would be (docs/vins.md,
    "The camera-IMU time offset", "Measured")."""
    stats = window_statistics(runs[(td, "on")], td)
    assert stats["windows_excited"] >= 20, stats
    assert abs(stats["window_error_ms_median"]) < 0.5 * GOAL_S * 1e3, stats


def test_without_an_offset_the_estimate_stays_near_zero(runs):
    offsets = np.array(runs[(0.0, "on")].offsets)
    assert np.all(np.abs(offsets) < GOAL_S), np.abs(offsets).max()


def test_without_an_offset_estimating_it_costs_no_accuracy(runs):
    on, off = runs[(0.0, "on")].position_errors(), runs[(0.0, "off")].position_errors()
    assert runs[(0.0, "on")].resets == 0
    assert on.max() < MAX_POSITION_ERROR_M
    assert on.max() < off.max() + 0.005


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_with_a_hidden_offset_the_flight_is_tracked_throughout(runs, td):
    """The climb (2-5.5 s) is flown before anything shows the offset (no rotation), and the
    error it leaves stays: hence a wider bound than without an offset (docs/vins.md)."""
    run = runs[(td, "on")]
    assert run.resets == 0 and "LOST" not in run.health
    assert run.position_errors().max() < MAX_ERROR_WITH_OFFSET_M


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_the_window_is_moved_to_the_offset_in_use(flights, td):
    """The offset moves from 0 to ``td`` as the vehicle pitches (5.5-6 s); with
    ``retime_window``, at each keyframe the window's keyframes are moved to the exposure times
    the offset in use then gives their stamps (docs/vins.md, "The window moved with the time
    offset"). Half a second later, with keyframes filed at offsets ``td`` apart still in the
    window, each sits at its stamp less the offset the newest was filed at."""
    options = VinsOptions(estimate_time_offset=True, retime_window=True)
    run = run_vins_offset(flights[td], options, max_frames=MOVED_BY_FRAME)
    backend, stamps = run.vins.backend, np.array(run.stamps)
    offset = run.offsets[run.exposures.index(backend.latest.t)]
    assert abs(offset - td) < GOAL_S
    oldest = backend.window_keyframes[0][1]
    filed_at = np.array(run.offsets)[np.array(run.exposures) >= oldest - 1e-9]
    assert np.ptp(filed_at) > 0.5 * abs(td)  # the window spans the offset's move
    for _, t in backend.window_keyframes:
        assert np.abs(stamps - offset - t).min() <= RETIME_TOLERANCE_S, t


@pytest.mark.parametrize("td", [0.015, -0.015])
def test_the_take_offs_window_is_kept_open_until_the_offset_is_known(flights, td):
    """With ``takeoff_window_s``, the window stops sliding as the vehicle starts its climb, the
    camera's stamps ``td`` off and the offset unknown, and keeps the climb until the vehicle
    pitches and the offset is known (5.5-6 s); then it is the lag's again. Moved to the offset
    with the rest of the window, the climb no longer leaves its error in the marginal. Measured
    on this flight, the VINS ends 6.3 / 7.2 mm from the truth (td = +15 / -15 ms), as it does
    started from the true offset (6.7 / 6.2 mm), where with the retiming alone it ends 21.6 /
    15.0 mm off (docs/vins.md, "The take-off's window kept open")."""
    options = VinsOptions(estimate_time_offset=True, retime_window=True, takeoff_window_s=8.0)
    run = run_vins_offset(flights[td], options)
    window_s, sigmas = np.array(run.window_s), np.array(run.sigmas)
    known = int(np.argmax(sigmas <= options.time_offset_max_sigma_s))
    assert sigmas[known] <= options.time_offset_max_sigma_s
    assert window_s[:known].max() > 2 * options.smoother_lag_s
    settled = np.array(run.stamps) > run.stamps[known] + 2 * options.keyframe_interval_s
    assert window_s[settled].max() <= options.smoother_lag_s + options.keyframe_interval_s
    assert run.position_errors()[-1] < 0.012


def test_with_estimation_off_the_stamps_are_used_as_they_are(runs):
    """The default: no estimator, no correction, the offset reported as fixed at zero."""
    run = runs[(0.0, "off")]
    assert run.vins._offset_estimator is None
    assert run.exposures == run.stamps
    assert set(run.offsets) == {0.0} and all(math.isnan(s) for s in run.sigmas)
    assert run.vins.time_offset == TimeOffset()
    assert run.vins.backend.latest.t in run.stamps


def test_a_fixed_offset_is_subtracted_without_estimation(flights):
    options = VinsOptions(time_offset_s=0.015)
    run = run_vins_offset(flights[0.015], options, max_frames=60)
    assert all(t - e == pytest.approx(0.015, abs=1e-12) for t, e in zip(run.stamps, run.exposures))
    assert run.vins.time_offset == TimeOffset(0.015)
    assert run.vins.backend.latest.t in run.exposures


def test_the_estimators_work_never_lands_on_a_keyframe(runs):
    """It waits for a frame that does not update the smoother (docs/vins.md, "The method")."""
    run = runs[(0.015, "on")]
    assert any(ms > 0.0 for _, ms in run.offset_ms)
    assert all(ms == 0.0 for keyframe, ms in run.offset_ms if keyframe)


# ------------------------------------------------------------------ the realistic profile


def test_the_realistic_cameras_hidden_offset_is_recovered_within_2_ms(tmp_path):
    """A realistic-profile recording carries every error source at once: blur, the lens,
    noise and auto-exposure, a mounting error, jitter, lost frames, a vibrating IMU with scale
    errors, and frames stamped 15 ms late (drivers/sim/sensor.py). The VINS is told none of it
    but the lens."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.imu import ImuOptions
    from drivers.sim.options import SimOptions
    from drivers.sim.quadrotor import VehicleOptions
    from drivers.sim.record import record_dataset
    from drivers.sim.sensor import SensorOptions

    hidden = SensorOptions().time_offset_ms * 1e-3
    record_dataset(tmp_path, SimOptions(world="mine", seed=0, profile="realistic"),
                   CameraOptions(), VehicleOptions(), ImuOptions(), duration=SECONDS)
    run = run_vins_offset(tmp_path, VinsOptions(estimate_time_offset=True))
    stamps, offsets = np.array(run.stamps), np.array(run.offsets)
    late = stamps >= CONVERGED_BY_S + 0.5
    assert late.any()
    assert np.abs(offsets[late] - hidden).max() < GOAL_S


@pytest.mark.parametrize("setting, words", [
    ("sim.profile=ideal", "--set takes [vins] options only, got sim.profile=ideal"),
    ("vins.retime_window=maybe", "vins.retime_window"),
    ("vins.no_such_option=1", "no_such_option"),
])
def test_the_offset_runs_command_refuses_a_setting_it_cannot_use(tmp_path, capsys, setting,
                                                                  words):
    """``python -m tests.time_offset_runs`` names a bad ``--set`` before it reads anything."""
    from tests.time_offset_runs import main
    with pytest.raises(SystemExit) as stopped:
        main([str(tmp_path), "--set", setting])
    assert stopped.value.code == 2 and words in capsys.readouterr().err
