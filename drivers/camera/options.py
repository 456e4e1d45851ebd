"""The camera's geometry and rate, as a person writes them in the config.

Where the intrinsics come from is ``calibration``: ``"config"`` (the keys here: ``fx``...,
or an ideal pinhole of ``hfov_deg`` when ``fx`` is 0), ``"device"`` (the camera's own factory
calibration, read by its driver: a RealSense or an OAK) or ``"kalibr"`` (a Kalibr
``camchain-imucam.yaml``: intrinsics, distortion, the camera-IMU extrinsics and time offset,
replacing ``mount_*`` and ``time_offset_s``). :mod:`drivers.camera.calibration` resolves them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.lens import DISTORTION_MODELS, CameraModel
from autonomy.options import OptionError, option, validate

DRIVERS = ("v4l2", "realsense", "oak")
CALIBRATION_SOURCES = ("config", "device", "kalibr")


@dataclass(frozen=True)
class CameraOptions:
    """The forward camera: its driver and mode, its lens, and where it sits on the body.

    The defaults are an ideal pinhole the size of a RealSense D455's colour stream: 640x480 at
    about 90 degrees horizontal field of view (the simulator's camera).
    """

    driver: str = option("v4l2", choices=DRIVERS, doc="which camera `companion fly` reads: "
                         "v4l2 ([v4l2]), realsense ([realsense]) or oak ([oak])")
    width: int = option(640, ge=16, le=8192, doc="image width, pixels")
    height: int = option(480, ge=16, le=8192, doc="image height, pixels")
    hfov_deg: float = option(90.0, gt=10.0, lt=170.0, doc="horizontal field of view, degrees")
    rate_hz: float = option(20.0, gt=0.0, le=120.0, doc="frames per second")
    calibration: str = option(
        "config", choices=CALIBRATION_SOURCES,
        doc="where intrinsics come from: config (fx, fy, cx, cy, distortion here), device "
            "(the camera's factory calibration), kalibr (kalibr_file)")
    fx: float = option(0.0, ge=0.0, doc="focal length along x, pixels; 0: from hfov_deg")
    fy: float = option(0.0, ge=0.0, doc="focal length along y, pixels; 0: equal to fx")
    cx: float = option(0.0, ge=0.0, doc="principal point x, pixels; 0: the image centre")
    cy: float = option(0.0, ge=0.0, doc="principal point y, pixels; 0: the image centre")
    distortion_model: str = option("none", choices=tuple(DISTORTION_MODELS),
                                   doc="lens model: none, radtan (k1 k2 p1 p2 [k3]) or "
                                       "equidistant (k1 k2 k3 k4, a fisheye)")
    distortion: tuple[float, ...] = option((), doc="the lens model's coefficients, in "
                                           "Kalibr's and OpenCV's order")
    rectified_hfov_deg: float = option(
        0.0, ge=0.0, lt=170.0, doc="horizontal field of view of the pinhole image the stack "
                                  "works on; 0: keep the lens's focal length (set it for a "
                                  "fisheye, whose whole view no pinhole image holds)")
    kalibr_file: str = option("", doc="Kalibr camchain-imucam.yaml (calibration = kalibr)")
    kalibr_camera: str = option("cam0", doc="the camera's entry in kalibr_file")
    kalibr_imu_frame: str = option(
        "flu", choices=("flu", "frd"),
        doc="axes of the IMU Kalibr was given: flu (MAVROS imu/data_raw, ROS) or frd (PX4's "
            "own body frame, e.g. from a ulog)")
    time_offset_s: float = option(
        0.0, ge=-0.5, le=0.5, doc="added to each frame's time to put it on the IMU's clock "
                                  "(Kalibr's timeshift_cam_imu: t_imu = t_cam + shift)")
    stamps_from_counter: bool = option(
        False, doc="stamp each frame at its counter's place on the camera's frame grid (a line "
                   "fitted to the last frames' counters and stamps) rather than when it "
                   "arrived: takes out a host-stamped camera's jitter "
                   "(drivers/camera/stamps.py); a frame with no counter keeps its stamp")
    mount_x: float = option(0.10, ge=-2.0, le=2.0, doc="camera centre ahead of the body "
                            "origin (the IMU / flight controller), metres")
    mount_y: float = option(0.0, ge=-2.0, le=2.0, doc="camera centre left of the body "
                            "origin, metres")
    mount_z: float = option(0.05, ge=-2.0, le=2.0, doc="camera centre above the body origin, "
                            "metres")
    mount_roll_deg: float = option(0.0, ge=-90.0, le=90.0, doc="camera rolled about the body's "
                                   "x axis, degrees (right-handed: positive lowers its left)")
    mount_pitch_deg: float = option(0.0, ge=-90.0, le=90.0, doc="camera tilted about the "
                                    "body's y axis, degrees (positive looks down)")
    mount_yaw_deg: float = option(0.0, ge=-180.0, le=180.0, doc="camera turned about the "
                                  "body's z axis, degrees (positive looks left)")
    learned_time_offset_file: str = option("", doc="where `companion fly` keeps the "
                                           "camera-IMU time offset a flight estimated, for the "
                                           "next flight of this camera to start from (relative:"
                                           " to the working directory); \"\" = not kept")
    learned_gyro_alignment_file: str = option("", doc="where `companion fly` keeps the gyro's "
                                              "response to the yaw rate a flight estimated "
                                              "([vins] estimate_gyro_alignment), which every "
                                              "later flight of this camera is corrected by "
                                              "(relative: to the working directory); \"\" = "
                                              "not kept")

    def __post_init__(self) -> None:
        validate(self)
        if self.calibration == "kalibr" and not self.kalibr_file:
            raise OptionError("kalibr_file", "calibration = kalibr needs the path of Kalibr's "
                              "camchain-imucam.yaml")
        if self.calibration == "config":
            try:
                self.model()
            except ValueError as error:
                raise OptionError("distortion", str(error)) from None

    def T_B_C(self) -> np.ndarray:
        """The camera's optical frame (x right, y down, z along the view) in the body frame
        (x forward, y left, z up): ``R = Rz(yaw) Ry(pitch) Rx(roll) R_BODY_CAMERA`` at
        ``(mount_x, mount_y, mount_z)``; the defaults are the simulator's mounting, level,
        10 cm ahead and 5 cm above the body origin."""
        tilt = (rot_z(math.radians(self.mount_yaw_deg))
                @ so3_exp(np.array([0.0, math.radians(self.mount_pitch_deg), 0.0]))
                @ so3_exp(np.array([math.radians(self.mount_roll_deg), 0.0, 0.0])))
        return make_pose(tilt @ R_BODY_CAMERA,
                         np.array([self.mount_x, self.mount_y, self.mount_z]))

    def pinhole(self) -> PinholeCamera:
        """The configured intrinsics: ``fx``, ``fy``, ``cx``, ``cy`` where given, else square
        pixels across ``hfov_deg`` and the principal point at the image centre."""
        ideal = PinholeCamera.from_hfov(self.width, self.height, math.radians(self.hfov_deg))
        fx = self.fx or ideal.fx
        return PinholeCamera(self.width, self.height, fx, self.fy or fx,
                             self.cx or ideal.cx, self.cy or ideal.cy)

    def model(self) -> CameraModel:
        """The lens as the config describes it (``calibration = "config"``)."""
        return CameraModel(self.pinhole(), self.distortion_model, self.distortion)
