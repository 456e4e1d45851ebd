"""The navigation decisions on their own (autonomy/navigation): the route, the flown trail, the
behaviours at corners and dead ends (turn, parallax glide, approach, backing off) and the
failsafe rules, without asyncio, a socket or a simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autonomy.geometry import PinholeCamera, make_pose, rot_z
from autonomy.navigation.behaviours import (BACKOFF_REASON, LOOK_ASIDE, PARALLAX_LANDMARKS,
                                            PARALLAX_REASON, PARALLAX_WAIT_S, TURN_STOP_REASON,
                                            TURN_STEP, Backoff, Blocked, NoPathClock,
                                            OffsetSwing, ParallaxGlide, Step, approach_targets,
                                            depth_lapsed, facing, must_turn, offset_unknown,
                                            on_glide, pause_turn, still_turning, turn_rate,
                                            view_starved)
from autonomy.navigation.failsafes import (BlindClock, Vitals, failsafe_reason, vins_failed,
                                           vins_problem)
from autonomy.navigation.mission import (MISSION_TIMEOUT, SITE_SEEKING_FAILSAFES, FlightOptions,
                                         FlightState, Mission)
from autonomy.navigation.route import Route, heading_error, stop_waypoints
from autonomy.navigation.trail import Trail
from autonomy.options import OptionError
from autonomy.planning.planner import Candidates, Planner, PlannerOptions
from autonomy.vins.health import HealthState
from autonomy.vins.time_offset import TimeOffset

OPTIONS = FlightOptions()
IDENTITY = np.eye(4)


def fly_trail(trail: Trail, points, climbing=False) -> None:
    for point in points:
        trail.record(np.asarray(point, dtype=float), climbing)


def an_l_shaped_trail() -> Trail:
    """Up the take-off column to 1.5 m, 3 m east, 2 m north (steps of 0.125 m, exact)."""
    trail = Trail()
    fly_trail(trail, [(0.0, 0.0, z) for z in np.linspace(0.0, 1.5, 13)], climbing=True)
    fly_trail(trail, [(x, 0.0, 1.5) for x in np.linspace(0.0, 3.0, 25)[1:]])
    fly_trail(trail, [(3.0, y, 1.5) for y in np.linspace(0.0, 2.0, 17)[1:]])
    return trail


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner(PinholeCamera.from_hfov(160, 120, math.radians(90.0)), PlannerOptions())


# ---------------------------------------------------------------- the route

def test_the_vehicle_stops_at_the_goal_and_at_sharp_corners_only():
    route = np.array([[0.0, 0.0, 1.5], [10.0, 0.0, 1.5], [20.0, 2.0, 1.5],  # 11 deg: on
                      [20.0, 12.0, 1.5], [10.0, 12.0, 2.5]])  # then 79 and 90 deg: stop
    assert stop_waypoints(route, math.radians(30.0)) == [False, False, True, True, True]
    assert stop_waypoints(route[:1], math.radians(30.0)) == [True]


def test_waypoints_pass_within_their_tolerance_and_a_corner_only_close_up():
    route = Route([[10.0, 0.0, 1.5], [10.0, 10.0, 1.5], [20.0, 10.0, 1.5]],
                  math.radians(OPTIONS.corner_turn_deg))
    assert route.stop_at == [False, True, True]
    # 2.1 m short of the first waypoint: not passed (waypoint_tolerance 2 m)
    assert route.advance(np.array([7.9, 0.0, 1.5]), IDENTITY, OPTIONS).passed == 0
    progress = route.advance(np.array([8.1, 0.0, 1.5]), IDENTITY, OPTIONS)
    assert (progress.passed, progress.corner, route.index) == (1, False, 1)
    # the corner needs corner_tolerance (0.5 m); passing it asks for a stop and turn
    assert route.advance(np.array([10.0, 9.4, 1.5]), IDENTITY, OPTIONS).passed == 0
    progress = route.advance(np.array([10.0, 9.6, 1.5]), IDENTITY, OPTIONS)
    assert progress.corner and route.index == 2 and route.at_last


def test_the_goal_is_reached_within_its_horizontal_and_height_tolerances():
    route = Route([[5.0, 0.0, 1.5]], math.radians(30.0))
    assert not route.advance(np.array([4.0, 0.0, 2.6]), IDENTITY, OPTIONS).goal_reached
    assert route.advance(np.array([4.0, 0.0, 2.4]), IDENTITY, OPTIONS).goal_reached
    assert not route.advance(np.array([3.4, 0.0, 1.5]), IDENTITY, OPTIONS).goal_reached


def test_waypoints_in_px4s_frame_are_followed_in_the_vins_world():
    T_L_W = make_pose(rot_z(math.pi / 2), [1.0, 2.0, 0.0])  # W is L turned a quarter left
    route = Route([[1.0, 12.0, 1.5]], math.radians(30.0))
    np.testing.assert_allclose(route.next_W(T_L_W), [10.0, 0.0, 1.5], atol=1e-12)
    assert heading_error(IDENTITY, route.next_W(T_L_W)) == pytest.approx(0.0, abs=1e-9)
    assert heading_error(make_pose(rot_z(0.5), [0.0, 0.0, 1.5]),
                         route.next_W(T_L_W)) == pytest.approx(-0.5)


@pytest.mark.parametrize("waypoints", [[], [[1.0, 2.0]], [[0.0, math.nan, 1.0]]])
def test_a_malformed_route_is_refused(waypoints):
    with pytest.raises(ValueError, match="waypoints must be"):
        Route(waypoints, 0.5)


# ---------------------------------------------------------------- the flown trail

def test_the_way_back_follows_the_flown_trail_and_never_descends_the_take_off_column():
    trail = an_l_shaped_trail()
    here = np.array([3.0, 2.0, 1.5])
    # from here through every trail point back: down the north leg, round the corner, west
    way = trail.way_back(here, 3.0)
    expected = [(3.0, y, 1.5) for y in np.linspace(2.0, 0.0, 17)] + \
        [(x, 0.0, 1.5) for x in np.linspace(2.875, 2.0, 8)]
    np.testing.assert_allclose(way, [here] + expected, atol=1e-9)
    # farther than the trail above the column: its first point up there, never down the column
    way = trail.way_back(here, 20.0)
    assert np.allclose(way[-1], (0.125, 0.0, 1.5)) and way[:, 2].min() == 1.5


def test_a_glide_back_and_forth_is_erased_from_the_trail():
    trail = Trail()
    fly_trail(trail, [(x, 0.0, 1.5) for x in np.linspace(0.0, 2.0, 17)])
    fly_trail(trail, [(x, 0.0, 1.5) for x in np.linspace(2.0, 1.5, 5)])  # back for parallax
    fly_trail(trail, [(x, 0.0, 1.5) for x in np.linspace(1.5, 2.0, 5)])  # and forth again
    fly_trail(trail, [(2.0, 0.005, 1.5)] * 50)  # hovering adds nothing
    assert len(trail) == 17 and len(trail.climbing) == 17
    assert np.allclose(trail.points[-1], (2.0, 0.0, 1.5))
    way = trail.way_back(np.array([2.0, 0.0, 1.5]), 1.0)
    np.testing.assert_allclose(way[:, 0], [2.0, 2.0, 1.875, 1.75, 1.625, 1.5, 1.375, 1.25,
                                           1.125, 1.0])


def test_no_way_back_shorter_than_one_glide():
    trail = Trail()
    fly_trail(trail, [(0.0, 0.0, z) for z in np.linspace(0.0, 1.5, 13)], climbing=True)
    assert trail.way_back(np.array([0.0, 0.0, 1.5]), 2.0) is None
    fly_trail(trail, [(0.125, 0.0, 1.5), (0.25, 0.0, 1.5), (0.375, 0.0, 1.5)])
    assert trail.way_back(np.array([0.375, 0.0, 1.5]), 2.0) is None


# ---------------------------------------------------------------- turning at a corner

def test_a_passed_corner_or_a_waypoint_far_off_the_heading_makes_the_vehicle_turn(planner):
    assert must_turn(True, 0.0, None, OPTIONS)
    threshold = OPTIONS.align_threshold_deg  # 90 degrees: nearer the heading, the arcs turn
    assert not must_turn(False, math.radians(threshold - 1.0), None, OPTIONS)
    assert must_turn(False, math.radians(threshold + 1.0), None, OPTIONS)
    # on an approach glide the bearing to the point swings wildly close to it: no turn
    approach = planner.glide(0.0, make_pose(np.eye(3), [0.0, 0.0, 1.5]),
                             np.array([1.0, 0.0, 1.5]), "approach")
    assert not must_turn(False, math.radians(170.0), approach, OPTIONS)
    assert must_turn(True, math.radians(170.0), approach, OPTIONS)


def test_only_the_stop_before_a_turn_counts_as_braking_to_turn(planner):
    """The failsafe on stale depth waits while the vehicle brakes to a turn (that stop was
    checked at the last round); a stop for any other reason is not it."""
    T_W_B, velocity = make_pose(np.eye(3), [0.0, 0.0, 1.5]), np.array([1.0, 0.0, 0.0])
    turn_stop = planner.stop_plan(0.0, T_W_B, velocity, TURN_STOP_REASON)
    assert on_glide(turn_stop, TURN_STOP_REASON, 0.5)
    assert not on_glide(turn_stop, TURN_STOP_REASON, turn_stop.end_time)  # run out
    assert not on_glide(planner.stop_plan(0.0, T_W_B, velocity, "no safe primitive"),
                        TURN_STOP_REASON, 0.5)
    assert not on_glide(planner.glide(0.0, T_W_B, np.array([1.0, 0.0, 1.5]), PARALLAX_REASON),
                        TURN_STOP_REASON, 0.5)
    assert not on_glide(None, TURN_STOP_REASON, 0.5)


def test_a_turn_in_place_turns_toward_the_waypoint_until_within_align_done():
    assert turn_rate(0.5, OPTIONS) == pytest.approx(math.radians(30.0))  # align_yaw_rate_deg
    assert turn_rate(-2.0, OPTIONS) == pytest.approx(-math.radians(30.0))
    assert still_turning(math.radians(15.1), OPTIONS) and not facing(math.radians(15.1), OPTIONS)
    assert facing(math.radians(-14.9), OPTIONS) and not still_turning(math.radians(14.9), OPTIONS)


# ---------------------------------------------------------------- the offset swing

#: The swing measured (off by default): 10 degrees each way, 2 s a period.
SWING = FlightOptions(offset_swing_deg=10.0)


def test_the_offset_swing_yaws_its_amplitude_each_way_and_back_every_period():
    swing, period = OffsetSwing(SWING), SWING.offset_swing_period_s
    dt = period / 2000
    rates = np.array([swing.rate(k * dt) for k in range(2000)])
    heading = np.concatenate([[0.0], np.cumsum(rates) * dt])  # the rate integrated
    assert heading.max() == pytest.approx(math.radians(SWING.offset_swing_deg), rel=1e-2)
    assert heading.min() == pytest.approx(-math.radians(SWING.offset_swing_deg), rel=1e-2)
    assert heading[-1] == pytest.approx(0.0, abs=1e-3)  # back where it began
    assert heading[1000] == pytest.approx(0.0, abs=1e-3)  # and half a period in
    # the rate changes all the time: what shows the camera's time offset
    assert np.all(np.abs(np.diff(rates)) > 0)


def test_the_offset_swing_ends_when_the_heading_is_back_after_the_offset_is_known():
    half = SWING.offset_swing_period_s / 2.0
    swing = OffsetSwing(SWING)
    assert not swing.over(0.4, known=False)
    assert not swing.over(half + 0.3, known=True)  # known: on to the next half period
    assert not swing.over(2 * half - 0.01, known=False)  # decided once known
    assert swing.over(2 * half, known=False)
    # known on a half period's end: over at once
    assert OffsetSwing(SWING).over(half, known=True)


def test_the_offset_swing_ends_unknown_at_its_timeout():
    swing = OffsetSwing(SWING)
    assert not swing.over(SWING.offset_swing_timeout_s - 0.01, known=False)
    assert swing.over(SWING.offset_swing_timeout_s, known=False)


@pytest.mark.parametrize("settings, words", [
    ({"offset_swing_deg": 30.0, "offset_swing_period_s": 1.0}, "peaks at 188 deg/s"),
    ({"offset_swing_period_s": 4.0, "offset_swing_timeout_s": 1.5}, "at least half")])
def test_a_swing_too_fast_or_a_timeout_shorter_than_half_a_swing_is_refused(settings, words):
    with pytest.raises(OptionError, match=words):
        FlightOptions(**settings)
    assert FlightOptions(offset_swing_deg=0.0).offset_swing_deg == 0.0  # off: never swings


@pytest.mark.parametrize("offset, unknown", [
    (TimeOffset(0.015), False),  # fixed by the options
    (TimeOffset(0.0, estimating=True), True),  # nothing has shown it yet
    (TimeOffset(0.012, sigma=0.0015, estimating=True), True),  # too uncertain
    (TimeOffset(0.015, sigma=0.0004, estimating=True), False)])
def test_the_offset_is_unknown_only_while_estimated_and_not_yet_shown(offset, unknown):
    assert offset_unknown(offset, max_sigma_s=0.001) is unknown


# ---------------------------------------------------------------- the parallax glide

def test_after_a_turn_it_glides_back_half_a_metre_and_returns_until_depth_comes(planner):
    trail = an_l_shaped_trail()
    corner = np.array([3.0, 2.0, 1.5])
    parallax = ParallaxGlide()
    parallax.start(trail, corner)
    starved = view_starved(math.inf, None)  # no fit
    back = parallax.step(None, 10.0, starved)
    np.testing.assert_allclose(back, (3.0, 1.5, 1.5))  # half a metre back along the trail
    glide = planner.glide(10.0, make_pose(np.eye(3), corner), back, PARALLAX_REASON)
    assert parallax.step(glide, 10.5, starved) is Step.KEEP  # gliding back
    # returns to the corner even when the fit came back on the way
    np.testing.assert_allclose(parallax.step(glide, glide.end_time, False), corner)
    assert not parallax.active and parallax.step(None, 20.0, starved) is Step.IDLE


def test_the_parallax_glide_is_given_up_when_a_fresh_fit_and_landmarks_come_before_it_starts():
    parallax = ParallaxGlide()
    parallax.start(an_l_shaped_trail(), np.array([3.0, 2.0, 1.5]))
    assert parallax.step(None, 10.0, view_starved(PARALLAX_WAIT_S, PARALLAX_LANDMARKS)) \
        is Step.IDLE
    assert not parallax.active


@pytest.mark.parametrize("fit_age_s, landmarks, starved", [
    (PARALLAX_WAIT_S + 0.01, 80, True),  # no fresh fit (estimated depth without anchors)
    (0.0, PARALLAX_LANDMARKS - 1, True),  # a fresh fit, but a VINS flying on the IMU alone
    (0.0, 0, True),
    (0.0, PARALLAX_LANDMARKS, False),
    (0.0, None, False),  # no VINS update yet: the fit alone decides
])
def test_the_view_after_a_turn_is_starved_by_a_lapsed_fit_or_too_few_landmarks(
        fit_age_s, landmarks, starved):
    """True depth never lacks a fit, so after a turn in place that left the VINS no landmark
    (a realistic mine flight, docs/results.md) only the landmark count starts the glide."""
    assert view_starved(fit_age_s, landmarks) is starved


@pytest.mark.parametrize("turned, landmarks, paused", [
    (TURN_STEP, PARALLAX_LANDMARKS - 1, True),  # the VINS running out of landmarks
    (TURN_STEP, PARALLAX_LANDMARKS, False),
    (TURN_STEP - 0.01, 0, False),  # began starved: a step of the turn before the next glide
    (math.pi, None, False),  # no VINS update yet
])
def test_a_long_turn_is_paused_for_parallax_when_the_landmarks_run_low(turned, landmarks,
                                                                       paused):
    assert pause_turn(turned, landmarks) is paused


def test_depth_lapsed_on_the_arcs_half_way_to_the_staleness_failsafe():
    """Half of depth_timeout_s leaves the other half for braking on the checked stop before
    the glide, while the failsafe waits."""
    half = 0.5 * OPTIONS.depth_timeout_s
    assert not depth_lapsed(half, OPTIONS) and depth_lapsed(half + 0.01, OPTIONS)
    assert failsafe_reason(vitals(depth_age_s=half + 0.01), OPTIONS) == ""


def test_no_parallax_glide_without_half_a_metre_of_trail_behind():
    parallax = ParallaxGlide()
    parallax.start(Trail(), np.array([3.0, 2.0, 1.5]))
    assert not parallax.active


# ---------------------------------------------------------------- the approach

def test_a_corner_is_approached_exactly_and_the_goal_short_of_its_point():
    here, corner = np.array([0.0, 0.0, 1.5]), np.array([3.0, 0.0, 1.5])
    kwargs = dict(stop_here=True, slowest_speed=0.5, options=OPTIONS)
    np.testing.assert_allclose(approach_targets(corner, here, 0.1, is_goal=False, **kwargs),
                               [corner])
    # the goal: half goal_tolerance (0.75 m) short, then 0.9 of it (1.35 m) short
    np.testing.assert_allclose(approach_targets(corner, here, 0.1, is_goal=True, **kwargs),
                               [(2.25, 0.0, 1.5), (1.65, 0.0, 1.5)])


@pytest.mark.parametrize("stop_here, distance, speed", [
    (False, 3.0, 0.1),  # a waypoint the route flies through
    (True, 4.1, 0.1),  # beyond approach_distance (4 m)
    (True, 3.0, 0.71),  # faster than the slowest tier (0.5 m/s) + stopped_speed (0.2 m/s)
])
def test_no_approach_far_off_fast_or_to_a_waypoint_flown_through(stop_here, distance, speed):
    assert approach_targets(np.array([distance, 0.0, 1.5]), np.array([0.0, 0.0, 1.5]), speed,
                            stop_here=stop_here, is_goal=False, slowest_speed=0.5,
                            options=OPTIONS) == []


# ---------------------------------------------------------------- blocked: turn, back off

def test_blocked_it_brakes_then_turns_once_then_backs_off_after_half_the_no_path_time():
    clock = NoPathClock()
    far_off = math.radians(40.0)
    assert clock.blocked(0.0, False, far_off, OPTIONS) == Blocked.WAIT  # still braking
    assert clock.blocked(0.5, True, far_off, OPTIONS) == Blocked.TURN
    assert clock.since is None and clock.turned  # the turn restarts the clock
    assert clock.blocked(2.0, True, 0.0, OPTIONS) == Blocked.WAIT
    assert clock.blocked(3.4, True, far_off, OPTIONS) == Blocked.WAIT  # turned once already
    assert clock.blocked(3.5, True, 0.0, OPTIONS) == Blocked.BACK_OFF  # 1.5 s = half of 3 s
    assert not clock.expired(5.0, OPTIONS) and clock.expired(5.01, OPTIONS)
    clock.reset()
    assert clock.since is None and not clock.turned and not clock.expired(100.0, OPTIONS)


def test_a_stop_by_choice_restarts_the_no_path_clock_and_keeps_the_turn_made():
    """A corner's turn or a parallax glide while blocked: the clock starts again at the next
    blocked round, so the back-off still comes after half the no-path time; the one turn
    toward the waypoint stays spent."""
    clock = NoPathClock()
    far_off = math.radians(40.0)
    assert clock.blocked(0.0, True, far_off, OPTIONS) == Blocked.TURN
    assert clock.blocked(1.0, True, 0.0, OPTIONS) == Blocked.WAIT
    assert clock.expired(4.5, OPTIONS)  # a glide from 1.0 s to 4.5 s, the clock running
    clock.restart()
    assert not clock.expired(4.5, OPTIONS)
    assert clock.blocked(4.5, True, far_off, OPTIONS) == Blocked.WAIT  # no second turn
    assert clock.blocked(6.0, True, 0.0, OPTIONS) == Blocked.BACK_OFF
    assert not clock.expired(7.5, OPTIONS)


def _candidates_blocked_on(planner, side: float) -> Candidates:
    """The slowest tier, every arc turning to ``side`` (+1 left, -1 right) blocked."""
    tier = planner.tiers[-1]
    blocked = np.sign(tier.yaw_rates) == side
    return Candidates(tier.speed, tier.library, np.zeros(len(blocked), bool), -1, blocked, 1.0)


@pytest.mark.parametrize("blocked_side, first", [(-1.0, LOOK_ASIDE), (1.0, -LOOK_ASIDE)])
def test_blocked_with_no_way_back_it_looks_to_the_freer_side_then_the_other(
        planner, blocked_side, first):
    clock = NoPathClock()
    clock.blocked(0.0, True, 0.0, OPTIONS)
    assert clock.look_aside(_candidates_blocked_on(planner, blocked_side)) == first
    assert clock.aim == first and clock.since is None  # the look restarts the clock
    assert clock.look_aside(None) == -first and clock.aim == -first
    assert clock.look_aside(None) is None  # both sides seen: the failsafe is next
    clock.blocked(9.0, True, 0.0, OPTIONS)
    assert clock.expired(12.01, OPTIONS)
    clock.reset()  # a safe plan: aimed at the waypoint again, both looks allowed again
    assert clock.aim == 0.0 and clock.look_aside(None) == LOOK_ASIDE


def _glides(planner: Planner) -> tuple[float, float]:
    """A backing-off's glides: the slowest tier's speed and its braking distance."""
    slowest = planner.tiers[-1].speed
    return slowest, slowest * planner.options.stop_duration_s / 2.0


def _fly_back(planner: Planner, backoff: Backoff, here: np.ndarray, period: float = 1.0 / 12.0):
    """Fly a backing-off's glides, each round from where the last plan's setpoint is: the
    time it took, the positions flown, and the kind of every plan."""
    t, plan, flown, kinds = 0.0, None, [here], []
    while (step := backoff.step(plan, t, flown[-1], *_glides(planner))) is not Step.IDLE:
        if step is not Step.KEEP:
            plan = planner.glide(t, make_pose(np.eye(3), flown[-1]), step.target,
                                 BACKOFF_REASON, stop_at_goal=step.stop)
            kinds.append(plan.kind)
        t += period
        flown.append(plan.setpoint(t).position_W)
    return t, np.array(flown), kinds, plan


@pytest.mark.parametrize("stop_duration, seconds", [(2.0, 7.0), (1.0, 6.25)])
def test_backing_off_is_one_run_along_the_trail_that_brakes_once_at_its_end(stop_duration,
                                                                          seconds):
    planner = Planner(PinholeCamera.from_hfov(160, 120, math.radians(90.0)),
                      PlannerOptions(stop_duration_s=stop_duration))
    trail, here = an_l_shaped_trail(), np.array([3.0, 2.0, 1.5])
    backoff = Backoff()
    assert backoff.start(trail, here, FlightOptions(backoff_distance=3.0))
    flown_s, flown, kinds, last = _fly_back(planner, backoff, here)
    # through the corner at (3, 0) to the trail 3 m back, and at rest there
    np.testing.assert_allclose(flown[-1], (2.0, 0.0, 1.5), atol=1e-6)
    np.testing.assert_allclose(last.setpoint(flown_s).velocity_W, 0.0, atol=1e-9)
    # braked once: every plan before the last glides on through its point
    assert kinds[-1] == "stop" and set(kinds[:-1]) == {"glide"}
    # about 2.8 m (the corner cut) at the slowest tier's 0.5 m/s until its braking distance
    # is left, then braking over it: 0.5 m in 2 s, or 0.25 m in 1 s (glides from rest to
    # rest half a metre apart took 12 s)
    assert flown_s == pytest.approx(seconds, abs=0.2)
    # never farther from the trail than the corner's cut, half the pursuit distance
    from_north_leg = np.hypot(flown[:, 0] - 3.0, flown[:, 1] - np.clip(flown[:, 1], 0.0, 2.0))
    from_east_leg = np.hypot(flown[:, 1], flown[:, 0] - np.clip(flown[:, 0], 0.0, 3.0))
    assert np.minimum(from_north_leg, from_east_leg).max() <= Backoff.PURSUIT_M / 2.0
    assert np.all(flown[:, 2] == pytest.approx(1.5))


def test_backing_off_at_most_max_backoffs_times_and_only_with_a_way_back(planner):
    trail, here = an_l_shaped_trail(), np.array([3.0, 2.0, 1.5])
    backoff = Backoff()
    assert backoff.start(trail, here, OPTIONS) and backoff.active
    _, flown, _, _ = _fly_back(planner, backoff, here)
    np.testing.assert_allclose(flown[-1], (3.0, 0.0, 1.5), atol=1e-6)  # 2 m back
    assert not backoff.active
    assert backoff.start(trail, here, OPTIONS)  # the second of max_backoffs = 2
    assert not backoff.start(trail, here, OPTIONS)
    backoff.count = 0  # a waypoint passed
    assert not backoff.start(Trail(), here, OPTIONS)  # no trail, no way back


def test_a_backing_off_held_back_comes_to_rest_on_the_way_in_twice_its_time(planner):
    """The vehicle does not move (held back, or its estimate drifting): the run does not go
    on for ever, keeping the staleness failsafe waiting; after twice the way's time at the
    glides' speed it glides to rest on the nearest point of the way."""
    trail, here = an_l_shaped_trail(), np.array([3.0, 2.0, 1.5])
    backoff, (slowest, braking) = Backoff(), _glides(planner)
    assert backoff.start(trail, here, OPTIONS)
    t = 0.0
    while not isinstance(step := backoff.step(None, t, here, slowest, braking),
                         Step) and not step.stop:
        t += 1.0 / 12.0
    assert t == pytest.approx(2.0 * 2.0 / slowest, abs=0.1)  # 2 m at 0.5 m/s, twice over
    np.testing.assert_allclose(step.target, here)  # the nearest point: where it is
    # already there, no glide: the application brakes where it is for the backing-off
    assert planner.glide(t, make_pose(np.eye(3), here), step.target, BACKOFF_REASON) is None
    stop = planner.stop_plan(t, make_pose(np.eye(3), here), np.zeros(3), BACKOFF_REASON)
    assert backoff.step(stop, t + 0.1, here, slowest, braking) is Step.KEEP
    assert backoff.step(stop, stop.end_time, here, slowest, braking) is Step.IDLE


