"""The planner on rendered depth: walls block arcs, unknown space is unsafe, the history
remembers, the choice makes progress and holds steady, the fallback is last round's checked
stop, and the setpoints fly the arcs that were checked."""

import math

import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z
from autonomy.messages import DepthDiagnostics, MetricDepth
from autonomy.options import OptionError
from autonomy.planning.history import (
    _block_minima, _known_range, fill_small_holes, DepthHistory, min_table, read_depth,
    window_min,
)
from autonomy.planning.landing import column_points
from autonomy.planning.planner import Plan, Planner, PlannerOptions

CAMERA = PinholeCamera.from_hfov(160, 120, math.radians(90.0))
ALTITUDE = 5.0
#: Far walls all round filling every view, so that open space is observed (clipped to
#: max_range).
ROOM = [((40.0, -200.0, -200.0), (41.0, 200.0, 200.0)),
        ((-41.0, -200.0, -200.0), (-40.0, 200.0, 200.0)),
        ((-200.0, 40.0, -200.0), (200.0, 41.0, 200.0)),
        ((-200.0, -41.0, -200.0), (200.0, -40.0, 200.0))]
#: A wall on the left ahead, its edge 0.5 m left of the straight arc.
WALL_LEFT = ((4.0, 0.5, -50.0), (4.5, 50.0, 50.0))
DIAGNOSTICS = DepthDiagnostics(anchors=50, anchors_used=50, residual_rms=0.0, method="poly1",
                               fit_age_s=0.0)


def body(x=0.0, y=0.0, yaw=0.0, z=ALTITUDE):
    return make_pose(rot_z(yaw), np.array([x, y, z]))


def camera_pose(T_W_B):
    return T_W_B @ make_pose(R_BODY_CAMERA, np.zeros(3))


def render(T_W_C, boxes, camera=CAMERA):
    """Depth (z along the optical axis) of the nearest axis-aligned box on each pixel's ray,
    NaN where none is hit (slab intersection)."""
    rays_C = camera.rays().reshape(-1, 3)
    d = rays_C @ T_W_C[:3, :3].T  # world direction per unit optical depth
    o = T_W_C[:3, 3]
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in boxes:
            t1 = (np.asarray(lo) - o) / d
            t2 = (np.asarray(hi) - o) / d
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (far >= near) & (far > 0)
            best = np.where(hit, np.minimum(best, np.maximum(near, 0.0)), best)
    depth = np.where(np.isfinite(best), best, np.nan).astype(np.float32)
    return depth.reshape(camera.height, camera.width)


def metric(depth, t, confidence=None):
    if confidence is None:
        confidence = np.ones_like(depth)
    return MetricDepth(t, depth, np.asarray(confidence, dtype=np.float32), False, DIAGNOSTICS)


def planner_seeing(boxes, T_W_B=None, t=0.0, options=None):
    planner = Planner(CAMERA, options)
    T_W_B = body() if T_W_B is None else T_W_B
    planner.add_depth(metric(render(camera_pose(T_W_B), boxes), t), camera_pose(T_W_B))
    return planner


FORWARD = np.array([2.0, 0.0, 0.0])
AHEAD = np.array([30.0, 0.0, ALTITUDE])


# ---------------------------------------------------------------- the window look-up


def test_the_min_table_holds_the_minimum_of_each_square_inside_the_image():
    rng = np.random.default_rng(7)
    H, W = 37, 70  # not powers of two: squares leave the image at the right and bottom
    image = rng.uniform(1.0, 9.0, (H, W)).astype(np.float32)
    table = min_table(image)
    assert table.shape == (6, H, W)  # k = 0 .. floor(log2(37))
    for k in range(len(table)):
        side = 1 << k
        for j, i in zip(rng.integers(0, H, 40), rng.integers(0, W, 40)):
            assert table[k, j, i] == image[j:j + side, i:i + side].min(), (k, j, i)


def test_block_minima_are_each_blocks_minimum_clipped_at_the_edges():
    rng = np.random.default_rng(8)
    image = rng.uniform(1.0, 9.0, (37, 70)).astype(np.float32)
    for side in (4, 16):
        blocks = _block_minima(image, side)
        expected = [image[j:j + side, i:i + side].min()
                    for j in range(0, 37, side) for i in range(0, 70, side)]
        np.testing.assert_array_equal(blocks, expected)


def test_window_minimum_equals_the_brute_force_minimum_or_a_superset_of_it():
    rng = np.random.default_rng(3)
    H, W = 48, 64
    image = rng.uniform(1.0, 9.0, (H, W)).astype(np.float32)
    flat = min_table(image).reshape(-1)
    for _ in range(400):
        u = np.sort(rng.uniform(-10, W + 10, 2))
        v = np.sort(rng.uniform(-10, H + 10, 2))
        got = window_min(flat, H, W, np.array([u[:1], v[:1]]), np.array([u[1:], v[1:]]))[0]
        i0, i1 = (int(np.clip(np.floor(a + 0.5), 0, W - 1)) for a in u)
        j0, j1 = (int(np.clip(np.floor(a + 0.5), 0, H - 1)) for a in v)
        exact = image[j0:j1 + 1, i0:i1 + 1].min()
        assert got <= exact  # never misses a pixel of the window
        w, h = i1 - i0 + 1, j1 - j0 + 1
        if max(w, h) <= 2 * min(w, h):
            assert got == exact  # exact for windows no thinner than 2:1


# ---------------------------------------------------------------- the sphere check


def test_a_wall_blocks_points_whose_sphere_reaches_it_and_no_others():
    T_W_C = camera_pose(body())
    history = DepthHistory()
    history.add(render(T_W_C, [((6.0, -50, -50), (6.5, 50, 50))]), np.ones((120, 160)),
                T_W_C, CAMERA, 0.0)
    xs = np.array([2.0, 3.0, 4.5, 5.1, 5.5])
    result = history.check(np.column_stack([xs, np.zeros(5), np.full(5, ALTITUDE)]))
    np.testing.assert_array_equal(result.free, [True, True, True, False, False])
    # the centre ray's margin: range to the wall minus L + R (the nearest pixel ray is half a
    # pixel off the axis, 2e-4 m longer)
    np.testing.assert_allclose(result.clearance[:3], 6.0 - (xs[:3] + 1.0), atol=1e-3)
    assert np.all(result.frame[:4] == 0.0)


def test_unknown_depth_low_confidence_and_beyond_range_are_not_free():
    T_W_C = camera_pose(body())
    depth = render(T_W_C, ROOM)
    point = np.array([[4.0, 0.0, ALTITUDE]])
    history = DepthHistory()
    history.add(depth, np.ones_like(depth), T_W_C, CAMERA, 0.0)
    assert history.check(point).free.all()
    assert not history.check([[9.5, 0.0, ALTITUDE]]).free.any()  # z + R beyond max_range
    holes = depth.copy()
    holes[40:80, 60:100] = np.nan  # a patch of unknown around the point's pixel, 40 px wide
    only = DepthHistory(max_frames=1)
    only.add(holes, np.ones_like(depth), T_W_C, CAMERA, 0.0)
    assert not only.check(point).free.any()
    unsure = np.ones_like(depth)
    unsure[40:80, 60:100] = 0.1  # unsure, but of walls beyond max_range: far all the same
    only.add(depth, unsure, T_W_C, CAMERA, 1.0)
    assert only.check(point).free.all()
    sliver = depth.copy()
    sliver[55:65, 75:85] = np.nan  # 10 px: filled from the surfaces around it
    only.add(sliver, np.ones_like(depth), T_W_C, CAMERA, 1.5)
    assert only.check(point).free.all()
    only.add(depth, np.ones_like(depth), T_W_C, CAMERA, 2.0)
    assert only.check(point).free.all()


def test_a_hole_takes_the_nearest_range_around_it_and_a_wide_one_keeps_an_unknown_core():
    image = np.full((60, 80), 5.0, np.float32)
    image[20:30, 30:40] = -1.0  # small hole
    image[0:10, 0:10] = 2.0  # a near surface far from the hole
    image[25, 45] = 3.0  # a near surface next to the hole
    filled = fill_small_holes(image, 15)
    assert (filled >= 0).all()
    assert filled[25, 35] == 3.0  # the nearest range within reach, not the far wall
    wide = np.full((100, 100), 5.0, np.float32)
    wide[10:90, 10:90] = -1.0
    out = fill_small_holes(wide, 15)
    assert (out[30:70, 30:70] < 0).all() and (out[10:25, 10:90] == 5.0).all()


