"""The metric depth stage: network output checked, paired with the VINS map of its frame,
rescaled, held briefly when a frame gets no fit, and "no depth" after that."""

import math

import numpy as np
import pytest

from autonomy.depth import metrics
from autonomy.depth.rescale import RescaleOptions
from autonomy.depth.stage import (
    NO_SPARSE_MAP, DepthStageOptions, MetricDepthStage, Rejection, check_relative_disparity,
)
from autonomy.geometry import PinholeCamera
from autonomy.messages import RelativeDepth, SparseMap
from autonomy.options import OptionError

CAMERA = PinholeCamera.from_hfov(64, 48, math.radians(90.0))


def _scene_depth() -> np.ndarray:
    """A floor receding to 12 m, a wall at 6 m on the left and a box at 1.5 m on the right;
    the anchors of :func:`_grid_pixels` span its whole depth range."""
    rows = np.arange(CAMERA.height, dtype=np.float32)[:, None]
    depth = np.broadcast_to(np.minimum(12.0, 40.0 / (rows + 1.0)), (48, 64)).copy()
    depth[:, :16] = 6.0
    depth[10:30, 40:56] = 1.5
    return depth


def _network(depth: np.ndarray) -> np.ndarray:
    """A network's relative disparity: an unknown monotone map of 1/z."""
    return (2.0 * (1.0 / depth) ** 0.9 + 0.1).astype(np.float32)


def _sparse_map(t: float, depth: np.ndarray, pixels: np.ndarray, *, tracked=None,
                depth_error: float = 1.0) -> SparseMap:
    """Landmarks seen at ``pixels`` whose metric depth is the scene's times ``depth_error``:
    the nearest surface of the four pixels around each (where the stage samples the network)."""
    u, v = pixels.T
    u0, v0 = np.floor(u).astype(int).clip(0, 63), np.floor(v).astype(int).clip(0, 47)
    u1, v1 = np.minimum(u0 + 1, 63), np.minimum(v0 + 1, 47)
    z = np.minimum.reduce([depth[v0, u0], depth[v0, u1], depth[v1, u0], depth[v1, u1]])
    z = z * depth_error
    points = np.column_stack([(u - CAMERA.cx) / CAMERA.fx * z, (v - CAMERA.cy) / CAMERA.fy * z, z])
    n = len(pixels)
    tracked = np.ones(n, bool) if tracked is None else np.asarray(tracked)
    return SparseMap(t, np.arange(n), points, 0.01 * z, pixels, tracked)


def _grid_pixels(step: int = 6) -> np.ndarray:
    v, u = np.mgrid[2:46:step, 2:62:step]
    return np.column_stack([u.ravel(), v.ravel()]).astype(float)


def _stage(**options) -> MetricDepthStage:
    return MetricDepthStage(RescaleOptions(), DepthStageOptions(**options))


def test_a_frame_with_its_sparse_map_gets_metric_depth_and_diagnostics():
    depth = _scene_depth()
    stage = _stage()
    pixels = _grid_pixels()
    result = stage.process(RelativeDepth(1.0, _network(depth)), _sparse_map(1.0, depth, pixels))
    assert result.ok and not result.held
    assert result.depth.shape == depth.shape and result.depth.dtype == np.float32
    assert metrics.abs_rel(result.depth, depth) < 0.02
    assert result.confidence.shape == depth.shape
    assert 0.0 <= result.confidence.min() and result.confidence.max() <= 1.0
    d = result.diagnostics
    assert d.anchors == len(pixels) and d.anchors_used >= 10
    assert d.method == "monotone_spline" and d.fit_age_s == 0.0 and d.reason == ""
    assert d.residual_rms < 0.01


def test_the_map_of_the_frames_own_time_is_used_and_no_other():
    depth = _scene_depth()
    stage = _stage(max_map_offset_s=0.002)
    own = _sparse_map(1.0, depth, _grid_pixels())
    assert metrics.abs_rel(stage.process(RelativeDepth(1.0005, _network(depth)), own).depth,
                           depth) < 0.02
    # a map 20 ms off belongs to another frame: refused, and the fit of 1.0005 is held
    neighbour = _sparse_map(1.0, depth, _grid_pixels(), depth_error=2.0)  # twice too deep
    between = stage.process(RelativeDepth(1.02, _network(depth)), neighbour)
    assert between.ok and between.held
    assert metrics.abs_rel(between.depth, depth) < 0.02
    assert stage.process(RelativeDepth(1.04, _network(depth)), None).held
    assert stage.no_fit[NO_SPARSE_MAP] == 2


