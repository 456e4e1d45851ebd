"""A V4L2 camera (a USB UVC camera, or a CSI camera behind a V4L2 node) read through OpenCV.

``cv2.VideoCapture.read`` blocks until the driver has a frame, so the reader thread and the
newest-frame slot of :class:`~drivers.camera.base.ThreadedCamera` carry it to asyncio.

Timestamps. OpenCV's V4L2 backend reports ``CAP_PROP_POS_MSEC`` as the kernel buffer's
timestamp, taken when the driver received the frame; UVC and most capture drivers stamp it on
CLOCK_MONOTONIC (``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``), the clock ``time.monotonic`` reads on
Linux. So with a :class:`~drivers.clock.MonotonicClock` a frame's ``t`` is that timestamp,
free of the read thread's scheduling delay. With any other clock, or when the device gives no
plausible timestamp (none, or more than :data:`MAX_STAMP_AGE_S` off the arrival time), the
frame is stamped on the given clock when the read returns.

A device that stops delivering is an error, never a hang: :attr:`V4l2Options.max_failed_reads`
failed reads in a row (what an unplugged camera gives), a frame of the wrong size or format, or
no frame at all for :attr:`V4l2Options.frame_timeout_s` make :meth:`V4l2Camera.next_frame`
raise :class:`CameraError` naming the device.
"""

from __future__ import annotations

import fcntl
import logging
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from autonomy.options import option, validate
from drivers.camera.base import CameraError, DeviceInfo, RawFrame, ThreadedCamera
from drivers.camera.options import CameraOptions
from drivers.clock import Clock, MonotonicClock

log = logging.getLogger(__name__)

MAX_STAMP_AGE_S = 1.0
"""A device timestamp further than this from the arrival time is not trusted, seconds."""


@dataclass(frozen=True)
class V4l2Options:
    """Which V4L2 device to read and how; the image size and rate come from CameraOptions.

    ``pixel_format`` is the FOURCC asked of the driver: MJPG gives full rate at 640x480 and
    above over USB 2, YUYV avoids JPEG artefacts where the bandwidth allows; "" keeps the
    driver's default. ``buffers`` is the driver's queue length: 1 gives the lowest latency.
    """

    device: str = option("/dev/video0", doc="V4L2 device node, e.g. /dev/video0 or a udev link")
    pixel_format: str = option("MJPG", choices=("MJPG", "YUYV", ""),
                               doc="FOURCC asked of the driver; '' keeps its default")
    buffers: int = option(1, ge=1, le=8, doc="driver buffer queue length; 1 = lowest latency")
    max_failed_reads: int = option(5, ge=1, le=1000,
                                   doc="failed reads in a row after which the camera is dead")
    frame_timeout_s: float = option(1.0, gt=0.0, le=60.0,
                                    doc="no frame for this long and the camera is dead, s")

    def __post_init__(self) -> None:
        validate(self)


