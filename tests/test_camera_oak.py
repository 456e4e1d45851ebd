"""The OAK driver against a fake of depthai's v3 API (tests/fake_depthai.py): depthai cannot run
without a device, so only the vendor boundary is faked, and the fake's names and call shapes
are checked against the real depthai where it is installed."""

from __future__ import annotations

import asyncio
import sys
import time

import numpy as np
import pytest

import tests.fake_depthai as fake
from autonomy.options import OptionError
from drivers.camera.base import CameraError, MissingExtra
from drivers.camera.oak import OakCamera, OakOptions, list_devices
from drivers.camera.options import CameraOptions
from drivers.clock import MonotonicClock, SimClock

CAMERA = CameraOptions(width=64, height=40, rate_hz=100.0)


@pytest.fixture(autouse=True)
def depthai(monkeypatch):
    monkeypatch.setattr(fake, "DEVICE", fake.FakeOak())
    monkeypatch.setitem(sys.modules, "depthai", fake)
    return fake


def frames(options: OakOptions, count: int, clock=None, camera=CAMERA):
    async def run():
        async with OakCamera(camera, options, clock or MonotonicClock()) as oak:
            got = [await oak.next_frame() for _ in range(count)]
            return oak, got
    return asyncio.run(run())


def test_a_mono_camera_delivers_rgb_frames_on_the_host_clock_with_manual_exposure():
    before = time.monotonic()
    oak, got = frames(OakOptions(), 5)
    assert all(f.image.shape == (40, 64, 3) and f.image.dtype == np.uint8 for f in got)
    assert all((f.image == f.image[..., :1]).all() for f in got)  # grey in three channels
    assert [f.t for f in got] == sorted(f.t for f in got)
    assert before - 0.01 < got[0].t < time.monotonic()
    assert fake.DEVICE.requested == {"socket": fake.CameraBoardSocket.CAM_B, "size": (64, 40),
                                     "type": fake.ImgFrame.Type.GRAY8, "fps": 100.0}
    assert fake.DEVICE.controls == [("manual", 5000, 400)]
    assert fake.DEVICE.closed


def test_the_colour_socket_asks_for_rgb_and_auto_exposure_when_configured():
    frames(OakOptions(socket="CAM_A", auto_exposure=True), 1)
    assert fake.DEVICE.requested["type"] == fake.ImgFrame.Type.RGB888i
    assert fake.DEVICE.controls == [("auto",)]


def test_an_auto_exposure_limit_goes_to_the_firmware():
    oak, _ = frames(OakOptions(auto_exposure=True, auto_exposure_limit_us=8000), 1)
    assert fake.DEVICE.controls == [("auto",), ("auto limit", 8000)]
    assert oak.exposure_us == 8000  # what `fly check` reports against the frame period
    assert frames(OakOptions(auto_exposure=True), 1)[0].exposure_us is None


def test_the_lens_comes_from_the_device_calibration():
    oak, _ = frames(OakOptions(), 1)
    model = oak.camera_model
    assert model.distortion == "radtan"
    assert model.coefficients == (-0.1, 0.02, 0.001, -0.001, 0.0)
    assert (model.pinhole.fx, model.pinhole.cx) == (32.0, 32.0)


def test_a_fisheye_calibration_is_equidistant_and_rational_terms_are_refused():
    fake.DEVICE.model = fake.CameraModel.Fisheye
    fake.DEVICE.coefficients = [0.1, -0.02, 0.003, -0.001] + [0.0] * 10
    oak, _ = frames(OakOptions(), 1)
    assert oak.camera_model.distortion == "equidistant"
    assert oak.camera_model.coefficients == (0.1, -0.02, 0.003, -0.001)
    fake.DEVICE.model = fake.CameraModel.Perspective
    fake.DEVICE.coefficients = [0.1, 0.0, 0.0, 0.0, 0.0, 0.3] + [0.0] * 8
    with pytest.raises(CameraError, match="terms k4, which radtan cannot hold"):
        frames(OakOptions(), 1)
    assert fake.DEVICE.closed  # a refused device is released


def test_gaps_in_the_sequence_are_lost_frames_not_a_failure():
    fake.DEVICE.sequence = [0, 1, 2, 5, 6, 9, 10] + list(range(11, 100))
    oak, got = frames(OakOptions(), 7)
    assert oak.lost == 4


