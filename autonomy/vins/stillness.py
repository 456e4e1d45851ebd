"""Standing still, as the camera and the IMU see it; the zero-velocity update it allows.

The vehicle stands still over a stretch of time when the features it tracks have not moved
(their median displacement, in undistorted pixels, at most ``still_flow_px``) and its body has
not turned (mean rate at most ``still_rate``). Both the restart after an IMU gap
(:mod:`autonomy.vins.imu_gap`) and the zero-velocity update below use this one test.

**Zero-velocity update.** A vehicle waiting on the ground for the operator's go gives the
window keyframes with no parallax: no landmark can be triangulated, and the window knows its
velocity only through the IMU factors' chain back to the last prior, whose information fades
as the window slides. Within a few seconds GTSAM's Cholesky calls the window indeterminate and
the smoother is rebuilt, again and again (a go 20 s after the initialisation: 4 rebuilds on
the ground, 9 in the flight, and a "diverging" failsafe; docs/vins.md, "Standing on the
ground"). A keyframe taken while standing still therefore gets a prior ``V(k) = 0`` with width
``zero_velocity_sigma``: velocity, and through the IMU factor the tilt and the accelerometer
bias, are observed again. It is the "zero velocity prior" Kimera-VIO adds on low disparity
(Rosinol et al., ICRA 2020, ``VioBackend::addZeroVelocityPrior``) and Astrobee's standstill
factor (Soussan et al., ICRA 2022). The test runs over the last ``zero_velocity_window_s``
(a pixel over half a second resolves a few centimetres a second at the depths we fly by), and
only while the estimate itself says at most ``zero_velocity_max_speed``, as OpenVINS's
``zupt_max_velocity`` does: far features barely move under a slow flight, and such a flight
must not be stopped by a prior.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from autonomy.geometry import so3_log
from autonomy.vins.frontend import Tracks
from autonomy.vins.options import VinsOptions


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
    """Keeps the last ``zero_velocity_window_s`` of keyframes (time, attitude ``R_W_B``,
    tracks) and says whether a new keyframe stands still since the one that long before it."""

    options: VinsOptions
    focal_px: float
    keyframes: list[tuple[float, np.ndarray, Tracks]] = field(default_factory=list)

    def still(self, t: float, R_W_B: np.ndarray, speed: float, tracks: Tracks) -> bool:
        """Whether the keyframe at ``t`` (IMU-predicted attitude ``R_W_B`` and ``speed``,
        m/s) gets a zero-velocity prior (module docstring)."""
        o = self.options
        earlier = [k for k in self.keyframes if k[0] <= t - o.zero_velocity_window_s]
        if not o.zero_velocity_update or not earlier or speed > o.zero_velocity_max_speed:
            return False
        t0, R0, tracks0 = earlier[-1]
        rate = float(np.linalg.norm(so3_log(R0.T @ R_W_B))) / (t - t0)
        flow = median_flow_px(tracks, tracks0, self.focal_px, o.min_tracked_ok)
        return is_still(flow, rate, o)

    def add(self, t: float, R_W_B: np.ndarray, tracks: Tracks) -> None:
        """The keyframe at ``t`` as the smoother estimated it; older ones than the window
        needs are dropped."""
        self.keyframes.append((t, np.asarray(R_W_B, float), tracks))
        keep_from = t - self.options.zero_velocity_window_s
        while len(self.keyframes) > 1 and self.keyframes[1][0] <= keep_from:
            self.keyframes.pop(0)

    def clear(self) -> None:
        """Forget the keyframes (a restart: their attitudes are of another smoother)."""
        self.keyframes.clear()
