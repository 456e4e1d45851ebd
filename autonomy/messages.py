"""The typed messages the stages pass to each other (DESIGN.md, "The process").

Frozen dataclasses of numpy arrays, SI units, times in float seconds on the companion's
monotonic clock, frames as DESIGN.md names them (world ``W`` gravity-aligned z up, body ``B``
FLU, camera ``C`` optical).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


#: Static pressures a barometer on a flying vehicle can read, Pa (:class:`ImuSample`
#: ``pressure_pa``): from about 9 km above sea level to the Dead Sea's shore in a deep low.
PRESSURE_RANGE_PA = (30e3, 110e3)


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample at time ``t``: body-frame angular rate (rad/s) and specific force (m/s^2).

    The sample holds over ``[t, t_next)`` (zero-order hold), the convention of the
    preintegration and of the simulator's recordings. ``pressure_pa`` is the static pressure
    (Pa) of a barometer sample the flight controller published within the interval, None when
    it published none (PX4's barometer runs at 20 Hz, its IMU at 200 Hz): the barometer's
    time is the interval's, to within its length.
    """

    t: float
    gyro: np.ndarray
    accel: np.ndarray
    pressure_pa: float | None = None


@dataclass(frozen=True)
class Frame:
    """One camera image taken at ``t``: ``image`` uint8 RGB (H, W, 3), the camera's resolution.

    ``truth_depth`` is the renderer's ground-truth depth (float32 metres, NaN where nothing
    was hit) in simulation only, for the synthetic stand-in network and for evaluation (the
    ground-truth-depth baseline, ``companion sim fly --depth truth``); ``truth_pose`` the
    simulator's true body pose at the exposure, ``T_L_B`` in PX4's local frame (4x4), for the
    flight recording's VINS error (``companion log vins``). A real camera driver leaves both
    None and nothing else on the flight path may rely on them.

    ``counter`` is the device's own number of the frame (a RealSense frame number, an OAK
    sequence number, the simulated camera's exposure index), None where the device has none.
    A driver whose buffer stopped updating delivers the same number again under a newer stamp:
    the application refuses such a frame as stale.
    """

    t: float
    image: np.ndarray
    truth_depth: np.ndarray | None = None
    truth_pose: np.ndarray | None = None
    counter: int | None = None


@dataclass(frozen=True)
class SparseMap:
    """The VINS landmarks at one frame time, expressed in that frame's camera coordinates.

    Row ``i`` describes track ``ids[i]``: ``points_C[i]`` is its position in the camera frame
    (metres; ``z`` is the depth along the optical axis, always positive here), and
    ``depth_sigma[i]`` the one-sigma uncertainty of that depth in metres. ``tracked[i]`` is True
    when the front-end saw the track in this very frame, and ``pixels[i]`` is then where it saw
    it (distorted image coordinates); otherwise ``pixels[i]`` is the point's projection.
    """

    t: float
    ids: np.ndarray
    points_C: np.ndarray
    depth_sigma: np.ndarray
    pixels: np.ndarray
    tracked: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Odometry:
    """The body's state at time ``t`` in the world frame.

    ``T_W_B`` (4x4) pose, ``velocity_W`` (m/s, world frame), ``angular_velocity_B`` (rad/s,
    bias-corrected, body frame), and ``pose_covariance`` (6x6, rotation then position, right
    perturbation of the pose) when the estimator has one (NaN-filled otherwise).
    """

    t: float
    T_W_B: np.ndarray
    velocity_W: np.ndarray
    angular_velocity_B: np.ndarray
    pose_covariance: np.ndarray


@dataclass(frozen=True)
class RelativeDepth:
    """The depth network's output for the camera frame taken at ``t``: relative disparity
    (float32, the camera's resolution; larger is nearer, known only up to an unknown monotone
    map, affine for a good network)."""

    t: float
    disparity: np.ndarray


@dataclass(frozen=True)
class DepthDiagnostics:
    """How a :class:`MetricDepth` was made.

    ``anchors``: VINS landmarks sampled in the frame; ``anchors_used``: those the applied fit
    was made from (after outlier rejection; 0 without a fit). ``residual_rms``: the fit's RMS
    residual in metric disparity, 1/m (NaN without a fit). ``method``: the curve family applied
    (empty without one). ``fit_age_s``: the frame's time minus the time of the frame the
    applied fit was made on (0 for a fresh fit). ``reason``: why the frame got no fresh fit
    of the configured method (empty when it did). ``fallback``: the map applied is the affine
    one fitted to this frame's too few anchors (:func:`autonomy.depth.stage.affine_fallback`).
    """

    anchors: int
    anchors_used: int
    residual_rms: float
    method: str
    fit_age_s: float
    reason: str = ""
    fallback: bool = False


@dataclass(frozen=True, eq=False)
class FitSamples:
    """The fit behind a :class:`MetricDepth`, for the flight recorder: the anchors it was made
    from (``anchor_relative``, relative disparity; ``anchor_depth``, the VINS depth in metres;
    empty for a held fit, whose anchors belong to an earlier frame) and the curve sampled over
    the anchors' range (``curve_relative`` to ``curve_metric_disparity``, 1/m)."""

    anchor_relative: np.ndarray
    anchor_depth: np.ndarray
    curve_relative: np.ndarray
    curve_metric_disparity: np.ndarray


@dataclass(frozen=True)
class MetricDepth:
    """Metric depth for the camera frame taken at ``t``.

    ``depth``: float32 metres along the optical axis, NaN where unknown; ``confidence``: float32
    in [0, 1] per pixel, how densely anchors support that disparity. Both are None when there is
    no depth (no fit within the hold time, or the network output was rejected): the planner
    treats that as stop. ``held`` is True when the fit applied was made on an earlier frame.
    ``relative``: the network's relative disparity it was made from and ``fit`` the curve
    applied (None without one), kept for the flight recorder.
    """

    t: float
    depth: np.ndarray | None
    confidence: np.ndarray | None
    held: bool
    diagnostics: DepthDiagnostics
    relative: np.ndarray | None = None
    fit: FitSamples | None = None

    @property
    def ok(self) -> bool:
        """True when there is a depth image to plan on."""
        return self.depth is not None
