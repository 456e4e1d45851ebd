"""The height wave: arcs flown swinging up and down about their path, fading out over the
braking, checked at the wave's crest and trough with swept spheres
(autonomy/planning/height_wave.py)."""

import json
import math

import numpy as np
import pytest

from autonomy.options import OptionError
from autonomy.planning.height_wave import HeightWave
from autonomy.planning.planner import Plan, Planner, PlannerOptions
from autonomy.planning.primitives import PrimitiveOptions, forward_arc
from autonomy.planning.speed_wave import SpeedWave
from companion.recording.topics import encode_plan
from drivers.sim.record import PathFollower

from tests.test_planning import AHEAD, CAMERA, FORWARD, ROOM, WALL_LEFT, body, planner_seeing

WAVE = HeightWave(0.08, 2.0)


def _arc_plan(t0=0.37, height_wave=WAVE, speed_wave=None, yaw_rate=0.3, climb=0.2):
    arc = forward_arc(2.0, yaw_rate, climb, PrimitiveOptions())
    return Plan(t0, body(x=1.0, y=-2.0, yaw=0.4), arc, "arc", "", 1, 3.0, 1.0,
                wave=speed_wave, height_wave=height_wave)


@pytest.mark.parametrize("amplitude, period", [(0.0, 2.0), (-0.1, 2.0), (0.08, 0.0),
                                               (math.nan, 2.0), (0.08, math.inf)])
def test_a_wave_without_a_positive_amplitude_and_period_is_refused(amplitude, period):
    with pytest.raises(ValueError, match="height wave"):
        HeightWave(amplitude, period)


def test_no_amplitude_means_no_wave():
    assert HeightWave.of(0.0, 2.0) is None
    assert Planner(CAMERA, PlannerOptions()).height_wave is None


@pytest.mark.parametrize("key, value", [("height_swing", -0.1), ("height_swing", 0.6),
                                        ("height_swing_period_s", 0.2)])
def test_bad_height_wave_options_are_refused(key, value):
    with pytest.raises(OptionError, match=key):
        PlannerOptions(**{key: value})


def test_a_waved_arc_flies_the_level_path_offset_only_vertically_and_comes_to_rest_on_it():
    waved, level = _arc_plan(), _arc_plan(height_wave=None)
    heights = []
    for t in np.linspace(waved.t, waved.end_time, 200):
        flown, planned = waved.setpoint(t), level.setpoint(t)
        np.testing.assert_allclose(flown.position_W[:2], planned.position_W[:2], atol=1e-12)
        np.testing.assert_allclose(flown.velocity_W[:2], planned.velocity_W[:2], atol=1e-12)
        heights.append(flown.position_W[2] - planned.position_W[2])
    # it swings by the whole amplitude on the arc, never more, and at rest holds the path
    assert max(heights) == pytest.approx(0.08, abs=1e-3)
    assert min(heights) == pytest.approx(-0.08, abs=1e-3)
    rest = waved.end_time + 0.5
    np.testing.assert_allclose(waved.setpoint(rest).position_W, level.setpoint(rest).position_W,
                               atol=1e-12)
    np.testing.assert_allclose(waved.setpoint(rest).velocity_W, 0.0, atol=1e-12)


@pytest.mark.parametrize("speed_wave", [None, SpeedWave(0.6, 3.3)])
def test_a_waved_plans_velocity_and_acceleration_are_its_positions_derivatives(speed_wave):
    plan, h = _arc_plan(speed_wave=speed_wave), 1e-5
    braking = plan.t + plan.primitive.duration
    # along the arc, then twice within the braking, where the wave fades out
    for t in (0.5, 1.3, braking + 0.2, braking + 0.7):
        before, now, after = (plan.setpoint(t + d) for d in (-h, 0.0, h))
        np.testing.assert_allclose(now.velocity_W,
                                   (after.position_W - before.position_W) / (2 * h), atol=1e-6)
        np.testing.assert_allclose(now.acceleration_W,
                                   (after.velocity_W - before.velocity_W) / (2 * h), atol=1e-5)


