"""The V4L2 camera driver against a fake at the vendor boundary: cv2.VideoCapture is replaced by
a small class with OpenCV's surface (isOpened, read, get, set, release) that generates images,
so everything of the driver above that line runs as on the vehicle."""

import asyncio
import threading
import time

import cv2
import numpy as np
import pytest

from autonomy.options import OptionError
from drivers.camera.options import CameraOptions
from drivers.camera.v4l2 import CameraError, V4l2Camera, V4l2Options
from drivers.clock import MonotonicClock, SimClock

CAMERA = CameraOptions(width=64, height=48, rate_hz=100.0)


class FakeCapture:
    """A camera at ``period`` seconds per frame delivering BGR images whose blue channel is 255
    and green channel the frame's index (mod 256); behaviour set by the class attributes."""

    opens = True
    delivered_size = None  # (w, h) the "driver" settles on; None = whatever was asked
    period = 0.002
    fail_after = None  # read() returns (False, None) from this frame index on
    hang_after = None  # read() blocks from this frame index until `unblock` is set
    wrong_shape_after = None
    stamp_age_ms = 5.0  # CAP_PROP_POS_MSEC is CLOCK_MONOTONIC this long before read() returns
    unblock = threading.Event()
    last = None

    def __init__(self, device, api=None):
        self.device, self.api = device, api
        self.props = {}
        self.index = 0
        self.stamp_ms = 0.0
        self.released = False
        FakeCapture.last = self

    def isOpened(self):
        return self.opens and not self.released

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            if self.delivered_size is not None:
                return float(self.delivered_size[prop == cv2.CAP_PROP_FRAME_HEIGHT])
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.stamp_ms
        return float(self.props.get(prop, 0.0))

    def read(self):
        time.sleep(self.period)
        if self.hang_after is not None and self.index >= self.hang_after:
            self.unblock.wait(10.0)
            return False, None
        if self.fail_after is not None and self.index >= self.fail_after:
            return False, None
        w = int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        h = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT])
        if self.wrong_shape_after is not None and self.index >= self.wrong_shape_after:
            h //= 2
        image = np.zeros((h, w, 3), np.uint8)
        image[..., 0] = 255
        image[..., 1] = self.index % 256
        self.index += 1
        self.stamp_ms = time.monotonic() * 1000.0 - self.stamp_age_ms
        return True, image

    def release(self):
        self.released = True


@pytest.fixture
def fake(monkeypatch):
    """The fake installed as cv2.VideoCapture; returns a subclass whose attributes a test sets."""
    cls = type("Fake", (FakeCapture,), {"unblock": threading.Event()})
    monkeypatch.setattr(cv2, "VideoCapture", cls)
    yield cls
    cls.unblock.set()


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, 10.0))


def index(frame):
    return int(frame.image[0, 0, 1])


def test_frames_are_rgb_of_the_configured_size_and_device(fake):
    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(device="/dev/video7"), SimClock(3.0)) as cam:
            return await cam.next_frame()

    frame = run(scenario())
    assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
    assert np.all(frame.image[..., 0] == 0) and np.all(frame.image[..., 2] == 255)  # BGR -> RGB
    assert not frame.image.flags.writeable and frame.truth_depth is None
    assert frame.t == 3.0  # not a MonotonicClock: stamped on the given clock at arrival
    assert fake.last.device == "/dev/video7" and fake.last.api == cv2.CAP_V4L2
    assert fake.last.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"MJPG")
    assert fake.last.props[cv2.CAP_PROP_FPS] == 100.0
    assert fake.last.props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert fake.last.released  # closed on leaving the context


def test_next_frame_gives_the_newest_and_counts_the_dropped(fake):
    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(), MonotonicClock()) as cam:
            seen = [index(await cam.next_frame())]
            await asyncio.sleep(0.1)  # the consumer is busy; about 50 frames arrive meanwhile
            for _ in range(5):
                seen.append(index(await cam.next_frame()))
            pending = int(cam.delivered > len(seen) + cam.dropped)
            return seen, cam.dropped, cam.delivered, pending

    seen, dropped, delivered, pending = run(scenario())
    assert all(b > a for a, b in zip(seen, seen[1:])), seen  # always newer, never repeated
    assert seen[1] - seen[0] > 5 and dropped >= seen[1] - seen[0] - 1
    assert delivered == len(seen) + dropped + pending  # every frame returned, dropped or pending


