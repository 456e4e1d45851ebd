"""Anchored tracks: a track found against its own patch of an earlier frame, and let go of that
patch where the fit and Lucas-Kanade disagree."""

import cv2
import numpy as np
import pytest

from autonomy.vins.affine_refine import SampledImage
from autonomy.vins.anchored_tracks import Anchors

from tests.test_vins_frontend import BIG, crop, texture


def warped(image: np.ndarray, linear, shift) -> np.ndarray:
    """``image`` under ``x -> linear x + shift`` (cubic interpolation)."""
    M = np.column_stack([np.asarray(linear, float), np.asarray(shift, float)])
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def anchored_grid(image: np.ndarray) -> tuple[Anchors, np.ndarray]:
    """Anchors on a grid of points of ``image``, every one of them anchored."""
    points = np.array([(x, y) for x in range(120, 540, 60) for y in range(100, 400, 60)], float)
    anchors = Anchors(half=7, max_shift=1.0, max_deformation=1.0)
    anchors.extend(len(points))
    anchors.anchor(SampledImage(image), points, np.arange(len(points)))
    assert anchors.anchored.all()
    return anchors, points


def test_an_anchor_finds_its_point_under_a_growing_warp_from_a_rough_guess():
    """Three frames of a patch scaling by 3 % and turning 1 deg each: from guesses 0.4 px off,
    each anchored track lands within 0.05 px of its point, frame after frame."""
    base = crop(texture(0, BIG)).astype(np.float32)
    anchors, points = anchored_grid(base.astype(np.uint8))
    centre = np.array([320.0, 240.0])
    rng = np.random.default_rng(1)
    for k in (1, 2, 3):
        angle, scale = np.radians(k), 1.03 ** k
        linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        shift = centre - linear @ centre + [1.5 * k, -0.7 * k]
        frame = warped(base, linear, shift).astype(np.uint8)
        truth = points @ linear.T + shift
        found = anchors.follow(SampledImage(frame), truth + rng.uniform(-0.4, 0.4, truth.shape))
        assert not anchors.given_up.any() and anchors.anchored.all()
        assert np.median(np.linalg.norm(found - truth, axis=1)) < 0.05
        assert np.linalg.norm(found - truth, axis=1).max() < 0.2


def test_an_anchor_that_disagrees_with_lucas_kanade_is_given_up_for_its_answer():
    """Where Lucas-Kanade's answer is over ``max_shift`` from where the anchor fits (a wrong
    match, or a view the anchor no longer describes), the answer stands and the track loses its
    anchor, to be anchored again; the others keep theirs."""
    base = crop(texture(0, BIG))
    anchors, points = anchored_grid(base)
    frame = crop(warped(texture(0, BIG), np.eye(2), [2.0, 1.0]))
    truth = points + [2.0, 1.0]
    guesses = truth.copy()
    guesses[:3] += [2.5, 0.0]
    found = anchors.follow(SampledImage(frame), guesses)
    assert np.array_equal(found[:3], guesses[:3])
    assert not anchors.anchored[:3].any() and anchors.anchored[3:].all()
    assert anchors.given_up.sum() == 3
    assert np.linalg.norm(found[3:] - truth[3:], axis=1).max() < 0.1


def test_rows_follow_their_tracks_through_keep_extend_and_anchor():
    """The anchors stay row for row with the tracks: kept by a mask, new rows unanchored,
    anchoring some rows leaves the others' patches in place."""
    base = crop(texture(0, BIG))
    anchors, points = anchored_grid(base)
    n = len(points)
    keep = np.arange(n) % 3 != 0
    anchors.keep(keep)
    anchors.extend(4)
    assert len(anchors) == keep.sum() + 4
    assert anchors.anchored[:-4].all() and not anchors.anchored[-4:].any()
    frame = crop(warped(texture(0, BIG), np.eye(2), [1.0, 0.5]))
    kept_points = np.vstack([points[keep], [[300.0, 200.0], [330.0, 260.0], [270.0, 320.0],
                                            [360.0, 150.0]]])
    anchors.anchor(SampledImage(base), kept_points,
                   np.arange(len(kept_points) - 4, len(kept_points)))
    assert anchors.anchored.all()
    found = anchors.follow(SampledImage(frame), kept_points + [1.2, 0.3])
    assert np.linalg.norm(found - (kept_points + [1.0, 0.5]), axis=1).max() < 0.1


