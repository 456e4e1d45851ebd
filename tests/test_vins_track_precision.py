"""Each track's position noise from its patch's texture (autonomy/vins/track_precision.py):
the structure tensor's least eigenvalue, the relative noise the front-end gives each track, and
that this ranks real Lucas-Kanade errors under image noise as the bound says."""

import dataclasses

import cv2
import numpy as np
import pytest

from autonomy.geometry import PinholeCamera
from autonomy.vins import FeatureTracker, FrontendOptions
from autonomy.vins.backend import SlidingWindowSmoother
from autonomy.vins.track_precision import (SCALE_RANGE, BirthTextures, least_eigenvalues,
                                           relative_noise)

CAMERA = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)


def texture(contrast: float, seed: int = 0, shape=(480, 640)) -> np.ndarray:
    """Smooth random texture about mid-grey, ``contrast`` grey levels from darkest to
    brightest (float32)."""
    noise = np.random.default_rng(seed).uniform(0, 1, shape).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min()) - 0.5
    return 128.0 + contrast * smooth


def brute_force_least_eigenvalue(gray: np.ndarray, x: int, y: int, half: int) -> float:
    """The structure tensor of central differences over the window, summed pixel by pixel."""
    tensor = np.zeros((2, 2))
    for row in range(y - half, y + half + 1):
        for column in range(x - half, x + half + 1):
            g = 0.5 * np.array([gray[row, column + 1] - gray[row, column - 1],
                                gray[row + 1, column] - gray[row - 1, column]], float)
            tensor += np.outer(g, g)
    return float(np.linalg.eigvalsh(tensor)[0])


def test_the_least_eigenvalue_is_the_structure_tensors():
    gray = texture(100.0)
    points = np.array([[100.2, 50.7], [320.0, 240.0], [600.4, 400.4]])
    expected = [brute_force_least_eigenvalue(gray, int(round(x)), int(round(y)), 7)
                for x, y in points]
    np.testing.assert_allclose(least_eigenvalues(gray, points, 7), expected, rtol=1e-4)


def test_an_edge_and_a_flat_patch_have_no_least_eigenvalue_and_a_corner_has():
    gray = np.zeros((100, 100), np.float32)
    gray[:, 50:] = 200.0  # a vertical edge at x = 50
    gray[70:, 70:] = 100.0  # a corner at (70, 70)
    eigenvalues = least_eigenvalues(gray, np.array([[50.0, 30.0], [20.0, 20.0],
                                                    [70.0, 70.0]]), 5)
    assert eigenvalues[0] == pytest.approx(0.0, abs=1e-6)  # along the edge nothing is found
    assert eigenvalues[1] == pytest.approx(0.0, abs=1e-6)
    assert eigenvalues[2] > 1000.0


def test_points_at_the_border_are_measured_on_the_clamped_image():
    gray = texture(100.0)
    eigenvalues = least_eigenvalues(gray, np.array([[0.0, 0.0], [639.0, 479.0]]), 7)
    assert np.isfinite(eigenvalues).all() and (eigenvalues >= -1e-6).all()


def test_the_frames_typical_track_keeps_its_noise_and_faint_ones_get_more():
    """Half the image at a tenth of the contrast: its patches are found with about ten times
    the error (the eigenvalue scales with the contrast squared), so they get the range's most
    noise, and the strong half the range's least relative to the median."""
    gray = texture(200.0)
    gray[:, 320:] = 128.0 + 0.1 * (gray[:, 320:] - 128.0)
    rng = np.random.default_rng(1)
    strong = np.column_stack([rng.uniform(20, 300, 21), rng.uniform(20, 460, 21)])
    faint = np.column_stack([rng.uniform(340, 620, 20), rng.uniform(20, 460, 20)])
    scales = relative_noise(least_eigenvalues(gray, np.vstack([strong, faint]), 7))
    assert np.median(scales) == pytest.approx(1.0, rel=0.3)
    assert (scales[:21] < 1.5).all() and (scales[21:] == SCALE_RANGE[1]).mean() > 0.5
    assert (scales >= SCALE_RANGE[0]).all() and (scales <= SCALE_RANGE[1]).all()


