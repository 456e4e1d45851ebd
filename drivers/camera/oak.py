"""A Luxonis OAK camera (colour or mono sensor) read through depthai's v3 API.

The pipeline is the smallest v3 one (depthai-core ``examples/python/Camera``): a
``dai.node.Camera`` built on the configured board socket, one output requested at
``[camera] width x height @ rate_hz`` (``RGB888i`` for a colour sensor, ``GRAY8`` for a mono
one, whose grey is copied to three channels: the stack takes RGB), read from a non-blocking
host queue by the reader thread of :class:`~drivers.camera.base.ThreadedCamera`. Manual
exposure is set in the camera's ``initialControl`` before the pipeline starts.

Timestamps: ``ImgFrame.getTimestamp()`` is the device's capture time already converted by
depthai to the host's ``std::chrono::steady_clock`` (the device clock is synchronised to the
host's), which on Linux is CLOCK_MONOTONIC, the clock :class:`~drivers.clock.MonotonicClock`
reads. With that clock and a plausible stamp (within :data:`MAX_STAMP_AGE_S` before arrival)
the frame's time is that stamp; otherwise its arrival time, with one warning.

Intrinsics come from the device's factory calibration (``Device.readCalibration()``) for the
requested size: a ``Perspective`` model's 14 OpenCV coefficients become ``radtan`` when only
``k1 k2 p1 p2 k3`` are non-zero (else the lens is refused, naming the terms), a ``Fisheye``
model's first four become ``equidistant`` (OpenCV's fisheye order). Gaps in
``getSequenceNum`` are counted as lost frames. A device that disappears (depthai raises, or
the pipeline stops running) is a failed read, then a :class:`~drivers.camera.base.CameraError`.

depthai is the optional extra ``companion[oak]``; this module imports without it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.lens import CameraModel
from autonomy.options import option, validate
from drivers.camera.base import CameraError, DeviceInfo, RawFrame, ThreadedCamera, import_sdk
from drivers.camera.exposure import check_limit, longest_us
from drivers.camera.options import CameraOptions
from drivers.clock import Clock, MonotonicClock

log = logging.getLogger(__name__)

MAX_STAMP_AGE_S = 1.0
"""A device timestamp further than this before the arrival time is not trusted, seconds."""
SOCKETS = ("CAM_A", "CAM_B", "CAM_C", "CAM_D")
#: Sockets whose sensor is monochrome on OAK-D boards (the stereo pair, global shutter).
MONO_SOCKETS = ("CAM_B", "CAM_C")
POLL_S = 0.002
#: Perspective coefficients beyond radtan's, OpenCV's order after k1 k2 p1 p2 k3.
EXTRA_TERMS = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")


def _sdk():
    """depthai (:func:`~drivers.camera.base.import_sdk`)."""
    return import_sdk("depthai", "oak")


@dataclass(frozen=True)
class OakOptions:
    """Which OAK and sensor to read, and how to expose it (the ``[oak]`` table).

    Manual exposure by default, for the feature tracker (see ``[realsense]``); the OAK-D's
    OV9282 mono sensors are global shutter, its IMX378 colour sensor rolling shutter, which
    is why the presets fly the left mono camera (CAM_B).
    """

    device_id: str = option("", doc="device id (MxId) of the OAK to open; '' = the first found")
    socket: str = option("CAM_B", choices=SOCKETS, doc="board socket: CAM_A colour, CAM_B/"
                                                       "CAM_C the mono pair")
    auto_exposure: bool = option(False, doc="let the camera choose exposure and ISO")
    auto_exposure_limit_us: int = option(0, ge=0, le=33000, doc="longest exposure the "
                                         "auto-exposure may choose, microseconds (the "
                                         "firmware's limit, depthai setAutoExposureLimit); 0: "
                                         "up to a frame period")
    exposure_us: int = option(5000, ge=20, le=33000, doc="manual exposure, microseconds")
    iso: int = option(400, ge=100, le=1600, doc="manual sensitivity (ISO)")
    max_failed_reads: int = option(5, ge=1, le=1000, doc="failed reads in a row after which "
                                                         "the camera is dead")
    frame_timeout_s: float = option(1.0, gt=0.0, le=60.0,
                                    doc="no frame for this long and the camera is dead, s")

    def __post_init__(self) -> None:
        validate(self)
        check_limit(self)

    @property
    def mono(self) -> bool:
        return self.socket in MONO_SOCKETS


@dataclass
class _Stream:
    device: object
    pipeline: object
    queue: object


class OakCamera(ThreadedCamera):
    """Frames of one OAK sensor (module docstring); ``camera_model`` after start."""

    def __init__(self, camera: CameraOptions, options: OakOptions, clock: Clock):
        super().__init__(options.device_id or "OAK", (camera.width, camera.height), clock,
                         frame_timeout_s=options.frame_timeout_s,
                         max_failed_reads=options.max_failed_reads,
                         retry_wait_s=0.5 / camera.rate_hz)
        self.camera, self.options = camera, options
        self.camera_model: CameraModel | None = None
        self._polls = max(1, round(options.frame_timeout_s / POLL_S))
        self._warned_stamp = False

    @property
    def exposure_us(self) -> int | None:
        """The longest a frame is exposed, us (:func:`~drivers.camera.exposure.longest_us`)."""
        return longest_us(self.options)

    def _open(self) -> _Stream:
        dai = _sdk()
        try:
            device = self._device(dai)
        except RuntimeError as error:
            raise CameraError(f"{self.name}: cannot open the OAK ({error})") from None
        try:
            stream = self._start(dai, device)
            self.camera_model = camera_model(dai, device.readCalibration(),
                                             self._socket(dai), self.camera)
            return stream
        except RuntimeError as error:
            device.close()
            raise CameraError(f"{self.name}: {self.options.socket} at {self.camera.width}x"
                              f"{self.camera.height}@{self.camera.rate_hz:g}: {error}") from None
        except CameraError:
            device.close()
            raise

    def _device(self, dai):
        if self.options.device_id:
            return dai.Device(dai.DeviceInfo(self.options.device_id))
        return dai.Device()

    def _socket(self, dai):
        return getattr(dai.CameraBoardSocket, self.options.socket)

    def _start(self, dai, device) -> _Stream:
        cam, opt = self.camera, self.options
        pipeline = dai.Pipeline(device)
        node = pipeline.create(dai.node.Camera).build(self._socket(dai))
        if opt.auto_exposure:
            node.initialControl.setAutoExposureEnable()
            if opt.auto_exposure_limit_us:
                node.initialControl.setAutoExposureLimit(opt.auto_exposure_limit_us)
        else:
            node.initialControl.setManualExposure(opt.exposure_us, opt.iso)
        kind = dai.ImgFrame.Type.GRAY8 if opt.mono else dai.ImgFrame.Type.RGB888i
        output = node.requestOutput((cam.width, cam.height), type=kind, fps=cam.rate_hz)
        queue = output.createOutputQueue(maxSize=4, blocking=False)
        pipeline.start()
        return _Stream(device, pipeline, queue)

    def _read(self, stream: _Stream) -> RawFrame | None:
        for _ in range(self._polls):
            if self._stop.is_set():
                return None
            if not stream.pipeline.isRunning():
                raise CameraError("the OAK pipeline stopped (device disconnected?)")
            frame = stream.queue.tryGet()
            if frame is not None:
                return self._raw(frame)
            time.sleep(POLL_S)
        return None

    def _raw(self, frame) -> RawFrame:
        arrival = self.clock.now()
        image = np.asarray(frame.getFrame())
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        stamp = frame.getTimestamp().total_seconds()
        return RawFrame(np.ascontiguousarray(image), self._stamp(stamp, arrival),
                        int(frame.getSequenceNum()))

    def _stamp(self, stamp: float, arrival: float) -> float:
        if isinstance(self.clock, MonotonicClock) and -MAX_STAMP_AGE_S <= stamp - arrival <= 0.0:
            return stamp
        if isinstance(self.clock, MonotonicClock) and not self._warned_stamp:
            log.warning("%s: device timestamp %.3f s is not near the arrival time %.3f s on "
                        "the host's steady clock; stamping frames on arrival", self.name,
                        stamp, arrival)
            self._warned_stamp = True
        return arrival

    def _release(self, stream: _Stream) -> None:
        stream.pipeline.stop()
        stream.device.close()


def camera_model(dai, calibration, socket, camera: CameraOptions) -> CameraModel:
    """The lens of ``socket`` at the configured size from the device's calibration."""
    K = np.asarray(calibration.getCameraIntrinsics(socket, camera.width, camera.height))
    pinhole = PinholeCamera(camera.width, camera.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    coefficients = [float(c) for c in calibration.getDistortionCoefficients(socket)]
    model = calibration.getDistortionModel(socket)
    if model == dai.CameraModel.Fisheye:
        return CameraModel(pinhole, "equidistant", tuple(coefficients[:4]))
    if model != dai.CameraModel.Perspective:
        raise CameraError(f"the calibration's {model.name} lens model is not supported "
                          "(Perspective or Fisheye); set [camera] calibration = kalibr")
    extra = dict(zip(EXTRA_TERMS, coefficients[5:]))
    used = [name for name, value in extra.items() if abs(value) > 1e-9]
    if used:
        raise CameraError(f"the calibration uses the terms {', '.join(used)}, which radtan "
                          "cannot hold; calibrate with Kalibr and set [camera] calibration = "
                          "kalibr")
    return CameraModel(pinhole, "radtan", tuple((coefficients + [0.0] * 5)[:5]))


def list_devices() -> list[DeviceInfo]:
    """Each OAK depthai finds (id, name, state); its sockets and modes need it opened."""
    dai = _sdk()
    return [DeviceInfo("oak", info.getDeviceId(), f"{info.name} ({info.state.name})",
                       ("sockets and modes: open it, e.g. `companion fly --check`",))
            for info in dai.Device.getAllAvailableDevices()]