def test_low_confidence_counts_as_unknown_when_near_and_as_far_beyond_range():
    T_W_C = camera_pose(body())
    far = np.full((CAMERA.height, CAMERA.width), 60.0, np.float32)  # the sky at max_depth
    history = DepthHistory()
    history.add(far, np.zeros_like(far), T_W_C, CAMERA, 0.0)
    assert history.check([[4.0, 0.0, ALTITUDE]]).free.all()
    unsure = DepthHistory()
    unsure.add(np.full_like(far, 6.0), np.zeros_like(far), T_W_C, CAMERA, 1.0)
    assert not unsure.check([[2.0, 0.0, ALTITUDE]]).free.any()


def test_low_confidence_nearer_than_a_confident_depth_counts_as_that_depth():
    """Confidence follows the relative disparity and the curve is monotone, so a
    low-confidence patch (a floor without landmarks) is at least as far as the confident
    surface just nearer than it; nearer than every confident surface it stays unknown. A
    sphere holding the camera (near the vehicle, at the start) needs every pixel known."""
    T_W_C, start = camera_pose(body()), np.array([0.0, 0.0, ALTITUDE])
    near = [[0.5, 0.0, ALTITUDE]]
    depth = np.full((CAMERA.height, CAMERA.width), 6.0, np.float32)  # a wall, confident
    confidence = np.ones_like(depth)
    depth[60:110, 40:120], confidence[60:110, 40:120] = 4.0, 0.1  # the floor, unsure
    alone = DepthHistory()
    alone.add(depth, confidence, T_W_C, CAMERA, 0.0)
    assert not alone.check(near, start_W=start).free.any()  # nothing nearer bounds it
    depth[0:20, 0:20] = 3.0  # a confident surface nearer than the floor
    bounded = DepthHistory()
    bounded.add(depth, confidence, T_W_C, CAMERA, 0.0)
    result = bounded.check(near, start_W=start)
    assert result.free.all()
    # the floor counts as (a little less than) 3 m, not its own 4 m: L + R = 1.5 m
    assert 3.0 * 0.98 - 1.5 <= result.clearance[0] <= 3.0 - 1.5


def test_low_confidence_nearer_than_every_confident_depth_counts_as_a_share_of_itself():
    """The rescaling's near tail (no landmark that near) reads as ``near_tail_share`` of its
    depth: the unsure patch at 4 m, nearer than the confident wall, counts as 2 m at half,
    which leaves the sphere 0.5 m ahead free (L + R = 1.5 m), and as 1.2 m at 0.3, which does
    not."""
    T_W_C, start = camera_pose(body()), np.array([0.0, 0.0, ALTITUDE])
    near = [[0.5, 0.0, ALTITUDE]]
    depth = np.full((CAMERA.height, CAMERA.width), 6.0, np.float32)  # a wall, confident
    confidence = np.ones_like(depth)
    depth[60:110, 40:120], confidence[60:110, 40:120] = 4.0, 0.1  # the floor, unsure
    verdicts = {}
    for share in (0.5, 0.3):
        history = DepthHistory(near_tail_share=share)
        history.add(depth, confidence, T_W_C, CAMERA, 0.0)
        verdicts[share] = history.check(near, start_W=start)
    assert verdicts[0.5].free.all()
    assert verdicts[0.5].clearance[0] == pytest.approx(4.0 * 0.5 - 1.5, abs=1e-3)
    assert not verdicts[0.3].free.any() and verdicts[0.3].occupied.all()


def test_a_thin_pole_nearer_than_every_landmark_is_kept_only_by_the_near_tail():
    """A realistic dome flight's collision (docs/results.md, "The gyro's yaw response in
    navigation"): the network saw a thin pole ahead, but nearer than every landmark, so with
    no confident depth. As unknown it is a small hole, which takes the range of the wall
    around it (``fill_small_holes``), and the arc through it is free; as 0.9 of its depth it
    is occupied."""
    wall = ((8.0, -50.0, -50.0), (9.0, 50.0, 50.0))
    pole = ((3.95, -0.05, -50.0), (4.05, 0.05, 50.0))
    T_W_C = camera_pose(body(x=1.5))
    depth = render(T_W_C, [pole, wall])
    confidence = np.where(depth < 5.0, 0.1, 1.0).astype(np.float32)  # landmarks on the wall
    at_the_pole = [[4.0, 0.0, ALTITUDE]]
    verdicts = {}
    for share in (0.0, 0.9):
        history = DepthHistory(near_tail_share=share)
        history.add(depth, confidence, T_W_C, CAMERA, 0.0)
        verdicts[share] = history.check(at_the_pole)
    assert verdicts[0.0].free[0]
    assert verdicts[0.9].occupied[0] and not verdicts[0.9].free[0]


def test_low_confidence_farther_than_every_confident_depth_counts_as_a_share_of_itself():
    """The rescaling's far tail (no landmark that far): a wall 8 m ahead whose only
    confident pixels are a strip at 3 m. At a share of 0 the wall counts as the farthest
    confident depth, 3 m, and the sphere 5 m ahead is occupied (L + R = 6 m); at 0.9 it counts
    as 7.2 m and the sphere is free. A share never puts the tail nearer than that floor: at
    0.3 (2.4 m) it is still 3 m."""
    T_W_C = camera_pose(body())
    ahead = [[5.0, 0.0, ALTITUDE]]
    depth = np.full((CAMERA.height, CAMERA.width), 8.0, np.float32)  # the wall, unsure
    confidence = np.full_like(depth, 0.1)
    depth[:10], confidence[:10] = 3.0, 1.0  # landmarks on a beam overhead
    results = {}
    for share in (0.0, 0.3, 0.9):
        history = DepthHistory(far_tail_share=share)
        history.add(depth, confidence, T_W_C, CAMERA, 0.0)
        results[share] = history.check(ahead)
    assert results[0.0].occupied.all() and not results[0.0].free.any()
    assert results[0.9].free.all()
    assert results[0.9].clearance[0] == pytest.approx(8.0 * 0.9 - 6.0, abs=1e-3)
    assert results[0.3].clearance[0] == pytest.approx(results[0.0].clearance[0], abs=1e-6)


def test_a_far_tail_share_leaves_pixels_between_confident_depths_at_their_floor():
    """Only pixels farther than every confident one are the far tail: an unsure patch at 8 m
    with a confident wall at 9 m beside it is bounded by the confident depth nearer than it,
    as without a share (docs/planner.md, low confidence)."""
    T_W_C = camera_pose(body())
    depth = np.full((CAMERA.height, CAMERA.width), 9.0, np.float32)  # a wall, confident
    confidence = np.ones_like(depth)
    depth[:, 40:120], confidence[:, 40:120] = 8.0, 0.1  # the middle, unsure
    depth[:10, :40] = 3.0  # a confident beam at 3 m
    ahead = [[5.0, 0.0, ALTITUDE]]
    clearances = []
    for share in (0.0, 0.9):
        history = DepthHistory(far_tail_share=share)
        history.add(depth, confidence, T_W_C, CAMERA, 0.0)
        clearances.append(history.check(ahead).clearance[0])
    assert clearances[0] == clearances[1] < 0.0


def test_a_view_whose_landmarks_lie_near_is_flown_fast_on_its_far_tail():
    """A wall 9.5 m ahead with landmarks only on a beam 3 m ahead: bounded at 3 m, no arc of
    the fastest tier (2 m/s: 6 m of arc and braking) is free and a slower one is flown; with
    the far tail at 0.9 the wall counts as 8.55 m and the straight arc at 2 m/s is."""
    T_W_C = camera_pose(body())
    depth = render(T_W_C, [((9.5, -50.0, -50.0), (10.0, 50.0, 50.0))])
    confidence = np.full_like(depth, 0.1)
    depth[:10], confidence[:10] = 3.0, 1.0
    speeds = {}
    for share in (0.0, 0.9):
        planner = Planner(CAMERA, PlannerOptions(far_tail_share=share))
        planner.add_depth(metric(depth, 0.0, confidence), T_W_C)
        plan = planner.plan(0.05, body(), FORWARD, AHEAD)
        assert plan.kind == "arc"
        speeds[share] = plan.primitive.speed
    assert speeds[0.0] < speeds[0.9] == PlannerOptions().speed


