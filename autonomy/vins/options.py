"""Options of the VINS back-end, keyframe selection, landmark gate and health monitor.

One flat options object (a config section, ``[vins]``); the front-end and the static
initialisation keep their own (``[vins_frontend]``, ``[vins_init]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from autonomy.options import OptionError, option, validate

#: Largest gyro response to the yaw rate a calibration may give, per axis (fraction): ten times
#: the datasheet's cross-axis tolerance; more is a wrong column, not a gyro.
MAX_GYRO_ALIGNMENT = 0.2


@dataclass(frozen=True)
class VinsOptions:
    """How the sliding-window smoother is built and judged."""

    # --- smoother
    smoother_lag_s: float = option(1.5, gt=0.0, le=30.0, doc="fixed-lag smoother window, "
                                   "seconds: older keyframes and landmarks are marginalised")
    relinearize_threshold: float = option(0.05, gt=0.0, doc="iSAM2 relinearises a variable "
                                          "whose update exceeds this (tangent-space norm)")
    extra_iterations: int = option(0, ge=0, le=10, doc="extra iSAM2 iterations after each "
                                   "keyframe's update (each relinearises what moved)")
    factorization: str = option("cholesky", choices=("cholesky", "qr"), doc="iSAM2's "
                                "elimination: cholesky, or qr (no indeterminate-system rebuilds "
                                "in the sewer's hallway, about 3x the update time)")
    hold_gauge: bool = option(True, doc="hold the window's position and yaw at a keyframe "
                              "inside it, moved to a newer one as the window slides, taken out "
                              "again of every covariance reported (docs/vins.md, the gauge "
                              "hold); false: only the first keyframe's prior holds them, "
                              "fading as it is marginalised")
    covariance_period_s: float = option(0.5, ge=0.0, le=10.0, doc="the odometry's pose "
                                        "covariance is refreshed at most this often, seconds "
                                        "of keyframe time (a marginal takes about a thirtieth "
                                        "of a keyframe's back-end time; 0: at every keyframe)")
    # --- keyframes
    keyframe_interval_s: float = option(0.1, gt=0.0, le=5.0, doc="a frame this long after the "
                                        "last keyframe becomes one, seconds")
    keyframe_min_interval_s: float = option(0.045, ge=0.0, le=5.0, doc="no keyframe sooner "
                                            "than this after the last, seconds")
    keyframe_parallax_px: float = option(10.0, gt=0.0, doc="mean feature displacement since "
                                         "the last keyframe that makes a frame a keyframe "
                                         "sooner, pixels")
    # --- measurement noise
    pixel_sigma: float = option(1.0, gt=0.0, le=20.0, doc="feature position noise, pixels")
    huber_k: float = option(1.345, gt=0.0, doc="Huber threshold on the whitened "
                            "reprojection error (in pixel_sigma units)")
    imu_noise_scale: float = option(2.0, ge=1.0, le=100.0, doc="multiplies the IMU's white-noise"
                                    " densities (datasheet values are optimistic on a vehicle "
                                    "with rotors)")
    gyro_noise_scale: float = option(1.0, ge=1.0, le=1000.0, doc="multiplies the gyro's "
                                     "white-noise density on top of imu_noise_scale (the "
                                     "gyro's unmodelled errors: its cross-axis response, the "
                                     "rotors' vibration; docs/vins.md, \"The gyro's weight\": "
                                     "10 measured, not adopted)")
    imu_bias_walk_scale: float = option(2.0, gt=0.0, le=100.0, doc="multiplies the IMU's bias "
                                        "random-walk densities (docs/vins.md, \"The bias walk "
                                        "at its datasheet value\": 1 measured, not adopted)")
    drag_coefficient: float = option(0.0, ge=0.0, le=5.0, doc="the vehicle's rotor drag "
                                     "per unit mass, 1/s (PX4's EKF2_MCOEF; the simulator's "
                                     "[vehicle] drag): the horizontal specific force then "
                                     "measures the speed, in still air (autonomy/vins/drag.py; "
                                     "0: not used)")
    drag_noise: float = option(0.02, gt=0.0, le=10.0, doc="the drag factor's noise, m/s^2 "
                               "sqrt(s): its sigma over a keyframe interval dt is this over "
                               "sqrt(dt) (the rotors' vibration, averaged)")
    rest_accel_scale_share: float = option(0.0, ge=0.0, le=1.0, doc="the share of the "
                                           "specific force's excess over gravity at the static "
                                           "initialisation taken as the accelerometer's z "
                                           "sensitivity error, divided out of every sample "
                                           "after it; the rest is the bias "
                                           "(autonomy/vins/accel_scale.py: 0.71 for a vehicle "
                                           "PX4 calibrated by hand; 0: all bias)")
    barometer_sigma_m: float = option(0.0, ge=0.0, le=100.0, doc="the flight controller's "
                                      "barometer as a height, one sample's noise in metres "
                                      "(autonomy/vins/barometer.py; 0: not used)")
    barometer_drift_m_per_sqrt_s: float = option(0.02, gt=0.0, le=10.0, doc="how fast the "
                                                 "barometer's height offset may wander, "
                                                 "m/sqrt(s) (the simulator's drift, 0.2 Pa/"
                                                 "sqrt(s), is 0.017)")
    barometer_min_height_m: float = option(1.0, ge=0.0, le=100.0, doc="the barometer is used "
                                           "from this height above the ground the VINS "
                                           "started on, metres: twice PX4's "
                                           "EKF2_GND_MAX_HGT, the rotors' ground effect")
    keyframe_prior_position_sigma: float = option(0.0, ge=0.0, le=100.0, doc="loose prior "
                                                  "on each new keyframe's position at its IMU "
                                                  "prediction, metres (0: none; 0.1 keeps the "
                                                  "smoother from its resets, docs/vins.md)")
    keyframe_prior_rotation_sigma: float = option(0.05, gt=0.0, le=10.0, doc="the same prior's "
                                                  "rotation, radians")
    # --- initial state uncertainty (one sigma)
    prior_tilt_sigma_deg: float = option(1.0, gt=0.0, le=30.0, doc="roll/pitch after static "
                                         "initialisation, degrees")
    gauge_position_sigma: float = option(1e-3, gt=0.0, le=10.0, doc="the prior holding the "
                                         "first keyframe at the world's origin, metres (the "
                                         "gauge: position is unobservable; docs/vins.md, the "
                                         "resets)")
    gauge_yaw_sigma: float = option(1e-3, gt=0.0, le=1.0, doc="the same prior's yaw, radians")
    prior_velocity_sigma: float = option(0.02, gt=0.0, doc="velocity at static "
                                         "initialisation, m/s")
    prior_gyro_bias_sigma: float = option(0.005, gt=0.0, doc="gyro bias after static "
                                          "initialisation, rad/s")
    prior_accel_bias_sigma: float = option(0.1, gt=0.0, doc="accelerometer bias (static "
                                           "initialisation assumes zero), m/s^2")
    reinit_velocity_sigma: float = option(0.5, gt=0.0, doc="velocity after an IMU gap, "
                                          "relocalised on the map, m/s")
    # Measured in the sewer's pipe: the speed is 5-7 % short (0.1 m/s at 1.6 m/s) when the
    # divergence check fires; 0.5 m/s let the new map start at 0.66 of the true scale.
    propagated_velocity_sigma: float = option(
        0.1, gt=0.0, doc="velocity error of the smoother's last state, which an in-flight "
        "re-initialisation propagates with the IMU; grows with the time LOST by "
        "prior_accel_bias_sigma (Vins.reinit_velocity_prior), m/s")
    max_propagated_gap_s: float = option(0.5, ge=0.0, doc="an IMU gap up to this long is "
                                         "bridged by holding the last sample when the VINS "
                                         "re-initialises; after a longer one it re-initialises "
                                         "from what it observes (autonomy/vins/imu_gap.py), "
                                         "seconds")
    max_propagation_disagreement_m: float = option(0.1, gt=0.0, doc="a propagation across "
                                                   "a short IMU gap farther than this from "
                                                   "the pose relocalised on the map is not "
                                                   "restarted from, metres")
    reinit_imu_window_s: float = option(0.2, gt=0.0, doc="IMU samples after a longer gap "
                                        "before the VINS re-initialises, seconds")
    reinit_tilt_sigma_deg: float = option(5.0, gt=0.0, le=30.0, doc="roll/pitch after an "
                                          "IMU gap from the mean specific force, degrees (a "
                                          "vehicle accelerating at 0.9 m/s^2 tilts it by 5)")
    relocalise_min_landmarks: int = option(6, ge=4, doc="landmarks a frame must track, "
                                           "agreeing within max_reprojection_px, to be "
                                           "relocalised on the map after an IMU gap")
    relocalise_window_s: float = option(0.5, gt=0.0, doc="the relocalised poses whose "
                                        "velocity the re-initialisation after an IMU gap "
                                        "starts with, the last this many seconds")
    relocalise_min_poses: int = option(3, ge=2, doc="relocalised poses within "
                                       "relocalise_window_s needed for that velocity")
    still_flow_px: float = option(1.0, gt=0.0, doc="standing still (after an IMU gap, or for "
                                  "a zero-velocity update): the features' median motion over "
                                  "the stretch judged at most this, undistorted pixels")
    still_rate: float = option(0.05, gt=0.0, doc="standing still: the body's mean rate over "
                               "the stretch judged at most this, rad/s")
    still_velocity_sigma: float = option(0.1, gt=0.0, doc="velocity when re-initialised "
                                         "standing still after an IMU gap, m/s")
    # --- zero-velocity update (autonomy.vins.stillness)
    zero_velocity_update: bool = option(True, doc="a keyframe standing still on the ground "
                                        "gets a zero-velocity prior")
    zero_velocity_window_s: float = option(0.5, gt=0.0, le=10.0, doc="standing still is judged "
                                           "over this long before the keyframe, seconds")
    zero_velocity_sigma: float = option(0.01, gt=0.0, le=1.0, doc="the zero-velocity prior's "
                                        "width, m/s")
    # --- landmark gate
    min_observations: int = option(3, ge=2, le=100, doc="keyframes a track must be seen in "
                                   "before it becomes a landmark")
    min_parallax_deg: float = option(2.0, ge=0.0, lt=90.0, doc="least angle between a "
                                     "landmark's viewing rays, degrees")
    max_reprojection_px: float = option(3.0, gt=0.0, doc="largest reprojection error of a "
                                        "triangulated landmark in any of its keyframes, pixels")
    max_observation_px: float = option(1.5, gt=0.0, doc="a landmark's observation further "
                                       "than this from its projection at the IMU-predicted "
                                       "pose (widened by the keyframe's median error, the "
                                       "prediction's own) is not used, and the landmark is "
                                       "retired, pixels")
    max_landmarks: int = option(80, ge=1, le=10000, doc="landmarks the smoother holds at most "
                                "(its update time grows with them); new ones fill the emptiest "
                                "parts of the image first")
    landmark_top_up: bool = option(True, doc="while fewer than half the budget are in view, "
                                   "new landmarks bring the view back to half, with up to 1.5 "
                                   "times the budget held")
    min_depth: float = option(0.2, gt=0.0, doc="nearest landmark depth accepted, metres")
    max_depth: float = option(40.0, gt=0.0, doc="farthest landmark depth accepted, metres")
    # --- camera-IMU time offset (autonomy/vins/time_offset.py, docs/vins.md)
    estimate_time_offset: bool = option(False, doc="estimate the camera's time offset online "
                                        "(its rotation between frames against the gyro's) "
                                        "and correct the frame times by it")
    time_offset_s: float = option(0.0, ge=-0.1, le=0.1, doc="frames are exposed this long "
                                  "before their stamp: the fixed offset, or the estimate's "
                                  "starting value, seconds")
    max_time_offset_s: float = option(0.05, gt=0.0, le=0.1, doc="the estimate stays within "
                                      "plus or minus this, seconds")
    time_offset_window_s: float = option(3.0, ge=0.5, le=30.0, doc="the estimate is fitted "
                                         "to the frame pairs of this long a window, seconds")
    time_offset_pair_s: float = option(0.3, ge=0.05, le=2.0, doc="a frame is paired with one"
                                       " up to this long (and at least half as long) before "
                                       "it, seconds")
    time_offset_min_features: int = option(20, ge=8, le=1000, doc="least features a frame "
                                           "pair must share")
    time_offset_max_sigma_s: float = option(0.001, gt=0.0, le=0.05, doc="the estimate moves "
                                            "only when the window's one-sigma is below this "
                                            "(enough rotational excitation), seconds")
    time_offset_max_step_s: float = option(0.002, gt=0.0, le=0.05, doc="largest change of the "
                                           "estimate per frame, seconds")
    retime_window: bool = option(False, doc="with estimate_time_offset, move the window's "
                                 "keyframes to the times the offset gives their stamps when "
                                 "it moves, the IMU between them preintegrated again (off: "
                                 "measured, docs/vins.md, \"The window moved with the time "
                                 "offset\")")
    takeoff_window_s: float = option(0.0, ge=0.0, le=20.0, doc="with retime_window, the "
                                     "window stops sliding when the vehicle first moves and "
                                     "keeps every keyframe until the time offset is known, the "
                                     "window spanning at most this long, seconds, so that the "
                                     "climb's keyframes are moved to it too (0: the lag alone; "
                                     "docs/vins.md, \"The take-off's window kept open\")")
    # --- the gyro's response to yaw (autonomy/vins/gyro_alignment.py, docs/vins.md)
    estimate_gyro_alignment: bool = option(False, doc="estimate the gyro's response to the "
                                           "yaw rate against the camera's rotation online and "
                                           "correct the gyro by it (needs "
                                           "estimate_time_offset: its frame pairs)")
    gyro_alignment_rates: str = option("yaw", choices=("yaw", "all"), doc="the rates whose "
                                       "responses estimate_gyro_alignment estimates: the yaw "
                                       "rate's alone (three numbers), or all three's (the "
                                       "whole matrix: the roll and pitch rates' responses "
                                       "tilt the gyro's attitude whenever the vehicle "
                                       "pitches; docs/vins.md, \"The gyro's whole "
                                       "misalignment in navigation\")")
    gyro_cross_axis_sigma: float = option(0.014, gt=0.0, le=0.2, doc="sigma of each axis' "
                                          "response to the others' rates (cross-axis "
                                          "sensitivity with the mounting's error), fraction: "
                                          "the estimate's prior, and gyro_axes_noise's weight")
    gyro_scale_sigma: float = option(0.005, gt=0.0, le=0.2, doc="sigma of each axis' scale "
                                     "error, fraction: the estimate's prior (the z axis'), "
                                     "and gyro_axes_noise's weight")
    gyro_axes_noise: bool = option(False, doc="weigh each keyframe interval's gyro less by "
                                   "what the two sigmas above make of its turn, as noise "
                                   "(autonomy/vins/preintegration.py gyro_axes_density; "
                                   "docs/vins.md, \"The gyro's axes as noise\")")
    gyro_axes_noise_axes: str = option("body", choices=("body", "vertical"), doc="the axes "
                                       "gyro_axes_noise weighs the gyro less about: the body's "
                                       "three, or the vertical alone (the heading: the tilt "
                                       "is held by gravity, and a gyro weighed less about it "
                                       "weighs the velocity less; docs/vins.md, \"The gyro's "
                                       "axes about the vertical\")")
    gyro_alignment: tuple[float, ...] = option(
        (0.0, 0.0, 0.0), doc="the gyro's response to the yaw rate (x, y and z axes, fractions), "
        "or its whole misalignment (nine numbers, by rows), calibrated on an earlier flight of "
        "this vehicle (eval vio's gyro_alignment column): the gyro is corrected by it from the "
        "first sample, and with estimate_gyro_alignment it is the estimate's prior mean")
    # --- the camera's mounting (autonomy/vins/backend.py, docs/vins.md)
    estimate_camera_mounting: bool = option(False, doc="estimate the rotation of the camera's "
                                            "mounting on the body in the smoother, from the "
                                            "configured one (its position stays as configured)")
    mounting_rotation_sigma_deg: float = option(1.0, gt=0.0, le=10.0, doc="the estimate's "
                                                "prior: the configured mounting's rotation "
                                                "error, one sigma per axis, degrees")
    # --- health
    min_tracked_ok: int = option(40, ge=0, doc="fewer tracked features than this is DEGRADED")
    min_tracked_lost: int = option(10, ge=0, doc="fewer tracked features than this for "
                                   "lost_after_s is LOST")
    min_landmarks_ok: int = option(15, ge=0, doc="fewer landmarks in the window than this is "
                                   "DEGRADED once the vehicle has moved")
    lost_after_s: float = option(0.5, gt=0.0, doc="how long tracking may starve before LOST, "
                                 "seconds")
    max_speed: float = option(15.0, gt=0.0, doc="a faster velocity estimate is divergence, m/s")
    max_gyro_bias: float = option(0.3, gt=0.0, doc="a larger gyro bias estimate is divergence, "
                                  "rad/s")
    max_accel_bias: float = option(2.0, gt=0.0, doc="a larger accelerometer bias estimate is "
                                   "divergence, m/s^2")
    max_keyframe_correction_m: float = option(
        1.0, gt=0.0, le=1000.0, doc="a keyframe the smoother puts farther than this from the "
        "IMU's propagation of the last one is divergence: the update is dropped and the VINS "
        "is LOST until it re-initialises at the propagation, metres (docs/vins.md)")
    max_imu_gap_s: float = option(0.1, gt=0.0, doc="an IMU gap longer than this before a frame "
                                  "is LOST (nothing to propagate with), seconds")
    degraded_after_reset_s: float = option(1.0, ge=0.0, doc="DEGRADED for this long after a "
                                           "reset, seconds")
    max_update_ms: float = option(50.0, gt=0.0, doc="a back-end update slower than this is "
                                  "DEGRADED, milliseconds")
    moving_speed: float = option(0.2, gt=0.0, doc="speed above which the vehicle counts as "
                                 "moving (landmarks are then expected), m/s")

    def __post_init__(self) -> None:
        validate(self)
        if self.min_depth >= self.max_depth:
            raise OptionError("max_depth", f"must exceed min_depth ({self.min_depth}), "
                              f"got {self.max_depth}")
        if self.keyframe_min_interval_s > self.keyframe_interval_s:
            raise OptionError("keyframe_min_interval_s", "must not exceed keyframe_interval_s "
                              f"({self.keyframe_interval_s}), got {self.keyframe_min_interval_s}")
        if abs(self.time_offset_s) > self.max_time_offset_s:
            raise OptionError("time_offset_s", "must be within plus or minus max_time_offset_s "
                              f"({self.max_time_offset_s}), got {self.time_offset_s}")
        if self.time_offset_pair_s >= self.time_offset_window_s:
            raise OptionError("time_offset_pair_s", "must be shorter than time_offset_window_s"
                              f" ({self.time_offset_window_s}), got {self.time_offset_pair_s}")
        if self.retime_window and not self.estimate_time_offset:
            raise OptionError("retime_window", "needs estimate_time_offset = true (a fixed "
                              "offset never moves)")
        if self.takeoff_window_s > 0.0 and not self.retime_window:
            raise OptionError("takeoff_window_s", "needs retime_window = true (a window kept "
                              "open for the offset is moved to it by the retiming)")
        if 0.0 < self.takeoff_window_s < self.smoother_lag_s:
            raise OptionError("takeoff_window_s", "must be 0 or at least smoother_lag_s "
                              f"({self.smoother_lag_s}), got {self.takeoff_window_s}")
        if self.estimate_gyro_alignment and not self.estimate_time_offset:
            raise OptionError("estimate_gyro_alignment", "needs estimate_time_offset = true "
                              "(the gyro is aligned on the time-offset estimator's frame pairs)")
        if len(self.gyro_alignment) not in (3, 9) or not all(
                math.isfinite(c) and abs(c) <= MAX_GYRO_ALIGNMENT for c in self.gyro_alignment):
            raise OptionError("gyro_alignment", "takes the x, y and z axes' responses to the "
                              "yaw rate, or the whole misalignment by rows (nine numbers), "
                              f"each within +-{MAX_GYRO_ALIGNMENT}, "
                              f"got {list(self.gyro_alignment)}")
        if self.min_tracked_lost > self.min_tracked_ok:
            raise OptionError("min_tracked_lost", "must not exceed min_tracked_ok "
                              f"({self.min_tracked_ok}), got {self.min_tracked_lost}")
