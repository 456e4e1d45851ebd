"""The camera's calibration from wherever the config says, and frames the stack can use.

:func:`resolve` picks the lens, the camera-body extrinsics and the camera-IMU time offset from
``[camera] calibration`` (the config's keys, the device's factory calibration, or a Kalibr
camchain). :class:`CalibratedCamera` wraps any camera driver so that every frame the VINS, the
depth network and the planner see is rectified onto one ideal pinhole and stamped on the IMU's
clock: one geometry for the whole stack.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.lens import CameraModel, Rectifier
from autonomy.messages import Frame
from drivers.camera.base import CameraError
from drivers.camera.kalibr import KalibrError, read_camchain
from drivers.camera.options import CameraOptions
from drivers.camera.stamps import GridStamps

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraCalibration:
    """The camera as calibrated: ``model`` the lens of the raw frames, ``rectified`` the ideal
    pinhole of the frames the stack sees, ``T_B_C`` the optical frame in the body frame (FLU),
    ``time_offset_s`` added to frame times to put them on the IMU's clock, ``source`` where the
    intrinsics came from (for the logs and ``fly --check``)."""

    model: CameraModel
    rectified: PinholeCamera
    T_B_C: np.ndarray
    time_offset_s: float
    source: str


def grid_stamps(camera: CameraOptions) -> GridStamps | None:
    """The frame-grid stamps ``[camera] stamps_from_counter`` asks for, None when off."""
    return GridStamps.for_rate(camera.rate_hz) if camera.stamps_from_counter else None


def resolve(camera: CameraOptions, device_model: CameraModel | None = None) -> CameraCalibration:
    """The calibration ``[camera]`` asks for; ``device_model`` is what the opened camera's
    driver read from the device (None for a camera that carries none, as V4L2 cameras).
    Raises :class:`CameraError` saying what to fix."""
    if camera.calibration == "kalibr":
        try:
            chain = read_camchain(camera.kalibr_file, camera.kalibr_camera,
                                  camera.kalibr_imu_frame)
        except KalibrError as error:
            raise CameraError(f"[camera] kalibr_file: {error}") from None
        model, T_B_C, offset = chain.model, chain.T_B_C, chain.time_offset_s
        source = f"kalibr {camera.kalibr_file} {camera.kalibr_camera}"
    elif camera.calibration == "device":
        if device_model is None:
            raise CameraError(f"the {camera.driver} camera carries no calibration; set [camera] "
                              "calibration = config (fx, fy, cx, cy, distortion) or kalibr")
        model, T_B_C, offset = device_model, camera.T_B_C(), camera.time_offset_s
        source = f"device ({camera.driver})"
    else:
        model, T_B_C, offset = camera.model(), camera.T_B_C(), camera.time_offset_s
        source = "config"
    size = (model.pinhole.width, model.pinhole.height)
    if size != (camera.width, camera.height):
        raise CameraError(f"the calibration ({source}) is for {size[0]}x{size[1]} images, "
                          f"[camera] asks for {camera.width}x{camera.height}")
    return CameraCalibration(model, model.rectified(camera.rectified_hfov_deg), T_B_C, offset,
                             source)


class CalibratedCamera:
    """A camera driver whose frames (and a simulated camera's true depth) come rectified onto
    ``calibration.rectified`` and shifted by ``calibration.time_offset_s``, each first
    stamped on the camera's frame grid by ``stamps`` where given
    (:class:`~drivers.camera.stamps.GridStamps`). Everything else (``name``, ``dropped``,
    ``close``...) is the wrapped driver's."""

    def __init__(self, camera, calibration: CameraCalibration,
                 stamps: GridStamps | None = None):
        self._camera = camera
        self.calibration, self.stamps = calibration, stamps
        model = calibration.model
        needs_resampling = not model.is_pinhole or model.pinhole != calibration.rectified
        self._rectify = Rectifier(model, calibration.rectified) if needs_resampling else None
        log.info("camera %s: %s lens from %s, frames %s", getattr(camera, "name", "?"),
                 model.distortion, calibration.source,
                 "rectified" if self._rectify else "used as they come")

    def __getattr__(self, name: str):
        return getattr(self._camera, name)

    async def next_frame(self) -> Frame:
        frame = await self._camera.next_frame()
        t = frame.t if self.stamps is None else self.stamps.stamp(frame.t, frame.counter)
        shifted = replace(frame, t=t + self.calibration.time_offset_s)
        if self._rectify is None:
            return shifted
        truth = frame.truth_depth  # a simulated camera's, aligned with its image
        return replace(shifted, image=self._rectify(frame.image),
                       truth_depth=None if truth is None else self._rectify.depth(truth))
