"""A RealSense colour stream (the paper's camera: a D455's RGB sensor) read through pyrealsense2.

The colour sensor is opened with librealsense's sensor API (``sensor.open(profile)``,
``sensor.start(syncer)``, ``syncer.try_wait_for_frames``), the same way for a connected camera,
for a recording played back from a file (``context.load_device``) and for an in-process
``software_device`` (the test seam, ``device=``), so all three go through one read path. Not
the ``pipeline``: a ``software_device`` cannot reach one in pyrealsense2 2.59.1, the context
never lists it (in 2.56's source, src/rs.cpp ``rs2_context_add_software_device`` hands the
context only a weak pointer to a device-info nobody else holds). Not a
``frame_queue`` either: pyrealsense2 binds ``sensor.start(callback)`` before
``sensor.start(frame_queue)`` and a frame_queue is callable, so frames would be pushed under
the GIL, which deadlocks playback (its frames wait for room in the queue holding the GIL);
``syncer`` is not callable and its waits release the GIL (wrappers/python/pyrs_processing.cpp).

Timestamps, on the companion clock like every other timestamp (DESIGN.md, "Time"):

- A connected camera, with a :class:`~drivers.clock.MonotonicClock`: librealsense's *global
  time* (``global_time = true``) maps the device's hardware clock onto the host's
  ``std::chrono::system_clock`` in milliseconds since the epoch, by a linear fit over the last
  15 samples of both clocks, taken every second (src/global_timestamp_reader.cpp,
  ``time_diff_keeper``); without frame metadata the frame comes in *system time*, the host's
  arrival time on the same clock (src/core/time-service.h). Either is moved onto
  ``time.monotonic`` by the offset between the two clocks read back to back when the frame
  arrives, ``t = stamp - (time.time() - clock.now())``: a step of the host's clock (NTP) then
  errs only until librealsense's fit has followed it. A stamp more than
  :data:`MAX_STAMP_AGE_S` from the arrival time, or one in the device's own hardware-clock
  domain, is not trusted: the frame is stamped on arrival, with one warning.
- A connected camera with any other clock (the simulator's), or ``global_time = false``: the
  arrival time on that clock.
- A recording: its own frame times, shifted so that its first frame is at the clock's time when
  it was read. A time that does not advance (a damaged or spliced recording) restarts the
  timeline one frame period after the previous frame, with a warning.

A recording replays every frame at the consumer's pace: the SDK's real-time playback is off
(``set_real_time(False)``: it skips nothing and waits for the reader, src/media/playback/
playback_device.cpp), and the reader takes the next recorded frame only once the consumer took
the last, so nothing is dropped and the same recording gives the same frames every run. Frame
times are the recording's, so they run ahead of or behind the clock as the consumer is faster or
slower than the camera was.

Frames the device numbered but never delivered (gaps in ``get_frame_number``) are counted in
:attr:`~drivers.camera.base.ThreadedCamera.lost`, a recording's gaps included. A camera that
stops delivering (unplugged, dead) is a :class:`CameraError` from ``next_frame`` after
``frame_timeout_s`` (the base class's rule), the end of a recording one at once.

Exposure. Manual by default (``exposure_us``, ``gain``); ``auto_exposure`` hands both to the
camera, whose colour sensor lengthens the exposure up to a frame period in dim light (motion
blur the tracker cannot follow) since it takes no limit (realsense-ros issue 2798).
``auto_exposure_limit_us`` instead runs the auto-exposure on the host within that limit
(:class:`HostAutoExposure`, the law of :mod:`drivers.camera.exposure`), setting exposure and
gain on the sensor by hand after each frame.

The camera model comes from the device's own calibration, :func:`camera_model`.

pyrealsense2 is the optional extra ``companion[realsense]``: this module imports without it, and
using the driver or :func:`list_devices` without it raises
:class:`~drivers.camera.base.MissingExtra` naming the extra.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.lens import CameraModel
from autonomy.options import OptionError, option, validate
from drivers.camera.base import CameraError, DeviceInfo, RawFrame, ThreadedCamera, import_sdk
from drivers.camera.exposure import (STEP_RATE, TARGET_LEVEL, ExposureLaw, check_limit,
                                     longest_us, mean_level)
from drivers.camera.options import CameraOptions
from drivers.clock import Clock, MonotonicClock

log = logging.getLogger(__name__)

MAX_STAMP_AGE_S = 1.0
"""A device timestamp further than this from the arrival time is not trusted, seconds."""

EXPOSURE_UNIT_US = 100
"""The colour sensor's ``rs.option.exposure`` counts 100 us steps (1 to 10000 on a D4xx:
librealsense issue #8243), unlike the depth sensor's microseconds."""

