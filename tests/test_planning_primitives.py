"""The forward-arc library: the paper's 75 arcs, exact geometry, a stop at the end of each."""

import math

import numpy as np
import pytest

from autonomy.options import OptionError
from autonomy.planning.primitives import (
    PrimitiveOptions, braking_points, forward_arc, library, stop_primitive, tier_speeds,
)

OPTIONS = PrimitiveOptions()


def _steps(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(points, axis=0), axis=1)


def test_the_default_library_is_the_papers_75_arcs_at_2_m_s_for_2_s():
    arcs = library()
    assert len(arcs) == 75
    assert {a.speed for a in arcs} == {2.0}
    assert len({a.yaw_rate for a in arcs}) == 15 and len({a.vertical_speed for a in arcs}) == 5
    assert max(a.yaw_rate for a in arcs) == pytest.approx(math.radians(45.0))
    assert min(a.vertical_speed for a in arcs) == pytest.approx(-0.5)
    assert all(a.t[0] == 0.0 and a.t[-1] == pytest.approx(2.0) for a in arcs)
    assert any(a.yaw_rate == 0.0 and a.vertical_speed == 0.0 for a in arcs)


def test_slower_tiers_are_a_ratio_slower_and_keep_the_turn_rates():
    assert tier_speeds() == [2.0, 1.0, 0.5]
    assert tier_speeds(PrimitiveOptions(speed_tiers=1)) == [2.0]
    # a finer ladder: a tier between each two of the default ones
    finer = tier_speeds(PrimitiveOptions(speed_tiers=5, tier_ratio=math.sqrt(0.5)))
    assert finer == pytest.approx([2.0, math.sqrt(2.0), 1.0, math.sqrt(0.5), 0.5])
    slow = library(speed=0.5)
    assert len(slow) == 75 and {a.speed for a in slow} == {0.5}
    assert {a.yaw_rate for a in slow} == {a.yaw_rate for a in library()}
    straight = next(a for a in slow if a.yaw_rate == 0.0 and a.vertical_speed == 0.0)
    # 1 m of arc, 0.5 m of braking (u T / 2): a slow arc needs little room
    assert straight.stop_points_S[-1, 0] == pytest.approx(1.5)


def test_an_arc_may_be_given_its_own_duration_but_a_positive_one():
    arc = forward_arc(0.5, 0.0, 0.0, OPTIONS, 7.0)
    assert arc.duration == pytest.approx(7.0) and arc.points_S[-1, 0] == pytest.approx(3.5)
    for duration in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="duration"):
            forward_arc(0.5, 0.0, 0.0, OPTIONS, duration)


@pytest.mark.parametrize("yaw_rate, climb", [(math.radians(40.0), 0.5), (0.0, -0.25)])
def test_the_motion_along_a_primitive_is_its_points_and_their_derivatives(yaw_rate, climb):
    arc = forward_arc(1.5, yaw_rate, climb, OPTIONS)
    T = OPTIONS.stop_duration_s
    for tau, point in zip(arc.t, arc.points_S):
        np.testing.assert_allclose(arc.motion_S(tau, T)[0], point, atol=1e-12)
    np.testing.assert_allclose(arc.motion_S(10.0, T)[0], arc.stop_points_S[-1], atol=1e-12)
    np.testing.assert_allclose(arc.motion_S(10.0, T)[1:3], 0.0)
    h = 1e-6
    for tau in (0.3, 1.7, 2.0 + 0.5, 2.0 + 1.9):  # on the arc, then braking
        p0, v0, a0, _ = arc.motion_S(tau - h, T)
        p1, v1, a1, _ = arc.motion_S(tau + h, T)
        position, velocity, acceleration, rate = arc.motion_S(tau, T)
        np.testing.assert_allclose((p1 - p0) / (2 * h), velocity, atol=1e-6)
        np.testing.assert_allclose((v1 - v0) / (2 * h), acceleration, atol=1e-5)
        assert rate == (yaw_rate if tau < 2.0 else 0.0)