def test_the_planner_starts_each_arc_at_the_body_wherever_it_is_on_the_wave():
    options = PlannerOptions(height_swing=0.08)
    for t in (0.05, 0.55, 1.3):  # the body near the line, near the crest, below the line
        planner = planner_seeing(ROOM, t=t, options=options)
        plan = planner.plan(t, body(), FORWARD, AHEAD)
        assert plan.kind == "arc" and plan.height_wave == HeightWave(0.08, 2.0)
        # the sphere checked, recorded
        assert plan.candidates.radius == pytest.approx(math.hypot(1.0, 0.08))
        np.testing.assert_allclose(plan.setpoint(t).position_W, body()[:3, 3], atol=1e-12)
        # planned from the line it swings about
        line = body()[2, 3] - 0.08 * math.sin(math.pi * t)
        assert plan.T_W_S[2, 3] == pytest.approx(line)


def test_consecutive_waved_plans_join_without_a_jump_in_vertical_velocity():
    """The phase runs on the clock: a new round's arc goes on at the vertical speed the last
    one commanded."""
    first, second = _arc_plan(t0=0.0, climb=0.0), _arc_plan(t0=1.1, climb=0.0)
    assert first.setpoint(1.1).velocity_W[2] == pytest.approx(second.setpoint(1.1).velocity_W[2])
    assert abs(first.setpoint(1.1).velocity_W[2]) > 0.1


def test_the_checked_stop_goes_on_along_the_wave():
    planner = planner_seeing(ROOM, options=PlannerOptions(height_swing=0.08))
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    stop = planner.stop_plan(0.1, body(x=0.1), FORWARD, "vins lost")
    assert stop.height_wave == plan.height_wave
    np.testing.assert_allclose(stop.setpoint(0.1).velocity_W, plan.setpoint(0.1).velocity_W)
    np.testing.assert_allclose(stop.setpoint(0.1).position_W, plan.setpoint(0.1).position_W)


FLOOR_BELOW = ((3.0, -50.0, -50.0), (50.0, 50.0, 3.93))  # 1.07 m below the vehicle, ahead
CEILING_ABOVE = ((3.0, -50.0, 6.07), (50.0, 50.0, 50.0))  # 1.07 m above it


@pytest.mark.parametrize("obstacle", [WALL_LEFT, FLOOR_BELOW, CEILING_ABOVE])
def test_the_arcs_are_checked_at_the_waves_crest_and_trough_with_swept_spheres(obstacle):
    swing, swept = 0.1, math.hypot(1.0, 0.1)
    waved = planner_seeing(ROOM + [obstacle], options=PlannerOptions(height_swing=swing))
    level = planner_seeing(ROOM + [obstacle], options=PlannerOptions(robot_radius=swept))
    check = waved.check(0.0, body())
    crest, trough = (level.check(0.0, body(z=5.0 + dz)) for dz in (swing, -swing))
    np.testing.assert_array_equal(check.safe, crest.safe & trough.safe)
    np.testing.assert_array_equal(check.blocked, crest.blocked | trough.blocked)
    if obstacle is FLOOR_BELOW:  # the trough, nearer the floor, rules out arcs the crest keeps
        assert trough.safe.sum() < crest.safe.sum()
    if obstacle is CEILING_ABOVE:  # and the crest, nearer the ceiling, those the trough keeps
        assert crest.safe.sum() < trough.safe.sum()


def test_an_approach_glide_flown_level_is_checked_with_the_robots_own_sphere():
    goal = np.array([3.0, 0.0, 5.0])
    waved = planner_seeing(ROOM + [WALL_LEFT], options=PlannerOptions(height_swing=0.3))
    level = planner_seeing(ROOM + [WALL_LEFT])
    glides = [p.approach(0.0, body(), goal) for p in (waved, level)]
    assert glides[0] is not None and glides[0].height_wave is None
    assert glides[0].clearance == pytest.approx(glides[1].clearance)


