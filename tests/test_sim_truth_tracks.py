"""Truth tracks (``sim fly --tracks truth``): the tracker's tracks with the truth's pixels,
checked against the renderer that drew the frames; and the truth with one part of the
tracker's error (``--tracks early-error`` / ``late-error``)."""

import math

import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z
from autonomy.messages import Frame
from autonomy.vins import Tracks
from autonomy.vins.frontend import FeatureTracker
from drivers.sim.render import Renderer
from drivers.sim.truth_tracks import ERROR_SPLIT_AGE, TruthTracks, replacement_for
from drivers.sim.world import build_world

CAMERA = PinholeCamera(640, 480, 320.0, 320.0, 319.5, 239.5)
T_B_C = make_pose(R_BODY_CAMERA, np.array([0.1, 0.0, 0.05]))  # the default mounting's offset


@pytest.fixture(scope="module")
def hall(opengl):
    """Frames down the sewer's hall (seed 0, pair 5 starts in it), 8 cm apart, as a vehicle
    cruising at 1.6 m/s sees them at 20 Hz, with their true body poses and depths (skipped
    without OpenGL: conftest's ``opengl``)."""
    world = build_world("sewer", seed=0)
    start = np.array([*world.routes[5].start[:2], 1.5])
    heading = math.pi  # down the hall, towards the route's goal
    poses = [make_pose(rot_z(heading), start + [-0.08 * k, 0.0, 0.0]) for k in range(6)]
    with Renderer(world, CAMERA) as renderer:
        frames = []
        for k, T_L_B in enumerate(poses):
            rgb, depth = renderer.render(T_L_B @ T_B_C)
            frames.append(Frame(0.05 * k, np.array(rgb), np.array(depth), T_L_B))
    return frames


def test_newborn_tracks_keep_the_trackers_pixels(hall):
    tracks = FeatureTracker(CAMERA).track(hall[0].image)
    truth = TruthTracks(CAMERA, T_B_C)(hall[0], tracks)
    assert len(truth) > 0.8 * len(tracks)
    rows = np.searchsorted(tracks.ids, truth.ids)
    np.testing.assert_allclose(truth.pixels, tracks.pixels[rows], atol=1e-6)
    np.testing.assert_allclose(truth.normalised, (truth.pixels - (CAMERA.cx, CAMERA.cy))
                               / (CAMERA.fx, CAMERA.fy), atol=1e-9)


def test_later_pixels_land_on_their_points_in_the_rendered_depth_and_near_the_tracker(hall):
    """Independent of the projection's code: where the truth puts a point in a later frame,
    that frame's rendered depth is the point's depth (a wrong pose, mounting or focal length
    would put it elsewhere on the slanted walls). Lucas-Kanade on clean frames agrees within a
    pixel for most tracks."""
    tracker, truth_tracks = FeatureTracker(CAMERA), TruthTracks(CAMERA, T_B_C)
    for frame in hall:
        tracks = tracker.track(frame.image)
        truth = truth_tracks(frame, tracks)
    last = hall[-1]
    assert len(truth) >= 50 and (truth.ages >= len(hall)).sum() >= 30
    T_C_L = np.linalg.inv(last.truth_pose @ T_B_C)
    u, v = np.rint(truth.pixels).astype(int).T
    rendered = last.truth_depth[v, u]
    points_L = np.array([truth_tracks._points_L[int(key)] for key in truth.ids])
    depth = (points_L @ T_C_L[:3, :3].T + T_C_L[:3, 3])[:, 2]
    assert np.mean(np.abs(rendered / depth - 1.0) < 0.02) > 0.9
    rows = np.searchsorted(tracks.ids, truth.ids)
    assert np.median(np.linalg.norm(truth.pixels - tracks.pixels[rows], axis=1)) < 1.0


