"""Re-initialising after the IMU fell silent in flight: from what the camera and the IMU
observe, not from a propagation across the gap.

Across a gap the estimator has nothing to propagate with. Holding the last sample for the
gap's seconds (zero-order hold) is what the in-flight re-initialisation used to start from; in
a flight that braked during a 2 s gap it turned 8 degrees of tilt into 53 and 0 m/s into 2, and
the new smoother ran away (docs/vins.md, "An IMU gap in flight"). Once the IMU is back, the
estimator (:meth:`autonomy.vins.estimator.Vins._restart_after_gap`) restarts from the first of:

1. **relocalised on the map.** The camera kept tracking features whose landmarks the window
   had placed in the world. Their world points and the frame's undistorted observations give
   the camera's pose by Perspective-n-Point (RANSAC on P3P, then Levenberg-Marquardt on the
   inliers; OpenCV's ``solvePnPRansac`` and ``solvePnPRefineLM``) with the normalised image
   plane as the camera (``K = I``):

       x_i ~ R_C_W p_W,i + t_C_W,    T_W_B = (T_C_W)^-1 T_C_B,

   and the frames relocalised over the last ``relocalise_window_s`` give the velocity (the
   least-squares slope of their positions). A propagation across the gap that lands within
   ``max_propagation_disagreement_m`` of it is confirmed by the map, and restarted from
   instead (it is the more precise).
2. **the propagation**, when no frame is relocalised, across a gap of up to
   ``max_propagated_gap_s``: a held sample errs little over a fraction of a second.
3. **standing still**, after ``reinit_imu_window_s`` of samples: standing still over that
   window by :func:`autonomy.vins.stillness.is_still` (the vehicle holds, as the
   application's failsafe makes it). Velocity zero within
   ``still_velocity_sigma``; position and yaw the newest known: those of the gap's last
   frame relocalised on the map, once a second frame within ``relocalise_window_s`` was too
   (one PnP alone is not trusted to move it), or else the estimate from before the gap (the
   motion since is unobserved: the restart moves the world's origin, as any reset does);
   roll and pitch those of the window's mean specific force (the static initialisation's
   gravity alignment), within ``reinit_tilt_sigma_deg``.

Otherwise (the map lost and the camera moving) it stays LOST and says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from autonomy.geometry import invert_pose, make_pose, rot_z, yaw_of
from autonomy.vins.frontend import Tracks
from autonomy.vins.imu_buffer import NavState
from autonomy.vins.options import VinsOptions
from autonomy.vins.static_init import gravity_aligned_rotation
from autonomy.vins.stillness import is_still, median_flow_px

#: RANSAC's iterations and confidence for the P3P hypotheses.
PNP_ITERATIONS = 100
PNP_CONFIDENCE = 0.99

#: Frames relocalised within ``relocalise_window_s`` before the newest of them is where the
#: vehicle is last known: the gap's first frames after a turn may see the map in only two.
CONFIRMING_POSES = 2


def body_pose_from_landmarks(landmark_ids: np.ndarray, points_W: np.ndarray, tracks: Tracks,
                             T_C_B: np.ndarray, min_inliers: int,
                             max_error: float) -> np.ndarray | None:
    """``T_W_B`` (4x4) of the frame seeing ``tracks``, from the landmarks ``landmark_ids``
    (sorted, M) at ``points_W`` (M, 3) it still tracks (module docstring); None when fewer
    than ``min_inliers`` of them agree within ``max_error`` (normalised image units)."""
    _, rows, cols = np.intersect1d(landmark_ids, tracks.ids, return_indices=True)
    if len(rows) < max(min_inliers, 4):
        return None
    world = np.ascontiguousarray(points_W[rows], dtype=np.float64)
    image = np.ascontiguousarray(tracks.normalised[cols], dtype=np.float64)
    try:
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            world, image, np.eye(3), None, iterationsCount=PNP_ITERATIONS,
            reprojectionError=max_error, confidence=PNP_CONFIDENCE, flags=cv2.SOLVEPNP_AP3P)
        if not found or inliers is None or len(inliers) < min_inliers:
            return None
        inliers = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(world[inliers], image[inliers], np.eye(3), None,
                                          rvec, tvec)
    except cv2.error:  # a degenerate point set (all on one line, say): not relocalised
        return None
    T_W_B = invert_pose(make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())) @ T_C_B
    return T_W_B if np.isfinite(T_W_B).all() else None


def velocity_from_poses(times: np.ndarray, positions: np.ndarray,
                        min_poses: int) -> np.ndarray | None:
    """The least-squares constant velocity through ``positions`` (N, 3) at ``times`` (N,):
    the slope of ``p(t) = p0 + v t``; None with fewer than ``min_poses`` poses or no time
    between them."""
    times = np.asarray(times, float)
    if len(times) < max(min_poses, 2) or np.ptp(times) <= 0.0:
        return None
    return np.polyfit(times - times.mean(), np.asarray(positions, float), 1)[0]


@dataclass(frozen=True)
class Restart:
    """Where a smoother restarts after a gap: ``state``, its velocity's and tilt's prior
    widths (m/s, radians), and ``how`` it was found."""

    state: NavState
    velocity_sigma: float
    tilt_sigma: float
    how: str


@dataclass
class ImuGap:
    """The IMU fell silent after ``last_sample_t``. Where the vehicle was last known
    (``position``, ``yaw``: the estimate before the gap, then the gap's frames relocalised on
    the map, :data:`CONFIRMING_POSES` at a time), the accelerometer bias, and what the frames
    since showed: the body poses relocalised on the map and the recent frames' tracks."""

    last_sample_t: float
    position: np.ndarray
    yaw: float
    bias_a: np.ndarray
    options: VinsOptions
    focal_px: float
    poses: list[tuple[float, np.ndarray]] = field(default_factory=list)
    frames: list[tuple[float, Tracks]] = field(default_factory=list)

    def observe(self, t: float, tracks: Tracks, landmark_ids: np.ndarray, points_W: np.ndarray,
                T_C_B: np.ndarray) -> None:
        """Relocalise the frame at ``t`` on the landmarks, when it can be, and keep its
        tracks for the stillness check."""
        o = self.options
        T_W_B = body_pose_from_landmarks(landmark_ids, points_W, tracks, T_C_B,
                                         o.relocalise_min_landmarks,
                                         o.max_reprojection_px / self.focal_px)
        if T_W_B is not None:
            self.poses.append((t, T_W_B))
            if len(self._recent_poses(t)) >= CONFIRMING_POSES:
                self.position, self.yaw = T_W_B[:3, 3], yaw_of(T_W_B[:3, :3])
        self.frames.append((t, tracks))
        keep_from = t - 2.0 * max(o.reinit_imu_window_s, o.relocalise_window_s)
        self.poses = [(s, T) for s, T in self.poses if s >= keep_from]
        self.frames = [(s, f) for s, f in self.frames if s >= keep_from]

    def relocalised(self, t: float) -> Restart | None:
        """This frame's relocalised pose (after :meth:`observe` of it) with the velocity of
        those of the last ``relocalise_window_s``; None when this frame or too few recent
        ones were not relocalised."""
        o = self.options
        recent = self._recent_poses(t)
        if not recent or recent[-1][0] != t:
            return None
        velocity = velocity_from_poses(np.array([s for s, _ in recent]),
                                       np.array([T[:3, 3] for _, T in recent]),
                                       o.relocalise_min_poses)
        if velocity is None:
            return None
        T_W_B = recent[-1][1]
        return Restart(NavState(t, T_W_B[:3, :3], T_W_B[:3, 3], velocity),
                       o.reinit_velocity_sigma, math.radians(o.prior_tilt_sigma_deg),
                       "relocalised on the map")

    def _recent_poses(self, t: float) -> list[tuple[float, np.ndarray]]:
        """The poses relocalised within ``relocalise_window_s`` of ``t``."""
        return [(s, T) for s, T in self.poses if s >= t - self.options.relocalise_window_s]

    def standing_still(self, t: float, imu_t: np.ndarray, gyro: np.ndarray,
                       accel: np.ndarray) -> Restart | str:
        """The restart standing still at ``t`` (module docstring), given the IMU samples
        since the gap (times, gyro with its bias removed, accel); or why not (yet)."""
        o = self.options
        back_s = t - imu_t[0]
        if back_s < o.reinit_imu_window_s:
            return (f"IMU back after a {imu_t[0] - self.last_sample_t:.2f} s gap: "
                    f"{back_s:.2f} of {o.reinit_imu_window_s:g} s of samples")
        recent = imu_t >= t - o.reinit_imu_window_s
        if not self._still(t, gyro[recent]):
            return ("IMU back after a gap; the map is not tracked and the camera moves: "
                    "waiting to relocalise or to stand still")
        up_B = (accel[recent] - self.bias_a).mean(axis=0)
        R_W_B = rot_z(self.yaw) @ gravity_aligned_rotation(up_B)
        return Restart(NavState(t, R_W_B, self.position, np.zeros(3)), o.still_velocity_sigma,
                       math.radians(o.reinit_tilt_sigma_deg), "standing still")

    def _still(self, t: float, gyro: np.ndarray) -> bool:
        """Standing still (:func:`autonomy.vins.stillness.is_still`) since the frame
        ``reinit_imu_window_s`` ago, the gyro's mean rate over that time standing for the
        body's."""
        o = self.options
        earlier = [f for s, f in self.frames if s <= t - o.reinit_imu_window_s]
        if not earlier:
            return False
        flow = median_flow_px(self.frames[-1][1], earlier[-1], self.focal_px, o.min_tracked_ok)
        return is_still(flow, float(np.linalg.norm(gyro.mean(axis=0))), o)