MAX_FIT_ERROR_PX = 0.1
"""Largest pixel error accepted when a modified Brown-Conrady lens is refitted as radtan."""

POLL_S = 0.1
"""A read waits for frames in slices this long, so that the end of a recording and a close are
seen at once."""

CONSUMER_POLL_S = 0.002
"""How often a paused replay looks whether the consumer took its frame, seconds."""

SYNCER_QUEUE = 2
"""Frames the SDK keeps for the reader thread; the newest-frame slot is in the base class."""


def _sdk():
    """pyrealsense2 (:func:`~drivers.camera.base.import_sdk`)."""
    return import_sdk("pyrealsense2", "realsense")


@dataclass(frozen=True)
class RealSenseOptions:
    """Which RealSense to read and how to expose it; size and rate come from CameraOptions.

    Manual exposure is the default: the feature tracker matches patches between frames, which a
    brightness change breaks. 5 ms keeps motion blur near 1.6 px at 1 rad/s with the D455 colour
    stream's focal length at 640x480 (about 320 px); raise ``gain`` in dim light before
    lengthening it. The colour sensor sets exposure in 100 us steps from 100 us to 1 s.
    """

    serial: str = option("", doc="serial number of the RealSense to read; '' = the only one "
                         "connected")
    auto_exposure: bool = option(False, doc="automatic exposure and gain; false keeps "
                                 "exposure_us and gain fixed")
    auto_exposure_limit_us: int = option(0, ge=0, le=1_000_000, doc="longest exposure the "
                                         "auto-exposure may choose, microseconds; 0 leaves it "
                                         "to the camera, which has no limit on its colour "
                                         "sensor, others run it on the host within the limit")
    exposure_us: int = option(5000, ge=100, le=1_000_000, doc="manual exposure, microseconds "
                              "(rounded to the sensor's 100 us steps; at most one frame "
                              "period); the host auto-exposure's first")
    gain: int = option(64, ge=0, le=128, doc="manual analogue gain of the colour sensor (D4xx "
                       "range 0-128, 64 its default); the host auto-exposure's lowest")
    global_time: bool = option(True, doc="stamp frames with the device's hardware clock mapped "
                               "to host time by librealsense; false stamps them on arrival")
    max_failed_reads: int = option(5, ge=1, le=1000, doc="reads in a row with no frame after "
                                   "which the camera is dead")
    frame_timeout_s: float = option(1.0, gt=0.0, le=60.0,
                                    doc="no frame for this long and the camera is dead, s")

    def __post_init__(self) -> None:
        validate(self)
        check_limit(self)
        if self.host_auto_exposure and self.gain < 1:
            raise OptionError("gain", "the host auto-exposure multiplies gain from it: at "
                              f"least 1, got {self.gain}")

    @property
    def host_auto_exposure(self) -> bool:
        """Whether the driver runs the auto-exposure itself (a limit was set)."""
        return self.auto_exposure and self.auto_exposure_limit_us > 0


@dataclass(frozen=True)
class _Stream:
    """The opened colour stream the reader thread owns: the device is kept so that its sensor
    lives; ``playback`` is the same device when it plays a recording, else None."""

    device: Any
    sensor: Any
    syncer: Any
    playback: Any = None