def test_a_backoff_distance_under_half_a_metre_still_backs_off_that_far():
    trail, here = an_l_shaped_trail(), np.array([3.0, 2.0, 1.5])
    way = trail.way_back(here, 0.3)
    np.testing.assert_allclose(way[-1], (3.0, 1.625, 1.5))  # the first point 0.3 m back
    assert trail.way_back(here, 0.0) is None  # 0: never


# ---------------------------------------------------------------- failsafe rules

def vitals(**changes) -> Vitals:
    healthy = dict(stop_requested="", loop_lag_s=0.01, watchdog_in_charge=False,
                   camera_age_s=0.05, imu_age_s=0.005, vins_problem="", depth_age_s=0.05,
                   depth_reason="", blind_s=0.5, blind_expired=False, on_flown_ground=False,
                   no_path_expired=False)
    return Vitals(**{**healthy, **changes})


@pytest.mark.parametrize("changes, reason", [
    ({}, ""),
    ({"stop_requested": "stop requested (SIGTERM)"}, "stop requested (SIGTERM)"),
    ({"loop_lag_s": 0.45}, "event loop stalled (450 ms late)"),
    ({"watchdog_in_charge": True}, "setpoint deadline missed (watchdog sent the stop)"),
    ({"camera_age_s": 0.6}, "camera silent"),
    ({"imu_age_s": math.inf}, "IMU silent"),
    ({"vins_problem": "VINS reset in flight"}, "VINS reset in flight"),
    ({"blind_s": 3.04, "blind_expired": True}, "VINS blind (< 5 landmarks for 3.0 s)"),
    ({"blind_s": 3.04, "blind_expired": True, "on_flown_ground": True},
     "VINS blind (< 5 landmarks for 3.0 s)"),
    ({"depth_age_s": 1.2, "depth_reason": "no fit (too_few_anchors)"},
     "no metric depth (no fit (too_few_anchors))"),
    ({"depth_age_s": math.inf}, "no metric depth (none yet)"),
    ({"depth_age_s": 5.0, "on_flown_ground": True}, ""),  # depth may lapse on flown ground
    ({"no_path_expired": True}, "no safe primitive"),
])
def test_each_failsafe_rule_names_its_reason(changes, reason):
    assert failsafe_reason(vitals(**changes), OPTIONS) == reason