def test_monotonic_clock_takes_the_kernel_buffer_timestamp(fake):
    fake.stamp_age_ms = 30.0

    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(), MonotonicClock()) as cam:
            frame = await cam.next_frame()
            return frame.t, fake.last.stamp_ms / 1000.0, time.monotonic()

    t, stamp, now = run(scenario())
    assert t <= now - 0.03
    assert t == pytest.approx(stamp, abs=0.05)  # the frame's stamp, or a later one's


def test_implausible_buffer_timestamp_falls_back_to_arrival(fake):
    fake.stamp_age_ms = -3.6e6  # an hour in the future: not CLOCK_MONOTONIC

    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(), MonotonicClock()) as cam:
            before = time.monotonic()
            frame = await cam.next_frame()
            return before, frame.t, time.monotonic()

    before, t, after = run(scenario())
    assert before - 0.05 <= t <= after


def test_a_size_the_camera_does_not_give_is_a_clear_error(fake):
    fake.delivered_size = (640, 480)
    camera = V4l2Camera(CAMERA, V4l2Options(device="/dev/cam-front"), MonotonicClock())
    with pytest.raises(CameraError, match=r"/dev/cam-front: delivers 640x480.*asks for 64x48"):
        run(camera.start())
    assert fake.last.released


def test_a_wrong_frame_mid_stream_is_an_error(fake):
    fake.wrong_shape_after = 3

    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(), MonotonicClock()) as cam:
            while True:
                await cam.next_frame()

    with pytest.raises(CameraError, match=r"/dev/video0: delivered a uint8 image of shape"):
        run(scenario())


def test_a_device_that_cannot_be_opened(fake):
    fake.opens = False
    with pytest.raises(CameraError, match="/dev/video3: cannot open.*group 'video'"):
        run(V4l2Camera(CAMERA, V4l2Options(device="/dev/video3"), MonotonicClock()).start())


def test_unplugged_camera_failing_reads_raises_with_the_device_name(fake):
    fake.fail_after = 4

    async def scenario():
        async with V4l2Camera(CAMERA, V4l2Options(device="/dev/video2"), MonotonicClock()) as cam:
            frames = 0
            try:
                while True:
                    await cam.next_frame()
                    frames += 1
            except CameraError as error:
                return frames, str(error)

    frames, message = run(scenario())
    assert 1 <= frames <= 4
    assert message == "/dev/video2: 5 reads in a row failed (unplugged or dead?)"
    assert fake.last.released


def test_a_stalled_camera_times_out_instead_of_hanging(fake):
    fake.hang_after = 2

    async def scenario():
        cam = V4l2Camera(CAMERA, V4l2Options(frame_timeout_s=0.2), MonotonicClock())
        await cam.start()
        try:
            with pytest.raises(CameraError, match=r"/dev/video0: no frame for 0.2 s"):
                while True:
                    await cam.next_frame()
        finally:
            fake.unblock.set()
            cam.close()

    run(scenario())


def test_close_releases_the_device_and_wakes_a_waiting_consumer(fake):
    fake.period = 0.05

    async def scenario():
        cam = V4l2Camera(CAMERA, V4l2Options(), MonotonicClock())
        await cam.start()
        await cam.next_frame()
        waiter = asyncio.create_task(cam.next_frame())
        await asyncio.sleep(0)
        cam.close()
        with pytest.raises(CameraError, match="/dev/video0: closed"):
            await waiter
        with pytest.raises(CameraError, match="closed"):
            await cam.next_frame()

    run(scenario())
    assert fake.last.released


def test_options_are_validated():
    with pytest.raises(OptionError, match="pixel_format"):
        V4l2Options(pixel_format="H264")
    with pytest.raises(OptionError, match="frame_timeout_s"):
        V4l2Options(frame_timeout_s=0.0)
    with pytest.raises(CameraError, match="not started"):
        run(V4l2Camera(CAMERA, V4l2Options(), MonotonicClock()).next_frame())