def test_a_device_that_disappears_is_a_camera_error_not_a_hang():
    """The device dies after its third frame: the reader keeps only the newest frame, so the
    consumer sees one to three of them, then the camera fault, never a wait without end (the
    outer timeout is the hang guard, far beyond the 0.3 s frame timeout)."""
    fake.DEVICE.dies_after = 3

    async def run() -> int:
        frames = 0
        async with OakCamera(CAMERA, OakOptions(frame_timeout_s=0.3), MonotonicClock()) as oak:
            with pytest.raises(CameraError, match="pipeline stopped"):
                while True:
                    await oak.next_frame()
                    frames += 1
        return frames
    assert 1 <= asyncio.run(asyncio.wait_for(run(), 10.0)) <= 3


def test_no_device_or_an_impossible_mode_is_a_clear_error():
    with pytest.raises(CameraError, match="cannot open the OAK"):
        frames(OakOptions(device_id="nope"), 1)
    with pytest.raises(CameraError, match="CAM_B at 4000x40@100: No sensor config"):
        frames(OakOptions(), 1, camera=CameraOptions(width=4000, height=40, rate_hz=100.0))


def test_another_clock_stamps_frames_on_arrival():
    clock = SimClock(50.0)
    _, got = frames(OakOptions(), 2, clock=clock)
    assert all(f.t == 50.0 for f in got)


def test_listing_and_a_missing_sdk(monkeypatch):
    [device] = list_devices()
    assert device.address == "14442C10D13EABCE00" and device.kind == "oak"
    monkeypatch.setitem(sys.modules, "depthai", None)
    with pytest.raises(MissingExtra, match=r"pip install 'companion\[oak\]'"):
        list_devices()
    with pytest.raises(MissingExtra):
        frames(OakOptions(), 1)


@pytest.mark.parametrize("options", [{"socket": "CAM_Z"}, {"exposure_us": 0}, {"iso": 5},
                                     {"auto_exposure_limit_us": 40000, "auto_exposure": True},
                                     {"auto_exposure_limit_us": 8000}])
def test_bad_options_name_their_key(options):
    key = next(iter(options))
    with pytest.raises(OptionError, match=key):
        OakOptions(**options)


def test_the_fake_has_the_real_depthais_names(monkeypatch):
    """Every name the fake provides exists in depthai v3 with the same members."""
    monkeypatch.delitem(sys.modules, "depthai")
    dai = pytest.importorskip("depthai", reason="depthai (extra companion[oak]) not installed")
    assert dai.__version__.startswith("3.")
    for cls, names in ((dai.Device, ("readCalibration", "close", "getAllAvailableDevices")),
                       (dai.DeviceInfo, ("getDeviceId", "name", "state")),
                       (dai.CalibrationHandler, ("getCameraIntrinsics",
                                                 "getDistortionCoefficients",
                                                 "getDistortionModel")),
                       (dai.ImgFrame, ("getFrame", "getTimestamp", "getSequenceNum")),
                       (dai.CameraControl, ("setManualExposure", "setAutoExposureEnable",
                                            "setAutoExposureLimit")),
                       (dai.node.Camera, ("build", "requestOutput", "initialControl")),
                       (dai.Node.Output, ("createOutputQueue",)),
                       (dai.MessageQueue, ("tryGet",)),
                       (dai.Pipeline, ("create", "start", "stop", "isRunning"))):
        for name in names:
            assert hasattr(cls, name), f"{cls.__name__}.{name}"
    for enum_type, fake_enum in ((dai.CameraBoardSocket, fake.CameraBoardSocket),
                                 (dai.CameraModel, fake.CameraModel),
                                 (dai.ImgFrame.Type, fake.ImgFrame.Type)):
        for member in fake_enum.__members__:
            assert hasattr(enum_type, member), f"{enum_type.__name__}.{member}"
    assert "boardSocket" in dai.node.Camera.build.__doc__
    assert "size: tuple[int, int], type:" in dai.node.Camera.requestOutput.__doc__
    assert "fps: Optional[float]" in dai.node.Camera.requestOutput.__doc__