def test_only_the_missions_own_failures_glide_to_a_landing_site_before_landing():
    """docs/flight.md, "Where it lands": after an operator's stop (maybe for something
    ahead), a stalled loop or a failed sensor the vehicle lands where it stopped."""
    seeking = {failsafe_reason(vitals(no_path_expired=True), OPTIONS), MISSION_TIMEOUT}
    assert seeking == SITE_SEEKING_FAILSAFES
    for changes in ({"stop_requested": "stop requested (SIGTERM)"}, {"loop_lag_s": 0.45},
                    {"watchdog_in_charge": True}, {"camera_age_s": 0.6},
                    {"vins_problem": "VINS lost (no tracks)"}, {"depth_age_s": 1.2}):
        assert failsafe_reason(vitals(**changes), OPTIONS) not in SITE_SEEKING_FAILSAFES


def test_the_most_basic_failure_is_the_one_reported():
    # a silent camera starves the depth too: the camera is the cause
    assert failsafe_reason(vitals(camera_age_s=2.0, depth_age_s=2.0), OPTIONS) == \
        "camera silent"
    assert failsafe_reason(vitals(stop_requested="stop", loop_lag_s=9.0), OPTIONS) == "stop"


def test_a_blind_vins_is_reported_after_its_loss_and_before_the_depth_it_starves():
    assert failsafe_reason(vitals(vins_problem="VINS lost (no tracks)", blind_s=9.0,
                                  blind_expired=True), OPTIONS) == "VINS lost (no tracks)"
    assert failsafe_reason(vitals(blind_s=9.0, blind_expired=True, depth_age_s=9.0),
                           OPTIONS).startswith("VINS blind")


