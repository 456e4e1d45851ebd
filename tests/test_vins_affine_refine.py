"""The affine refinement of Lucas-Kanade's tracks (autonomy/vins/affine_refine.py)."""

import cv2
import numpy as np
import pytest

from autonomy.vins.affine_refine import bilinear, refine_affine, with_gradients

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
    refined, ok = refine_affine(with_gradients(previous), current, starts,
                                truth + [0.3, -0.2], half=5)
    lk_error = np.linalg.norm(lk.reshape(-1, 2) - truth, axis=1)
    error = np.linalg.norm(refined - truth, axis=1)
    assert status.all() and ok.all()
    assert np.median(error) < 0.04 and error.max() < 0.1
    assert np.median(lk_error) > 1.5 * np.median(error)


def test_a_change_of_exposure_is_not_read_as_motion():
    previous, current, starts, truth = warped_pair(0)
    brighter = np.clip(1.3 * current.astype(float) + 5.0, 0, 255).astype(np.uint8)
    refined, ok = refine_affine(with_gradients(previous), brighter, starts,
                                truth + [0.3, -0.2], half=5)
    assert ok.all()
    assert np.median(np.linalg.norm(refined - truth, axis=1)) < 0.04


def test_a_patch_without_texture_keeps_its_guess():
    previous = np.full((60, 80), 120, np.uint8)
    guesses = np.array([[40.3, 30.2]])
    refined, ok = refine_affine(with_gradients(previous), previous, np.array([[40.0, 30.0]]),
                                guesses, half=5)
    assert not ok.any()
    assert np.array_equal(refined, guesses)


def test_a_guess_on_another_feature_is_not_moved_far():
    """A refinement that would move a track further than ``max_shift`` from Lucas-Kanade's
    answer leaves it: the refinement sharpens a track; it does not re-track it."""
    previous, current, starts, truth = warped_pair(0)
    refined, ok = refine_affine(with_gradients(previous), current, starts, truth + [1.5, 0.0],
                                half=5, max_shift=0.5)
    assert not ok.any()
    assert np.array_equal(refined, truth + [1.5, 0.0])
    # The limit, not a divergence, is what kept them: without it they come back to the truth.
    unlimited, ok = refine_affine(with_gradients(previous), current, starts,
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
    refined, ok = refine_affine(with_gradients(previous), spoiled, starts, truth + [0.3, -0.2],
                                half=5)
    assert np.isfinite(refined).all()
    assert not ok[0] and np.array_equal(refined[0], truth[0] + [0.3, -0.2])
    assert ok[1:].all()


def test_no_tracks():
    previous = textured(0)
    refined, ok = refine_affine(with_gradients(previous), previous, np.zeros((0, 2)),
                                np.zeros((0, 2)), half=5)
    assert refined.shape == (0, 2) and ok.shape == (0,)


def test_bilinear_is_exact_on_a_plane_and_replicates_the_border():
    y, x = np.mgrid[0:5, 0:7].astype(float)
    plane = np.dstack([2.0 * x + 3.0 * y + 1.0, x - y])
    at_x, at_y = np.array([0.25, 5.5, 3.0]), np.array([0.75, 3.9, 2.0])
    expected = np.column_stack([2 * at_x + 3 * at_y + 1, at_x - at_y])
    assert np.allclose(bilinear(plane, at_x, at_y), expected)
    assert np.allclose(bilinear(plane[..., 0], np.array([-3.0, 9.0]), np.array([-1.0, 8.0])),
                       [1.0, 2 * 6 + 3 * 4 + 1])
