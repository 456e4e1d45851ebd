"""The VINS's restart after an IMU gap (autonomy/vins/imu_gap.py): the pose relocalised on
the map's landmarks by real OpenCV PnP, the velocity of the relocalised poses, and the
standing-still restart with its tilt from the specific force; and what makes each refuse."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autonomy.geometry import invert_pose, make_pose, rot_z, so3_exp, yaw_of
from autonomy.vins import Tracks, VinsOptions
from autonomy.vins.imu_gap import ImuGap, Restart, body_pose_from_landmarks, velocity_from_poses

FOCAL_PX = 400.0
#: The camera looks along the body's x axis (z forward, x right, y down).
T_B_C = make_pose(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                  np.array([0.1, 0.0, 0.05]))
T_C_B = invert_pose(T_B_C)


def landmarks_ahead(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` landmarks 3-12 m ahead of the origin along +x, ids 100, 101, ..."""
    rng = np.random.default_rng(seed)
    points = np.c_[rng.uniform(3.0, 12.0, count), rng.uniform(-4.0, 4.0, count),
                   rng.uniform(-1.0, 3.0, count)]
    return np.arange(100, 100 + count), points


def seen_from(T_W_B: np.ndarray, ids: np.ndarray, points_W: np.ndarray, *, frame: int = 0,
              shift_px: float = 0.0) -> Tracks:
    """The tracks of a camera on the body at ``T_W_B`` seeing ``points_W`` (all moved by
    ``shift_px`` pixels along the image's x)."""
    T_C_W = T_C_B @ invert_pose(T_W_B)
    p_C = points_W @ T_C_W[:3, :3].T + T_C_W[:3, 3]
    normalised = p_C[:, :2] / p_C[:, 2:] + [shift_px / FOCAL_PX, 0.0]
    return Tracks(frame, ids, normalised * FOCAL_PX + [320.0, 240.0], normalised,
                  np.full(len(ids), 10))


def body_pose(x: float, yaw_deg: float = 10.0) -> np.ndarray:
    R_W_B = rot_z(math.radians(yaw_deg)) @ so3_exp(np.array([0.05, 0.0, 0.0]))
    return make_pose(R_W_B, np.array([x, 0.3, 1.5]))


def test_a_frame_tracking_the_map_is_relocalised_exactly_despite_outliers():
    ids, points = landmarks_ahead(30)
    truth = body_pose(0.4)
    tracks = seen_from(truth, ids, points)
    tracks.normalised[:5] += 0.05  # five tracks slid 20 px onto something else
    found = body_pose_from_landmarks(ids, points, tracks, T_C_B, 6, 3.0 / FOCAL_PX)
    assert found is not None
    assert np.allclose(found, truth, atol=1e-6)


@pytest.mark.parametrize("tracked, min_inliers", [(5, 6), (30, 31)])
def test_too_few_landmarks_tracked_or_agreeing_is_no_relocalisation(tracked, min_inliers):
    ids, points = landmarks_ahead(30)
    tracks = seen_from(body_pose(0.0), ids[:tracked], points[:tracked])
    assert body_pose_from_landmarks(ids, points, tracks, T_C_B, min_inliers,
                                    3.0 / FOCAL_PX) is None


def test_landmarks_all_on_one_line_are_no_relocalisation_and_no_error():
    ids = np.arange(100, 110)
    points = np.c_[np.linspace(4.0, 8.0, 10), np.zeros(10), np.full(10, 1.5)]
    tracks = seen_from(body_pose(0.0, yaw_deg=20.0), ids, points)
    assert body_pose_from_landmarks(ids, points, tracks, T_C_B, 6, 3.0 / FOCAL_PX) is None


def test_the_velocity_is_the_least_squares_slope_of_the_positions():
    rng = np.random.default_rng(1)
    times = np.linspace(10.0, 10.5, 11)
    positions = np.c_[1.2 * times, -0.4 * times, np.full_like(times, 1.5)]
    noisy = positions + rng.normal(0.0, 0.005, positions.shape)
    assert np.allclose(velocity_from_poses(times, noisy, 3), [1.2, -0.4, 0.0], atol=0.05)
    assert velocity_from_poses(times[:2], positions[:2], 3) is None
    assert velocity_from_poses(np.full(4, 10.0), positions[:4], 3) is None


def gap(options: VinsOptions | None = None) -> ImuGap:
    """A gap after t = 10 s, the estimate before it at (5, 1, 1.5) heading 30 degrees."""
    return ImuGap(10.0, np.array([5.0, 1.0, 1.5]), math.radians(30.0), np.zeros(3),
                  options or VinsOptions(), FOCAL_PX)


def test_flying_through_the_gap_on_the_map_restarts_at_the_relocalised_pose_and_speed():
    ids, points = landmarks_ahead(40)
    g = gap()
    times = np.arange(10.05, 12.0, 0.05)
    for t in times:
        g.observe(t, seen_from(body_pose(0.8 * (t - 10.0)), ids, points), ids, points, T_C_B)
    restart = g.relocalised(times[-1])
    assert isinstance(restart, Restart) and restart.how == "relocalised on the map"
    assert np.allclose(restart.state.position, body_pose(0.8 * (times[-1] - 10.0))[:3, 3],
                       atol=1e-6)
    assert np.allclose(restart.state.velocity, [0.8, 0.0, 0.0], atol=1e-6)


