"""The RealSense driver against the real librealsense SDK: a pyrealsense2 ``software_device``
shaped like a D455's colour sensor is the camera (frames, timestamps, frame numbers, calibration
and controls injected in-process), and the SDK's own recorder makes the recordings played back.
No stand-in for our code or the SDK's: only the USB camera is replaced, by the SDK's own seam.
"""

import asyncio
import importlib.util
import sys
import threading
import time

import numpy as np
import pytest

# the realsense extra, and the system's libusb-1.0 its wheel loads: the reason names the cause
rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)

from autonomy.options import OptionError  # noqa: E402
from drivers.camera import realsense  # noqa: E402
from drivers.camera.base import CameraError, DeviceInfo, MissingExtra  # noqa: E402
from drivers.camera.options import CameraOptions  # noqa: E402
from drivers.camera.realsense import (RealSenseCamera, RealSenseOptions,  # noqa: E402
                                      camera_model, describe, list_devices)
from drivers.clock import MonotonicClock, SimClock  # noqa: E402

CAMERA = CameraOptions(width=64, height=48, rate_hz=30.0)
#: A D455 colour calibration as librealsense reports it (model and coefficients of the kind
#: src/ds/d400/d400-private.cpp gives), scaled to the 64x48 test image.
D455_COEFFS = [-0.0553, 0.0653, -0.0006, 0.0007, -0.0209]


def option_range(low, high, step, default):
    """An option_range set field by field: pyrealsense2 2.59's 4-argument constructor swaps
    step and default (wrappers/python/pyrs_types.cpp fills the struct {min, max, def, step} in
    the order min, max, step, default)."""
    r = rs.option_range()
    r.min, r.max, r.step, r.default = low, high, step, default
    return r


def intrinsics(width, height, model=rs.distortion.inverse_brown_conrady, coeffs=D455_COEFFS):
    i = rs.intrinsics()
    i.width, i.height = width, height
    i.fx, i.fy = 0.5 * width, 0.5 * width + 0.4  # a D455's 90 degrees
    i.ppx, i.ppy = width / 2 - 0.7, height / 2 + 0.3
    i.model, i.coeffs = model, list(coeffs)
    return i


class SoftwareD455:
    """A software_device with a D455-like colour sensor: RGB8 modes 64x48@30 and 32x24@15, a
    YUYV mode, the colour controls of a D4xx (exposure in 100 us steps 1-10000, gain 0-128,
    auto exposure, global time), and frames whose pixels are ``(x, y, n)``."""

    serial = "213622078123"

    def __init__(self, *, model=rs.distortion.inverse_brown_conrady, coeffs=D455_COEFFS,
                 controls=True, gain_max=128):
        self.device = rs.software_device()
        for info, value in ((rs.camera_info.name, "Intel RealSense D455"),
                            (rs.camera_info.serial_number, self.serial),
                            (rs.camera_info.firmware_version, "5.16.0.1"),
                            (rs.camera_info.usb_type_descriptor, "3.2")):
            self.device.register_info(info, value)
        self.sensor = self.device.add_sensor("RGB Camera")
        self.profile = self._stream(64, 48, 30, rs.format.rgb8, 1, model, coeffs)
        self._stream(32, 24, 15, rs.format.rgb8, 2, model, coeffs)
        self._stream(64, 48, 60, rs.format.yuyv, 3, model, coeffs)
        if controls:
            for which, bounds in ((rs.option.exposure, (1, 10000, 1, 156)),
                                  (rs.option.gain, (0, gain_max, 1, min(64, gain_max))),
                                  (rs.option.enable_auto_exposure, (0, 1, 1, 1)),
                                  (rs.option.global_time_enabled, (0, 1, 1, 1))):
                self.sensor.add_option(which, option_range(*bounds), True)
        self.pushed = []  # (frame number, time.monotonic() when pushed)

    def _stream(self, width, height, fps, fmt, uid, model, coeffs):
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid = rs.stream.color, 0, uid
        stream.width, stream.height, stream.fps = width, height, fps
        stream.bpp, stream.fmt = 2 if fmt == rs.format.yuyv else 3, fmt
        stream.intrinsics = intrinsics(width, height, model, coeffs)
        return self.sensor.add_video_stream(stream).as_video_stream_profile()

    def push(self, n, *, stamp_ms=None, domain=rs.timestamp_domain.global_time, sensor=None,
             rgb=None):
        """Inject frame ``n`` (pixels ``rgb``, default :func:`image`); its stamp defaults to
        host (epoch) time 20 ms ago."""
        frame = rs.software_video_frame()
        frame.pixels = image(n) if rgb is None else rgb
        frame.stride, frame.bpp = 64 * 3, 3
        frame.timestamp = time.time() * 1000.0 - 20.0 if stamp_ms is None else stamp_ms
        frame.domain, frame.frame_number, frame.profile = domain, n, self.profile
        self.pushed.append((n, time.monotonic()))
        (sensor or self.sensor).on_video_frame(frame)

    def play(self, numbers, period=0.005, **kwargs):
        """Push ``numbers`` from a thread, one every ``period`` seconds; returns the thread."""
        def run():
            time.sleep(0.05)  # let the driver start its stream
            for n in numbers:
                self.push(n, **kwargs)
                time.sleep(period)
        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread


