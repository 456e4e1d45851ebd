"""Landmark triangulation and the gate in front of the smoother: the midpoint method recovers a
known point, and the gate keeps only points the observations pin down (enough views, enough
parallax, in front of every camera within the depth range, consistent with every observation);
the depth uncertainty follows the observation geometry; a landmark's later observations are used
within a limit widened by what the whole keyframe shares (the predicted pose's own error)."""

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from autonomy.geometry import so3_exp
from autonomy.vins.landmarks import (MIN_OBSERVATIONS_FOR_MEDIAN, Gate, depth_sigma,
                                     gate_candidates, midpoint_triangulate,
                                     observation_limit_px, spread_choice, widest_ray_angle,
                                     world_rays)

FOCAL = 400.0
GATE = Gate(min_observations=3, min_parallax_rad=math.radians(2.0), min_depth=0.2,
            max_depth=40.0, max_reprojection_px=3.0, focal_px=FOCAL)
POINT = np.array([1.0, 0.5, 6.0])


def look_at(centre, target, roll: float = 0.0) -> np.ndarray:
    """``R_W_C`` of a camera at ``centre`` whose optical axis (z) points at ``target``."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return R @ so3_exp(np.array([0.0, 0.0, roll]))


def observe(R_W_C, centres, point):
    """Normalised image coordinates of ``point`` in each camera, and the cameras' depths."""
    p_C = np.einsum("kji,kj->ki", R_W_C, point - centres)
    return p_C[:, :2] / p_C[:, 2:], p_C[:, 2]


def rig(centres, point=POINT, aim=None, rolls=None):
    """Cameras at ``centres`` aimed at ``aim`` (default: slightly beside ``point``, so it is
    off the optical axis), with their exact observations of ``point``."""
    centres = np.asarray(centres, float)
    aim = point + np.array([0.3, -0.2, 0.0]) if aim is None else aim
    rolls = np.zeros(len(centres)) if rolls is None else rolls
    R_W_C = np.stack([look_at(c, aim, r) for c, r in zip(centres, rolls)])
    normalised, depths = observe(R_W_C, centres, point)
    return R_W_C, centres, normalised, depths


def gate_one(R_W_C, centres, normalised, mask=None, gate=GATE):
    mask = np.ones(len(centres), bool) if mask is None else np.asarray(mask, bool)
    return gate_candidates(R_W_C[None], centres[None], normalised[None], mask[None], gate)


SPREAD = [[-1.0, 0.0, 0.0], [0.0, 0.3, 0.0], [1.0, 0.0, 0.2], [0.5, -0.6, -0.1]]


# ------------------------------------------------------------------ triangulation


@settings(max_examples=60, deadline=None)
@given(point=st.tuples(*[st.floats(-3.0, 3.0)] * 2, st.floats(3.0, 20.0)),
       seed=st.integers(0, 2**31 - 1), k=st.integers(2, 8))
def test_exact_rays_triangulate_to_the_point(point, seed, k):
    point = np.array(point)
    centres = np.random.default_rng(seed).uniform(-1.0, 1.0, (k, 3))
    R_W_C, centres, normalised, depths = rig(centres, point)
    assume((depths > 0.5).all())
    rays = world_rays(R_W_C, normalised)
    assume(widest_ray_angle(rays[None], np.ones((1, k), bool))[0] > math.radians(1.0))
    found = midpoint_triangulate(centres[None], rays[None], np.ones((1, k), bool))[0]
    np.testing.assert_allclose(found, point, atol=1e-9 * np.linalg.norm(point))


def test_noisy_rays_triangulate_near_the_point():
    rng = np.random.default_rng(7)
    centres = np.array([[-1.0, 0.0, 0.0], [-0.5, 0.5, 0.0], [0.0, 0.0, 0.3], [0.5, -0.4, 0.0],
                        [1.0, 0.2, -0.2]])
    R_W_C, centres, normalised, _ = rig(centres)
    errors = []
    for _ in range(200):
        noisy = normalised + rng.normal(0.0, 1.0 / FOCAL, normalised.shape)  # 1 px noise
        rays = world_rays(R_W_C, noisy)
        found = midpoint_triangulate(centres[None], rays[None], np.ones((1, 5), bool))[0]
        errors.append(np.linalg.norm(found - POINT))
    # 1 px at 400 px focal over a 2 m baseline at 6 m: depth sigma ~ 6 * 0.0025 / 0.33 = 5 cm
    assert np.median(errors) < 0.05
    assert np.max(errors) < 0.25