def test_the_reading_sorts_pixels_into_confident_the_tails_and_beyond_range():
    depth = np.array([[3.0, 6.0, 2.0, 5.0, 8.0, 12.0, np.nan, -1.0, 60.0]], np.float32)
    confidence = np.array([[1.0, 1.0, 0.1, 0.1, 0.1, 0.1, 1.0, 1.0, 1.0]], np.float32)
    reading = read_depth(depth, confidence, 0.3, 10.0)
    assert reading.in_range.tolist() == [[1, 1, 0, 0, 0, 0, 0, 0, 0]]
    assert reading.confident.tolist() == [[1, 1, 0, 0, 0, 0, 0, 0, 1]]
    assert reading.unsure.tolist() == [[0, 0, 1, 1, 1, 0, 0, 0, 0]]
    assert reading.beyond.tolist() == [[0, 0, 0, 0, 0, 1, 0, 0, 0]]
    assert reading.near_tail(depth).tolist() == [[0, 0, 1, 0, 0, 0, 0, 0, 0]]
    assert reading.far_tail(depth).tolist() == [[0, 0, 0, 0, 1, 0, 0, 0, 0]]
    alone = read_depth(depth, np.zeros_like(confidence), 0.3, 10.0)  # no confident pixel
    assert alone.unsure.any()
    assert not alone.near_tail(depth).any() and not alone.far_tail(depth).any()


def test_each_kind_of_pixel_becomes_the_range_the_check_reads():
    """The history's range image (``_known_range``) pixel by pixel, on unit ray norms: the
    confident depth as it is (clipped to the range), a less confident one beyond the range at
    the range, one between confident depths at the nearer one's bin floor (at most 1.4 %
    under it), the near tail at its share, the far tail at its share or its floor, whichever
    is farther; invalid pixels, and the tails without a confident depth in range, unknown."""
    depth = np.array([[2.0, 6.0, np.inf, 12.0, np.nan, 0.0, 1.0, 4.0, 8.0, 7.0]], np.float32)
    confidence = np.array([[1, 1, 1, 0, 1, 1, 0, 0, 0, 0]], np.float32)
    ranges = _known_range(depth, confidence, 0.3, 10.0, np.ones_like(depth), 0.5, 0.8)
    assert ranges.dtype == np.float32
    assert ranges[0, :7].tolist() == [2.0, 6.0, 10.0, 10.0, -1.0, -1.0, 0.5]
    between, far, far_floor = ranges[0, 7:]
    assert 2.0 * (1 - 0.014) <= between <= 2.0
    assert far == np.float32(8.0) * np.float32(0.8)  # its share, beyond its floor (6 m)
    assert 6.0 * (1 - 0.014) <= far_floor <= 6.0  # its floor, beyond its share (5.6 m)
    tails_alone = _known_range(depth, np.zeros_like(confidence), 0.3, 10.0,
                               np.ones_like(depth), 0.5, 0.8)
    assert tails_alone[0].tolist() == [-1.0] * 2 + [10.0] * 2 + [-1.0] * 6  # beyond: the range


@pytest.mark.parametrize("name", ["near_tail_share", "far_tail_share"])
@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_a_tail_share_outside_0_to_1_is_refused(name, share):
    with pytest.raises(ValueError, match=f"{name} must be in"):
        DepthHistory(**{name: share})


def test_an_older_frame_decides_where_the_newest_cannot_tell():
    T_W_C = camera_pose(body())
    depth = render(T_W_C, ROOM)
    history = DepthHistory()
    history.add(depth, np.ones_like(depth), T_W_C, CAMERA, 0.0)
    history.add(np.full_like(depth, np.nan), np.ones_like(depth), T_W_C, CAMERA, 0.1)
    result = history.check([[4.0, 0.0, ALTITUDE]])
    assert result.free.all() and result.frame[0] == 0.0


@pytest.mark.parametrize("unknown_beside", [False, True])
def test_a_surface_the_newest_frame_measures_near_the_vehicle_is_not_freed_by_an_older_one(
        unknown_beside):
    """A realistic sewer flight's collision: from 2 m back the network had misread a thin pole
    (the older frame sees only the wall); 0.75 m from it the newest frame sees it beside the
    arc, inside the spheres of the arc's first points (which reach the camera plane: the
    block rule judges them). The older frame saw those spheres whole and free, a strong
    verdict; the newest frame's measured surface must still decide, also when other pixels
    the spheres meet are unknown (``unknown_beside``: no depth right of the pole, wider than
    the hole filling closes)."""
    wall = ((8.0, -50.0, -50.0), (9.0, 50.0, 50.0))
    pole = ((0.63, -0.37, -50.0), (0.67, -0.33, 50.0))  # 0.75 m ahead-right, off every centre ray
    history = DepthHistory()
    for t, x, scene in ((0.0, -2.0, [wall]), (0.5, 0.0, [pole, wall])):
        T_W_C = camera_pose(body(x=x))
        depth = render(T_W_C, scene)
        if t > 0.0 and unknown_beside:
            depth[:, 126:] = np.nan
        history.add(depth, np.ones_like(depth), T_W_C, CAMERA, t)
    start = [0.0, 0.0, ALTITUDE]
    arc = [[0.1, 0.0, ALTITUDE], [0.3, 0.0, ALTITUDE], [0.5, 0.0, ALTITUDE]]
    result = history.check(arc, start_W=start, now=0.5)
    assert not result.free.any() and result.occupied.all()
    np.testing.assert_array_equal(result.frame, 0.5)  # the newest frame decided
    aside = history.check([[0.3, 0.9, ALTITUDE]], start_W=start, now=0.5)
    assert aside.free.all()  # a near sphere 1.3 m from the pole is not refused by it


def test_the_history_remembers_an_obstacle_that_left_the_view():
    post = ((3.0, -0.3, -50.0), (3.6, 0.3, 50.0))
    scene = [post, *ROOM]
    ahead, left = camera_pose(body()), camera_pose(body(yaw=math.pi / 2))
    points = np.array([[2.5, 0.0, ALTITUDE], [0.0, 4.0, ALTITUDE]])
    for frames, expected_first in ((8, False), (1, False)):
        history = DepthHistory(max_frames=frames)
        for t, T in ((0.0, ahead), (0.1, left)):
            depth = render(T, scene)
            history.add(depth, np.ones_like(depth), T, CAMERA, t)
        result = history.check(points)
        assert result.free[0] == expected_first  # occupied (seen) or unknown (forgotten)
        assert result.free[1]  # the newest frame sees open space to the left
    remembered = DepthHistory()
    for t, T in ((0.0, ahead), (0.1, left)):
        depth = render(T, scene)
        remembered.add(depth, np.ones_like(depth), T, CAMERA, t)
    assert remembered.check(points).frame[0] == 0.0  # decided by the frame that saw the post


def test_points_near_the_start_whose_sphere_reaches_the_camera_are_judged_by_their_ray():
    T_W_C = camera_pose(body())
    history = DepthHistory()
    open_space = render(T_W_C, ROOM)
    history.add(open_space, np.ones_like(open_space), T_W_C, CAMERA, 0.0)
    start = np.array([0.0, 0.0, ALTITUDE])
    near = np.array([[0.5, 0.0, ALTITUDE], [0.0, 0.0, ALTITUDE - 0.5]])  # ahead; below, unseen
    result = history.check(near, start_W=start)
    np.testing.assert_array_equal(result.free, [True, False])
    assert not history.check(near[:1]).free.any()  # without the start its sphere is unseen
    wall = render(T_W_C, [((0.7, -50, -50), (0.8, 50, 50))])
    history.add(wall, np.ones_like(wall), T_W_C, CAMERA, 0.1)
    assert not history.check([[0.9, 0.0, ALTITUDE]], start_W=start).free.any()


def _exact_free(depth, T_W_C, points_W, camera=CAMERA, R=1.0, max_range=10.0):
    """The exact per-ray rule by brute force: every known pixel ray through the sphere sees its
    surface at least as far as the ray's exit distance s2 = d.c + sqrt((d.c)² - |c|² + R²)."""
    rays = camera.rays().reshape(-1, 3)
    norms = np.linalg.norm(rays, axis=1)
    unit = rays / norms[:, None]
    ranges = np.minimum(depth.reshape(-1), max_range) * norms
    R_C_W, t_C_W = T_W_C[:3, :3].T, -T_W_C[:3, :3].T @ T_W_C[:3, 3]
    verdicts = []
    for p in np.asarray(points_W, dtype=float):
        c = R_C_W @ p + t_C_W
        b = unit @ c
        disc = b * b - c @ c + R * R
        hit = disc >= 0.0
        verdicts.append(bool(np.all(ranges[hit] >= b[hit] + np.sqrt(disc[hit]))))
    return np.array(verdicts)