def image(n):
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = np.arange(64)[None, :]
    rgb[..., 1] = np.arange(48)[:, None]
    rgb[..., 2] = n
    return rgb


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, 20.0))


async def frames_until_error(cam, limit=1000):
    """Every frame next_frame gives until it raises; returns (frames, the error)."""
    frames = []
    try:
        while len(frames) < limit:
            frames.append(await cam.next_frame())
    except CameraError as error:
        return frames, error
    raise AssertionError("the camera never stopped")


def record(path, numbers, *, stamps_ms=None):
    """Record frames ``numbers`` of a SoftwareD455 (stamped 33.3 ms apart per number unless
    ``stamps_ms`` says otherwise) with the SDK's recorder, the way librealsense's
    unit-tests/live/rec-play/test-record-software-device.py does."""
    stamps_ms = stamps_ms or [1000.0 + 33.3 * n for n in numbers]
    camera = SoftwareD455()
    recorder = rs.recorder(str(path), camera.device)
    sensor = recorder.query_sensors()[0]
    syncer = rs.syncer(100)
    sensor.open([p for p in sensor.get_stream_profiles() if p.unique_id() == 1])
    sensor.start(syncer)
    for n, stamp_ms in zip(numbers, stamps_ms):
        camera.push(n, stamp_ms=stamp_ms)
    sensor.stop()
    sensor.close()
    recorder.pause()
    del recorder, sensor


# ---- frames and timestamps -------------------------------------------------------------------

def test_frames_carry_the_device_pixels_numbers_and_host_time():
    camera = SoftwareD455()

    async def scenario():
        async with RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(),
                                   device=camera.device) as cam:
            camera.play(range(10), period=0.02)
            return [await cam.next_frame() for _ in range(5)], cam

    frames, cam = run(scenario())
    pushed = dict(camera.pushed)
    for frame in frames:
        n = int(frame.image[0, 0, 2])
        assert np.array_equal(frame.image, image(n))
        assert not frame.image.flags.writeable
        # global time is epoch milliseconds; on the companion clock, 20 ms before the push
        assert frame.t == pytest.approx(pushed[n] - 0.020, abs=2e-3)
    assert [f.t for f in frames] == sorted(f.t for f in frames)
    assert cam.lost == 0