def test_missing_observations_are_ignored():
    R_W_C, centres, normalised, _ = rig(SPREAD)
    rays = world_rays(R_W_C, normalised)
    rays[1] = [1.0, 0.0, 0.0]  # garbage where the mask says there is nothing
    mask = np.array([[True, False, True, True]])
    found = midpoint_triangulate(centres[None], rays[None], mask)[0]
    np.testing.assert_allclose(found, POINT, atol=1e-9)


def test_parallel_rays_give_nan_not_a_point():
    centres = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])
    rays = np.tile([0.0, 0.0, 1.0], (3, 1))
    found = midpoint_triangulate(centres[None], rays[None], np.ones((1, 3), bool))
    assert np.isnan(found).all()


# ------------------------------------------------------------------ the gate


def test_a_well_conditioned_point_is_accepted_where_it_is():
    R_W_C, centres, normalised, _ = rig(SPREAD)
    result = gate_one(R_W_C, centres, normalised)
    assert result.accepted.tolist() == [True]
    np.testing.assert_allclose(result.points[0], POINT, atol=1e-9)
    rays = POINT - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    widest = max(math.acos(np.clip(a @ b, -1, 1)) for a in rays for b in rays)
    assert result.parallax_rad[0] == pytest.approx(widest, abs=1e-9)


def test_too_few_observations_are_rejected():
    R_W_C, centres, normalised, _ = rig(SPREAD)
    result = gate_one(R_W_C, centres, normalised, mask=[True, False, False, True])
    assert result.accepted.tolist() == [False]
    assert np.isnan(result.points).all()
    # the same two views pass a gate that asks for two
    two = replace(GATE, min_observations=2)
    assert gate_one(R_W_C, centres, normalised, [True, False, False, True], two).accepted[0]


def test_cameras_along_the_ray_give_no_parallax_and_are_rejected():
    direction = POINT / np.linalg.norm(POINT)
    centres = np.outer([0.0, 1.0, 2.0, 3.0], direction)  # moving straight at the point
    R_W_C, centres, normalised, depths = rig(centres)
    assert (depths > 1.0).all()
    result = gate_one(R_W_C, centres, normalised)
    assert result.parallax_rad[0] < 1e-6
    assert result.accepted.tolist() == [False]


@pytest.mark.parametrize("baseline, accepted", [(0.05, False), (0.15, False), (0.3, True)])
def test_the_baseline_must_give_the_minimum_parallax(baseline, accepted):
    """At 6.1 m, 2 degrees of parallax needs a baseline of about 0.21 m."""
    centres = np.array([[-0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]) * baseline
    R_W_C, centres, normalised, _ = rig(centres)
    result = gate_one(R_W_C, centres, normalised)
    assert (result.parallax_rad[0] >= GATE.min_parallax_rad) == accepted
    assert result.accepted.tolist() == [accepted]


def test_a_point_behind_one_camera_is_rejected():
    """The third camera faces away; its (exact) observation is of the point behind it. The
    rays' lines still meet at the point, so only the depth check can catch it."""
    centres = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.5, 8.0]])
    R_W_C = np.stack([look_at(centres[0], POINT), look_at(centres[1], POINT),
                      look_at(centres[2], [0.0, 0.5, 20.0])])
    normalised, depths = observe(R_W_C, centres, POINT)
    assert depths[2] < 0 < depths[:2].min()
    result = gate_one(R_W_C, centres, normalised)
    np.testing.assert_allclose(result.points[0], POINT, atol=1e-9)
    assert result.accepted.tolist() == [False]
    assert gate_one(R_W_C, centres, normalised, mask=[True, True, False],
                    gate=replace(GATE, min_observations=2)).accepted[0]