def test_a_track_born_on_a_depth_edge_or_out_of_view_has_no_truth(hall):
    frame = hall[0]
    depth = frame.truth_depth
    spread = np.full(depth.shape, np.nan)
    spread[1:-1, 1:-1] = np.max([np.abs(depth[1:-1, 1:-1] - depth[1 + dv:depth.shape[0] - 1 + dv,
                                                                  1 + du:depth.shape[1] - 1 + du])
                                 for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=0)
    edge_v, edge_u = np.argwhere(spread > 0.2 * depth)[0]
    flat_v, flat_u = np.argwhere(spread < 0.001 * depth)[0]
    pixels = np.array([[edge_u, edge_v], [flat_u, flat_v]], dtype=float)
    tracks = Tracks(0, np.array([7, 8]), pixels, (pixels - (CAMERA.cx, CAMERA.cy))
                    / (CAMERA.fx, CAMERA.fy), np.array([1, 1]))
    truth_tracks = TruthTracks(CAMERA, T_B_C)
    assert list(truth_tracks(frame, tracks).ids) == [8]
    # the vehicle turned round: its point is behind the camera
    turned = Frame(0.05, frame.image, frame.truth_depth,
                   frame.truth_pose @ make_pose(rot_z(math.pi), np.zeros(3)))
    later = Tracks(1, np.array([8]), pixels[1:], tracks.normalised[1:], np.array([2]))
    assert len(truth_tracks(turned, later)) == 0


def test_a_frame_without_the_truth_is_refused(hall):
    tracks = FeatureTracker(CAMERA).track(hall[0].image)
    with pytest.raises(ValueError, match="true pose and depth"):
        TruthTracks(CAMERA, T_B_C)(Frame(0.0, hall[0].image), tracks)


def _sideways_past_a_wall(frames: int):
    """Frames of a camera sliding sideways 5 cm a frame past a wall 5 m ahead (every pixel's
    depth 5 m, nothing rendered): no OpenGL needed."""
    depth = np.full((CAMERA.height, CAMERA.width), 5.0, dtype=np.float32)
    image = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    return [Frame(0.05 * k, image, depth, make_pose(np.eye(3), np.array([0.0, -0.05 * k, 0.0])))
            for k in range(frames)]


def _fed(truth_tracks: TruthTracks, frame: Frame, ids: np.ndarray, pixels: np.ndarray,
         age: int) -> Tracks:
    normalised = (pixels - (CAMERA.cx, CAMERA.cy)) / (CAMERA.fx, CAMERA.fy)
    return truth_tracks(frame, Tracks(age - 1, ids, pixels, normalised, np.full(len(ids), age)))


@pytest.mark.parametrize("source", ["early-error", "late-error"])
def test_early_and_late_error_keep_the_trackers_error_before_or_after_the_split(source):
    """A tracker whose error grows by a known step each frame, its own for each track:
    early-error keeps what a track had at its split age and holds it, late-error keeps only
    what it gathers after; each track its own, whatever the order of the tracks, and a
    track lost on the way takes nothing of the others'."""
    born = np.array([[200.0, 150.0], [420.0, 300.0], [320.0, 240.0]])
    steps = np.array([[0.1, -0.05], [-0.2, 0.0], [0.03, 0.15]])  # each track's error a frame
    exact, mixed = TruthTracks(CAMERA, T_B_C), TruthTracks(CAMERA, T_B_C, source)
    ids, pixels, rows = np.arange(3), born, np.arange(3)
    for age, frame in enumerate(_sideways_past_a_wall(ERROR_SPLIT_AGE + 4), start=1):
        if age == ERROR_SPLIT_AGE + 2:  # track 1 lost; the others handed over in reverse
            ids, pixels, rows = ids[[2, 0]], pixels[[2, 0]], rows[[2, 0]]
        truth = _fed(exact, frame, ids, pixels, age)
        tracker = truth.pixels + (age - 1) * steps[rows]
        out = _fed(mixed, frame, ids, tracker if age > 1 else born, age)
        before_split = min(age, ERROR_SPLIT_AGE) - 1
        frames_kept = before_split if source == "early-error" else age - 1 - before_split
        np.testing.assert_array_equal(out.ids, ids)
        np.testing.assert_allclose(out.pixels, truth.pixels + frames_kept * steps[rows],
                                   atol=1e-9)
        np.testing.assert_allclose(out.normalised, (out.pixels - (CAMERA.cx, CAMERA.cy))
                                   / (CAMERA.fx, CAMERA.fy), atol=1e-12)
        pixels = tracker
    assert age > ERROR_SPLIT_AGE + 1 and np.abs(truth.pixels - born[rows]).max() > 20.0


def test_an_unknown_track_source_names_the_choices():
    assert replacement_for("tracker", CAMERA, T_B_C) is None
    assert replacement_for("late-error", CAMERA, T_B_C).source == "late-error"
    with pytest.raises(ValueError, match="tracks must be one of tracker, truth, early-error, "
                                         "late-error, got 'oracle'"):
        replacement_for("oracle", CAMERA, T_B_C)
    with pytest.raises(ValueError, match="source must be one of truth, early-error"):
        TruthTracks(CAMERA, T_B_C, "tracker")
