"""What every real camera driver shares: a reader thread and a newest-frame slot for asyncio.

A vendor SDK's read call blocks until the device has a frame, so a dedicated thread reads and
the asyncio side only ever takes the newest frame (DESIGN.md: a stale frame is useless): an
unconsumed frame is replaced by the next one and counted in :attr:`ThreadedCamera.dropped`.
Frames the device itself lost (a gap in its frame counter) are counted apart, in
:attr:`ThreadedCamera.lost`.

A device that stops delivering is an error, never a hang: ``max_failed_reads`` failed reads
in a row, a frame of the wrong size or format, or no frame for ``frame_timeout_s`` make
:meth:`ThreadedCamera.next_frame` raise :class:`CameraError` naming the device. The flight
application turns that into its camera-silent failsafe.

A driver subclasses :class:`ThreadedCamera` and implements three methods, all called on the
reader thread except :meth:`~ThreadedCamera._open` (called in a worker thread by ``start``):

- ``_open()`` opens and configures the device and returns a handle (raise CameraError);
- ``_read(handle)`` blocks for one frame and returns a :class:`RawFrame`, or None when a read
  failed (counted towards ``max_failed_reads``); it raises CameraError for a fatal fault;
- ``_release(handle)`` frees the device.
"""

from __future__ import annotations

import asyncio
import importlib
import logging
import threading
from dataclasses import dataclass

import numpy as np

from autonomy.messages import Frame
from drivers.clock import Clock

log = logging.getLogger(__name__)


class CameraError(RuntimeError):
    """The camera cannot be opened, delivers the wrong thing, or stopped delivering."""


@dataclass(frozen=True)
class RawFrame:
    """One frame as a driver read it: ``rgb`` uint8 (H, W, 3); ``t`` its exposure time on the
    companion clock; ``counter`` the device's frame number (None where it has none), whose
    gaps count frames the device lost."""

    rgb: np.ndarray
    t: float
    counter: int | None = None