def test_the_ring_rule_never_calls_free_what_the_exact_per_ray_rule_does_not():
    rng = np.random.default_rng(7)
    rings_free = exact_free = 0
    for trial in range(6):
        T_W_C = camera_pose(body())
        boxes = list(ROOM)
        for _ in range(12):
            lo = np.array([rng.uniform(2.0, 9.0), rng.uniform(-4.0, 4.0),
                           rng.uniform(ALTITUDE - 4.0, ALTITUDE + 3.0)])
            boxes.append((lo, lo + rng.uniform(0.05, 1.0, 3)))
        depth = render(T_W_C, boxes)
        history = DepthHistory(max_range=30.0)
        history.add(depth, np.ones_like(depth), T_W_C, CAMERA, 0.0)
        points = np.column_stack([rng.uniform(1.5, 8.0, 300), rng.uniform(-3.0, 3.0, 300),
                                  rng.uniform(ALTITUDE - 2.5, ALTITUDE + 2.5, 300)])
        rings = history.check(points).free
        exact = _exact_free(depth, T_W_C, points, max_range=30.0)
        assert not np.any(rings & ~exact)  # conservative
        rings_free += rings.sum()
        exact_free += exact.sum()
    assert exact_free > 600 and rings_free > 0.65 * exact_free  # cautious, not hopelessly


def test_near_spheres_are_judged_ray_by_ray_never_freer_than_the_exact_rule():
    """In a 2.5 m corridor the image's nearest surface (a wall seen at the view's edge, 1.8 m
    off) is nearer than ``L + R`` for spheres 0.8 m ahead or more, which the whole-image test
    would refuse; ray by ray, block by block, most are free, and none that a ray through it
    contradicts."""
    rng = np.random.default_rng(3)
    corridor = [((-50.0, 1.25, -50.0), (50.0, 2.0, 50.0)),
                ((-50.0, -2.0, -50.0), (50.0, -1.25, 50.0)),
                ((-50.0, -50.0, ALTITUDE - 2.5), (50.0, 50.0, ALTITUDE - 2.0)),
                ((-50.0, -50.0, ALTITUDE + 2.0), (50.0, 50.0, ALTITUDE + 2.5)), ROOM[0]]
    T_W_C = camera_pose(body())
    depth = render(T_W_C, corridor)
    history = DepthHistory()
    history.add(depth, np.ones_like(depth), T_W_C, CAMERA, 0.0)
    start = np.array([0.0, 0.0, ALTITUDE])
    points = start + np.column_stack([rng.uniform(0.2, 1.0, 400), rng.uniform(-0.3, 0.3, 400),
                                      rng.uniform(-0.3, 0.3, 400)])
    free = history.check(points, start_W=start).free
    exact = _exact_free(depth, T_W_C, points)
    assert not np.any(free & ~exact)
    whole_image = np.nanmin(depth * np.linalg.norm(CAMERA.rays(), axis=-1)) >= \
        np.linalg.norm(points - T_W_C[:3, 3], axis=1) + 1.0
    assert (free & ~whole_image).sum() > 30 and free.sum() > 0.8 * exact.sum()


# ---------------------------------------------------------------- over a floor


WIDE = PinholeCamera.from_hfov(640, 480, math.radians(90.0))
FAR_WALL = ((30.0, -200.0, -50.0), (31.0, 200.0, 50.0))


def floor_scene(altitude, boxes=(), options=None):
    """The 640x480 depth of a level camera ``altitude`` above a flat floor (world z = 0): the
    floor plane analytically, depth ``altitude / ((v - cy) / fy)`` below the horizon, and a
    wall 30 m ahead and any ``boxes`` rendered; the planner seeing it from the origin."""
    T_W_B = body(z=altitude)
    down = WIDE.rays()[..., 1]
    with np.errstate(divide="ignore"):
        floor = np.where(down > 0.0, altitude / down, np.inf)
    walls = render(camera_pose(T_W_B), [FAR_WALL, *boxes], WIDE)
    depth = np.fmin(floor, walls).astype(np.float32)
    planner = Planner(WIDE, options)
    planner.add_depth(metric(depth, 0.0), camera_pose(T_W_B))
    return planner, T_W_B, depth


def _kinds(planner):
    fastest = planner.tiers[0]
    return fastest.yaw_rates, fastest.vertical_speeds


def test_level_arcs_1_5_m_over_a_floor_are_safe():
    planner, T_W_B, _ = floor_scene(1.5)
    plan = planner.plan(0.05, T_W_B, FORWARD, np.array([30.0, 0.0, 1.5]))
    # straight on; it climbs (the floor's nearness costs), but level would do
    assert plan.kind == "arc" and plan.primitive.yaw_rate == 0.0
    safe = planner.check(0.05, plan.T_W_S).safe
    yaw, climb = _kinds(planner)
    level = climb == 0.0
    # every level arc whose end the camera sees (the two hardest turns each way end beside
    # the 90 degree view from a standstill), and the climbs
    assert safe[level & (abs(yaw) <= math.radians(33.0))].all()
    assert safe[(climb > 0.0) & (abs(yaw) <= math.radians(33.0))].all()
    # sinking 0.25 or 0.5 m/s for 2 s, then braking, ends within 1 m of the floor: unsafe
    assert not safe[climb < 0.0].any()


def test_level_arcs_0_8_m_over_a_floor_are_unsafe():
    planner, T_W_B, depth = floor_scene(0.8)
    plan = planner.plan(0.05, T_W_B, FORWARD, np.array([30.0, 0.0, 0.8]))
    for tier in planner.tiers:
        safe = planner.check(0.05, plan.T_W_S, tier).safe
        assert not safe[tier.vertical_speeds <= 0.0].any()
    # what is left is the steepest climb, away from the floor
    assert plan.kind == "arc"
    assert plan.primitive.vertical_speed == planner.options.max_vertical_speed
    ahead = np.array([[x, 0.0, 0.8] for x in (2.0, 4.0, 6.0)])  # spheres reach 0.2 m under
    assert not planner.history.check(ahead).free.any()
    assert not _exact_free(depth, camera_pose(T_W_B), ahead, WIDE).any()


def test_a_wall_2_5_m_ahead_over_a_floor_leaves_only_the_slowest_arcs_safe():
    wall = ((2.5, -50.0, -1.0), (3.0, 50.0, 50.0))
    planner, T_W_B, _ = floor_scene(1.5, [wall])
    # spheres 0.1 m short of the wall are free, 0.1 m into it are not
    result = planner.history.check([[1.4, 0.0, 1.5], [1.6, 0.0, 1.5]])
    np.testing.assert_array_equal(result.free, [True, False])
    plan = planner.plan(0.05, T_W_B, FORWARD, np.array([30.0, 0.0, 1.5]))
    # geometrically right: the hardest turn (45 deg/s at 2 m/s) has radius 2.55 m and reaches
    # x = 2.55 m when it has turned 90 degrees, its sphere 1 m beyond the wall's face; at
    # 1 m/s the straight arc and its braking end 3 m ahead
    for tier in planner.tiers[:2]:
        safe = planner.check(0.05, plan.T_W_S, tier).safe
        assert not safe.any()
    # at 0.5 m/s: 1 m of arc and 0.5 m of braking, the sphere just short of the wall's face
    assert plan.kind == "arc" and plan.primitive.speed == pytest.approx(0.5)
    slowest = planner.tiers[-1]
    safe = planner.check(0.05, plan.T_W_S, slowest).safe
    for i in np.flatnonzero(safe):
        points = np.vstack([slowest.library[i].points_S, slowest.library[i].stop_points_S,
                            slowest.branches[i].stop_points_S])
        assert points[:, 0].max() + planner.options.robot_radius <= 2.5 + 1e-9


@pytest.mark.parametrize("gap, blocked", [(0.9, True), (1.3, False)])
def test_a_thin_pole_within_the_radius_of_the_arc_is_seen(gap, blocked):
    """A 0.1 m pole 5 m ahead, its near side ``gap`` from the straight arc."""
    pole = ((4.95, gap, -1.0), (5.05, gap + 0.1, 50.0))
    planner, T_W_B, depth = floor_scene(1.5, [pole])
    point = [[5.0, 0.0, 1.5]]
    assert planner.history.check(point).free[0] == (not blocked)
    assert _exact_free(depth, camera_pose(T_W_B), point, WIDE)[0] == (not blocked)
    safe = planner.check(0.05, planner.plan(0.05, T_W_B, FORWARD, AHEAD).T_W_S).safe
    yaw, climb = _kinds(planner)
    assert safe[(yaw == 0.0) & (climb == 0.0)][0] == (not blocked)


