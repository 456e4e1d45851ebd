"""`eval vio`'s track error (companion/tools/eval/tracks.py): the front-end's tracks against
the truth, through a real lens model, on a camera flying past a wall at a known depth."""

import math

import numpy as np
import pytest

from autonomy.geometry import PinholeCamera, distort_points, make_pose, rot_z, undistort_points
from autonomy.vins.frontend import Tracks
from companion.tools.eval.tracks import (AGE_BINS, TEXTURE_BINS, TrackErrors, texture_summary,
                                         track_error_summary)

CAMERA = PinholeCamera.from_hfov(160, 120, math.radians(90.0))
RADTAN = (-0.28, 0.07, 2e-4, 2e-5)
#: Optical frame looking along body x (z forward, x right, y down).
T_B_C = np.array([[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.05],
                  [0.0, 0.0, 0.0, 1.0]])
WALL_X = 6.0  # a wall across the way, in the world, 6 m ahead of the start
FIT_WINDOW = 11  # the side of the patch the tracker fits (for the texture's prediction)


def body_pose(k: int) -> np.ndarray:
    """Flying forward 5 cm a frame, turning 0.01 rad a frame."""
    return make_pose(rot_z(0.01 * k), np.array([0.05 * k, 0.02 * k, 1.5]))


def wall_depth(T_W_B: np.ndarray) -> np.ndarray:
    """The true z-depth image of :data:`WALL_X` seen through the radtan lens."""
    T_W_C = T_W_B @ T_B_C
    grid = np.stack(np.meshgrid(np.arange(CAMERA.width, dtype=float),
                                np.arange(CAMERA.height, dtype=float)), -1).reshape(-1, 2)
    rays_C = np.column_stack([undistort_points(CAMERA, RADTAN, grid), np.ones(len(grid))])
    rays_W = rays_C @ T_W_C[:3, :3].T
    scale = (WALL_X - T_W_C[0, 3]) / rays_W[:, 0]  # z-depth: the ray's length along z is 1
    return scale.reshape(CAMERA.height, CAMERA.width).astype(np.float32)


def wall_point(pixel, T_W_B) -> np.ndarray:
    T_W_C = T_W_B @ T_B_C
    ray_W = T_W_C[:3, :3] @ np.r_[undistort_points(CAMERA, RADTAN, [pixel])[0], 1.0]
    return T_W_C[:3, 3] + ray_W * (WALL_X - T_W_C[0, 3]) / ray_W[0]


def tracks_of(points_W, T_W_B, ages, ids, shift=(0.0, 0.0)) -> Tracks:
    """The tracks of world points seen from ``T_W_B`` through the lens, the pixels moved by
    ``shift`` on every track older than its birth frame."""
    T_C_W = np.linalg.inv(T_W_B @ T_B_C)
    points_C = points_W @ T_C_W[:3, :3].T + T_C_W[:3, 3]
    normalised_true = points_C[:, :2] / points_C[:, 2:]
    pixels = distort_points(CAMERA, RADTAN, normalised_true)
    pixels = pixels + np.where(np.asarray(ages)[:, None] > 1, shift, 0.0)
    return Tracks(0, np.asarray(ids), pixels, undistort_points(CAMERA, RADTAN, pixels),
                  np.asarray(ages))


BIRTH_PIXELS = np.array([[40.0, 30.0], [80.0, 60.0], [120.0, 90.0], [20.0, 100.0]])


def fly(frames: int, shift=(0.0, 0.0)) -> TrackErrors:
    """Four tracks born in frame 0 on the wall, followed for ``frames`` frames."""
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    points_W = np.array([wall_point(p, body_pose(0)) for p in BIRTH_PIXELS])
    for k in range(frames):
        ages = np.full(len(points_W), k + 1)
        pose = body_pose(k)
        errors.observe(tracks_of(points_W, pose, ages, np.arange(4), shift), pose,
                       wall_depth(pose) if k == 0 else None)
    return errors


def test_exact_tracks_through_a_lens_have_no_error():
    errors = fly(12)
    assert len(errors.errors_px) == 4 * 11
    # the birth depth is read at the nearest pixel, so the points are named to a few
    # hundredths of a pixel
    assert max(errors.errors_px) < 0.05


def test_a_tracker_that_slides_half_a_pixel_is_measured_at_half_a_pixel():
    errors = fly(25, shift=(0.3, -0.4))
    summary = errors.summary()
    assert summary["track_error_px_median"] == pytest.approx(0.5, abs=0.05)
    counts = {b["ages"]: b["observations"] for b in summary["track_error_by_age"]}
    assert counts == {"2-4": 12, "5-9": 20, "10-19": 40, "20+": 24}
    assert all(b["median_px"] == pytest.approx(0.5, abs=0.05)
               for b in summary["track_error_by_age"])
    # the slide is shared by every track, so it is the mean error too
    assert all(b["mean_px"] == pytest.approx([0.3, -0.4], abs=0.05)
               for b in summary["track_error_by_age"])


