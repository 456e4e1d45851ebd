"""The part of depthai's v3 API that drivers/camera/oak.py calls, for tests without an OAK.

Only the vendor boundary is faked: names and call shapes are depthai's (checked against the
real module by tests/test_camera_oak.py where depthai is installed). A test configures the
device through the module-level ``DEVICE`` (frames, calibration, faults).
"""

from __future__ import annotations

import datetime
import enum
import time
import types
from dataclasses import dataclass, field

import numpy as np


class CameraBoardSocket(enum.Enum):
    CAM_A = 0
    CAM_B = 1
    CAM_C = 2
    CAM_D = 3


class CameraModel(enum.Enum):
    Perspective = 0
    Fisheye = 1
    Equirectangular = 2


class XLinkDeviceState(enum.Enum):
    X_LINK_UNBOOTED = 1


@dataclass
class FakeOak:
    """What the one fake device does: ``frames`` delivered per second of wall time,
    ``sequence`` numbers (gaps = frames the device lost), ``dies_after`` frames then the
    pipeline stops; the calibration of every socket."""

    rate_hz: float = 200.0
    sequence: list[int] = field(default_factory=lambda: list(range(10_000)))
    dies_after: int | None = None
    stamp_offset_s: float = -0.005  # capture this long before the host sees the frame
    model: CameraModel = CameraModel.Perspective
    coefficients: list[float] = field(default_factory=lambda: [-0.1, 0.02, 0.001, -0.001, 0.0]
                                      + [0.0] * 9)
    ids: tuple[str, ...] = ("14442C10D13EABCE00",)
    requested: dict = field(default_factory=dict)
    controls: list = field(default_factory=list)
    closed: bool = False


DEVICE = FakeOak()


class DeviceInfo:
    def __init__(self, device_id: str = ""):
        if device_id and device_id not in DEVICE.ids:
            raise RuntimeError(f"No available devices ({device_id})")
        self._id = device_id or DEVICE.ids[0]
        self.name = "1.2.3"
        self.state = XLinkDeviceState.X_LINK_UNBOOTED

    def getDeviceId(self) -> str:
        return self._id


class CalibrationHandler:
    def getCameraIntrinsics(self, socket, width, height):
        return [[0.5 * width, 0.0, width / 2], [0.0, 0.5 * width, height / 2], [0.0, 0.0, 1.0]]

    def getDistortionCoefficients(self, socket):
        return list(DEVICE.coefficients)

    def getDistortionModel(self, socket):
        return DEVICE.model


class Device:
    def __init__(self, info: DeviceInfo | None = None):
        if not DEVICE.ids:
            raise RuntimeError("No available devices")
        self.info = info or DeviceInfo()

    def readCalibration(self) -> CalibrationHandler:
        return CalibrationHandler()

    def close(self) -> None:
        DEVICE.closed = True

    @staticmethod
    def getAllAvailableDevices() -> list[DeviceInfo]:
        return [DeviceInfo(i) for i in DEVICE.ids]


class ImgFrame:
    class Type(enum.Enum):
        RGB888i = 0
        GRAY8 = 1

    def __init__(self, image: np.ndarray, stamp: float, sequence: int):
        self._image, self._stamp, self._sequence = image, stamp, sequence

    def getFrame(self) -> np.ndarray:
        return self._image

    def getTimestamp(self) -> datetime.timedelta:
        return datetime.timedelta(seconds=self._stamp)

    def getSequenceNum(self) -> int:
        return self._sequence


class CameraControl:
    def setManualExposure(self, exposure_us: int, iso: int) -> "CameraControl":
        DEVICE.controls.append(("manual", exposure_us, iso))
        return self

    def setAutoExposureEnable(self) -> "CameraControl":
        DEVICE.controls.append(("auto",))
        return self

    def setAutoExposureLimit(self, max_exposure_us: int) -> "CameraControl":
        DEVICE.controls.append(("auto limit", max_exposure_us))
        return self


class MessageQueue:
    def __init__(self, size, kind, pipeline):
        self.size, self.kind, self.pipeline = size, kind, pipeline
        self.index, self.next_t = 0, time.monotonic()

    def tryGet(self):
        if not self.pipeline.running:
            raise RuntimeError("Communication exception - possible device error/misconfiguration")
        if time.monotonic() < self.next_t:
            return None
        self.next_t += 1.0 / DEVICE.rate_hz
        if DEVICE.dies_after is not None and self.index >= DEVICE.dies_after:
            self.pipeline.running = False
            return None
        width, height = self.size
        shape = (height, width) if self.kind == ImgFrame.Type.GRAY8 else (height, width, 3)
        sequence = DEVICE.sequence[self.index]
        image = np.full(shape, sequence % 256, np.uint8)
        self.index += 1
        return ImgFrame(image, time.monotonic() + DEVICE.stamp_offset_s, sequence)


class Output:
    def __init__(self, pipeline, size, kind):
        self.pipeline, self.size, self.kind = pipeline, size, kind

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = False) -> MessageQueue:
        return MessageQueue(self.size, self.kind, self.pipeline)


class Camera:
    def __init__(self, pipeline):
        self.pipeline = pipeline
        self.initialControl = CameraControl()

    def build(self, boardSocket=None):
        self.socket = boardSocket
        return self

    def requestOutput(self, size, type=None, fps=None):  # noqa: A002 - depthai's name
        if size[0] > 1920:
            raise RuntimeError(f"No sensor config can produce {size[0]}x{size[1]}")
        DEVICE.requested.update(socket=self.socket, size=size, type=type, fps=fps)
        return Output(self.pipeline, size, type)


node = types.SimpleNamespace(Camera=Camera)


class Pipeline:
    def __init__(self, device: Device):
        self.device, self.running = device, False

    def create(self, kind):
        return kind(self)

    def start(self) -> None:
        self.running = True

    def stop(self) -> None:
        self.running = False

    def isRunning(self) -> bool:
        return self.running