@pytest.mark.parametrize("changes, failed", [
    ({"vins_problem": "VINS lost (no tracks)"}, True),
    ({"vins_problem": "VINS reset in flight"}, True),
    ({"blind_s": 3.04, "blind_expired": True}, True),
    ({"blind_s": 2.0}, False),  # blind, but not yet past the timeout
    ({"camera_age_s": 0.6}, False),
    ({"depth_age_s": 1.2, "depth_reason": "no fit (too_few_anchors)"}, False),
    ({"no_path_expired": True}, False),
])
def test_only_a_lost_reset_or_blind_vins_has_its_stop_flown_off_the_vins(changes, failed):
    assert vins_failed(vitals(**changes)) is failed


def blind_readings(landmarks_and_counting, rate_hz=20.0) -> list[tuple[float, bool]]:
    """``(blind_s, expired)`` after each check of a ``rate_hz`` monitor fed these pairs."""
    clock, readings = BlindClock(), []
    for i, (landmarks, counting) in enumerate(landmarks_and_counting):
        clock.update(i / rate_hz, landmarks, counting, OPTIONS)
        readings.append((clock.blind_s, clock.expired(OPTIONS)))
    return readings


def test_the_blind_clock_counts_time_with_too_few_landmarks_only_off_a_turn_in_place():
    # 1 s blind in flight, 2 s turning in place (held), 1 s blind again: 2 s counted
    readings = blind_readings([(2, True)] * 21 + [(0, False)] * 40 + [(0, True)] * 20)
    assert readings[20][0] == pytest.approx(1.0)
    assert readings[60][0] == pytest.approx(1.0)
    assert readings[-1] == (pytest.approx(2.0), False)