class V4l2Camera(ThreadedCamera):
    """Frames from one V4L2 device (the reader thread and newest-frame slot of
    :class:`~drivers.camera.base.ThreadedCamera`).

    ``async with V4l2Camera(camera, v4l2, clock) as cam: frame = await cam.next_frame()``.
    """

    def __init__(self, camera: CameraOptions, options: V4l2Options, clock: Clock):
        super().__init__(options.device, (camera.width, camera.height), clock,
                         frame_timeout_s=options.frame_timeout_s,
                         max_failed_reads=options.max_failed_reads,
                         retry_wait_s=0.5 / camera.rate_hz)
        self.camera = camera
        self.options = options
        self._warned_stamp = False

    # ---- the device --------------------------------------------------------------------------

    def _open(self):
        """The opened, configured capture. The driver may settle on another size than asked
        (the nearest mode it has), so the size is read back and a mismatch refused here, before
        any consumer sees a frame the camera model does not describe."""
        cam, opt = self.camera, self.options
        capture = cv2.VideoCapture(opt.device, cv2.CAP_V4L2)
        if not capture.isOpened():
            capture.release()
            raise CameraError(f"{opt.device}: cannot open it as a V4L2 camera (does the node "
                              "exist, and is the user in group 'video'?)")
        if opt.pixel_format:
            capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*opt.pixel_format))
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, cam.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, cam.height)
        capture.set(cv2.CAP_PROP_FPS, cam.rate_hz)
        capture.set(cv2.CAP_PROP_BUFFERSIZE, opt.buffers)
        width = round(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = round(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (width, height) != (cam.width, cam.height):
            capture.release()
            raise CameraError(f"{opt.device}: delivers {width}x{height}, the config asks for "
                              f"{cam.width}x{cam.height}; set camera.width and camera.height to "
                              f"a mode it has (v4l2-ctl -d {opt.device} --list-formats-ext)")
        return capture

    def _read(self, capture) -> RawFrame | None:
        try:
            ok, image = capture.read()
        except cv2.error as error:
            raise CameraError(f"OpenCV failed reading: {error}") from None
        if not ok or image is None:
            return None
        arrival = self.clock.now()
        if image.dtype != np.uint8 or image.ndim != 3:
            raise CameraError(f"delivered a {image.dtype} image of shape {image.shape}, "
                              "expected uint8 BGR")
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        return RawFrame(rgb, self._stamp(capture.get(cv2.CAP_PROP_POS_MSEC), arrival))

    def _release(self, capture) -> None:
        capture.release()

    def _stamp(self, pos_msec: float, arrival: float) -> float:
        """The frame time on the companion clock: the kernel's CLOCK_MONOTONIC buffer stamp
        when the clock is that one and the stamp is plausible, else the arrival time."""
        if not isinstance(self.clock, MonotonicClock):
            return arrival
        stamp = pos_msec / 1000.0
        if stamp > 0.0 and -MAX_STAMP_AGE_S <= stamp - arrival <= 0.0:
            return stamp
        if not self._warned_stamp:
            log.warning("%s: buffer timestamp %.3f s is not on CLOCK_MONOTONIC near the arrival "
                        "time %.3f s; stamping frames on arrival", self.name, stamp, arrival)
            self._warned_stamp = True
        return arrival


# ---- discovery (`companion devices`) ---------------------------------------------------------

#: VIDIOC_ENUM_FMT, VIDIOC_ENUM_FRAMESIZES and VIDIOC_QUERYCAP from linux/videodev2.h (64-bit
#: layouts: struct v4l2_fmtdesc is 64 bytes, v4l2_frmsizeenum 44, v4l2_capability 104).
_VIDIOC_QUERYCAP = 0x80685600
_VIDIOC_ENUM_FMT = 0xC0405602
_VIDIOC_ENUM_FRAMESIZES = 0xC02C564A
_V4L2_BUF_TYPE_VIDEO_CAPTURE = 1
_V4L2_CAP_VIDEO_CAPTURE = 0x1
_V4L2_CAP_DEVICE_CAPS = 0x80000000
_V4L2_FRMSIZE_TYPE_DISCRETE = 1


def list_devices(dev: str = "/dev") -> list[DeviceInfo]:
    """The V4L2 capture nodes under ``dev`` with their card name and their discrete modes
    (pixel format and size), read with the kernel's own ioctls; a node that cannot be opened
    (permissions, busy) is listed with the reason instead of its modes."""
    found = []
    for node in sorted(Path(dev).glob("video*"), key=lambda p: (len(p.name), p.name)):
        try:
            fd = os.open(node, os.O_RDWR | os.O_NONBLOCK)
        except OSError as error:
            found.append(DeviceInfo("v4l2", str(node), f"cannot open: {error.strerror}"))
            continue
        try:
            card, capture = _query_capability(fd)
            if capture:  # metadata nodes of the same camera are not cameras
                found.append(DeviceInfo("v4l2", str(node), card, tuple(_modes(fd))))
        except OSError as error:
            found.append(DeviceInfo("v4l2", str(node), f"not a V4L2 device: {error.strerror}"))
        finally:
            os.close(fd)
    return found


def _query_capability(fd: int) -> tuple[str, bool]:
    buffer = bytearray(104)
    fcntl.ioctl(fd, _VIDIOC_QUERYCAP, buffer)
    card = bytes(buffer[16:48]).split(b"\0", 1)[0].decode(errors="replace")
    capabilities, device_caps = struct.unpack_from("II", buffer, 84)
    if capabilities & _V4L2_CAP_DEVICE_CAPS:  # the node's own, not the whole device's
        capabilities = device_caps
    return card, bool(capabilities & _V4L2_CAP_VIDEO_CAPTURE)


def _modes(fd: int) -> list[str]:
    modes = []
    for fmtdesc in _enumerate(fd, _VIDIOC_ENUM_FMT, 64, _V4L2_BUF_TYPE_VIDEO_CAPTURE):
        fourcc = struct.unpack_from("I", fmtdesc, 44)[0]
        name = fourcc.to_bytes(4, "little").decode(errors="replace")
        modes += [f"{w}x{h} {name}" for w, h in _sizes(fd, fourcc)]
    return modes


def _sizes(fd: int, fourcc: int) -> list[tuple[int, int]]:
    sizes = []
    for frmsize in _enumerate(fd, _VIDIOC_ENUM_FRAMESIZES, 44, fourcc):
        kind, width, height = struct.unpack_from("III", frmsize, 8)
        if kind != _V4L2_FRMSIZE_TYPE_DISCRETE:
            break  # a stepwise range: the config may ask for any size in it
        sizes.append((width, height))
    return sizes


def _enumerate(fd: int, request: int, size: int, selector: int):
    """The structs an enumerating ioctl fills for index 0, 1, ... until the driver has no more
    (EINVAL); each struct starts with ``u32 index, u32 selector``."""
    for index in range(64):
        buffer = bytearray(size)
        struct.pack_into("II", buffer, 0, index, selector)
        try:
            fcntl.ioctl(fd, request, buffer)
        except OSError:
            return
        yield buffer