def test_an_anchor_that_fits_beyond_the_border_keeps_lucas_kanades_answer():
    """A track Lucas-Kanade kept inside the border is never moved out of it by its anchor (the
    tracker indexes its mask at the rounded position): there the answer stands and the anchor
    is given up."""
    base = crop(texture(0, BIG))
    points = np.array([[636.5, 200.0], [636.5, 300.0], [320.0, 240.0]])
    anchors = Anchors(half=7, max_shift=1.0, max_deformation=1.0, border=1)
    anchors.extend(len(points))
    anchors.anchor(SampledImage(base), points, np.arange(len(points)))
    frame = crop(warped(texture(0, BIG), np.eye(2), [2.0, 0.0]))
    guesses = np.array([[637.9, 200.0], [637.9, 300.0], [322.3, 240.0]])  # inside: x <= 638
    found = anchors.follow(SampledImage(frame), guesses)
    assert np.array_equal(found[:2], guesses[:2]) and not anchors.anchored[:2].any()
    assert anchors.anchored[2] and abs(found[2, 0] - 322.0) < 0.1


def side_wall_approached(share: float) -> np.ndarray:
    """The homography (pixels) by which the simulator's camera sees a wall parallel to its axis
    1.5 m to its right after flying ``share`` metres towards it along the axis: normalised
    ``x -> x / (1 - share x / 1.5)``."""
    K = np.array([[320.0, 0, 319.5], [0, 320.0, 239.5], [0, 0, 1]])
    return K @ np.array([[1, 0, 0], [0, 1, 0], [-share / 1.5, 0, 1]]) @ np.linalg.inv(K)


def test_a_homography_anchor_has_no_outward_error_on_a_wall_seen_at_a_slant():
    """Flying 1 m towards a wall on the right, the patches on it grow more on their outer side
    than on their inner: the affine map fitted to that is off by the perspective's second-order
    term, outward (by the window's second moment times it), where the homography fits it. Five
    frames, the tracks followed from guesses 0.3 px off."""
    base = crop(texture(0, BIG))
    points = np.array([(x, y) for x in range(340, 460, 20) for y in range(100, 400, 40)], float)
    errors = {}
    for warp in ("affine", "homography"):
        anchors = Anchors(half=7, max_shift=1.0, max_deformation=1.0, warp=warp)
        anchors.extend(len(points))
        anchors.anchor(SampledImage(base), points, np.arange(len(points)))
        for share in np.linspace(0.2, 1.0, 5):
            H = side_wall_approached(share)
            frame = cv2.warpPerspective(base, H, (640, 480), flags=cv2.INTER_CUBIC,
                                        borderMode=cv2.BORDER_REFLECT)
            moved = np.column_stack([points, np.ones(len(points))]) @ H.T
            truth = moved[:, :2] / moved[:, 2:]
            found = anchors.follow(SampledImage(frame), truth + 0.3)
            assert anchors.anchored.all()
        errors[warp] = found - truth
    assert errors["affine"][:, 0].mean() > 0.04  # outward: +x on the right
    assert abs(errors["homography"][:, 0].mean()) < 0.01
    assert np.median(np.linalg.norm(errors["homography"], axis=1)) < 0.02


def test_an_unknown_warp_is_refused_by_name():
    with pytest.raises(ValueError, match="unknown warp 'perspective'"):
        Anchors(half=7, max_shift=1.0, max_deformation=1.0, warp="perspective")