def test_the_blind_clock_restarts_when_landmarks_come_back():
    few, enough = OPTIONS.blind_landmarks - 1, OPTIONS.blind_landmarks
    readings = blind_readings([(few, True)] * 50 + [(enough, True)] + [(few, True)] * 11)
    assert readings[49][0] == pytest.approx(2.45)
    assert readings[50][0] == 0.0
    assert readings[-1][0] == pytest.approx(0.55)  # from the check that still saw enough
    # no VINS estimate yet is not blind (INITIALISING has its own rules)
    assert blind_readings([(None, True)] * 10)[-1] == (0.0, False)


def test_a_vins_blind_past_the_timeout_stops_the_flight():
    readings = blind_readings([(0, True)] * 70)
    reasons = [failsafe_reason(vitals(blind_s=s, blind_expired=expired), OPTIONS)
               for s, expired in readings]
    first = next(i for i, reason in enumerate(reasons) if reason)
    assert readings[first][0] > OPTIONS.blind_timeout_s >= readings[first - 1][0]
    assert reasons[first].startswith("VINS blind (< 5 landmarks for 3.")


def test_the_vins_is_flown_on_unless_lost_or_reset_since_the_take_off():
    assert vins_problem(None, "", 0, 0) == ""
    assert vins_problem(HealthState.OK, "", 1, 1) == ""
    assert vins_problem(HealthState.DEGRADED, "few tracks", 1, 1) == ""
    assert vins_problem(HealthState.LOST, "no tracks", 1, 1) == "VINS lost (no tracks)"
    assert vins_problem(HealthState.OK, "", 2, 1) == "VINS reset in flight"