class ThreadedCamera:
    """Frames from one device as :class:`~autonomy.messages.Frame` (RGB, companion time).

    ``async with Driver(...) as cam: frame = await cam.next_frame()``. One consumer is
    intended: "newer" is relative to the last frame :meth:`next_frame` returned, whoever asked.
    """

    def __init__(self, name: str, size: tuple[int, int], clock: Clock, *,
                 frame_timeout_s: float, max_failed_reads: int, retry_wait_s: float):
        self._name = name
        self._shape = (size[1], size[0], 3)  # size is (width, height)
        self.clock = clock
        self.frame_timeout_s = frame_timeout_s
        self.max_failed_reads = max_failed_reads
        self.retry_wait_s = retry_wait_s
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._sequence = 0  # frames delivered by the reader
        self._returned = 0  # sequence number of the last frame next_frame returned
        self._dropped = 0
        self._lost = 0
        self._last_counter: int | None = None
        self._error: CameraError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._arrived: asyncio.Event | None = None

    @property
    def name(self) -> str:
        return self._name

    @property
    def dropped(self) -> int:
        """Frames replaced by a newer one before anyone took them."""
        return self._dropped

    @property
    def lost(self) -> int:
        """Frames the device numbered but never delivered (gaps in its frame counter)."""
        return self._lost

    @property
    def delivered(self) -> int:
        """Frames read from the device so far."""
        return self._sequence

    async def __aenter__(self):
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        self.close()

    async def start(self) -> None:
        """Open and configure the device (off the event loop: opening can take seconds) and
        start reading; raises CameraError when it cannot be opened as configured."""
        if self._thread is not None:
            raise CameraError(f"{self.name}: already started")
        self._loop = asyncio.get_running_loop()
        self._arrived = asyncio.Event()
        handle = await asyncio.to_thread(self._open)
        self._thread = threading.Thread(target=self._read_loop, args=(handle,),
                                        name=f"camera {self.name}", daemon=True)
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
                await asyncio.wait_for(self._arrived.wait(), self.frame_timeout_s)
            except asyncio.TimeoutError:
                self._fail(f"no frame for {self.frame_timeout_s:g} s "
                           "(camera stalled or unplugged)")

    def close(self) -> None:
        """Stop reading and release the device; a waiting :meth:`next_frame` raises.

        Waits for a read in progress, up to ``frame_timeout_s`` + 1 s; a read stuck in the
        driver is left to the daemon thread, which releases the device when it returns."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=self.frame_timeout_s + 1.0)
        with self._lock:
            if self._error is None:
                self._error = CameraError(f"{self.name}: closed")
        self._wake()

    # ---- what a driver implements ------------------------------------------------------------

    def _open(self):
        raise NotImplementedError

    def _read(self, handle) -> RawFrame | None:
        raise NotImplementedError

    def _release(self, handle) -> None:
        raise NotImplementedError

    # ---- the reader thread -------------------------------------------------------------------

    def _read_loop(self, handle) -> None:
        """Read until stopped or failed; the thread owns ``handle`` and releases it."""
        failures = 0
        try:
            while not self._stop.is_set():
                raw = self._read(handle)
                if raw is None and self._stop.is_set():
                    return  # closed during the read: not a failure of the device
                if raw is None:
                    failures += 1
                    if failures >= self.max_failed_reads:
                        self._fail(f"{failures} reads in a row failed (unplugged or dead?)")
                        return
                    self._stop.wait(self.retry_wait_s)
                    continue
                failures = 0
                self._deliver(raw)
        except CameraError as error:
            self._fail(str(error))
        except Exception as error:  # noqa: BLE001 - an SDK fault must reach the consumer
            self._fail(f"{type(error).__name__} while reading: {error}")
        finally:
            try:
                self._release(handle)
            except Exception as error:  # noqa: BLE001 - a device gone cannot be released
                log.warning("%s: release failed: %s", self.name, error)

    def _wait_until_taken(self, poll_s: float) -> None:
        """Hold the reader until the consumer took the last frame (or the camera closes): a
        recording's reader hands over every frame, at the consumer's pace."""
        while not self._stop.is_set():
            with self._lock:
                if self._returned >= self._sequence:
                    return
            self._stop.wait(poll_s)

    def _deliver(self, raw: RawFrame) -> None:
        """Check the frame against the configured mode and put it in the slot."""
        image = raw.rgb
        if image.dtype != np.uint8 or image.shape != self._shape:
            raise CameraError(f"delivered a {image.dtype} image of shape {image.shape}, "
                              f"expected uint8 {self._shape}")
        image.setflags(write=False)
        with self._lock:
            if raw.counter is not None and self._last_counter is not None:
                self._lost += max(0, raw.counter - self._last_counter - 1)
            if raw.counter is not None:
                self._last_counter = raw.counter
            if self._sequence > self._returned:
                self._dropped += 1
            self._frame = Frame(raw.t, image, counter=raw.counter)
            self._sequence += 1
        self._wake()

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


@dataclass(frozen=True)
class DeviceInfo:
    """One device ``companion devices`` found: its ``kind`` (v4l2, realsense, oak, serial),
    the ``address`` a config names it by (a node path, a serial number, a device id), a
    human ``description``, and what it supports (``modes``: e.g. "640x480@30 RGB8")."""

    kind: str
    address: str
    description: str
    modes: tuple[str, ...] = ()


class MissingExtra(CameraError):
    """A vendor SDK that is not installed; the message names the extra that installs it."""

    def __init__(self, sdk: str, extra: str):
        super().__init__(f"{sdk} is not installed: pip install 'companion[{extra}]'")
        self.sdk, self.extra = sdk, extra


def import_sdk(module: str, extra: str):
    """The vendor SDK ``module``, imported when first used so that a driver's module imports
    without its extra. :class:`MissingExtra` when it is not installed; a :class:`CameraError`
    with the loader's own words when it is but does not load (pyrealsense2's wheel without the
    system's libusb-1.0: "not installed" would send the user to pip for nothing)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as error:
        if error.name == module:
            raise MissingExtra(module, extra) from None
        raise CameraError(f"{module} is installed but does not load: {error}") from error
    except ImportError as error:
        raise CameraError(f"{module} is installed but does not load: {error}") from error