def test_the_recorders_height_wave_swings_its_target_about_the_cruise_height():
    """`sim record` flies the wave as the planner does, its motion share 1 throughout: the
    target's height, vertical velocity and acceleration are ``h``, ``h'``, ``h''``."""
    path = np.array([[0.0, 0.0], [500.0, 0.0]])
    waved, level = PathFollower(path, 1.5, 1.0, height_wave=WAVE), PathFollower(path, 1.5, 1.0)
    times = np.linspace(0.0, 4.0, 4001)
    targets = [waved.target(t) for t in times]
    heights = np.array([target.position[2] for target in targets]) - 1.5
    np.testing.assert_allclose(heights, 0.08 * np.sin(math.pi * times), atol=1e-12)
    step = times[1] - times[0]
    rising = np.array([target.velocity[2] for target in targets])
    lifting = np.array([target.acceleration[2] for target in targets])
    np.testing.assert_allclose(np.gradient(heights, step)[1:-1], rising[1:-1], atol=1e-5)
    np.testing.assert_allclose(np.gradient(rising, step)[1:-1], lifting[1:-1], atol=1e-5)
    for t, target in zip(times[::250], targets[::250]):
        np.testing.assert_allclose(target.position[:2], level.target(t).position[:2])
        np.testing.assert_allclose(target.velocity[:2], level.target(t).velocity[:2])


def _slot(gap):
    """A floor and a ceiling ahead, each ``gap`` metres from the vehicle's height."""
    return [((3.0, -50.0, -50.0), (50.0, 50.0, 5.0 - gap)),
            ((3.0, -50.0, 5.0 + gap), (50.0, 50.0, 50.0))]


def test_a_passage_too_low_to_swing_through_is_flown_level_at_the_speed_it_allows():
    """The wave never costs speed: where no arc of a tier clears the crest and the trough but
    one clears the level path, that tier's arc is flown level, checked with the robot's own
    sphere, as a vehicle without the wave would fly it."""
    boxes = ROOM + _slot(1.2)
    waved = planner_seeing(boxes, options=PlannerOptions(height_swing=0.1))
    level = planner_seeing(boxes)
    assert not waved.check(0.0, body()).safe.any()  # nothing swings through the slot
    plan, expected = (p.plan(0.0, body(), FORWARD, AHEAD) for p in (waved, level))
    assert plan.kind == "arc" and plan.height_wave is None
    assert plan.candidates.speed == expected.candidates.speed == 2.0
    assert plan.candidates.radius == 1.0
    assert plan.candidates.chosen == expected.candidates.chosen
    np.testing.assert_array_equal(plan.candidates.safe, expected.candidates.safe)
    np.testing.assert_array_equal(plan.T_W_S, expected.T_W_S)
    for t in np.linspace(plan.t, plan.end_time, 50):  # no swing at any time
        np.testing.assert_allclose(plan.setpoint(t).position_W, expected.setpoint(t).position_W)
    stop = waved.stop_plan(0.1, body(x=0.1), FORWARD, "vins lost")
    assert stop.height_wave is None
    assert json.loads(encode_plan(plan))["height_swing"] == 0.0  # the record says it was level


def test_where_the_wave_fits_it_is_flown():
    planner = planner_seeing(ROOM + _slot(1.3), options=PlannerOptions(height_swing=0.1))
    plan = planner.plan(0.0, body(), FORWARD, AHEAD)
    assert plan.kind == "arc" and plan.candidates.speed == 2.0
    assert plan.height_wave == HeightWave(0.1, 2.0)
    assert json.loads(encode_plan(plan))["height_swing"] == 0.1
    assert plan.candidates.radius == pytest.approx(math.hypot(1.0, 0.1))
    # only the arcs that clear the crest and the trough are chosen from
    assert plan.candidates.safe.sum() < planner.check(0.0, body(), level=True).safe.sum()