# ---------------------------------------------------------------- choosing


def test_a_wall_ahead_leaves_nothing_safe_and_the_planner_brakes():
    planner = planner_seeing([((1.8, -50, -50), (2.3, 50, 50))])
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    assert plan.kind == "stop" and plan.reason == "no safe primitive" and plan.safe_count == 0
    # the record says why: the slowest tier, the arcs ahead blocked by the observed wall (the
    # sharpest turns leave the view: unknown space)
    candidates = plan.candidates
    assert candidates.chosen == -1 and candidates.speed == planner.tiers[-1].speed
    ahead = [i for i, p in enumerate(candidates.primitives)
             if p.yaw_rate == 0.0 and p.vertical_speed == 0.0]
    assert not candidates.safe.any() and candidates.blocked[ahead].all()
    assert 0 < candidates.blocked.sum() < len(candidates.primitives)
    velocity, yaw_rate, acceleration, position = plan.setpoint(0.05)
    np.testing.assert_allclose(velocity, FORWARD)  # braking from the present velocity
    np.testing.assert_allclose(acceleration, -FORWARD / planner.options.stop_duration_s)
    np.testing.assert_allclose(position, body()[:3, 3])
    assert yaw_rate == 0.0
    rest = plan.setpoint(0.05 + 2.0)
    np.testing.assert_allclose(rest.velocity_W, 0.0, atol=1e-12)
    np.testing.assert_allclose(rest.position_W - body()[:3, 3], FORWARD * 1.0)  # u T / 2
    # later rounds that find nothing safe continue this braking, they do not begin it afresh
    again = planner.plan(1.0, body(x=1.5), 0.5 * FORWARD, AHEAD)
    assert again.t == plan.t and again.primitive is plan.primitive
    # at rest it holds the stop's end point, where the vehicle has crept to within a radius...
    held = planner.plan(9.0, body(x=1.6), 0.1 * FORWARD, AHEAD)
    assert held.primitive is plan.primitive
    np.testing.assert_allclose(held.setpoint(9.0).position_W, rest.position_W)
    # ...and brakes afresh where it is when pushed farther than that
    pushed = planner.plan(9.5, body(x=-0.5), -0.1 * FORWARD, AHEAD)
    assert pushed.t == 9.5 and pushed.primitive is not plan.primitive


def test_a_wall_3_m_ahead_is_approached_by_a_slower_tier():
    planner = planner_seeing([((3.0, -50, -50), (3.5, 50, 50))])
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    # 2 m/s needs 4 m of arc, 2 m of braking and the radius; 1 m/s arcs stop in 3 m, too far
    assert plan.kind == "arc" and plan.primitive.speed == pytest.approx(0.5)
    safe = planner.check(0.05, plan.T_W_S, planner.tiers[0]).safe
    assert not safe.any()
    # the record says why not faster: each faster tier's arcs blocked by the wall, or (the
    # sharpest turns, which leave the view) meeting only unseen space
    faster = plan.candidates.faster
    assert [tier.speed for tier in faster] == [2.0, 1.0]
    for tier, checked in zip(faster, planner.tiers):
        check = planner.check(0.05, plan.T_W_S, checked)
        assert tier.blocked == check.blocked.sum() > 0
        assert tier.blocked + tier.unseen == len(checked.library)
    # nothing safe at all: the slowest tier's own masks say why, the faster tiers as above
    stop = planner_seeing([((1.8, -50, -50), (2.3, 50, 50))]).plan(0.05, body(), FORWARD, AHEAD)
    assert [tier.speed for tier in stop.candidates.faster] == [2.0, 1.0]


def test_a_middle_tier_flies_where_the_fastest_does_not_fit():
    # a tunnel 3.2 m wide ending 5.5 m ahead: 2 s at 2 m/s (4 m of arc, 2 m of braking and
    # the 1 m radius) reach past its end; at 1.41 m/s, 2.8 m and 1.4 m stop 0.3 m short of it
    tunnel = [((5.5, -50, -50), (6.0, 50, 50)), ((-5.0, 1.6, -50), (20.0, 2.1, 50)),
              ((-5.0, -2.1, -50), (20.0, -1.6, 50))]
    assert planner_seeing(tunnel).plan(0.05, body(), FORWARD, AHEAD).primitive.speed == 1.0
    finer = PlannerOptions(speed_tiers=5, tier_ratio=math.sqrt(0.5))
    plan = planner_seeing(tunnel, options=finer).plan(0.05, body(), FORWARD, AHEAD)
    assert plan.kind == "arc" and plan.primitive.speed == pytest.approx(math.sqrt(2.0))
    assert [tier.speed for tier in plan.candidates.faster] == [2.0]


def test_a_wall_on_the_left_turns_the_choice_right():
    planner = planner_seeing([WALL_LEFT, *ROOM])
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    assert plan.kind == "arc" and plan.reason == ""
    assert plan.primitive.yaw_rate < 0.0
    safe, clearance, _ = planner.check(0.05, plan.T_W_S)
    assert safe.sum() == plan.safe_count and 0 < plan.safe_count < len(planner.tiers[0].library)
    turns = planner.tiers[0].yaw_rates
    assert not safe[turns >= 0.0].any()  # straight on or left: into the wall
    assert safe[turns < 0.0].any()  # right turns clear of it
    assert np.all(clearance[safe] >= 0.0)



def corridor_planner(left_gap, yaw_deg, options=None):
    """At rest in a 3 m corridor along x, ``left_gap`` from its left wall, facing ``yaw_deg``
    toward it, seen once by the 640x480 camera."""
    left = ((-50.0, left_gap, -50.0), (50.0, left_gap + 0.5, 50.0))
    right = ((-50.0, left_gap - 3.5, -50.0), (50.0, left_gap - 3.0, 50.0))
    T_W_B = body(yaw=math.radians(yaw_deg))
    planner = Planner(WIDE, options)
    depth = render(camera_pose(T_W_B), [left, right, *ROOM], WIDE)
    planner.add_depth(metric(depth, 0.0), camera_pose(T_W_B))
    return planner, T_W_B


@pytest.mark.parametrize("left_gap, yaw_deg", [(0.8, 0.0), (0.8, 15.0), (0.7, 0.0)])
def test_a_vehicle_nearer_a_wall_than_its_radius_flies_out_keeping_the_room_it_has(left_gap,
                                                                                 yaw_deg):
    """Stopped at a corner that hugs the wall: every arc starts inside the robot's sphere, so
    none is safe with it; the arcs checked with the largest sphere that passes fly on, and
    nowhere along the chosen arc and its braking is the vehicle nearer the wall than that."""
    stuck, T_W_B = corridor_planner(left_gap, yaw_deg, PlannerOptions(escape_radius=1.0))
    assert stuck.plan(0.05, T_W_B, np.zeros(3), AHEAD).reason == "no safe primitive"
    planner, T_W_B = corridor_planner(left_gap, yaw_deg)
    plan = planner.plan(0.05, T_W_B, np.zeros(3), AHEAD)
    assert plan.kind == "arc" and plan.primitive.yaw_rate <= 0.0  # along or away from it
    radius = plan.candidates.radius
    assert planner.options.escape_radius <= radius < planner.options.robot_radius
    assert radius <= left_gap + 1e-9
    points = np.vstack([plan.primitive.points_S, plan.primitive.stop_points_S])
    y_W = (points @ plan.T_W_S[:3, :3].T + plan.T_W_S[:3, 3])[:, 1]
    assert left_gap - y_W.max() >= radius - 1e-6
    assert y_W.min() - (left_gap - 3.0) >= radius - 1e-6
    # the largest sphere that passes: one step larger, nothing is safe
    larger = planner.check(0.05, plan.T_W_S, planner.tiers[-1], radius + 0.1)
    assert not larger.safe.any()


def test_a_vehicle_nearer_a_wall_than_the_escape_radius_stays_stopped():
    planner, T_W_B = corridor_planner(0.55, 0.0)
    plan = planner.plan(0.05, T_W_B, np.zeros(3), AHEAD)
    assert plan.kind == "stop" and plan.reason == "no safe primitive"
    assert plan.candidates.radius == pytest.approx(planner.options.escape_radius)