@pytest.mark.parametrize("distance", [0.1, 60.0])
def test_points_nearer_than_min_depth_or_beyond_max_depth_are_rejected(distance):
    direction = np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0])
    point = direction * distance
    # a baseline wide enough for the parallax at either distance
    half = 0.03 if distance < 1 else 5.0
    centres = np.array([[-half, 0.0, 0.0], [0.0, half, 0.0], [half, 0.0, 0.0]])
    R_W_C, centres, normalised, depths = rig(centres, point, aim=point)
    result = gate_one(R_W_C, centres, normalised)
    assert result.parallax_rad[0] >= GATE.min_parallax_rad
    np.testing.assert_allclose(result.points[0], point, rtol=1e-9)
    assert result.accepted.tolist() == [False]
    wide = replace(GATE, min_depth=0.01, max_depth=100.0)
    assert gate_one(R_W_C, centres, normalised, gate=wide).accepted[0]


@pytest.mark.parametrize("shift_px, accepted", [(1.0, True), (20.0, False)])
def test_an_observation_moved_off_the_point_is_rejected(shift_px, accepted):
    R_W_C, centres, normalised, _ = rig(SPREAD)
    moved = normalised.copy()
    moved[2] += np.array([0.6, 0.8]) * shift_px / FOCAL
    result = gate_one(R_W_C, centres, moved)
    assert result.accepted.tolist() == [accepted]


def test_the_reprojection_limit_is_the_gate_value():
    """One observation off by 20 px is within a 30 px limit, outside a 3 px one."""
    R_W_C, centres, normalised, _ = rig(SPREAD)
    moved = normalised.copy()
    moved[2] += np.array([20.0, 0.0]) / FOCAL
    loose = replace(GATE, max_reprojection_px=30.0)
    assert gate_one(R_W_C, centres, moved, gate=loose).accepted[0]
    assert not gate_one(R_W_C, centres, moved).accepted[0]


def test_candidates_are_gated_independently_in_one_batch():
    good = rig(SPREAD)
    along = rig(np.outer([0.0, 1.0, 2.0, 3.0], POINT / np.linalg.norm(POINT)))
    moved = rig(SPREAD)
    moved[2][1] += np.array([0.0, 25.0]) / FOCAL
    R_W_C, centres, normalised = (np.stack([c[i] for c in (good, along, moved, good)])
                                  for i in range(3))
    mask = np.array([[True] * 4, [True] * 4, [True] * 4, [True, False, False, True]])
    result = gate_candidates(R_W_C, centres, normalised, mask, GATE)
    assert result.accepted.tolist() == [True, False, False, False]
    np.testing.assert_allclose(result.points[0], POINT, atol=1e-9)


# ------------------------------------------------------------------ spending the budget

SIZE, GRID = (640, 480), (4, 4)  # cells of 160 x 120 px


def test_new_landmarks_go_to_empty_cells_before_crowded_ones():
    occupied = np.array([[50.0, 50.0], [60.0, 70.0], [100.0, 40.0]])  # three in the top-left cell
    candidates = np.array([[40.0, 30.0], [600.0, 400.0], [70.0, 90.0], [300.0, 200.0]])
    parallax = np.array([0.9, 0.1, 0.8, 0.2])  # the crowded cell's are the best conditioned
    chosen = spread_choice(candidates, parallax, occupied, SIZE, GRID, 2)
    assert sorted(chosen.tolist()) == [1, 3]
    # with room for all, all are taken, the empty cells' first
    assert sorted(spread_choice(candidates, parallax, occupied, SIZE, GRID, 10).tolist()) == [
        0, 1, 2, 3]


def test_one_cell_is_filled_round_robin_with_the_widest_parallax_first():
    candidates = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [500.0, 300.0]])
    parallax = np.array([0.1, 0.3, 0.2, 0.05])
    chosen = spread_choice(candidates, parallax, np.zeros((0, 2)), SIZE, GRID, 3)
    assert chosen.tolist() == [1, 3, 2]  # turn 0: 1 (wider) then 3; turn 1: 2


