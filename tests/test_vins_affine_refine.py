"""The affine refinement of Lucas-Kanade's tracks (autonomy/vins/affine_refine.py)."""

import warnings

import cv2
import numpy as np
import pytest

from autonomy.vins.affine_refine import (SOBEL_SCALE, SampledImage, _patch_error,
                                         _patch_points, fit_warp, identity_warps,
                                         prepare_templates, refine_affine)

#: A patch grown by 5 % and sheared a little, as a wall's patch is from one frame to the next
#: flying forward at cruise speed, and shifted.
LINEAR = np.array([[1.05, 0.01], [-0.02, 1.04]])
SHIFT = np.array([-4.0, 3.0])


def textured(seed: int, shape=(240, 320)) -> np.ndarray:
    """Smooth random texture, uint8, full contrast."""
    noise = cv2.GaussianBlur(np.random.default_rng(seed).random(shape).astype(np.float32),
                             (0, 0), 2.0)
    return ((noise - noise.min()) / (noise.max() - noise.min()) * 255).astype(np.uint8)


def warped_pair(seed: int):
    """An image, the same warped by ``LINEAR`` and ``SHIFT`` (bicubic), 30 points in the first
    and where they truly are in the second."""
    image = textured(seed)
    h, w = image.shape
    current = cv2.warpAffine(image, np.column_stack([LINEAR, SHIFT]), (w, h),
                             flags=cv2.INTER_CUBIC)
    starts = np.random.default_rng(seed + 100).uniform(40, 200, (30, 2))
    return image, current, starts, starts @ LINEAR.T + SHIFT


