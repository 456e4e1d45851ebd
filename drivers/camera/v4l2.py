"""A V4L2 camera (a USB UVC camera, or a CSI camera behind a V4L2 node) read through OpenCV.

``cv2.VideoCapture.read`` blocks until the driver has a frame, so a dedicated thread reads and
the asyncio side only ever takes the newest frame (DESIGN.md: a stale frame is useless): an
unconsumed frame is replaced by the next one and counted in :attr:`V4l2Camera.dropped`.

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

import asyncio
import logging
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from autonomy.messages import Frame
from autonomy.options import option, validate
from drivers.camera.options import CameraOptions
from drivers.clock import Clock, MonotonicClock

log = logging.getLogger(__name__)

MAX_STAMP_AGE_S = 1.0
"""A device timestamp further than this from the arrival time is not trusted, seconds."""


class CameraError(RuntimeError):
    """The camera cannot be opened, delivers the wrong thing, or stopped delivering."""


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


class V4l2Camera:
    """Frames from one V4L2 device as :class:`~autonomy.messages.Frame` (RGB, companion time).

    ``async with V4l2Camera(camera, v4l2, clock) as cam: frame = await cam.next_frame()``.
    One consumer is intended: "newer" is relative to the last frame :meth:`next_frame`
    returned, whoever asked for it.
    """

    def __init__(self, camera: CameraOptions, options: V4l2Options, clock: Clock):
        self.camera = camera
        self.options = options
        self.clock = clock
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._sequence = 0  # frames delivered by the reader
        self._returned = 0  # sequence number of the last frame next_frame returned
        self._dropped = 0
        self._error: CameraError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._arrived: asyncio.Event | None = None
        self._warned_stamp = False

    @property
    def name(self) -> str:
        return self.options.device

    @property
    def dropped(self) -> int:
        """Frames replaced by a newer one before anyone took them."""
        return self._dropped

    @property
    def delivered(self) -> int:
        """Frames read from the device so far."""
        return self._sequence

    async def __aenter__(self) -> V4l2Camera:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        self.close()

    async def start(self) -> None:
        """Open and configure the device (off the event loop: opening can take a second) and
        start reading; raises CameraError when it cannot be opened or will not give the
        configured size."""
        if self._thread is not None:
            raise CameraError(f"{self.name}: already started")
        self._loop = asyncio.get_running_loop()
        self._arrived = asyncio.Event()
        capture = await asyncio.to_thread(self._open)
        self._thread = threading.Thread(target=self._read_loop, args=(capture,),
                                        name=f"v4l2 {self.name}", daemon=True)
        self._thread.start()

    async def next_frame(self) -> Frame:
        """The newest frame, waiting for one newer than the last returned; raises CameraError
        when the device failed, timed out or was closed."""
        if self._arrived is None:
            raise CameraError(f"{self.name}: not started")
        while True:
            self._arrived.clear()
            with self._lock:
                if self._error is not None:
                    raise self._error
                if self._sequence > self._returned:
                    self._returned = self._sequence
                    return self._frame
            try:
                await asyncio.wait_for(self._arrived.wait(), self.options.frame_timeout_s)
            except asyncio.TimeoutError:
                self._fail(f"no frame for {self.options.frame_timeout_s:g} s "
                           "(camera stalled or unplugged)")

    def close(self) -> None:
        """Stop reading and release the device; a waiting :meth:`next_frame` raises.

        Waits for a read in progress, up to ``frame_timeout_s`` + 1 s; a read stuck in the
        driver is left to the daemon thread, which releases the device when it returns."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.options.frame_timeout_s + 1.0)
        with self._lock:
            if self._error is None:
                self._error = CameraError(f"{self.name}: closed")
        self._wake()

    # ---- the reader thread -------------------------------------------------------------------

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

    def _read_loop(self, capture) -> None:
        """Read until stopped or failed; the thread owns ``capture`` and releases it."""
        failures = 0
        try:
            while not self._stop.is_set():
                ok, image = capture.read()
                if not ok or image is None:
                    failures += 1
                    if failures >= self.options.max_failed_reads:
                        self._fail(f"{failures} reads in a row failed (unplugged or dead?)")
                        return
                    self._stop.wait(0.5 / self.camera.rate_hz)
                    continue
                failures = 0
                arrival = self.clock.now()
                want = (self.camera.height, self.camera.width, 3)
                if image.dtype != np.uint8 or image.shape != want:
                    self._fail(f"delivered a {image.dtype} image of shape {image.shape}, "
                               f"expected uint8 {want}")
                    return
                rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                rgb.setflags(write=False)
                frame = Frame(self._stamp(capture.get(cv2.CAP_PROP_POS_MSEC), arrival), rgb)
                with self._lock:
                    if self._sequence > self._returned:
                        self._dropped += 1
                    self._frame = frame
                    self._sequence += 1
                self._wake()
        except cv2.error as error:
            self._fail(f"OpenCV failed reading: {error}")
        finally:
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

    def _fail(self, reason: str) -> None:
        """Record the first failure, for next_frame to raise, and wake it."""
        with self._lock:
            if self._error is None:
                self._error = CameraError(f"{self.name}: {reason}")
                log.error("%s", self._error)
        self._stop.set()
        self._wake()

    def _wake(self) -> None:
        """Set the asyncio event from whichever thread we are on."""
        if self._loop is None or self._arrived is None or self._loop.is_closed():
            return
        try:
            self._loop.call_soon_threadsafe(self._arrived.set)
        except RuntimeError:  # the loop closed between the check and the call
            pass