class RealSenseCamera(ThreadedCamera):
    """The colour stream of one RealSense, or of a recording of one, as companion frames.

    ``async with RealSenseCamera(camera, options, clock) as cam: frame = await
    cam.next_frame()``; :attr:`camera_model` is the device's calibration once started.
    ``playback`` reads a recording (``.bag``, or the ``.db3`` librealsense 2.57+ records)
    instead of a camera. ``device`` is the test seam: an already-made pyrealsense2 device (a
    ``software_device``) read instead of a connected one.
    """

    def __init__(self, camera: CameraOptions, options: RealSenseOptions, clock: Clock, *,
                 playback: str | None = None, device: Any = None):
        longest = {"exposure_us": 0 if options.auto_exposure else options.exposure_us,
                   "auto_exposure_limit_us": options.auto_exposure_limit_us}
        for key, exposure_us in longest.items():
            if exposure_us > 1e6 / camera.rate_hz:
                raise OptionError(key, f"{exposure_us} us is longer than a frame at "
                                  f"camera.rate_hz = {camera.rate_hz:g}")
        name = playback or (f"RealSense {options.serial}" if options.serial else "RealSense")
        super().__init__(name, (camera.width, camera.height), clock,
                         frame_timeout_s=options.frame_timeout_s,
                         max_failed_reads=options.max_failed_reads,
                         retry_wait_s=0.0)
        self.camera, self.options = camera, options
        self.playback, self._injected = playback, device
        self._polls = max(1, math.ceil(options.frame_timeout_s / POLL_S))
        self._model: CameraModel | None = None
        self._recording = _RecordingTimeline(1.0 / camera.rate_hz) if playback else None
        self._warned_stamp = False
        self.auto_exposure: HostAutoExposure | None = None

    @property
    def exposure_us(self) -> int | None:
        """The longest a frame is exposed, us (:func:`~drivers.camera.exposure.longest_us`)."""
        return longest_us(self.options)

    @property
    def camera_model(self) -> CameraModel:
        """The colour stream's intrinsics and lens model from the device's calibration (or the
        recording's), available once started."""
        if self._model is None:
            raise CameraError(f"{self.name}: not started")
        return self._model

    # ---- the device --------------------------------------------------------------------------

    def _open(self) -> _Stream:
        """The started colour stream; any SDK refusal becomes a CameraError naming the camera."""
        rs = _sdk()
        try:
            return self._start(rs)
        except (CameraError, RuntimeError) as error:
            raise CameraError(f"{self.name}: {error}") from None

    def _start(self, rs) -> _Stream:
        device, playback = self._source(rs)
        sensor = _colour_sensor(rs, device)
        profile = self._profile(rs, sensor)
        self._model = camera_model(profile.as_video_stream_profile().get_intrinsics())
        if playback is None:
            self._configure(rs, sensor)
            if self.options.host_auto_exposure:
                self.auto_exposure = HostAutoExposure(rs, sensor, self.options)
        syncer = rs.syncer(SYNCER_QUEUE)
        sensor.open(profile)
        try:
            sensor.start(syncer)
        except RuntimeError:
            sensor.close()
            raise
        return _Stream(device, sensor, syncer, playback)

    def _source(self, rs):
        """(device, playback device or None): the injected device, the recording, or the
        connected camera with the configured serial."""
        if self._injected is not None:
            return self._injected, None
        context = rs.context()
        if self.playback is not None:
            if not os.path.isfile(self.playback):
                raise CameraError("no such recording")
            playback = context.load_device(self.playback).as_playback()
            playback.set_real_time(False)
            return playback, playback
        return _connected(rs, context, self.options.serial), None

    def _profile(self, rs, sensor):
        """The colour profile of the configured size and rate in RGB8, or an error naming the
        modes there are."""
        cam = self.camera
        profiles = _rgb_profiles(rs, sensor)
        for profile in profiles:
            if _size_rate(profile) == (cam.width, cam.height, cam.rate_hz):
                return profile
        raise CameraError(f"has no {cam.width}x{cam.height}@{cam.rate_hz:g} RGB8 colour mode; "
                          f"set camera.width, camera.height and camera.rate_hz to one it has: "
                          f"{', '.join(_modes(profiles)) or 'none'}")

    def _configure(self, rs, sensor) -> None:
        """Exposure, gain and global time on the colour sensor (a recording's are fixed)."""
        opt = self.options
        if opt.auto_exposure and not opt.host_auto_exposure:
            _set(rs, sensor, "auto_exposure", rs.option.enable_auto_exposure, 1)
        else:
            _set(rs, sensor, "auto_exposure", rs.option.enable_auto_exposure, 0)
            _set(rs, sensor, "exposure_us", rs.option.exposure,
                 round(opt.exposure_us / EXPOSURE_UNIT_US))
            _set(rs, sensor, "gain", rs.option.gain, opt.gain)
        if sensor.supports(rs.option.global_time_enabled):
            _set(rs, sensor, "global_time", rs.option.global_time_enabled, int(opt.global_time))

    def _read(self, stream: _Stream) -> RawFrame | None:
        """The next frame, or None when none came for ``frame_timeout_s``; the end of a
        recording is an error at once."""
        rs = _sdk()
        if stream.playback is not None:
            self._wait_until_taken(CONSUMER_POLL_S)
        for _ in range(self._polls):
            if self._stop.is_set():  # closing: do not keep close() waiting
                return None
            ok, frames = stream.syncer.try_wait_for_frames(round(POLL_S * 1000))
            if ok:
                return self._raw(rs, frames.first_or_default(rs.stream.color))
            if (stream.playback is not None
                    and stream.playback.current_status() == rs.playback_status.stopped):
                raise CameraError("end of the recording")
        return None

    def _release(self, stream: _Stream) -> None:
        stream.sensor.stop()
        stream.sensor.close()

    def _raw(self, rs, frame) -> RawFrame:
        """The frame's pixels (copied: the SDK reuses its buffer) with its companion time."""
        arrival, epoch = self.clock.now(), time.time()
        rgb = np.asanyarray(frame.get_data()).copy()
        if self.auto_exposure is not None:
            self.auto_exposure.after(rgb)
        device_s = frame.get_timestamp() / 1000.0
        if self._recording is not None:
            t = self._recording(device_s, arrival)
        else:
            t = self._stamp(rs, frame.get_frame_timestamp_domain(), device_s - (epoch - arrival),
                            arrival)
        return RawFrame(rgb, t, frame.get_frame_number())

    def _stamp(self, rs, domain, stamp: float, arrival: float) -> float:
        """A live frame's time: its host-clock stamp moved onto the companion clock when that is
        time.monotonic and the stamp plausible, else the arrival time (module docstring)."""
        if not (isinstance(self.clock, MonotonicClock) and self.options.global_time):
            return arrival
        host_clock = domain in (rs.timestamp_domain.global_time, rs.timestamp_domain.system_time)
        if host_clock and abs(stamp - arrival) <= MAX_STAMP_AGE_S:
            return stamp
        if not self._warned_stamp:
            log.warning("%s: frame timestamp (%s) is not on the host clock near the arrival time "
                        "(%.3f s off); stamping frames on arrival", self.name, domain,
                        stamp - arrival)
            self._warned_stamp = True
        return arrival