def test_manual_exposure_gain_and_global_time_are_set_on_the_colour_sensor():
    camera = SoftwareD455()

    async def scenario():
        options = RealSenseOptions(exposure_us=3000, gain=80)
        async with RealSenseCamera(CAMERA, options, MonotonicClock(), device=camera.device):
            pass

    run(scenario())
    get = camera.sensor.get_option
    assert get(rs.option.enable_auto_exposure) == 0
    assert get(rs.option.exposure) == 30  # 100 us steps
    assert get(rs.option.gain) == 80
    assert get(rs.option.global_time_enabled) == 1


def test_auto_exposure_leaves_exposure_and_gain_to_the_camera():
    camera = SoftwareD455()
    camera.sensor.set_option(rs.option.enable_auto_exposure, 0)

    async def scenario():
        options = RealSenseOptions(auto_exposure=True, global_time=False)
        async with RealSenseCamera(CAMERA, options, MonotonicClock(), device=camera.device):
            pass

    run(scenario())
    assert camera.sensor.get_option(rs.option.enable_auto_exposure) == 1
    assert camera.sensor.get_option(rs.option.exposure) == 156  # untouched default
    assert camera.sensor.get_option(rs.option.global_time_enabled) == 0


@pytest.mark.parametrize("stamp_ms, domain", [
    (5000.0, rs.timestamp_domain.hardware_clock),  # the device's own clock: no host time
    (1.0e12, rs.timestamp_domain.global_time),  # host time, but decades off
])
def test_an_untrusted_stamp_falls_back_to_arrival_with_one_warning(stamp_ms, domain, caplog):
    camera = SoftwareD455()

    async def scenario():
        async with RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(),
                                   device=camera.device) as cam:
            before = time.monotonic()
            camera.play(range(3), stamp_ms=stamp_ms, domain=domain, period=0.03)
            frames = [await cam.next_frame() for _ in range(3)]
            return before, frames, time.monotonic()

    before, frames, after = run(scenario())
    assert all(before <= f.t <= after for f in frames)
    warnings = [r for r in caplog.records if "stamping frames on arrival" in r.message]
    assert len(warnings) == 1 and "RealSense" in warnings[0].message


def test_other_clocks_stamp_frames_on_arrival():
    camera = SoftwareD455()

    async def scenario():
        async with RealSenseCamera(CAMERA, RealSenseOptions(), SimClock(42.0),
                                   device=camera.device) as cam:
            camera.play(range(3))
            return await cam.next_frame()

    assert run(scenario()).t == 42.0


def test_a_camera_that_stops_mid_stream_is_an_error_not_a_hang():
    camera = SoftwareD455()

    async def scenario():
        options = RealSenseOptions(frame_timeout_s=0.3, serial=camera.serial)
        async with RealSenseCamera(CAMERA, options, MonotonicClock(),
                                   device=camera.device) as cam:
            camera.play(range(4))
            return await frames_until_error(cam)

    frames, error = run(scenario())
    assert frames
    assert str(error) == (f"RealSense {camera.serial}: no frame for 0.3 s "
                          "(camera stalled or unplugged)")


# ---- recordings ------------------------------------------------------------------------------

def test_a_recording_plays_back_every_frame_and_counts_the_dropped_ones(tmp_path):
    path = tmp_path / "flight.db3"  # librealsense 2.57+ records ROS 2 bags
    numbers = [0, 1, 2, 5, 6, 7, 8, 12, 13]  # the device lost 3, 4 and 9-11
    record(path, numbers)

    async def scenario():
        cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(), playback=str(path))
        async with cam:
            frames, error = await frames_until_error(cam)
            return cam, frames, error

    cam, frames, error = run(scenario())
    assert str(error) == f"{path}: end of the recording"
    assert [int(f.image[0, 0, 2]) for f in frames] == numbers  # every frame, in order
    assert all(np.array_equal(f.image, image(n)) for f, n in zip(frames, numbers))
    assert cam.delivered == len(numbers) and cam.lost == 5 and cam.dropped == 0
    # the recording's own times: 33.3 ms per frame number, from the first frame on
    times = np.array([f.t for f in frames])
    assert np.allclose(times - times[0], [0.0333 * n for n in numbers], atol=1e-6)
    assert cam.camera_model == camera_model(intrinsics(64, 48))  # the recorded calibration


