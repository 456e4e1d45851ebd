"""The guards beyond the paper, each with the failure it prevents reproduced first."""

import numpy as np
import pytest

from autonomy.depth.rescale import METHODS, MONOTONE_METHODS, TemporalBlend, fit

TRUE_MAP = (0.4, 0.02)  # metric disparity = 0.4 · relative disparity + 0.02


def relative_disparity_of(depth):
    a, b = TRUE_MAP
    return (1.0 / np.asarray(depth, dtype=float) - b) / a


def anchors_at_depths(depths, rng, noise=0.002):
    x = relative_disparity_of(depths)
    y = 1.0 / np.asarray(depths) + noise * rng.standard_normal(len(depths))
    return x, 1.0 / y


# ---- near-side guard -------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_near_side_guard_reads_an_obstacle_nearer_than_every_anchor(method):
    rng = np.random.default_rng(1)
    x, z = anchors_at_depths(rng.uniform(3.0, 10.0, 120), rng)  # all features 3 m or farther
    obstacle = relative_disparity_of([1.0, 0.6])  # a pole at 1 m and a branch at 0.6 m

    clamped = fit(x, z, method, extrapolation="clamp").depth(obstacle)
    assert np.all(clamped > 2.5)  # the failure: the reference port reads them ~3 m away

    guarded = fit(x, z, method)
    depth = guarded.depth(obstacle)
    nearest_anchor = z.min()
    assert np.all(depth <= nearest_anchor)  # never pushed farther than the nearest anchor
    if method == "exponential":
        # a·e^(bx) cannot be the affine truth; its steep tail errs to the safe, near side
        assert np.all(depth <= [1.0, 0.6])
    else:
        np.testing.assert_allclose(depth, [1.0, 0.6], rtol=0.15)


@pytest.mark.parametrize("method", MONOTONE_METHODS)
def test_near_tail_never_pushes_nearer_pixels_farther(method):
    rng = np.random.default_rng(2)
    x, z = anchors_at_depths(rng.uniform(2.0, 12.0, 80), rng, noise=0.01)
    model = fit(x, z, method)
    beyond = np.linspace(model.anchor_range[1], 10 * model.anchor_range[1], 1000)
    assert np.all(np.diff(model.depth(beyond)) <= 0)


# ---- near-end check ---------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["monotone_spline", "monotone_smoothing_spline",
                                    "smoothing_spline", "poly2"])
def test_a_lone_near_anchor_on_the_wrong_surface_does_not_push_a_pole_away(method):
    """A realistic sewer flight's anchors (docs/rescaling.md): landmarks on a wall 3.7–8 m
    away, and one on that wall just beside a thin pole, which sampled the pole's disparity
    (as if 1.7 m away) with the wall's depth, 4 m. Alone beyond a gap, the curve bent to it,
    and the pole, 1.1 m away, read about 3 m: the near tail continued from a near end set at
    the wall's depth. Judged by the others' extension, that anchor is dropped and the pole
    reads near its depth."""
    rng = np.random.default_rng(1)
    x, z = anchors_at_depths(rng.uniform(3.7, 8.0, 45), rng, noise=0.01)  # the VINS's noise
    x, z = np.append(x, relative_disparity_of([1.7])), np.append(z, 4.0)
    pole = relative_disparity_of([1.1])

    bent = fit(x, z, method, near_end_check=False)
    assert bent.depth(pole)[0] > 2.0  # the failure
    checked = fit(x, z, method)
    assert checked.anchors.used == bent.anchors.used - 1
    np.testing.assert_allclose(checked.depth(pole), [1.1], rtol=0.1)