def test_a_wall_ahead_beyond_the_radius_does_not_shrink_the_sphere():
    """The escape is for a vehicle already too near; one that is blocked farther ahead stops
    with the robot's own sphere (the behaviours turn or back it off)."""
    planner = planner_seeing([((1.8, -50, -50), (2.3, 50, 50))])
    plan = planner.plan(0.05, body(), np.zeros(3), AHEAD)
    assert plan.reason == "no safe primitive"
    assert plan.candidates.radius == planner.options.robot_radius


def test_a_check_with_a_smaller_sphere_frees_what_the_robots_sphere_does_not():
    history = planner_seeing([((2.0, -50, -50), (2.5, 50, 50)), *ROOM]).history
    point = [[1.2, 0.0, ALTITUDE]]  # 0.8 m short of the wall
    assert history.check(point).occupied[0]
    assert history.check(point, radius=0.7).free[0]
    assert not history.check(point, radius=0.9).free[0]
    with pytest.raises(ValueError, match="radius"):
        history.check(point, radius=1.5)


def test_a_primitives_check_stops_at_its_first_occupied_point_with_the_same_verdicts():
    """The planner checks each primitive's points as a group and stops judging a primitive at
    its first occupied point: which primitives are safe, and a safe one's clearance, are what
    judging every point gives."""
    planner = planner_seeing([WALL_LEFT, *ROOM])
    older = camera_pose(body(x=-0.5, yaw=0.2))
    depth = render(older, [WALL_LEFT, *ROOM])
    planner.history.add(depth, np.ones_like(depth), older, CAMERA, -0.05)
    T_W_S = planner.plan(0.05, body(), FORWARD, AHEAD).T_W_S
    tier = planner.tiers[0]
    points = tier.points_S @ T_W_S[:3, :3].T + T_W_S[:3, 3]
    every = planner.history.check(points, start_W=T_W_S[:3, 3], now=0.05)
    grouped = planner.history.check(points, start_W=T_W_S[:3, 3], now=0.05,
                                    groups=tier.primitive_of_point)
    safe, clearance, _ = planner.check(0.05, T_W_S)
    np.testing.assert_array_equal(safe, np.logical_and.reduceat(every.free, tier.starts))
    np.testing.assert_array_equal(
        clearance[safe], np.fmin.reduceat(every.clearance, tier.starts)[safe])
    assert 0 < safe.sum() < len(safe)
    assert not np.any(grouped.free & ~every.free)
    assert np.isnan(grouped.frame).sum() > np.isnan(every.frame).sum()  # points left unjudged
    with pytest.raises(ValueError, match="groups must be"):
        planner.history.check(points, groups=np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match="groups must be"):
        planner.history.check(points, groups=np.full(len(points), -1))

def test_no_depth_and_unknown_depth_mean_stop():
    planner = Planner(CAMERA)
    assert planner.plan(0.0, body(), FORWARD, AHEAD).reason == "no depth"
    nothing = MetricDepth(0.0, None, None, False, DIAGNOSTICS)
    assert planner.add_depth(nothing, camera_pose(body())) is False
    assert planner.plan(0.0, body(), FORWARD, AHEAD).reason == "no depth"
    blank = np.full((120, 160), np.nan, dtype=np.float32)
    planner.add_depth(metric(blank, 0.0), camera_pose(body()))
    unknown = planner.plan(0.05, body(), FORWARD, AHEAD)
    assert unknown.reason == "no safe primitive"
    assert not unknown.candidates.blocked.any()  # nothing observed: unsafe for unknown space
    stale = planner_seeing(ROOM, t=0.0)
    assert stale.plan(0.05, body(), FORWARD, AHEAD).kind == "arc"
    assert stale.plan(5.0, body(), FORWARD, AHEAD).reason == "no depth"  # older than history_s


def test_a_corridor_whose_near_walls_hold_no_landmark_is_flown_on_their_near_tail():
    """A 3.4 m wide corridor (floor and ceiling 1.7 m from the vehicle too) whose landmarks
    all lie 3 m or farther: every wall pixel nearer has no confident depth to bound it. As
    unknown they leave no arc safe; as 0.9 of their depth the straight arcs are, and no arc
    that turns into a wall is."""
    corridor = [((-50.0, 1.7, -50.0), (50.0, 1.8, 50.0)),
                ((-50.0, -1.8, -50.0), (50.0, -1.7, 50.0)),
                ((-50.0, -50.0, ALTITUDE - 1.8), (50.0, 50.0, ALTITUDE - 1.7)),
                ((-50.0, -50.0, ALTITUDE + 1.7), (50.0, 50.0, ALTITUDE + 1.8)), *ROOM]
    T_W_C = camera_pose(body())
    depth = render(T_W_C, corridor)
    confidence = np.where(depth >= 3.0, 1.0, 0.1).astype(np.float32)
    plans = {}
    for share in (0.0, 0.9):
        planner = Planner(CAMERA, PlannerOptions(near_tail_share=share))
        planner.add_depth(metric(depth, 0.0, confidence), T_W_C)
        plans[share] = planner.plan(0.05, body(), FORWARD, AHEAD)
    assert plans[0.0].reason == "no safe primitive"
    flown = plans[0.9].candidates
    assert plans[0.9].kind == "arc" and plans[0.9].primitive.yaw_rate == 0.0
    assert {flown.primitives[i].yaw_rate for i in np.flatnonzero(flown.safe)} == {0.0}


@pytest.mark.parametrize("share", [0.0, 0.9])
def test_low_confidence_everywhere_means_stop(share):
    """With no confident depth within range there is no near tail to trust, whatever the
    share: confident pixels only beyond ``max_range`` (the sky) do not make one."""
    planner = Planner(CAMERA, PlannerOptions(near_tail_share=share))
    T_W_C = camera_pose(body())
    depth = np.full((CAMERA.height, CAMERA.width), 6.0, np.float32)  # a wall within range
    confidence = np.full_like(depth, 0.2)
    depth[:5], confidence[:5] = 60.0, 1.0  # a confident strip beyond range
    planner.add_depth(metric(depth, 0.0, confidence), T_W_C)
    assert planner.plan(0.05, body(), FORWARD, AHEAD).reason == "no safe primitive"


@pytest.mark.parametrize("goal, turn, climb", [((10.0, 10.0, ALTITUDE), 1, 0),
                                               ((10.0, -10.0, ALTITUDE), -1, 0),
                                               ((30.0, 0.0, ALTITUDE + 10.0), 0, 1)])
def test_in_open_space_the_choice_heads_for_the_goal(goal, turn, climb):
    planner = planner_seeing(ROOM)
    plan = planner.plan(0.05, body(), FORWARD, np.array(goal))
    assert plan.kind == "arc" and plan.safe_count >= 45
    end_W = plan.T_W_S[:3, :3] @ plan.primitive.points_S[-1] + plan.T_W_S[:3, 3]
    start = np.array([0.0, 0.0, ALTITUDE])
    assert np.linalg.norm(end_W - goal) < np.linalg.norm(start - goal) - 3.0
    assert np.sign(plan.primitive.yaw_rate) == turn
    assert np.sign(plan.primitive.vertical_speed) == climb


@pytest.mark.parametrize("height_gap_in_time, sinks", [(True, True), (False, False)])
def test_a_goal_below_is_sunk_to_on_the_way_when_height_counts_in_time(height_gap_in_time,
                                                                       sinks):
    """2.5 m over a floor, the waypoint 12 m ahead at 1.5 m (a route's cruise height, the
    hallway's door in docs/planner.md "Height"): counted in time the height gap outweighs the
    floor's nearness and the choice sinks; as plain distance it climbs away from the floor."""
    options = PlannerOptions(height_gap_in_time=height_gap_in_time)
    planner, T_W_B, _ = floor_scene(2.5, options=options)
    plan = planner.plan(0.05, T_W_B, FORWARD, np.array([12.0, 0.0, 1.5]))
    assert plan.kind == "arc" and plan.primitive.yaw_rate == 0.0
    assert (plan.primitive.vertical_speed < 0.0) == sinks
    assert (plan.primitive.vertical_speed > 0.0) == (not sinks)


def test_smoothness_keeps_the_choice_near_the_previous_one():
    changes = {}
    for weight in (0.0, 3.0):
        options = PlannerOptions(smoothness_weight=weight)
        planner = planner_seeing(ROOM, options=options)
        first = planner.plan(0.05, body(), FORWARD, np.array([5.0, 10.0, ALTITUDE]))
        second = planner.plan(0.10, body(), FORWARD, AHEAD)
        changes[weight] = abs(second.primitive.yaw_rate - first.primitive.yaw_rate)
        again = planner.plan(0.15, body(), FORWARD, AHEAD)
        assert again.primitive is planner.plan(0.2, body(), FORWARD, AHEAD).primitive
    assert changes[3.0] < changes[0.0]


