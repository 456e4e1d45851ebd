"""Standing still, as the camera and the IMU see it; the zero-velocity update it allows.

The vehicle stands still over a stretch of time when the features it tracks have not moved
(their median displacement, in undistorted pixels, at most ``still_flow_px``) and its body has
not turned (mean rate at most ``still_rate``). Both the restart after an IMU gap
(:mod:`autonomy.vins.imu_gap`) and the zero-velocity update below use this one test.

**Zero-velocity update.** A vehicle waiting on the ground for the operator's go gives the
window keyframes with no parallax: no landmark can be triangulated, and the window knows its
velocity only through the IMU factors' chain back to the last prior, whose information fades
as the window slides. Within a few seconds GTSAM's Cholesky calls the window indeterminate and
the smoother is rebuilt, again and again (docs/vins.md, "Standing on the ground"). A keyframe
taken on the ground and standing still therefore gets a prior ``V(k) = 0`` with width
``zero_velocity_sigma``: velocity, and through the IMU factor the tilt and the accelerometer
bias, are observed again. It is the "zero velocity prior" Kimera-VIO adds on low disparity
(Rosinol et al., ICRA 2020, ``VioBackend::addZeroVelocityPrior``) and Astrobee's standstill
factor (Soussan et al., ICRA 2022).

Only where the caller says the vehicle is on the ground (disarmed: the application knows,
the estimator cannot): in the air a hover is never at rest, and features far away barely move
under a slow flight (a pixel over half a second is depth / 160 m/s at a 320 px focal length),
so the test alone would put a wrong prior on a slow flight or a hover. On the ground it still
must pass, against every keyframe of the last ``zero_velocity_window_s`` (a vehicle carried
and put back is not still): the largest median flow and the largest turn against any of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from autonomy.geometry import so3_log
from autonomy.vins.frontend import Tracks
from autonomy.vins.options import VinsOptions

#: Keyframe times compared to a window's length are equal within this, seconds.
STAMP_TOLERANCE_S = 1e-6


def median_flow_px(now: Tracks, earlier: Tracks, focal_px: float, min_common: int) -> float:
    """The median displacement, undistorted pixels, of the features ``now`` shares with
    ``earlier``; infinite when they share fewer than ``min_common`` (nothing to judge by)."""
    _, here, there = np.intersect1d(now.ids, earlier.ids, return_indices=True)
    if len(here) < max(min_common, 1):
        return float("inf")
    flow = np.linalg.norm(now.normalised[here] - earlier.normalised[there], axis=1)
    return float(np.median(flow)) * focal_px


def is_still(flow_px: float, rate: float, options: VinsOptions) -> bool:
    """Standing still by the module docstring's test: features within ``still_flow_px``, body
    rate (rad/s) within ``still_rate``."""
    return flow_px <= options.still_flow_px and rate <= options.still_rate


@dataclass
class ZeroVelocityDetector:
    """Keeps the keyframes (time, attitude ``R_W_B``, tracks) of the last
    ``zero_velocity_window_s`` and says whether a new one stands still over that stretch."""

    options: VinsOptions
    focal_px: float
    keyframes: list[tuple[float, np.ndarray, Tracks]] = field(default_factory=list)

    def still(self, t: float, R_W_B: np.ndarray, tracks: Tracks) -> bool:
        """Whether the keyframe at ``t`` (IMU-predicted attitude ``R_W_B``) stood still since
        the keyframe a window before it, judged against every keyframe since (module
        docstring); False until the keyframes span the window."""
        o = self.options
        stretch = self._stretch(t)
        if not o.zero_velocity_update or not stretch:
            return False
        flow = max(median_flow_px(tracks, k_tracks, self.focal_px, o.min_tracked_ok)
                   for _, _, k_tracks in stretch)
        turn = max(float(np.linalg.norm(so3_log(R.T @ R_W_B))) for _, R, _ in stretch)
        return is_still(flow, turn / (t - stretch[0][0]), o)

    def add(self, t: float, R_W_B: np.ndarray, tracks: Tracks) -> None:
        """The keyframe at ``t`` as the smoother estimated it; those older than the next
        keyframe's stretch can need are dropped."""
        self.keyframes.append((t, np.asarray(R_W_B, float), tracks))
        while len(self.keyframes) > 1 and self._reaches_back(self.keyframes[1][0], t):
            self.keyframes.pop(0)

    def clear(self) -> None:
        """Forget the keyframes (a restart: their attitudes are of another smoother)."""
        self.keyframes.clear()

    def _stretch(self, t: float) -> list[tuple[float, np.ndarray, Tracks]]:
        """The keyframes from the newest one at least a window before ``t`` on; empty when
        none is that old."""
        first = [i for i, k in enumerate(self.keyframes) if self._reaches_back(k[0], t)]
        return self.keyframes[first[-1]:] if first else []

    def _reaches_back(self, earlier: float, t: float) -> bool:
        """``earlier`` is a window or more before ``t`` (to a microsecond: keyframe times are
        sums of frame periods)."""
        return t - earlier >= self.options.zero_velocity_window_s - STAMP_TOLERANCE_S