@pytest.mark.parametrize("scale, kept", [(0.5, True), (1.0, True), (1.2, True), (2.0, False)])
def test_the_near_end_check_drops_only_anchors_that_claim_a_farther_surface(scale, kept):
    """A post 1.0–1.3 m away beyond a gap (the gap guard's scene), and a network that gives
    the post ``scale`` times the affine map's relative disparity. Read farther than affine
    (0.5) or nearer within the factor (1.2), its anchors stay, as with the check off; read
    2x nearer, the post's anchors claim a surface about twice as far as the wall's map says
    and go, and the post is read by the straight tail, nearer than it is: the safe side."""
    rng = np.random.default_rng(4)
    x, z = gap_anchors(rng)
    post = z < 2.0
    relative = np.where(post, x * scale, x)
    unchecked = fit(relative, z, "monotone_spline", near_end_check=False)
    checked = fit(relative, z, "monotone_spline")
    if kept:
        assert checked.anchors.used == unchecked.anchors.used
        np.testing.assert_allclose(checked.depth(relative_disparity_of([1.15]) * scale),
                                   [1.15], rtol=0.1)
    else:
        assert checked.anchors.used == unchecked.anchors.used - post.sum()
        assert checked.depth(relative_disparity_of([1.15]) * scale)[0] < 1.15


# ---- gap guard --------------------------------------------------------------------------------

def gap_anchors(rng):
    """Features on a wall 5–8 m away and on a post 1.0–1.3 m away: nothing in between."""
    depths = np.concatenate([rng.uniform(5.0, 8.0, 70), rng.uniform(1.0, 1.3, 30)])
    return anchors_at_depths(depths, rng)


def test_gap_guard_bridges_the_flat_a_plain_monotone_spline_makes():
    rng = np.random.default_rng(4)
    x, z = gap_anchors(rng)
    in_gap = relative_disparity_of([2.4])

    flat = fit(x, z, "monotone_spline", bridge_gaps=False)
    assert flat.depth(in_gap)[0] > 1.5 * 2.4  # the failure: a true 2.4 m read about twice as far

    bridged = fit(x, z, "monotone_spline")
    assert len(bridged.curve.bridges) == 1
    np.testing.assert_allclose(bridged.depth(in_gap), [2.4], rtol=0.1)


def test_confidence_is_low_across_a_gap_and_outside_the_anchors():
    rng = np.random.default_rng(4)
    x, z = gap_anchors(rng)
    model = fit(x, z, "monotone_spline")
    pixels = relative_disparity_of([6.0, 1.15, 2.4, 0.4, 60.0]).astype(np.float32)
    pixels = np.append(pixels, [np.nan, -1.0])
    confidence = model.confidence(pixels)
    assert confidence.dtype == np.float32
    np.testing.assert_array_equal(confidence[:2], [1.0, 1.0])  # densely anchored
    assert confidence[2] == 0.0  # middle of the gap
    assert confidence[3] == 0.0 and confidence[4] == 0.0  # far beyond either end
    np.testing.assert_array_equal(confidence[5:], [0.0, 0.0])  # invalid pixels


def test_confidence_fades_past_the_last_anchor():
    rng = np.random.default_rng(5)
    x, z = anchors_at_depths(rng.uniform(2.0, 10.0, 100), rng)
    model = fit(x, z, "poly2")
    lo, hi = model.anchor_range
    knot_spacing = (hi - lo) / model.options.segments
    pixels = np.array([hi - 2 * knot_spacing, hi + 0.5 * knot_spacing, hi + 2 * knot_spacing])
    inside, fading, beyond = model.confidence(pixels)
    assert inside == 1.0 and 0.0 < fading < 1.0 and beyond == 0.0


# ---- applying the fit ------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_lookup_table_matches_direct_evaluation(method):
    rng = np.random.default_rng(6)
    x, z = anchors_at_depths(rng.uniform(0.8, 30.0, 150), rng, noise=0.005)
    model = fit(x, z, method)
    image = rng.uniform(0.0, x.max() * 1.5, (120, 160)).astype(np.float32)
    image[::7, ::5] = np.nan
    lut, exact = model.depth(image), model.depth(image, exact=True)
    assert lut.dtype == exact.dtype == np.float32 and lut.shape == image.shape
    np.testing.assert_array_equal(np.isnan(lut), np.isnan(image))
    # Nearest entry of 4096: half a step in x, i.e. relative error ≤ step / (2·x) plus curve.
    valid = image >= 0.05 * np.nanmax(image)
    np.testing.assert_allclose(lut[valid], exact[valid], rtol=0.01)