def test_a_frame_that_lost_the_map_is_not_relocalised_on_older_poses():
    ids, points = landmarks_ahead(40)
    g = gap()
    for t in (10.05, 10.10, 10.15):
        g.observe(t, seen_from(body_pose(0.0), ids, points), ids, points, T_C_B)
    g.observe(10.20, seen_from(body_pose(0.0), ids[:3], points[:3]), ids, points, T_C_B)
    assert g.relocalised(10.20) is None


def still_imu(t0: float, t1: float, tilt_rad: float, rate: float = 0.0):
    """Samples at 200 Hz of a body pitched by ``tilt_rad``, turning at ``rate`` rad/s."""
    imu_t = np.arange(t0, t1 + 1e-9, 0.005)
    up_B = np.array([-math.sin(tilt_rad), 0.0, math.cos(tilt_rad)]) * 9.81
    return imu_t, np.tile([0.0, 0.0, rate], (len(imu_t), 1)), np.tile(up_B, (len(imu_t), 1))


def test_standing_still_after_the_gap_restarts_level_where_it_was_at_rest():
    ids, points = landmarks_ahead(40)
    g = gap()
    for t in np.arange(11.0, 12.31, 0.05):  # the map is not tracked: ids it never had
        g.observe(t, seen_from(body_pose(0.0), ids + 1000, points), ids, points, T_C_B)
    restart = g.standing_still(12.3, *still_imu(12.0, 12.3, math.radians(4.0)))
    assert isinstance(restart, Restart) and restart.how == "standing still"
    state = restart.state
    assert np.allclose(state.position, [5.0, 1.0, 1.5]) and np.allclose(state.velocity, 0.0)
    assert yaw_of(state.R_W_B) == pytest.approx(math.radians(30.0), abs=1e-9)
    up_W = state.R_W_B @ np.array([-math.sin(math.radians(4.0)), 0.0, math.cos(math.radians(4.0))])
    assert np.allclose(up_W, [0.0, 0.0, 1.0], atol=1e-9)  # the specific force made level
    assert restart.tilt_sigma == pytest.approx(math.radians(VinsOptions().reinit_tilt_sigma_deg))


def lose_the_map_after(relocalised_at: list[float]) -> tuple[Restart, np.ndarray]:
    """A gap whose frames at ``relocalised_at`` see the map, each from further along (body
    at x = 0.6 m + 1.5 m/s), and whose frames from 11 s on do not; the restart standing still
    at 12.3 s, and the last pose relocalised."""
    ids, points = landmarks_ahead(40)
    g = gap()
    for t in relocalised_at:
        seen = body_pose(0.6 + 1.5 * (t - 10.0), yaw_deg=12.0 + 10.0 * (t - 10.0))
        g.observe(t, seen_from(seen, ids, points), ids, points, T_C_B)
    for t in np.arange(11.0, 12.31, 0.05):  # the map out of view from here on
        g.observe(t, seen_from(seen, ids + 1000, points), ids, points, T_C_B)
    restart = g.standing_still(12.3, *still_imu(12.0, 12.3, 0.0))
    assert isinstance(restart, Restart) and restart.how == "standing still"
    return restart, seen


def test_standing_still_after_losing_the_map_restarts_where_it_was_last_relocalised():
    """The vehicle flew on into the gap, relocalised on the map until the map left the view:
    the restart takes the last relocalised position and yaw, not the estimate from before the
    gap (1.5 m behind, in the flight of docs/vins.md, "An IMU gap in flight", after a turn)."""
    restart, last_seen = lose_the_map_after([10.05, 10.10, 10.15])
    assert np.allclose(restart.state.position, last_seen[:3, 3], atol=1e-6)
    assert yaw_of(restart.state.R_W_B) == pytest.approx(yaw_of(last_seen[:3, :3]), abs=1e-6)


def test_one_frame_relocalised_alone_does_not_move_the_restart():
    """One PnP is not trusted to place the vehicle (a handful of landmarks that slid off their
    points may agree on a wrong pose): the restart stays at the estimate from before the gap."""
    restart, _ = lose_the_map_after([10.05])
    assert np.allclose(restart.state.position, [5.0, 1.0, 1.5])
    assert yaw_of(restart.state.R_W_B) == pytest.approx(math.radians(30.0), abs=1e-9)


@pytest.mark.parametrize("shift_px, rate, imu_from, why", [
    (0.0, 0.0, 12.2, "0.10 of 0.2 s of samples"),  # too little IMU since the gap yet
    (5.0, 0.0, 12.0, "the camera moves"),  # the features slid 5 px in 0.2 s
    (0.0, 0.2, 12.0, "the camera moves"),  # turning
])
def test_a_moving_camera_or_too_little_imu_waits(shift_px, rate, imu_from, why):
    ids, points = landmarks_ahead(40)
    g = gap()
    for t in np.arange(11.0, 12.31, 0.05):
        shift = shift_px * (t - 11.0) / 0.2
        g.observe(t, seen_from(body_pose(0.0), ids + 1000, points, shift_px=shift), ids, points,
                  T_C_B)
    restart = g.standing_still(12.3, *still_imu(imu_from, 12.3, 0.0, rate))
    assert isinstance(restart, str) and why in restart, restart