@pytest.mark.parametrize("seed", [0, 1])
def test_a_grown_patch_is_found_where_lucas_kanade_errs(seed):
    """Lucas-Kanade's translation, started where the point truly is, settles where the grown
    patch's gradients are centred; the affine fit, started 0.36 px off, finds the point."""
    previous, current, starts, truth = warped_pair(seed)
    lk, status, _ = cv2.calcOpticalFlowPyrLK(
        previous, current, starts.astype(np.float32).reshape(-1, 1, 2),
        truth.astype(np.float32).reshape(-1, 1, 2), winSize=(11, 11), maxLevel=2,
        criteria=(3, 30, 0.01), flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    refined, ok = refine_affine(SampledImage(previous), SampledImage(current), starts,
                                truth + [0.3, -0.2], half=5)
    lk_error = np.linalg.norm(lk.reshape(-1, 2) - truth, axis=1)
    error = np.linalg.norm(refined - truth, axis=1)
    assert status.all() and ok.all()
    assert np.median(error) < 0.04 and error.max() < 0.1
    assert np.median(lk_error) > 1.5 * np.median(error)


def test_a_change_of_exposure_is_not_read_as_motion():
    previous, current, starts, truth = warped_pair(0)
    brighter = np.clip(1.3 * current.astype(float) + 5.0, 0, 255).astype(np.uint8)
    refined, ok = refine_affine(SampledImage(previous), SampledImage(brighter), starts,
                                truth + [0.3, -0.2], half=5)
    assert ok.all()
    assert np.median(np.linalg.norm(refined - truth, axis=1)) < 0.04


def test_a_patch_without_texture_keeps_its_guess():
    previous = np.full((60, 80), 120, np.uint8)
    guesses = np.array([[40.3, 30.2]])
    refined, ok = refine_affine(SampledImage(previous), SampledImage(previous),
                                np.array([[40.0, 30.0]]),
                                guesses, half=5)
    assert not ok.any()
    assert np.array_equal(refined, guesses)


def test_a_guess_on_another_feature_is_not_moved_far():
    """A refinement that would move a track further than ``max_shift`` from Lucas-Kanade's
    answer leaves it: the refinement sharpens a track; it does not re-track it."""
    previous, current, starts, truth = warped_pair(0)
    refined, ok = refine_affine(SampledImage(previous), SampledImage(current), starts,
                                truth + [1.5, 0.0], half=5, max_shift=0.5)
    assert not ok.any()
    assert np.array_equal(refined, truth + [1.5, 0.0])
    # The limit, not a divergence, is what kept them: without it they come back to the truth.
    unlimited, ok = refine_affine(SampledImage(previous), SampledImage(current), starts,
                                  truth + [1.5, 0.0], half=5, max_shift=np.inf)
    assert ok.all()
    assert np.median(np.linalg.norm(unlimited - truth, axis=1)) < 0.05


def test_a_step_that_is_not_finite_gives_the_track_up_without_a_crash():
    """A step that is not finite (here from a NaN in the image; in flight, an ``I + D`` that
    is singular) would be sampled at NaN coordinates next; the track keeps its guess instead
    and the others are refined as before."""
    previous, current, starts, truth = warped_pair(0)
    spoiled = current.astype(np.float32)
    x, y = np.rint(truth[0]).astype(int)
    spoiled[y - 2:y + 3, x - 2:x + 3] = np.nan
    refined, ok = refine_affine(SampledImage(previous), SampledImage(spoiled), starts,
                                truth + [0.3, -0.2], half=5)
    assert np.isfinite(refined).all()
    assert not ok[0] and np.array_equal(refined[0], truth[0] + [0.3, -0.2])
    assert ok[1:].all()


def test_a_homography_that_folds_the_patch_gives_a_nan_residual_without_a_warning():
    """A homography fit that wandered until part of the patch lies past the line at infinity
    (w <= 0) has nothing in the image to compare there: its residual is NaN, which gives the
    track up, where it was once divided by zero and clamped to the image's border; the other
    patches are compared as before (the same image: no residual)."""
    image = SampledImage(textured(0))
    centres = np.array([[100.0, 80.0], [150.0, 90.0]])
    templates = prepare_templates(image, centres, half=5, warp="homography")
    warps = identity_warps(centres, half=5)
    warps[0, 2, 0] = 2.5  # w = 1 + 2.5 sx: nil at sx = -0.4, negative beyond
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        error = _patch_error(templates, np.arange(2), image, warps, _patch_points(5))
    assert np.isnan(error[0]).all()
    assert np.abs(error[1]).max() < 1e-3


def test_no_tracks():
    previous = textured(0)
    refined, ok = refine_affine(SampledImage(previous), SampledImage(previous), np.zeros((0, 2)),
                                np.zeros((0, 2)), half=5)
    assert refined.shape == (0, 2) and ok.shape == (0,)


def test_sampling_is_exact_bilinear_and_replicates_the_border():
    y, x = np.mgrid[0:5, 0:7].astype(float)
    surface = SampledImage(2.0 * x + 3.0 * y + 0.5 * x * y + 1.0)  # bilinear: reproduced
    at_x, at_y = np.array([0.25, 5.5, 3.0, 6.0]), np.array([0.75, 3.9, 2.0, 4.0])
    assert np.allclose(surface(at_x, at_y), 2 * at_x + 3 * at_y + 0.5 * at_x * at_y + 1,
                       atol=1e-5)
    assert np.allclose(surface(np.array([-3.0, 9.0]), np.array([-1.0, 8.0])),
                       [1.0, 2 * 6 + 3 * 4 + 0.5 * 6 * 4 + 1])


@pytest.mark.parametrize("shape", [(), (1,), (3, 225), (40_000,)])
def test_sampling_keeps_the_points_shape_beyond_one_remap_row(shape):
    image = textured(3).astype(np.float32)
    rng = np.random.default_rng(4)
    x, y = rng.uniform(-5, 330, shape), rng.uniform(-5, 250, shape)
    xc, yc = np.clip(x, 0, 319), np.clip(y, 0, 239)
    x0, y0 = np.minimum(xc.astype(int), 318), np.minimum(yc.astype(int), 238)
    fx, fy = xc - x0, yc - y0
    expected = (image[y0, x0] * (1 - fx) * (1 - fy) + image[y0, x0 + 1] * fx * (1 - fy)
                + image[y0 + 1, x0] * (1 - fx) * fy + image[y0 + 1, x0 + 1] * fx * fy)
    sampled = SampledImage(image)(x, y)
    assert sampled.shape == np.shape(x)
    assert np.abs(sampled - expected).max() < 0.02  # float32 weights, of 255 grey levels


def test_sampling_refuses_an_image_it_cannot_interpolate():
    for bad in (np.zeros((1, 5)), np.zeros((4, 4, 3)), np.zeros(7)):
        with pytest.raises(ValueError, match="grey image of 2x2"):
            SampledImage(bad)
    assert SampledImage(np.zeros((3, 3)))(np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 2)


def test_a_templates_gradient_is_the_images_sobel_at_its_pixels():
    """The patch's gradient, from Sobel's of a patch sampled a pixel wider, equals the whole
    image's Sobel interpolated there: steepest-descent images as the full-frame ones were."""
    image = textured(5).astype(np.float32)
    centre = np.array([[100.3, 80.7]])
    templates = prepare_templates(SampledImage(image), centre, half=5, warp="affine")
    gx = SampledImage(cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=SOBEL_SCALE))
    gy = SampledImage(cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=SOBEL_SCALE))
    offsets = np.arange(-5.0, 6.0)
    at_x, at_y = (a.ravel() for a in np.meshgrid(centre[0, 0] + offsets, centre[0, 1] + offsets))
    # descent = H^-1 SD^T with H = SD^T SD, so its pseudo-inverse is SD, whose affine columns
    # 4 and 5 are the gradient (per unit of scaled offset: times the half-width, 5).
    steepest = np.linalg.pinv(templates.descent[0].astype(float))
    expected = 5.0 * np.column_stack([gx(at_x, at_y), gy(at_x, at_y)])
    assert np.allclose(steepest[:, 4:6], expected, atol=1e-3 * np.abs(expected).max())


def test_a_blurred_frames_patches_converge_to_no_worse_a_residual():
    """A frame blurred along x by motion (9 px) is not the template under any warp: the
    inverse-compositional step, which uses the template's gradients, overshoots, and undamped
    it cycles on too many of these patches for this test. Damped, (nearly) all converge, none
    to a residual above its start's."""
    previous, current, starts, truth = warped_pair(0)
    blurred = cv2.filter2D(current.astype(np.float32), -1, np.full((1, 9), 1 / 9, np.float32))
    templates = prepare_templates(SampledImage(previous), starts, half=7, warp="homography")
    frame = SampledImage(blurred)
    start = identity_warps(truth + [0.3, -0.2], half=7)
    _, warps, converged = fit_warp(templates, frame, truth + [0.3, -0.2], half=7,
                                   epsilon=0.02)
    rows = np.arange(len(starts))
    residual = np.mean(_patch_error(templates, rows, frame, warps, _patch_points(7))**2, axis=1)
    at_start = np.mean(_patch_error(templates, rows, frame, start, _patch_points(7))**2, axis=1)
    assert templates.usable.all() and converged.mean() >= 0.95
    assert (residual[converged] <= at_start[converged]).all()