def test_a_flat_frame_or_no_tracks_give_plain_weights():
    flat = least_eigenvalues(np.full((480, 640), 90.0), np.array([[10.0, 10.0]]), 7)
    assert (relative_noise(flat) == 1.0).all()
    assert relative_noise(np.zeros(0)).shape == (0,)


def test_a_track_keeps_the_texture_it_was_born_on():
    """Its error is what it inherits from its first frames, so its weight is its birth
    patch's: a track born on a faint patch stays faint where the patch has since grown
    strong, and a new track is measured in its own frame."""
    textures = BirthTextures(7)
    faint, strong = texture(20.0), texture(200.0)
    points = np.array([[100.0, 100.0], [300.0, 200.0]])
    first = textures.update(faint, np.array([3, 8]), points, np.array([True, True]))
    np.testing.assert_allclose(first, least_eigenvalues(faint, points, 7))
    later = textures.update(strong, np.array([8, 12]), points, np.array([False, True]))
    assert later[0] == first[1]
    assert later[1] == pytest.approx(least_eigenvalues(strong, points[1:], 7)[0])
    with pytest.raises(ValueError, match="frame before"):  # 13 was never given
        textures.update(strong, np.array([8, 13]), points, np.array([False, False]))


GRID = np.stack(np.meshgrid(np.arange(60, 580, 40), np.arange(60, 420, 40)), -1).reshape(-1, 2)


def lucas_kanade_errors(contrast: float, noise: float, trials: int) -> np.ndarray:
    """OpenCV's Lucas-Kanade (11 px window, one level) of :data:`GRID`'s points on a texture of
    ``contrast`` moved by a known sub-pixel shift, both frames with white noise of ``noise``
    grey levels: the error of each track, pixels."""
    rng = np.random.default_rng(7)
    base = texture(contrast, seed=3)
    shift = np.array([0.37, -0.21])
    moved = cv2.warpAffine(base, np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]]),
                           (640, 480), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    points = GRID.reshape(-1, 1, 2).astype(np.float32)
    errors = []
    for _ in range(trials):
        frames = [np.clip(image + rng.normal(0.0, noise, image.shape), 0, 255).astype(np.uint8)
                  for image in (base, moved)]
        found, status, _ = cv2.calcOpticalFlowPyrLK(frames[0], frames[1], points, None,
                                                    winSize=(11, 11), maxLevel=0)
        ok = status.ravel() == 1
        errors.append(np.linalg.norm(found.reshape(-1, 2)[ok] - GRID[ok] - shift, axis=1))
    return np.concatenate(errors)


@pytest.mark.parametrize("contrast", [120.0, 40.0])
def test_real_tracking_errors_under_image_noise_are_the_bounds(contrast):
    """The premise: under white noise ``s_n`` a track errs by about ``s_n sqrt(2 /
    lambda_min)``. Measured (median error against the bound at the grid's median eigenvalue):
    contrast 160, 120, 80, 40 and 20 grey levels give 1.09, 1.04, 1.04, 1.18 and 1.16 times
    the bound (the faintest a little over it: Lucas-Kanade is not linear that far)."""
    noise = 4.0
    errors = lucas_kanade_errors(contrast, noise, trials=6)
    eigenvalue = np.median(least_eigenvalues(texture(contrast, seed=3), GRID, 5))
    bound = noise * np.sqrt(2.0 / eigenvalue)
    assert 0.9 < np.median(errors) / bound < 1.3, (np.median(errors), bound)


def test_the_tracker_gives_each_track_a_noise_only_when_asked():
    gray = texture(200.0).astype(np.uint8)
    plain = FeatureTracker(CAMERA).track(gray)
    assert plain.noise_scale is None
    weighed = FeatureTracker(CAMERA, options=FrontendOptions(texture_weights=True)).track(gray)
    assert weighed.noise_scale.shape == (len(weighed),) and len(weighed) > 50
    assert (weighed.noise_scale >= SCALE_RANGE[0]).all()
    assert (weighed.noise_scale <= SCALE_RANGE[1]).all()
    assert weighed.noise_scale.std() > 0.05  # corners differ, and the weights say so