def test_a_recording_whose_time_goes_back_keeps_frame_times_increasing(tmp_path, caplog):
    path = tmp_path / "spliced.db3"
    record(path, [0, 1, 2, 3], stamps_ms=[5000.0, 5033.3, 5066.6, 5010.0])

    async def scenario():
        cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(), playback=str(path))
        async with cam:
            return (await frames_until_error(cam))[0]

    times = np.array([f.t for f in run(scenario())])
    assert np.allclose(times - times[0], [0.0, 0.0333, 0.0666, 0.0666 + 1 / 30.0], atol=1e-6)
    assert any("does not advance" in r.message for r in caplog.records)


def test_a_missing_or_damaged_recording_is_a_clear_error(tmp_path):
    cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(),
                          playback=str(tmp_path / "none.bag"))
    with pytest.raises(CameraError, match=r"none.bag: no such recording"):
        run(cam.start())
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(b"not a recording" * 10)
    cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(), playback=str(damaged))
    with pytest.raises(CameraError, match=r"damaged.bag: .*ros reader"):
        run(cam.start())


# ---- modes, controls, calibration ------------------------------------------------------------

def test_a_mode_the_camera_does_not_have_names_those_it_has():
    camera = SoftwareD455()
    cam = RealSenseCamera(CameraOptions(width=64, height=48, rate_hz=20.0), RealSenseOptions(),
                          MonotonicClock(), device=camera.device)
    with pytest.raises(CameraError) as raised:
        run(cam.start())
    assert str(raised.value) == (
        "RealSense: has no 64x48@20 RGB8 colour mode; set camera.width, camera.height and "
        "camera.rate_hz to one it has: 32x24@15 RGB8, 64x48@30 RGB8")


@pytest.mark.parametrize("kwargs, message", [
    ({"controls": False},
     r"the colour sensor has no Enable Auto Exposure control \(realsense.auto_exposure\)"),
    ({"gain_max": 32}, r"realsense.gain: Gain 64 is outside the sensor's range 0 to 32"),
])
def test_controls_the_device_refuses_name_the_config_key(kwargs, message):
    camera = SoftwareD455(**kwargs)
    cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(), device=camera.device)
    with pytest.raises(CameraError, match=message):
        run(cam.start())


def projected(model, rays):
    """Pixels of normalised rays (N, 2) through a CameraModel."""
    d = model.distort(rays)
    p = model.pinhole
    return np.stack([p.fx * d[:, 0] + p.cx, p.fy * d[:, 1] + p.cy], axis=1)


def sdk_projected(intr, rays):
    return np.array([rs.rs2_project_point_to_pixel(intr, [x, y, 1.0]) for x, y in rays])


def image_rays(intr, n=15):
    """Rays through an n x n pixel grid spanning the image (deprojected with no distortion and
    shrunk a little, so they stay in the image through a mild lens)."""
    u = (np.linspace(0, intr.width - 1, n) - intr.ppx) / intr.fx * 0.95
    v = (np.linspace(0, intr.height - 1, n) - intr.ppy) / intr.fy * 0.95
    return np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)


@pytest.mark.parametrize("model, kind, tolerance", [
    (rs.distortion.none, "none", 1e-3),
    (rs.distortion.brown_conrady, "radtan", 1e-3),
    (rs.distortion.kannala_brandt4, "equidistant", 1e-3),
    (rs.distortion.modified_brown_conrady, "radtan", realsense.MAX_FIT_ERROR_PX),
    (rs.distortion.inverse_brown_conrady, "radtan", realsense.MAX_FIT_ERROR_PX),
])
def test_camera_model_projects_as_the_sdk_does(model, kind, tolerance):
    intr = intrinsics(640, 480, model, [0.0] * 5 if model == rs.distortion.none else D455_COEFFS)
    result = camera_model(intr)
    assert result.distortion == kind
    p = result.pinhole
    assert (p.width, p.height, p.fx, p.fy, p.cx, p.cy) == pytest.approx(
        (640, 480, intr.fx, intr.fy, intr.ppx, intr.ppy))
    rays = image_rays(intr)
    error = np.abs(projected(result, rays) - sdk_projected(intr, rays)).max()
    assert error <= tolerance