def creeping_errors(frames: int, creep: complex) -> TrackErrors:
    """Four tracks followed for ``frames`` frames, each moved ``k`` times ``creep`` pixels in
    frame ``k`` from where the lens puts its point: along the outward radius for a real
    ``creep``, across it for an imaginary one (a quarter turn)."""
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    points_W = np.array([wall_point(p, body_pose(0)) for p in BIRTH_PIXELS])
    centre = np.array([CAMERA.cx, CAMERA.cy])
    for k in range(frames):
        pose = body_pose(k)
        exact = tracks_of(points_W, pose, np.full(4, k + 1), np.arange(4))
        radius = exact.pixels - centre
        radius /= np.linalg.norm(radius, axis=1, keepdims=True)
        turned = radius @ np.array([[creep.real, creep.imag], [-creep.imag, creep.real]])
        pixels = exact.pixels + k * turned
        errors.observe(Tracks(0, exact.ids, pixels, undistort_points(CAMERA, RADTAN, pixels),
                              exact.ages), pose, wall_depth(pose) if k == 0 else None)
    return errors


def test_a_track_creeping_outward_shows_in_the_outward_mean_and_one_sliding_across_does_not():
    """The tracker's creep (docs/vins.md, "The scale's loss was the tracker's window"): 0.05 px
    a frame outward is +0.05 px per frame of age in the outward mean; the same across the
    radius is as large an error but no outward mean."""
    out = creeping_errors(25, 0.05).summary()["track_error_by_age"]
    across = creeping_errors(25, 0.05j).summary()["track_error_by_age"]
    for bin_out, bin_across in zip(out, across):
        assert bin_out["median_px"] == pytest.approx(bin_across["median_px"], abs=0.01)
        assert abs(bin_across["outward_mean_px"]) < 0.01
    # ages 2-4 have crept 0.05-0.15 px, ages 20-25 0.95-1.2 px
    assert out[0]["outward_mean_px"] == pytest.approx(0.10, abs=0.01)
    assert out[-1]["outward_mean_px"] == pytest.approx(1.075, abs=0.02)


def test_tracks_born_on_unknown_depth_or_without_a_depth_image_are_not_scored():
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    pose0, pose1 = body_pose(0), body_pose(1)
    points_W = np.array([wall_point(p, pose0) for p in BIRTH_PIXELS])
    depth = wall_depth(pose0)
    depth[:, :70] = np.nan  # the first and last birth pixels are on unknown depth
    errors.observe(tracks_of(points_W, pose0, [1, 1, 1, 1], [0, 1, 2, 3]), pose0, depth)
    # a track born in a frame without a depth image is never scored either
    later = np.vstack([points_W, wall_point([60.0, 60.0], pose1)])
    errors.observe(tracks_of(later, pose1, [2, 2, 2, 2, 1], [0, 1, 2, 3, 4]), pose1, None)
    errors.observe(tracks_of(later, body_pose(2), [3, 3, 3, 3, 2], [0, 1, 2, 3, 4]),
                   body_pose(2), wall_depth(body_pose(2)))
    assert errors.ages == [2, 2, 3, 3]


def test_a_track_born_on_a_depth_edge_is_not_scored():
    """A corner on the edge of a near surface may read the far one's depth: not named."""
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    pose = body_pose(0)
    depth = wall_depth(pose)
    depth[:, 81:] *= 3.0  # a step in depth between columns 80 and 81
    pixels = np.array([[80.4, 60.0], [40.0, 60.0], [120.0, 60.0]])  # on the edge, off it
    points_W = np.array([wall_point(p, pose) for p in pixels])
    errors.observe(tracks_of(points_W, pose, [1, 1, 1], [0, 1, 2]), pose, depth)
    errors.observe(tracks_of(points_W, body_pose(1), [2, 2, 2], [0, 1, 2]), body_pose(1), None)
    assert len(errors.errors_px) == 2  # tracks 1 and 2, named on either side of the edge


def test_a_depth_image_of_another_size_is_refused():
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    pose = body_pose(0)
    points_W = np.array([wall_point(p, pose) for p in BIRTH_PIXELS])
    with pytest.raises(ValueError, match="depth image of 80x60 for a 160x120 camera"):
        errors.observe(tracks_of(points_W, pose, [1, 1, 1, 1], [0, 1, 2, 3]), pose,
                       np.ones((60, 80), np.float32))


