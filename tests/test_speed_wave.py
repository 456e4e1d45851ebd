"""The speed wave: arcs flown slower and back along the same path, never faster than checked;
the recorder's cruise swung about its speed (autonomy/planning/speed_wave.py)."""

import math

import numpy as np
import pytest

from autonomy.options import OptionError
from autonomy.planning.planner import Plan, Planner, PlannerOptions
from autonomy.planning.primitives import PrimitiveOptions, forward_arc
from autonomy.planning.speed_wave import MAX_SHARE, SpeedWave
from drivers.sim.record import PathFollower, RecordError

from tests.test_planning import AHEAD, CAMERA, FORWARD, ROOM, body, planner_seeing

WAVE = SpeedWave(0.6, 3.3)


def _arc_plan(t0=0.37, wave=WAVE, speed=2.0, yaw_rate=0.3, climb=0.2):
    arc = forward_arc(speed, yaw_rate, climb, PrimitiveOptions())
    return Plan(t0, body(x=1.0, y=-2.0, yaw=0.4), arc, "arc", "", 1, 3.0, 1.0, wave=wave)


def test_the_waves_progress_is_the_integral_of_its_factor():
    share, t0 = WAVE.share(2.0), 0.37
    times = np.linspace(t0, t0 + 7.0, 70001)
    factors = np.array([WAVE.factor(t, share) for t in times])
    integral = np.concatenate([[0.0], np.cumsum((factors[1:] + factors[:-1]) / 2 * np.diff(times))])
    for k in (1000, 33333, 70000):
        assert WAVE.progress(t0, times[k], share) == pytest.approx(integral[k], abs=1e-8)
    rates = np.gradient(factors, times)
    assert [WAVE.rate(t, share) for t in times[1000:1003]] == pytest.approx(rates[1000:1003],
                                                                           abs=1e-6)
    assert factors.max() <= 1.0 + 1e-12 and factors.min() == pytest.approx(1.0 - share, abs=1e-6)


def test_the_share_is_the_swing_over_the_speed_held_below_half():
    assert WAVE.share(2.0) == pytest.approx(0.3)
    assert WAVE.share(0.5) == MAX_SHARE
    assert WAVE.share(0.0) == 0.0


def test_time_at_inverts_the_progress():
    share = WAVE.share(1.0)
    t = WAVE.time_at(2.0, 4.2, share)
    assert WAVE.progress(2.0, t, share) == pytest.approx(4.2, abs=1e-9)


@pytest.mark.parametrize("swing, period", [(0.0, 3.3), (-0.1, 3.3), (0.6, 0.0),
                                           (math.nan, 3.3), (0.6, math.inf)])
def test_a_wave_without_a_positive_swing_and_period_is_refused(swing, period):
    with pytest.raises(ValueError, match="speed wave"):
        SpeedWave(swing, period)


def test_no_swing_means_no_wave():
    assert SpeedWave.of(0.0, 3.3) is None
    assert Planner(CAMERA, PlannerOptions()).wave is None


def test_a_waved_arc_follows_the_same_path_never_faster_than_its_speed():
    waved, plain = _arc_plan(), _arc_plan(wave=None)
    # the waved plan's positions lie on the plain plan's path, reached later
    for t in np.linspace(waved.t, waved.end_time, 50):
        tau = WAVE.progress(waved.t, t, WAVE.share(2.0))
        np.testing.assert_allclose(waved.setpoint(t).position_W,
                                   plain.setpoint(waved.t + tau).position_W, atol=1e-12)
        assert np.linalg.norm(waved.setpoint(t).velocity_W) <= \
            np.linalg.norm(plain.setpoint(waved.t + tau).velocity_W) + 1e-12
    speeds = [np.linalg.norm(waved.setpoint(t).velocity_W[:2])
              for t in np.linspace(waved.t, waved.t + 3.3, 200)]
    assert max(speeds) <= 2.0 + 1e-9 and min(speeds) < 2.0 - 0.3
    # it comes to rest where the plain plan does, later
    assert waved.end_time > plain.end_time
    np.testing.assert_allclose(waved.setpoint(waved.end_time).position_W,
                               plain.setpoint(plain.end_time).position_W, atol=1e-6)
    np.testing.assert_allclose(waved.setpoint(waved.end_time + 1.0).velocity_W, 0.0)


def test_a_waved_arcs_velocity_and_acceleration_are_its_positions_derivatives():
    plan, h = _arc_plan(), 1e-5
    for t in (0.5, 1.3, 2.2):
        before, now, after = (plan.setpoint(t + d) for d in (-h, 0.0, h))
        np.testing.assert_allclose(now.velocity_W,
                                   (after.position_W - before.position_W) / (2 * h), atol=1e-6)
        np.testing.assert_allclose(now.acceleration_W,
                                   (after.velocity_W - before.velocity_W) / (2 * h), atol=1e-5)


def test_consecutive_waved_plans_join_without_a_jump_in_speed():
    """The phase runs on the clock: a new round's arc starts at the speed the last one had."""
    first, second = _arc_plan(t0=0.0, yaw_rate=0.0), _arc_plan(t0=1.1, yaw_rate=0.0)
    np.testing.assert_allclose(np.linalg.norm(first.setpoint(1.1).velocity_W),
                               np.linalg.norm(second.setpoint(1.1).velocity_W), rtol=1e-12)


def test_the_planner_flies_its_arc_and_checked_stop_on_the_wave():
    options = PlannerOptions(speed_swing=0.6)
    planner = planner_seeing(ROOM, options=options)
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    assert plan.kind == "arc" and plan.wave == SpeedWave(0.6, 3.3)
    stop = planner.stop_plan(0.1, body(x=0.1), FORWARD, "vins lost")
    assert stop.wave == plan.wave
    # the stop goes on from the arc's commands, the wave's speed included
    np.testing.assert_allclose(stop.setpoint(0.1).velocity_W, plan.setpoint(0.1).velocity_W)


@pytest.mark.parametrize("key, value", [("speed_swing", -0.1), ("speed_swing_period_s", 0.0)])
def test_bad_speed_wave_options_are_refused(key, value):
    with pytest.raises(OptionError, match=key):
        PlannerOptions(**{key: value})


def test_the_recorders_wave_swings_the_speed_about_its_cruise_and_keeps_the_length():
    path = np.array([[0.0, 0.0], [500.0, 0.0]])
    follower, steady = PathFollower(path, 1.5, 1.0, WAVE), PathFollower(path, 1.5, 1.0)
    speeds = [float(np.linalg.norm(follower.target(t).velocity)) for t in
              np.linspace(0.0, 3.3, 331)]
    assert max(speeds) == pytest.approx(1.3) and min(speeds) == pytest.approx(0.7, abs=1e-4)
    # a whole number of periods later it is where the steady cruise is
    np.testing.assert_allclose(follower.target(33.0).position, steady.target(33.0).position,
                               atol=1e-9)


def test_the_recorder_refuses_a_swing_that_would_stop_the_vehicle():
    with pytest.raises(RecordError, match="speed swing"):
        PathFollower(np.array([[0.0, 0.0], [5.0, 0.0]]), 1.5, 1.0, SpeedWave(2.0, 3.3))