def test_the_last_good_fit_is_held_for_hold_s_then_there_is_no_depth():
    depth = _scene_depth()
    stage = _stage(hold_s=0.5)
    assert stage.process(RelativeDepth(0.0, _network(depth)),
                         _sparse_map(0.0, depth, _grid_pixels())).ok
    few = _grid_pixels()[:3]
    for t in (0.3, 0.5):
        held = stage.process(RelativeDepth(t, _network(depth)), _sparse_map(t, depth, few))
        assert held.ok and held.held
        assert held.diagnostics.fit_age_s == pytest.approx(t)
        assert held.diagnostics.anchors == 3
        assert "too_few_anchors" in held.diagnostics.reason
        assert metrics.abs_rel(held.depth, depth) < 0.02
    late = stage.process(RelativeDepth(0.51, _network(depth)), _sparse_map(0.51, depth, few))
    assert not late.ok and late.depth is None and late.confidence is None
    assert "too_few_anchors" in late.diagnostics.reason
    assert stage.no_fit["too_few_anchors"] == 3


def _affine_network(depth: np.ndarray) -> np.ndarray:
    """A network whose relative disparity is exactly affine in 1/z, as Depth Anything is
    trained to be."""
    return (2.0 / depth + 0.1).astype(np.float32)


def _spread_pixels(count: int) -> np.ndarray:
    """``count`` pixels spread over the floor, the wall and the box of :func:`_scene_depth`."""
    pixels = _grid_pixels()
    return pixels[np.linspace(0, len(pixels) - 1, count).astype(int)]


def test_after_the_hold_too_few_anchors_for_the_curve_get_the_affine_fallback():
    depth = _scene_depth()
    stage = _stage(hold_s=0.5, fallback_min_anchors=5)
    assert stage.process(RelativeDepth(0.0, _affine_network(depth)),
                         _sparse_map(0.0, depth, _grid_pixels())).ok
    six = _spread_pixels(6)
    held = stage.process(RelativeDepth(0.3, _affine_network(depth)), _sparse_map(0.3, depth, six))
    assert held.held and not held.diagnostics.fallback  # the hold comes first
    result = stage.process(RelativeDepth(0.6, _affine_network(depth)),
                           _sparse_map(0.6, depth, six))
    assert result.ok and not result.held
    d = result.diagnostics
    assert d.fallback and d.method == "poly1" and d.fit_age_s == 0.0
    assert d.anchors == 6 and d.anchors_used == 6
    assert d.reason.startswith("affine fallback after no fit (too_few_anchors)")
    assert metrics.abs_rel(result.depth, depth) < 1e-3
    assert len(result.fit.anchor_relative) == 6
    assert stage.fallbacks == 1 and stage.no_fit["too_few_anchors"] == 2
    # the fallback is not held: the next frame without enough anchors has no depth
    assert not stage.process(RelativeDepth(0.65, _affine_network(depth)),
                             _sparse_map(0.65, depth, six[:3])).ok


def test_the_fallback_is_trusted_less_than_the_curve():
    """Confidence counts anchors near each disparity, so the planner's ``min_confidence``
    keeps fewer of the fallback's pixels."""
    depth = _scene_depth()
    full = _stage().process(RelativeDepth(0.0, _affine_network(depth)),
                            _sparse_map(0.0, depth, _grid_pixels()))
    fallback = _stage().process(RelativeDepth(0.0, _affine_network(depth)),
                                _sparse_map(0.0, depth, _spread_pixels(6)))
    assert fallback.diagnostics.fallback and not full.diagnostics.fallback
    assert np.mean(fallback.confidence >= 0.3) < np.mean(full.confidence >= 0.3)


def test_the_fallback_is_refused_when_off_too_few_or_the_anchors_disagree():
    depth = _scene_depth()
    six = _spread_pixels(6)
    relative = RelativeDepth(0.0, _affine_network(depth))
    assert not _stage(fallback_min_anchors=0).process(relative, _sparse_map(0.0, depth, six)).ok
    assert not _stage(fallback_min_anchors=7).process(relative, _sparse_map(0.0, depth, six)).ok
    # metric depth that grows with the network's disparity: no map rises through it
    backwards = RelativeDepth(0.0, (0.05 * depth).astype(np.float32))
    result = _stage().process(backwards, _sparse_map(0.0, depth, six))
    assert not result.ok and "too_few_anchors" in result.diagnostics.reason


def test_without_any_fit_yet_there_is_no_depth():
    stage = _stage()
    result = stage.process(RelativeDepth(0.0, _network(_scene_depth())), None)
    assert not result.ok and "no VINS sparse map" in result.diagnostics.reason


def test_hold_zero_never_holds():
    depth = _scene_depth()
    stage = _stage(hold_s=0.0)
    stage.process(RelativeDepth(0.0, _network(depth)), _sparse_map(0.0, depth, _grid_pixels()))
    assert not stage.process(RelativeDepth(0.05, _network(depth)),
                             _sparse_map(0.05, depth, _grid_pixels()[:2])).ok