class _RecordingTimeline:
    """A recording's frame times on the companion clock (module docstring, "A recording")."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._offset: float | None = None
        self._last: float | None = None

    def __call__(self, recorded_s: float, now: float) -> float:
        if self._offset is None:
            self._offset = now - recorded_s
        t = recorded_s + self._offset
        if self._last is not None and t <= self._last:
            log.warning("recording: frame time %.6f s does not advance past %.6f s; restarting "
                        "the timeline one frame later", t, self._last)
            self._offset += self._last + self.period_s - t
            t = self._last + self.period_s
        self._last = t
        return t


# ---- the device's calibration ----------------------------------------------------------------

def camera_model(intrinsics) -> CameraModel:
    """The project's camera model of a pyrealsense2 ``intrinsics`` (fx, fy, ppx, ppy, model,
    coeffs). librealsense puts pixel centres at integer coordinates, as PinholeCamera does
    (rs2_fov in include/librealsense2/rsutil.h measures the edges from ``ppx + 0.5``).

    Lens models, by what rs2_project_point_to_pixel (rsutil.h / src/rs.cpp) does with them:

    - ``none``: none;
    - ``brown_conrady``: OpenCV's radtan with the same coefficient order (k1, k2, p1, p2, k3);
    - ``kannala_brandt4``: equidistant, ``theta (1 + k1 theta^2 + ... + k4 theta^8)``;
    - ``modified_brown_conrady``, and ``inverse_brown_conrady`` (what a D4xx colour stream
      reports, src/ds/d400/d400-private.cpp), which librealsense projects the same way since
      2.25: the tangential terms are taken at the radially distorted point, which radtan cannot
      express exactly; the radtan coefficients closest to the SDK's own projection over the
      image are fitted (:func:`_fit_radtan`);
    - anything else (``ftheta``) is refused.
    """
    rs = _sdk()
    pinhole = PinholeCamera(intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy,
                            intrinsics.ppx, intrinsics.ppy)
    model, coeffs = intrinsics.model, tuple(intrinsics.coeffs)
    if model == rs.distortion.none:
        return CameraModel(pinhole)
    if model == rs.distortion.brown_conrady:
        return CameraModel(pinhole, "radtan", coeffs)
    if model == rs.distortion.kannala_brandt4:
        return CameraModel(pinhole, "equidistant", coeffs[:4])
    if model in (rs.distortion.modified_brown_conrady, rs.distortion.inverse_brown_conrady):
        return CameraModel(pinhole, "radtan", _fit_radtan(rs, intrinsics))
    raise CameraError(f"lens model {model} is not supported (none, brown_conrady, "
                      "modified_brown_conrady, inverse_brown_conrady, kannala_brandt4 are)")


def _fit_radtan(rs, intrinsics, samples: int = 41, margin: float = 1.25) -> tuple[float, ...]:
    """Radtan coefficients (k1, k2, p1, p2, k3) reproducing the SDK's projection of
    ``intrinsics`` within :data:`MAX_FIT_ERROR_PX` over the image.

    Rays on a grid over the pinhole field of view, widened by ``margin``, are projected with
    rs2_project_point_to_pixel; those landing in the image are the data. Radtan's displacement
    is linear in its coefficients, ``x_d - x = k1 x r^2 + k2 x r^4 + k3 x r^6 + 2 p1 x y +
    p2 (r^2 + 2 x^2)`` (and the same in y with p1, p2 swapped), so the pixel-weighted least
    squares is one linear solve. Raises CameraError when the best fit is worse than allowed.
    """
    i = intrinsics
    xs = np.linspace(-0.5 - i.ppx, i.width - 0.5 - i.ppx, samples) * margin / i.fx
    ys = np.linspace(-0.5 - i.ppy, i.height - 0.5 - i.ppy, samples) * margin / i.fy
    rays = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    pixels = np.array([rs.rs2_project_point_to_pixel(i, [x, y, 1.0]) for x, y in rays])
    inside = ((pixels >= -0.5) & (pixels <= [i.width - 0.5, i.height - 0.5])).all(axis=1)
    x, y = rays[inside].T
    r2 = x * x + y * y
    design = np.concatenate([
        i.fx * np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1),
        i.fy * np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)])
    shift = pixels[inside] - np.stack([i.fx * x + i.ppx, i.fy * y + i.ppy], axis=1)
    target = np.concatenate([shift[:, 0], shift[:, 1]])
    coefficients = np.linalg.lstsq(design, target, rcond=None)[0]
    error = float(np.abs(design @ coefficients - target).max())
    if error > MAX_FIT_ERROR_PX:
        raise CameraError(f"lens model {i.model} with coefficients {list(i.coeffs)} is not "
                          f"radtan within {MAX_FIT_ERROR_PX} px (best fit is {error:.3f} px off)")
    log.info("%s refitted as radtan %s, at most %.4f px off", i.model,
             np.round(coefficients, 6).tolist(), error)
    return tuple(float(c) for c in coefficients)


# ---- devices ---------------------------------------------------------------------------------

def list_devices() -> list[DeviceInfo]:
    """Each connected RealSense with its RGB8 colour modes ("640x480@30 RGB8"); [] when none.
    Raises MissingExtra when pyrealsense2 is not installed."""
    rs = _sdk()
    try:
        return [describe(device) for device in rs.context().query_devices()]
    except RuntimeError as error:
        raise CameraError(f"RealSense: cannot list devices: {error}") from None


def describe(device) -> DeviceInfo:
    """One pyrealsense2 device as ``companion devices`` shows it, addressed by its serial."""
    rs = _sdk()
    info = {key: device.get_info(getattr(rs.camera_info, key))
            for key in ("name", "serial_number", "firmware_version", "usb_type_descriptor")
            if device.supports(getattr(rs.camera_info, key))}
    details = ", ".join(f"{label} {info[key]}" for key, label in
                        (("firmware_version", "firmware"), ("usb_type_descriptor", "USB"))
                        if key in info)
    description = info.get("name", "RealSense") + (f" ({details})" if details else "")
    try:
        modes = _modes(_rgb_profiles(rs, _colour_sensor(rs, device)))
    except CameraError:  # a device without a colour stream is listed without modes
        modes = []
    return DeviceInfo("realsense", info.get("serial_number", ""), description, tuple(modes))


def _connected(rs, context, serial: str):
    """The connected device with ``serial``, or the only one when ``serial`` is ''."""
    devices = list(context.query_devices())
    serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
    if serial:
        if serial in serials:
            return devices[serials.index(serial)]
        raise CameraError(f"not connected (connected: {', '.join(serials) or 'none'})")
    if not devices:
        raise CameraError("no RealSense connected (check the USB 3 cable and the udev rules "
                          "in systemd/)")
    if len(devices) > 1:
        raise CameraError(f"{len(devices)} connected ({', '.join(serials)}): set "
                          "realsense.serial to one of them")
    return devices[0]


def _colour_sensor(rs, device):
    """The device's sensor that streams colour (a D4xx's "RGB Camera")."""
    for sensor in device.query_sensors():
        if any(p.stream_type() == rs.stream.color for p in sensor.get_stream_profiles()):
            return sensor
    raise CameraError("has no colour stream")


def _rgb_profiles(rs, sensor) -> list:
    return [p for p in sensor.get_stream_profiles()
            if p.stream_type() == rs.stream.color and p.format() == rs.format.rgb8]


def _size_rate(profile) -> tuple[int, int, int]:
    video = profile.as_video_stream_profile()
    return video.width(), video.height(), video.fps()


def _modes(profiles) -> list[str]:
    """The distinct modes of RGB8 profiles, smallest first: "640x480@30 RGB8"."""
    return [f"{w}x{h}@{fps} RGB8" for w, h, fps in sorted({_size_rate(p) for p in profiles})]


class HostAutoExposure:
    """The auto-exposure run on the host for a colour sensor without an exposure limit
    (module docstring): after each frame, :class:`~drivers.camera.exposure.ExposureLaw` from
    the frame's mean level, exposure up to ``auto_exposure_limit_us`` first, then gain from
    ``gain`` up to the sensor's highest, taken as proportional to the sensor's gain units. A
    setting is sent only when it changes the sensor's value; the sensor applies it some
    frames later, which the law's damped step allows for."""

    def __init__(self, rs, sensor, options: RealSenseOptions):
        self._rs, self._sensor = rs, sensor
        self.gain_min = options.gain
        self.gain_units_max = sensor.get_option_range(rs.option.gain).max
        self.law = ExposureLaw(TARGET_LEVEL, STEP_RATE, EXPOSURE_UNIT_US * 1e-6,
                               options.auto_exposure_limit_us * 1e-6,
                               max(1.0, self.gain_units_max / self.gain_min))
        self.product = options.exposure_us * 1e-6  # exposure x gain (as a multiple of gain_min)
        self.settings = (round(options.exposure_us / EXPOSURE_UNIT_US), options.gain)

    def after(self, rgb: np.ndarray) -> None:
        """Steer by the frame just read (uint8 RGB)."""
        self.product = self.law.step(self.product, mean_level(rgb))
        exposure = self.law.split(self.product)
        settings = (max(1, round(exposure.time_s * 1e6 / EXPOSURE_UNIT_US)),
                    min(self.gain_units_max, round(self.gain_min * exposure.gain)))
        if settings != self.settings:
            self._sensor.set_option(self._rs.option.exposure, settings[0])
            self._sensor.set_option(self._rs.option.gain, settings[1])
            self.settings = settings


def _set(rs, sensor, key: str, which, value: float) -> None:
    """Set one option of the colour sensor, or say which config key the device refuses."""
    if not sensor.supports(which):
        raise CameraError(f"the colour sensor has no {which} control (realsense.{key})")
    bounds = sensor.get_option_range(which)
    if not bounds.min <= value <= bounds.max:
        raise CameraError(f"realsense.{key}: {which} {value:g} is outside the sensor's range "
                          f"{bounds.min:g} to {bounds.max:g}")
    sensor.set_option(which, value)