def test_an_ended_track_is_forgotten_and_a_point_behind_the_camera_is_skipped():
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, FIT_WINDOW)
    pose = body_pose(0)
    points_W = np.array([wall_point(p, pose) for p in BIRTH_PIXELS])
    errors.observe(tracks_of(points_W, pose, [1, 1, 1, 1], [0, 1, 2, 3]), pose, wall_depth(pose))
    errors.observe(tracks_of(points_W[:2], pose, [2, 2], [0, 1]), pose, None)  # 2 and 3 end
    assert sorted(errors._births) == [0, 1]
    turned = pose @ make_pose(rot_z(math.pi), np.zeros(3))  # the wall now behind
    pixels = Tracks(0, np.array([0, 1]), BIRTH_PIXELS[:2], undistort_points(
        CAMERA, RADTAN, BIRTH_PIXELS[:2]), np.array([3, 3]))
    errors.observe(pixels, turned, None)
    assert errors.ages == [2, 2]


def test_no_scored_track_gives_none_and_empty_bins():
    summary = track_error_summary([], [], [])
    assert summary["track_error_px_median"] is None and summary["track_error_px_p90"] is None
    assert [b["observations"] for b in summary["track_error_by_age"]] == [0] * len(AGE_BINS)
    assert all(b["median_px"] is None and b["outward_mean_px"] is None and b["mean_px"] is None
               for b in summary["track_error_by_age"])


def test_a_gross_mistrack_is_left_out_of_the_means_not_the_median():
    """Two tracks of one age: 0.3 px to the right, and one 10 px off (a mistrack RANSAC would
    reject): the median and the count keep both, the means only the first."""
    summary = track_error_summary([(0.3, 0.0), (10.0, 0.0)], [0.3, 10.0], [5, 5])
    bin_ = next(b for b in summary["track_error_by_age"] if b["ages"] == "5-9")
    assert bin_["observations"] == 2 and bin_["median_px"] == pytest.approx(5.15)
    assert bin_["mean_px"] == pytest.approx([0.3, 0.0])
    assert bin_["outward_mean_px"] == pytest.approx(0.3)


def two_textures() -> np.ndarray:
    """The camera's image, textured: the left half at a tenth of the right half's contrast."""
    rng = np.random.default_rng(0)
    image = 128.0 + 100.0 * (rng.uniform(size=(CAMERA.height, CAMERA.width)) - 0.5)
    image[:, :CAMERA.width // 2] = 128.0 + 0.1 * (image[:, :CAMERA.width // 2] - 128.0)
    return image.astype(np.uint8)


def test_each_error_is_filed_under_the_texture_its_track_was_born_on():
    """Tracks born on the faint half (x 40 and 20) and on the strong half (x 120; the one at
    x 80 is on the boundary); later frames are flat, so only the birth frame can tell them
    apart: the faint ones are predicted several times the noise of the strong one, in every
    frame."""
    errors = TrackErrors(CAMERA, RADTAN, T_B_C, fit_window=7)
    pose = body_pose(0)
    points_W = np.array([wall_point(p, pose) for p in BIRTH_PIXELS])
    flat = np.full((CAMERA.height, CAMERA.width), 128, np.uint8)
    for k in range(6):
        pose = body_pose(k)
        errors.observe(tracks_of(points_W, pose, np.full(4, k + 1), np.arange(4)), pose,
                       wall_depth(pose) if k == 0 else None, two_textures() if k == 0 else flat)
    noise = np.reshape(errors.predicted_noise, (5, 4))  # BIRTH_PIXELS: x 40, 80 | 120, 20
    faint, strong = noise[:, [0, 3]], noise[:, [2]]
    assert (faint > 5.0 * strong.max()).all()
    summary = errors.summary()["track_error_by_texture"]
    assert len(summary["bins"]) == TEXTURE_BINS


def test_without_images_there_is_no_texture_summary():
    assert fly(6).summary()["track_error_by_texture"] is None


def test_errors_that_grow_with_the_predicted_noise_rank_with_it():
    noise = np.linspace(0.5, 2.0, 100)
    summary = texture_summary(0.1 * noise, noise)
    assert summary["spearman"] == pytest.approx(1.0)
    medians = [b["median_px"] for b in summary["bins"]]
    assert medians == sorted(medians) and medians[-1] > 2.5 * medians[0]  # 0.19 and 0.064
    assert texture_summary([0.1] * 9, [1.0] * 9) is None  # too few for five bins
    # a track whose birth was not seen has no prediction and is left out
    assert texture_summary([0.1] * 12, [np.nan, np.nan] + [1.0] * 10)["spearman"] is None
    assert texture_summary([0.1] * 11, [np.nan, np.nan] + [1.0] * 9) is None