def test_an_arc_is_a_circle_of_radius_v_over_w_at_constant_speed():
    w = math.radians(30.0)
    arc = forward_arc(2.0, w, 0.0, OPTIONS)
    centre = np.array([0.0, 2.0 / w])  # to the left for a positive (counter-clockwise) rate
    radii = np.linalg.norm(arc.points_S[:, :2] - centre, axis=1)
    np.testing.assert_allclose(radii, 2.0 / w, rtol=1e-12)
    assert arc.heading == pytest.approx(w * 2.0)
    horizontal = np.sum(_steps(arc.points_S))
    assert horizontal == pytest.approx(4.0, rel=1e-3)  # chords of a 4 m arc


def test_the_straight_arc_and_the_climb():
    arc = forward_arc(2.0, 0.0, 0.5, OPTIONS)
    np.testing.assert_allclose(arc.points_S[-1], [4.0, 0.0, 1.0])
    np.testing.assert_allclose(arc.points_S[:, 1], 0.0)


def test_left_and_right_turns_mirror_each_other():
    left, right = (forward_arc(2.0, s * 0.5, 0.0, OPTIONS) for s in (1, -1))
    np.testing.assert_allclose(left.points_S * [1, -1, 1], right.points_S, atol=1e-12)
    np.testing.assert_allclose(left.stop_points_S * [1, -1, 1], right.stop_points_S, atol=1e-12)


def test_points_are_at_most_sample_spacing_apart_along_arc_and_extension():
    for arc in library():
        path = np.vstack([arc.points_S, arc.stop_points_S])
        assert _steps(path).max() <= OPTIONS.sample_spacing + 1e-9


def test_the_extension_brakes_along_the_final_velocity_to_rest_half_its_distance_on():
    arc = forward_arc(2.0, 0.4, -0.5, OPTIONS)
    velocity = arc.end_velocity_S
    np.testing.assert_allclose(arc.stop_points_S[-1],
                               arc.points_S[-1] + velocity * OPTIONS.stop_duration_s / 2.0)
    direction = (arc.stop_points_S - arc.points_S[-1]) / np.linalg.norm(velocity)
    np.testing.assert_allclose(np.cross(direction, velocity), 0.0, atol=1e-12)
    steps = _steps(np.vstack([arc.points_S[-1:], arc.stop_points_S]))
    assert np.all(np.diff(steps) < 0)  # slowing down at a constant rate


def test_the_stop_primitive_brakes_from_the_present_velocity_and_from_rest_stays():
    stop = stop_primitive([1.0, -1.0, 0.2])
    np.testing.assert_allclose(stop.stop_points_S[-1], [1.0, -1.0, 0.2])  # v T / 2, T = 2 s
    assert stop.heading == pytest.approx(-math.pi / 4)
    at_rest = stop_primitive(np.zeros(3))
    np.testing.assert_allclose(at_rest.stop_points_S, 0.0)
    with pytest.raises(ValueError, match="finite"):
        stop_primitive([np.nan, 0.0, 0.0])


def test_braking_points_end_at_rest_at_v_t_over_2():
    points = braking_points(np.array([1.0, 2.0, 3.0]), np.array([4.0, 0.0, 0.0]), OPTIONS)
    np.testing.assert_allclose(points[-1], [5.0, 2.0, 3.0])


def test_a_single_yaw_rate_and_vertical_speed_give_the_straight_level_arc():
    arcs = library(PrimitiveOptions(yaw_rates=1, vertical_speeds=1, max_yaw_rate_deg=0.0))
    assert [(a.yaw_rate, a.vertical_speed) for a in arcs] == [(0.0, 0.0)]


@pytest.mark.parametrize("key, value", [("speed", 0.0), ("duration_s", -1.0), ("yaw_rates", 0),
                                        ("sample_spacing", 0.0), ("max_yaw_rate_deg", 0.0),
                                        ("tier_ratio", 0.0), ("tier_ratio", 1.0)])
def test_bad_options_are_named(key, value):
    with pytest.raises(OptionError, match=key):
        PrimitiveOptions(**{key: value})