def test_brown_conrady_coefficients_are_opencv_order():
    result = camera_model(intrinsics(640, 480, rs.distortion.brown_conrady))
    assert result.coefficients == pytest.approx(D455_COEFFS)  # k1 k2 p1 p2 k3


@pytest.mark.parametrize("model, coeffs, message", [
    (rs.distortion.ftheta, [0.9, 0, 0, 0, 0], "lens model distortion.ftheta is not supported"),
    (rs.distortion.modified_brown_conrady, [0.4, 0.2, 0.05, 0.05, 0.1],
     r"is not radtan within 0.1 px \(best fit is .* px off\)"),
])
def test_lens_models_radtan_cannot_carry_are_refused(model, coeffs, message):
    with pytest.raises(CameraError, match=message):
        camera_model(intrinsics(640, 480, model, coeffs))


def test_the_camera_model_is_the_device_calibration():
    camera = SoftwareD455()

    async def scenario():
        cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock(), device=camera.device)
        with pytest.raises(CameraError, match="not started"):
            cam.camera_model
        async with cam:
            return cam.camera_model

    model = run(scenario())
    intr = camera.profile.get_intrinsics()
    assert model == camera_model(intr) and model.distortion == "radtan"
    rays = image_rays(intr)
    assert np.abs(projected(model, rays) - sdk_projected(intr, rays)).max() <= 0.1


# ---- devices and the extra -------------------------------------------------------------------

def test_a_device_is_described_by_serial_firmware_usb_and_rgb_modes():
    assert describe(SoftwareD455().device) == DeviceInfo(
        "realsense", SoftwareD455.serial, "Intel RealSense D455 (firmware 5.16.0.1, USB 3.2)",
        ("32x24@15 RGB8", "64x48@30 RGB8"))


@pytest.fixture
def no_camera():
    """Skips the test where a RealSense is plugged in."""
    if len(rs.context().query_devices()):
        pytest.skip("a RealSense is connected here")


def test_list_devices_is_empty_without_a_camera(no_camera):
    assert list_devices() == []


def test_no_connected_camera_is_a_clear_error(no_camera):
    cam = RealSenseCamera(CAMERA, RealSenseOptions(), MonotonicClock())
    with pytest.raises(CameraError, match=r"RealSense: no RealSense connected"):
        run(cam.start())
    cam = RealSenseCamera(CAMERA, RealSenseOptions(serial="123"), MonotonicClock())
    with pytest.raises(CameraError, match=r"RealSense 123: not connected \(connected: none\)"):
        run(cam.start())


def test_without_pyrealsense2_the_module_imports_and_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import pyrealsense2 fails
    spec = importlib.util.spec_from_file_location("realsense_without_sdk", realsense.__file__)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    with pytest.raises(MissingExtra) as raised:
        module.list_devices()
    assert str(raised.value) == "pyrealsense2 is not installed: pip install 'companion[realsense]'"
    assert raised.value.extra == "realsense"
    cam = module.RealSenseCamera(CAMERA, module.RealSenseOptions(), MonotonicClock())
    with pytest.raises(MissingExtra):
        run(cam.start())


@pytest.mark.parametrize("kwargs, key", [
    ({"exposure_us": 50}, "exposure_us"),
    ({"gain": 200}, "gain"),
    ({"frame_timeout_s": 0.0}, "frame_timeout_s"),
    ({"max_failed_reads": 0}, "max_failed_reads"),
    ({"serial": 213622078123}, "serial"),
    ({"auto_exposure": "no"}, "auto_exposure"),
])
def test_bad_options_name_the_key(kwargs, key):
    with pytest.raises(OptionError) as raised:
        RealSenseOptions(**kwargs)
    assert raised.value.key == key


