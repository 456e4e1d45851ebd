"""The camera's geometry and rate, as a person writes them in the config."""

from __future__ import annotations

import math
from dataclasses import dataclass

from autonomy.geometry import PinholeCamera
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

    def __post_init__(self) -> None:
        validate(self)

    def pinhole(self) -> PinholeCamera:
        """The intrinsics: square pixels, principal point at the centre."""
        return PinholeCamera.from_hfov(self.width, self.height, math.radians(self.hfov_deg))