def test_when_nothing_is_safe_the_previous_rounds_checked_stop_is_continued():
    planner = planner_seeing(ROOM)
    first = planner.plan(0.05, body(), FORWARD, np.array([10.0, 10.0, ALTITUDE]))
    index = next(i for i, a in enumerate(planner.tiers[0].library) if a is first.primitive)
    T_W_B = body(x=0.15)
    wall = render(camera_pose(T_W_B), [((1.5, -50, -50), (2.0, 50, 50))])
    planner.add_depth(metric(wall, 0.1), camera_pose(T_W_B))
    stop = planner.plan(0.13, T_W_B, FORWARD, AHEAD)
    assert stop.kind == "stop" and stop.reason == "no safe primitive"
    assert stop.primitive is planner.tiers[0].branches[index]
    assert stop.t == first.t and np.array_equal(stop.T_W_S, first.T_W_S)
    assert stop.primitive.duration == pytest.approx(planner.options.period_s)
    # the same commands as the first plan for one period, then braking along that heading
    np.testing.assert_allclose(stop.setpoint(0.1)[0], first.setpoint(0.1)[0])
    mid = first.t + planner.options.period_s + 1.0
    np.testing.assert_allclose(np.linalg.norm(stop.setpoint(mid)[0]),
                               0.5 * np.linalg.norm(first.primitive.end_velocity_S), rtol=1e-9)
    assert stop.setpoint(mid)[1] == 0.0
    failsafe = planner.stop_plan(0.2, T_W_B, FORWARD, "vins lost")
    assert failsafe.primitive is stop.primitive and failsafe.reason == "vins lost"
    late = planner.stop_plan(first.t + 10.0, T_W_B, FORWARD, "vins lost")  # it has run out
    assert late.t == first.t + 10.0 and late.primitive.duration == 0.0


def test_a_stop_afresh_for_a_turn_holds_where_the_vehicle_came_to_rest():
    """Blocked, the rounds continue the stop checked with the last arc: that arc for a period,
    then braking along it. The vehicle at rest before that stop has run out, about to turn in
    place: the stop afresh holds it where it is, and the stops after it (a failsafe's, a blocked
    round's) continue it, not the older one that runs on toward the wall."""
    planner = planner_seeing(ROOM)
    first = planner.plan(0.05, body(), FORWARD, np.array([10.0, 10.0, ALTITUDE]))
    T_W_B = body(x=0.15)
    wall = render(camera_pose(T_W_B), [((1.5, -50, -50), (2.0, 50, 50))])
    planner.add_depth(metric(wall, 0.1), camera_pose(T_W_B))
    older = planner.plan(0.13, T_W_B, FORWARD, AHEAD)
    assert older.kind == "stop" and older.t == first.t
    at_rest = body(x=0.3)
    hold = planner.stop_afresh(0.6, at_rest, np.zeros(3), "holding where it turns")
    assert hold.t == 0.6 and hold.reason == "holding where it turns"
    for t in (0.6, 1.0, older.end_time, hold.end_time + 1.0):
        np.testing.assert_allclose(hold.setpoint(t).position_W, at_rest[:3, 3], atol=1e-9)
        np.testing.assert_allclose(hold.setpoint(t).velocity_W, 0.0, atol=1e-9)
    assert np.linalg.norm(older.setpoint(1.0).position_W - at_rest[:3, 3]) > 0.1
    failsafe = planner.stop_plan(1.0, at_rest, np.zeros(3), "vins lost")
    assert failsafe.primitive is hold.primitive and failsafe.t == hold.t


def test_a_failsafe_during_a_glide_continues_the_glide_held_not_the_older_rounds_stop():
    """A backing-off flies glides and holds each one's glide to rest as the checked stop;
    the last round's stop lies at the dead end behind it."""
    planner = planner_seeing(ROOM)
    planner.plan(0.05, body(), FORWARD, AHEAD)
    back = body(x=-1.0)
    to_rest = planner.glide(0.5, back, np.array([-2.0, 0.0, ALTITUDE]), "backing off")
    failsafe = planner.stop_plan(0.6, back, -0.5 * FORWARD, "vins lost", held=to_rest)
    assert failsafe.primitive is to_rest.primitive and failsafe.reason == "vins lost"
    np.testing.assert_allclose(failsafe.setpoint(9.0).position_W, (-2.0, 0.0, ALTITUDE),
                               atol=1e-9)
    # a newer round's stop is not replaced by the older glide held
    again = planner.plan(0.9, body(), FORWARD, AHEAD)
    assert again.kind == "arc"
    later = planner.stop_plan(1.0, back, np.zeros(3), "vins lost", held=to_rest)
    assert later.t == again.t and later.primitive is not to_rest.primitive


@pytest.mark.parametrize("distance", [0.3, 2.5])
def test_an_approach_glides_straight_to_rest_over_its_goal(distance):
    planner = planner_seeing(ROOM)
    goal = np.array([distance * math.cos(0.4), distance * math.sin(0.4), ALTITUDE + 0.1])
    plan = planner.approach(1.0, body(), goal)
    assert plan is not None and plan.kind == "stop" and plan.reason == "approach"
    rest = plan.setpoint(plan.end_time + 1.0)
    np.testing.assert_allclose(rest.position_W, goal, atol=1e-9)
    assert plan.setpoint(1.5).yaw_rate == 0.0  # heading held
    speeds = [np.linalg.norm(plan.setpoint(t).velocity_W[:2]) for t in np.arange(1.0, 9.0, 0.1)]
    assert max(speeds) <= planner.tiers[-1].speed + 1e-9
    # it is the stop the next rounds continue when they find nothing safe
    assert planner.stop_plan(1.5, body(), FORWARD, "vins lost").primitive is plan.primitive


def test_a_glide_through_its_goal_passes_it_at_the_slowest_speed_and_brakes_after_it():
    planner = planner_seeing(ROOM)
    goal = np.array([1.2 * math.cos(0.4), 1.2 * math.sin(0.4), ALTITUDE + 0.1])
    plan = planner.glide(1.0, body(), goal, "backing off", stop_at_goal=False)
    assert plan.kind == "glide" and plan.reason == "backing off"
    slowest = planner.tiers[-1].speed
    at_goal = plan.setpoint(1.0 + 1.2 / slowest)
    np.testing.assert_allclose(at_goal.position_W, goal, atol=1e-9)  # height included
    np.testing.assert_allclose(np.linalg.norm(at_goal.velocity_W[:2]), slowest)
    assert plan.setpoint(1.5).yaw_rate == 0.0  # heading held
    # its stopping extension runs on past the goal: the next round's glide replaces it
    beyond = plan.setpoint(plan.end_time).position_W - goal
    assert np.hypot(*beyond[:2]) == pytest.approx(slowest * planner.options.stop_duration_s / 2)


def test_an_approach_through_a_wall_is_refused():
    planner = planner_seeing([((1.5, -50, -50), (2.0, 50, 50))])
    assert planner.approach(1.0, body(), np.array([2.5, 0.0, ALTITUDE])) is None
    assert planner.approach(1.0, body(), body()[:3, 3]) is None  # already there


# ---------------------------------------------------------------- landing sites


def test_over_an_open_floor_the_landing_site_is_the_nearest_one_ahead():
    planner, T_W_B, _ = floor_scene(1.5)
    glide = planner.landing_glide(0.05, T_W_B, floor_z=0.0)
    assert glide is not None and glide.reason == "landing site" and glide.kind == "stop"
    np.testing.assert_allclose(glide.setpoint(glide.end_time).position_W, [2.0, 0.0, 1.5],
                               atol=1e-9)
    # the glide is what the watchdog falls back to, and what later stops continue
    assert planner.stop_plan(0.1, T_W_B, np.zeros(3), "x").primitive is glide.primitive