# ---------------------------------------------------------------- the mission

def test_mission_keeps_every_transition_with_its_reason_and_tells_its_listener():
    heard = []
    mission = Mission(0.0, on_transition=heard.append)
    mission.go(1.0, FlightState.INITIALISING, "link up")
    mission.go(1.0, FlightState.INITIALISING, "again")  # no-op
    mission.go(3.0, FlightState.TAKING_OFF, "VINS initialised")
    assert [(t.source, t.target, t.reason) for t in mission.transitions] == [
        (FlightState.PREFLIGHT, FlightState.INITIALISING, "link up"),
        (FlightState.INITIALISING, FlightState.TAKING_OFF, "VINS initialised")]
    assert heard == mission.transitions
    assert mission.elapsed(4.5) == pytest.approx(1.5)


def test_a_failsafe_stops_navigation_once_and_records_every_reason():
    mission = Mission(0.0)
    mission.go(1.0, FlightState.NAVIGATING, "offboard")
    assert mission.failsafe(2.0, "camera silent")
    assert mission.state == FlightState.FAILSAFE_STOP
    assert not mission.failsafe(2.1, "IMU silent")  # already stopping
    assert mission.failsafes == ["camera silent", "IMU silent"]
    assert mission.transitions[-1].reason == "failsafe: camera silent"
    assert mission.stopped_by == "camera silent"  # what decides where it lands


def test_a_failsafe_on_the_ground_changes_nothing():
    mission = Mission(0.0)
    assert not mission.failsafe(1.0, "camera silent")
    assert mission.state == FlightState.PREFLIGHT
