"""The camera's geometry and rate, as a person writes them in the config."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.options import option, validate


@dataclass(frozen=True)
class CameraOptions:
    """An undistorted pinhole camera looking along the body's x axis.

    The defaults are those of a RealSense D455's colour stream: 640x480 at about 90 degrees
    horizontal field of view.
    """

    width: int = option(640, ge=16, le=8192, doc="image width, pixels")
    height: int = option(480, ge=16, le=8192, doc="image height, pixels")
    hfov_deg: float = option(90.0, gt=10.0, lt=170.0, doc="horizontal field of view, degrees")
    rate_hz: float = option(20.0, gt=0.0, le=120.0, doc="frames per second")
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

    def __post_init__(self) -> None:
        validate(self)

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
        """The intrinsics: square pixels, principal point at the centre."""
        return PinholeCamera.from_hfov(self.width, self.height, math.radians(self.hfov_deg))