def test_depth_is_clipped_to_the_configured_range_and_marks_invalid_pixels():
    rng = np.random.default_rng(7)
    x, z = anchors_at_depths(rng.uniform(1.0, 10.0, 50), rng)
    model = fit(x, z, "monotone_spline", min_depth=0.5, max_depth=20.0)
    pixels = np.array([0.0, relative_disparity_of(40.0), 1e4, np.inf, -np.inf, -0.1, np.nan],
                      dtype=np.float32)
    for depth in (model.depth(pixels), model.depth(pixels, exact=True)):
        np.testing.assert_array_equal(depth[:3], [20.0, 20.0, 0.5])
        assert np.all(np.isnan(depth[3:]))


def test_depth_of_an_image_without_valid_pixels_is_all_nan():
    rng = np.random.default_rng(8)
    model = fit(*anchors_at_depths(rng.uniform(1.0, 10.0, 50), rng), "poly3")
    assert np.all(np.isnan(model.depth(np.full((4, 5), np.nan))))
    assert np.all(model.confidence(np.full((4, 5), -1.0)) == 0.0)
    assert model.depth(np.empty((0, 640), dtype=np.float32)).shape == (0, 640)


def test_depth_accepts_integer_images_and_rejects_non_numbers():
    rng = np.random.default_rng(9)
    model = fit(*anchors_at_depths(rng.uniform(1.0, 10.0, 50), rng), "monotone_spline")
    as_int = model.depth(np.array([[1, 2], [3, 4]], dtype=np.uint16))
    np.testing.assert_allclose(as_int, model.depth(np.array([[1.0, 2.0], [3.0, 4.0]])))
    with pytest.raises(TypeError, match="real-valued"):
        model.depth(np.array([1 + 2j]))
    with pytest.raises(TypeError, match="real-valued"):
        model.depth(np.array(["near"]))


# ---- temporal blending ------------------------------------------------------------------------

def noisy_fits(count, rng):
    for _ in range(count):
        yield fit(*anchors_at_depths(rng.uniform(1.0, 10.0, 40), rng, noise=0.02), "poly1")


def test_temporal_blend_off_passes_every_fit_through():
    rng = np.random.default_rng(10)
    blend = TemporalBlend(0.0)
    for model in noisy_fits(3, rng):
        assert blend.update(model) is model


def test_temporal_blend_mixes_curves_with_the_given_weight():
    rng = np.random.default_rng(11)
    first, second = noisy_fits(2, rng)
    blend = TemporalBlend(0.25)
    blend.update(first)
    mixed = blend.update(second)
    lo, hi = second.anchor_range
    grid = np.linspace(lo, hi, 256)
    expected = 0.75 * second.metric_disparity(grid) + 0.25 * first.metric_disparity(grid)
    np.testing.assert_allclose(mixed.metric_disparity(grid), expected, rtol=1e-9)
    assert any("blended" in note for note in mixed.notes)


def test_temporal_blend_steadies_the_depth_of_a_static_scene():
    pixel = relative_disparity_of([3.0])
    raw, smoothed = [], []
    blend = TemporalBlend(0.8)
    for model in noisy_fits(60, np.random.default_rng(12)):
        raw.append(model.depth(pixel)[0])
        smoothed.append(blend.update(model).depth(pixel)[0])
    assert np.std(smoothed[10:]) < 0.6 * np.std(raw[10:])
    assert abs(np.mean(smoothed[10:]) - 3.0) < 0.15


def test_temporal_blend_keeps_curves_monotone_and_forgets_after_a_missed_fit():
    rng = np.random.default_rng(13)
    blend = TemporalBlend(0.5)
    for model in noisy_fits(5, rng):
        blended = blend.update(model)
        grid = np.linspace(0, 5, 2000)
        assert np.all(np.diff(blended.metric_disparity(grid)) >= 0)
    no_fit = fit([1.0], [2.0])
    assert blend.update(no_fit) is no_fit
    fresh = next(noisy_fits(1, rng))
    assert blend.update(fresh) is fresh  # history forgotten: no stale curve carried over


def test_temporal_blend_rejects_a_weight_outside_its_range():
    with pytest.raises(ValueError, match="weight"):
        TemporalBlend(1.0)