def test_an_exposure_longer_than_a_frame_is_refused():
    with pytest.raises(OptionError, match="exposure_us: 40000 us is longer than a frame at "
                                          "camera.rate_hz = 30"):
        RealSenseCamera(CAMERA, RealSenseOptions(exposure_us=40000), MonotonicClock())
    RealSenseCamera(CAMERA, RealSenseOptions(exposure_us=40000, auto_exposure=True),
                    MonotonicClock())
    with pytest.raises(OptionError, match="auto_exposure_limit_us: 40000 us is longer than a "
                                          "frame at camera.rate_hz = 30"):
        RealSenseCamera(CAMERA, RealSenseOptions(auto_exposure=True,
                                                 auto_exposure_limit_us=40000),
                        MonotonicClock())


@pytest.mark.parametrize("kwargs, key", [
    ({"auto_exposure_limit_us": 8000}, "auto_exposure_limit_us"),  # without auto_exposure
    ({"auto_exposure": True, "auto_exposure_limit_us": 8000, "gain": 0}, "gain"),
])
def test_a_host_auto_exposure_needs_auto_exposure_and_a_gain_to_multiply(kwargs, key):
    with pytest.raises(OptionError) as raised:
        RealSenseOptions(**kwargs)
    assert raised.value.key == key


# ---- the host auto-exposure -----------------------------------------------------------------

def host_auto_exposure(levels, **options):
    """Stream frames of uniform grey ``levels`` (0-255) through a SoftwareD455 with the host
    auto-exposure limited to 8 ms; returns the camera's (exposure, gain) after each read frame
    and the SoftwareD455."""
    camera = SoftwareD455()
    settings = []

    async def scenario():
        options.setdefault("auto_exposure_limit_us", 8000)
        async with RealSenseCamera(CAMERA, RealSenseOptions(auto_exposure=True, **options),
                                   MonotonicClock(), device=camera.device) as cam:
            for n, level in enumerate(levels):
                camera.push(n, rgb=np.full((48, 64, 3), level, np.uint8))
                await cam.next_frame()
                settings.append((camera.sensor.get_option(rs.option.exposure),
                                 camera.sensor.get_option(rs.option.gain)))

    run(scenario())
    return settings, camera


def test_in_the_dark_the_host_auto_exposure_stops_at_its_limit_and_raises_gain():
    """A D455's colour sensor lengthens its exposure to a frame period in the dark; with a
    limit the driver runs the exposure itself, sensor auto-exposure off: 8 ms, then gain."""
    settings, camera = host_auto_exposure([10] * 12)
    assert camera.sensor.get_option(rs.option.enable_auto_exposure) == 0
    exposures = [e for e, _ in settings]
    assert exposures == sorted(exposures) and max(exposures) == 80  # 100 us steps
    assert settings[-1] == (80, 128)  # the limit, and the sensor's highest gain
    gains_at_limit = [g for e, g in settings if e < 80]
    assert all(g == 64 for g in gains_at_limit)  # gain only once the exposure is at its limit


def test_in_bright_light_the_host_auto_exposure_shortens_the_exposure_at_the_lowest_gain():
    settings, _ = host_auto_exposure([250] * 12, exposure_us=5000, gain=40)
    exposures = [e for e, _ in settings]
    assert exposures == sorted(exposures, reverse=True) and exposures[-1] < 10
    assert {g for _, g in settings} == {40}


def test_at_its_target_level_the_host_auto_exposure_holds_still():
    settings, _ = host_auto_exposure([round(0.4 * 255)] * 6, exposure_us=3000)
    assert set(settings) == {(30, 64)}