def test_untracked_landmarks_are_anchors_only_when_asked():
    """A landmark merely projected into view may be hidden behind an obstacle: with
    ``tracked_only`` its (here wrong) depth is not used."""
    depth = _scene_depth()
    pixels = _grid_pixels(4)
    tracked = np.arange(len(pixels)) % 2 == 0
    sparse = _sparse_map(0.0, depth, pixels, tracked=tracked)
    sparse.points_C[~tracked] *= 3.0
    results = {}
    for tracked_only in (True, False):
        stage = _stage(tracked_only=tracked_only)
        results[tracked_only] = stage.process(RelativeDepth(0.0, _network(depth)), sparse)
    assert results[True].diagnostics.anchors == tracked.sum()
    assert results[False].diagnostics.anchors == len(pixels)
    assert metrics.abs_rel(results[True].depth, depth) < 0.02


def test_landmarks_off_the_image_are_not_anchors():
    depth = _scene_depth()
    pixels = np.vstack([_grid_pixels(), [[-3.0, 10.0], [70.0, 5.0], [10.0, 48.5]]])
    stage = _stage()
    assert stage.process(RelativeDepth(0.0, _network(depth)),
                         _sparse_map(0.0, depth, pixels)).diagnostics.anchors == len(pixels) - 3


@pytest.mark.parametrize("corrupt, reason", [
    (lambda d: d.__setitem__((3, 4), np.nan), Rejection.NON_FINITE),
    (lambda d: d.__setitem__((3, 4), np.inf), Rejection.NON_FINITE),
    (lambda d: d.__setitem__((3, 4), -0.01), Rejection.NEGATIVE),
    (lambda d: d.fill(0.7), Rejection.CONSTANT),
    (lambda d: d.fill(0.0), Rejection.CONSTANT),
])
def test_bad_network_output_is_rejected_with_its_reason_counted_and_gives_no_depth(
        corrupt, reason):
    depth = _scene_depth()
    stage = _stage()
    assert stage.process(RelativeDepth(0.0, _network(depth)),
                         _sparse_map(0.0, depth, _grid_pixels())).ok
    bad = _network(depth)
    corrupt(bad)
    result = stage.process(RelativeDepth(0.05, bad), _sparse_map(0.05, depth, _grid_pixels()))
    assert not result.ok  # a rejected image has nothing to hold a fit on
    assert reason.value in result.diagnostics.reason
    assert stage.rejected == {reason.value: 1}


@pytest.mark.parametrize("image", [
    np.zeros((4, 4, 3), np.float32), np.zeros(5, np.float32), np.zeros((0, 3), np.float32),
    np.array([["a", "b"]]), np.ones((2, 2), complex),
])
def test_an_output_that_is_not_a_real_image_is_rejected(image):
    reason, detail = check_relative_disparity(image)
    assert reason is Rejection.NOT_AN_IMAGE and "2-D" in detail


def test_a_healthy_image_passes_the_check():
    assert check_relative_disparity(_network(_scene_depth())) is None
    assert check_relative_disparity(np.array([[0, 3], [1, 2]], np.uint8)) is None


@pytest.mark.parametrize("key, value", [("hold_s", -0.1), ("max_map_offset_s", 1.0),
                                        ("tracked_only", 1), ("scale_field_nodes", 1),
                                        ("scale_field_nodes", -1), ("scale_field_sigma", 0.0),
                                        ("fallback_min_anchors", 3),
                                        ("fallback_min_anchors", -1)])
def test_bad_stage_options_are_named(key, value):
    with pytest.raises(OptionError, match=key):
        DepthStageOptions(**{key: value})


def _network_reading_the_left_half_near(depth: np.ndarray) -> np.ndarray:
    """:func:`_network` with the left half of the image 15 % more disparate than the right:
    the spatially varying error no single curve removes."""
    left = np.arange(CAMERA.width) < CAMERA.width // 2
    return (_network(depth) * np.where(left, 1.15, 1.0)[None, :]).astype(np.float32)


def test_the_scale_field_removes_an_error_that_varies_over_the_image():
    depth, pixels = _scene_depth(), _grid_pixels(4)
    relative = RelativeDepth(1.0, _network_reading_the_left_half_near(depth))
    errors = {}
    for nodes in (0, 4):
        stage = _stage(scale_field_nodes=nodes)
        result = stage.process(relative, _sparse_map(1.0, depth, pixels))
        assert result.ok
        errors[nodes] = metrics.abs_rel(result.depth, depth)
    assert errors[4] < 0.6 * errors[0], errors


def test_a_held_fit_keeps_its_scale_field():
    depth, pixels = _scene_depth(), _grid_pixels(4)
    relative = _network_reading_the_left_half_near(depth)
    stage = _stage(scale_field_nodes=4)
    fresh = stage.process(RelativeDepth(1.0, relative), _sparse_map(1.0, depth, pixels))
    held = stage.process(RelativeDepth(1.2, relative), _sparse_map(1.2, depth, pixels[:3]))
    assert held.ok and held.held
    np.testing.assert_allclose(held.depth, fresh.depth, rtol=1e-6)