def test_a_crate_under_the_nearest_site_moves_the_site_clear_of_it():
    """A 0.35 m crate 2 m ahead: out of reach of the glide's spheres at 1.5 m (radius 1 m
    reaches down to 0.5 m), so only the column check can see it."""
    crate = ((1.8, -0.2, -1.0), (2.2, 0.2, 0.35))
    planner, T_W_B, _ = floor_scene(1.5, [crate])
    assert planner.approach(0.05, T_W_B, np.array([2.0, 0.0, 1.5])) is not None
    glide = planner.landing_glide(0.05, T_W_B, floor_z=0.0)
    assert glide is not None
    site = glide.setpoint(glide.end_time).position_W
    gap = np.linalg.norm(np.maximum(np.abs(site[:2] - [2.0, 0.0]) - 0.2, 0.0))
    assert gap >= planner.options.landing_radius, site
    # no farther than needed: the sites nearer than 3 m have the crate within their column's
    # radius, or (1 m aside) a glide whose spheres reach the floor's near rays
    assert np.hypot(*site[:2]) <= 3.0 + 1e-9, site


def test_a_pole_beside_the_way_to_the_nearest_site_moves_the_site_to_a_free_glide():
    """A pole 0.8 m left of the straight glide to the nearest site: the site's column is
    clear of it (1.3 m away), but the robot's sphere on the way is not."""
    pole = ((0.95, 0.75, -1.0), (1.05, 0.85, 50.0))
    planner, T_W_B, _ = floor_scene(1.5, [pole])
    column = column_points(np.array([2.0, 0.0, 1.5]), 0.0, planner.options.landing_radius)
    assert planner.history.check(column, now=0.05, radius=0.5).free.all()
    glide = planner.landing_glide(0.05, T_W_B, floor_z=0.0)
    assert glide is not None
    site = glide.setpoint(glide.end_time).position_W[:2]
    assert not np.allclose(site, [2.0, 0.0])
    # the glide's segment keeps the robot's radius from the pole's axis
    axis, along = np.array([1.0, 0.8]), site / np.linalg.norm(site)
    nearest = np.clip(axis @ along, 0.0, np.linalg.norm(site)) * along
    assert np.linalg.norm(axis - nearest) >= planner.options.robot_radius


def test_no_landing_site_without_room_to_glide_a_seen_floor_or_the_option():
    wall = ((2.5, -50.0, -1.0), (3.0, 50.0, 50.0))
    planner, T_W_B, _ = floor_scene(1.5, [wall])
    assert planner.landing_glide(0.05, T_W_B, floor_z=0.0) is None  # every glide meets it
    planner, T_W_B, depth = floor_scene(1.5)
    assert planner.landing_glide(5.0, T_W_B, floor_z=0.0) is None  # the frame is too old
    unseen = Planner(WIDE)
    unseen.add_depth(metric(np.where(WIDE.rays()[..., 1] > 0.0, np.nan, depth), 0.0),
                     camera_pose(T_W_B))
    assert unseen.landing_glide(0.05, T_W_B, floor_z=0.0) is None  # no floor seen
    off = Planner(WIDE, PlannerOptions(landing_radius=0.0))
    off.add_depth(metric(depth, 0.0), camera_pose(T_W_B))
    assert off.landing_glide(0.05, T_W_B, floor_z=0.0) is None
    with pytest.raises(ValueError, match="floor_z"):
        planner.landing_glide(0.05, T_W_B, floor_z=math.nan)


def test_the_chosen_primitives_stop_branch_was_checked_free():
    planner = planner_seeing([WALL_LEFT, *ROOM])
    plan = planner.plan(0.05, body(), FORWARD, AHEAD)
    i = next(i for i, a in enumerate(planner.tiers[0].library) if a is plan.primitive)
    branch = planner.tiers[0].branches[i]
    # the branch's short arc is the arc's first piece; its braking goes off the arc
    path_S = np.vstack([plan.primitive.points_S[1:], plan.primitive.stop_points_S,
                        branch.stop_points_S])
    path_W = path_S @ plan.T_W_S[:3, :3].T + plan.T_W_S[:3, 3]
    assert planner.history.check(path_W, start_W=plan.T_W_S[:3, 3]).free.all()


# ---------------------------------------------------------------- setpoints


def _fly(plan: Plan, t0: float, t1: float, dt: float = 1e-3):
    """Integrate the setpoints (midpoint rule): positions and yaw relative to T_W_S."""
    position, yaw, trace = plan.T_W_S[:3, 3].copy(), 0.0, []
    for t in np.arange(t0, t1, dt):
        velocity, yaw_rate, _, _ = plan.setpoint(t + dt / 2)
        position = position + velocity * dt
        yaw += yaw_rate * dt
        trace.append((t + dt, position.copy(), yaw))
    return trace


@pytest.mark.parametrize("yaw", [0.0, 2.0])
def test_integrated_setpoints_follow_the_arc_and_its_extension(yaw):
    planner = planner_seeing(ROOM, T_W_B=body(yaw=yaw))
    goal = body(yaw=yaw) @ np.array([10.0, 6.0, 5.0, 1.0])
    plan = planner.plan(1.0, body(yaw=yaw), FORWARD, goal[:3])
    arc = plan.primitive
    assert arc.yaw_rate != 0.0 and arc.vertical_speed != 0.0
    trace = _fly(plan, 1.0, 1.0 + arc.duration + plan.stop_duration_s + 0.5)
    times = np.array([t for t, _, _ in trace])
    positions_S = (np.array([p for _, p, _ in trace]) - plan.T_W_S[:3, 3]) @ plan.T_W_S[:3, :3]
    for tau, point in zip(arc.t, arc.points_S):
        k = int(np.argmin(abs(times - 1.0 - tau)))
        np.testing.assert_allclose(positions_S[k], point, atol=5e-3)
    at_rest = positions_S[-1]
    np.testing.assert_allclose(at_rest, arc.stop_points_S[-1], atol=5e-3)
    assert trace[-1][2] == pytest.approx(arc.heading, abs=1e-3)
    np.testing.assert_allclose(plan.setpoint(100.0)[0], 0.0)


# ---------------------------------------------------------------- bad input


def test_bad_inputs_raise_clear_errors():
    planner = planner_seeing(ROOM)
    with pytest.raises(ValueError, match="goal_W must be finite"):
        planner.plan(0.1, body(), FORWARD, [np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="velocity_W must be 3 numbers"):
        planner.plan(0.1, body(), [1.0, 2.0], AHEAD)
    with pytest.raises(ValueError, match="T_W_B must be finite"):
        planner.plan(0.1, np.full((4, 4), np.inf), FORWARD, AHEAD)
    with pytest.raises(ValueError, match="T_W_B must hold a rotation"):
        planner.plan(0.1, np.diag([2.0, 1.0, 1.0, 1.0]), FORWARD, AHEAD)
    with pytest.raises(ValueError, match="planning time"):
        planner.plan(math.nan, body(), FORWARD, AHEAD)
    with pytest.raises(ValueError, match="depth image must have the camera's shape"):
        planner.add_depth(metric(np.ones((10, 10), np.float32), 0.0), camera_pose(body()))
    with pytest.raises(ValueError, match="confidence must have"):
        planner.add_depth(metric(np.ones((120, 160), np.float32), 0.0, np.ones((2, 2))),
                          camera_pose(body()))
    with pytest.raises(ValueError, match="no confidence"):
        planner.add_depth(MetricDepth(0.0, np.ones((120, 160), np.float32), None, False,
                                      DIAGNOSTICS), camera_pose(body()))
    with pytest.raises(TypeError, match="MetricDepth"):
        planner.add_depth(np.ones((120, 160)), camera_pose(body()))
    tiny = PinholeCamera.from_hfov(40, 24, math.radians(90.0))
    with pytest.raises(ValueError, match="smaller than the 32-pixel blocks"):
        Planner(tiny)
    with pytest.raises(ValueError, match="reason"):
        planner.stop_plan(0.0, body(), FORWARD, "")


@pytest.mark.parametrize("key, value", [("period_s", 2.0), ("max_range", 0.5),
                                        ("max_yaw_rate_deg", 0.0), ("robot_radius", 0.0),
                                        ("escape_radius", 1.5), ("history_frames", 0),
                                        ("landing_radius", 1.5)])
def test_bad_options_are_named(key, value):
    with pytest.raises(OptionError, match=key):
        PlannerOptions(**{key: value})


def test_planner_options_give_the_library_shape():
    options = PlannerOptions(speed=1.5, yaw_rates=5, vertical_speeds=3)
    shape = options.primitives
    assert (shape.speed, shape.yaw_rates, shape.vertical_speeds) == (1.5, 5, 3)
    tiers = Planner(CAMERA, options).tiers
    assert [tier.speed for tier in tiers] == [1.5, 0.75, 0.375]
    assert all(len(tier.library) == 15 for tier in tiers)