@pytest.mark.parametrize("count", [0, -3])
def test_no_room_chooses_nothing(count):
    assert spread_choice(np.array([[5.0, 5.0]]), np.array([0.1]), np.zeros((0, 2)), SIZE, GRID,
                         count).tolist() == []


def test_pixels_off_the_image_count_in_the_nearest_cell():
    occupied = np.array([[-3.0, -2.0]])  # just off the top-left corner: the top-left cell
    candidates = np.array([[5.0, 5.0], [645.0, 485.0]])  # top-left, just off the bottom-right
    chosen = spread_choice(candidates, np.array([0.5, 0.1]), occupied, SIZE, GRID, 1)
    assert chosen.tolist() == [1]


# ------------------------------------------------------------------ depth uncertainty


def test_depth_sigma_follows_the_observation_geometry():
    parallax = math.radians(5.0)
    sigma = depth_sigma(np.array([2.0, 4.0, 8.0]), np.full(3, parallax), 1.0, FOCAL)
    np.testing.assert_allclose(sigma, np.array([2.0, 4.0, 8.0]) / FOCAL / math.sin(parallax))
    assert depth_sigma(np.array([5.0]), np.array([parallax]), 2.0, FOCAL)[0] == pytest.approx(
        2 * depth_sigma(np.array([5.0]), np.array([parallax]), 1.0, FOCAL)[0])


@settings(max_examples=100, deadline=None)
@given(depth=st.floats(0.2, 40.0), more=st.floats(1.01, 5.0),
       parallax_deg=st.floats(0.2, 17.0))
def test_depth_sigma_grows_with_depth_and_shrinks_with_parallax(depth, more, parallax_deg):
    """Up to 90 degrees of parallax (past it the rays' lines close in again)."""
    p = math.radians(parallax_deg)
    base = depth_sigma(np.array([depth]), np.array([p]), 1.0, FOCAL)[0]
    assert base > 0
    assert depth_sigma(np.array([depth * more]), np.array([p]), 1.0, FOCAL)[0] > base
    assert depth_sigma(np.array([depth]), np.array([p * more]), 1.0, FOCAL)[0] < base


def test_depth_sigma_stays_finite_without_parallax():
    sigma = depth_sigma(np.array([5.0, 5.0]), np.array([0.0, math.radians(0.01)]), 1.0, FOCAL)
    assert np.isfinite(sigma).all() and (sigma > 0).all()
    np.testing.assert_allclose(sigma, 5.0 / FOCAL / math.sin(math.radians(0.1)))


# ------------------------------------------------------------------ the observation gate


def test_the_limit_grows_only_by_the_keyframes_median_error():
    errors = np.full(40, 0.3)
    assert observation_limit_px(errors, 1.5) == pytest.approx(math.hypot(1.5, 0.3))
    assert observation_limit_px(np.zeros(40), 1.5) == 1.5


def test_an_error_the_whole_keyframe_shares_widens_the_limit():
    """A predicted pose 5 px off (a time offset not yet known, in the first pitch) moves every
    projection: the limit grows past it, so the keyframe keeps its observations, while a track
    3 px further off than the rest is still dropped."""
    errors = np.r_[np.full(30, 5.0), 8.0]
    limit = observation_limit_px(errors, 1.5)
    assert limit == pytest.approx(math.hypot(1.5, 5.0))
    assert (errors[:30] <= limit).all() and errors[30] > limit


def test_too_few_or_unknown_errors_leave_the_limit_as_it_is():
    few = np.full(MIN_OBSERVATIONS_FOR_MEDIAN - 1, 5.0)
    assert observation_limit_px(few, 1.5) == 1.5
    unknown = np.r_[few, np.nan, np.inf, -np.inf]
    assert observation_limit_px(unknown, 1.5) == 1.5
    assert observation_limit_px(np.zeros(0), 1.5) == 1.5
    enough = np.r_[np.full(MIN_OBSERVATIONS_FOR_MEDIAN, 2.0), np.nan, np.nan]
    assert observation_limit_px(enough, 1.5) == pytest.approx(2.5)