@pytest.mark.parametrize("scale", [np.ones(3), np.array([1.0, 0.0]), np.array([1.0, np.nan]),
                                   np.array([1.0, -2.0]), np.array([np.inf, 1.0])])
def test_tracks_refuse_a_noise_that_is_not_one_positive_number_per_feature(scale):
    tracks = FeatureTracker(CAMERA).track(texture(200.0).astype(np.uint8))
    two = dataclasses.replace(tracks, ids=tracks.ids[:2], pixels=tracks.pixels[:2],
                              normalised=tracks.normalised[:2], ages=tracks.ages[:2])
    with pytest.raises(ValueError, match="noise_scale"):
        dataclasses.replace(two, noise_scale=scale)


@pytest.mark.parametrize("anchor_age", [0, 2])
def test_the_tracker_weighs_each_track_by_its_birth_patch_over_a_sequence(anchor_age):
    """A texture panned over eight frames (one jump of 25 px, past the small window): every
    track's weight is its birth frame's texture, relative to the frame's tracks, in every
    frame, with anchors or without."""
    options = FrontendOptions(texture_weights=True, anchor_age=anchor_age)
    tracker = FeatureTracker(CAMERA, options=options)
    big = texture(150.0, seed=4, shape=(600, 800))
    births = {}
    x = 0.0
    for step in (0.0, 1.5, 1.5, 25.0, 1.5, 1.5, 1.5, 1.5):
        x += step
        frame = np.ascontiguousarray(cv2.warpAffine(
            big, np.array([[1.0, 0.0, -x], [0.0, 1.0, 0.0]]), (800, 600),
            flags=cv2.INTER_CUBIC)[60:540, 80:720]).astype(np.uint8)
        tracks = tracker.track(frame)
        born = tracks.ages == 1
        births.update(zip(tracks.ids[born].tolist(), least_eigenvalues(
            frame, tracks.pixels[born], options.fit_window // 2).tolist()))
        expected = relative_noise(np.array([births[i] for i in tracks.ids.tolist()]))
        np.testing.assert_allclose(tracks.noise_scale, expected)
    assert (tracks.ages > 5).sum() > 20  # the sequence did carry tracks through


def test_a_keyframe_keeps_each_observation_with_its_noise():
    """The back-end sorts a keyframe's observations by id: each keeps its own noise."""
    keyframe = SlidingWindowSmoother._keyframe(0, 0.0, [9, 2, 5], np.zeros((3, 2)),
                                               [3.0, 1.0, 2.0])
    assert keyframe.ids.tolist() == [2, 5, 9]
    assert keyframe.noise_scale.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="noise scale"):
        SlidingWindowSmoother._keyframe(0, 0.0, [9, 2], np.zeros((2, 2)), [1.0, np.inf])


def test_a_track_keeps_its_texture_whatever_the_order_of_the_ids():
    """A track restarted where it stands (``anchor_given_up = "restart"``) takes a new id in
    the middle of the frame's tracks: the others still find their birth textures."""
    textures = BirthTextures(7)
    gray = texture(100.0)
    points = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 300.0]])
    first = textures.update(gray, np.array([3, 8, 5]), points, np.array([True, True, True]))
    later = textures.update(texture(20.0), np.array([5, 9, 3]), points,
                            np.array([False, True, False]))
    assert later[0] == first[2] and later[2] == first[0]


def test_an_evaluation_that_skips_frames_gets_no_texture_for_a_birth_it_did_not_see():
    textures = BirthTextures(7, strict=False)
    gray = texture(100.0)
    points = np.array([[100.0, 100.0], [300.0, 200.0]])
    first = textures.update(gray, np.array([3, 8]), points, np.array([True, False]))
    assert np.isfinite(first[0]) and np.isnan(first[1])  # 8 was born in a frame not given
    later = textures.update(gray, np.array([3, 8]), points, np.array([False, False]))
    assert later[0] == first[0] and np.isnan(later[1])
