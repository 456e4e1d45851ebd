"""What a real camera does to the light the renderer computes: the simulated image sensor.

:class:`CameraSensor` turns a render of the world (:class:`drivers.sim.render.Renderer`: linear
radiance in ``[0, 1]`` and true z-depth) into the frame a real camera would deliver, in the
order the light meets the hardware (docs/simulator.md, "Camera sensor", cites every default):

1. **Motion during the exposure.** The renderer draws the pose at mid-exposure. Every pixel's
   image velocity follows exactly from its true depth and the camera's twist (the static-world
   optical flow, below); the image is the mean of ``n`` copies warped along it to instants
   spread evenly over the exposure ``E`` (motion blur), each row shifted by its readout instant
   (rolling shutter). The twist is held over the exposure (at most 33 ms: the vehicle's
   acceleration moves a pixel by ``a E^2 / 8 f / z``, well under one).
2. **The lens.** A radial-tangential lens (Kalibr's / OpenCV's model) maps the wide pinhole
   render onto the distorted image the driver delivers; the true depth follows the same map
   (nearest pixel), so it stays aligned with the image, as a RealSense's aligned depth does.
3. **Vignetting**: relative illumination ``1 - (1 - c) (r / r_corner)^2`` of the distorted
   radius, ``c`` at the corners.
4. **Exposure, gain and noise.** Electrons ``e = L (lux / 400) (E / 15.6 ms) full_well``, shot
   noise ``sqrt(e)``, read noise ``sigma_read``, both Gaussian; the value is
   ``clip(e G / full_well)`` in 8 bits. Auto-exposure (the law of msckf_vio's controller) scales
   the product ``E G`` by ``(target / mean)^rate`` after every frame, applied ``delay`` frames
   later; exposure first up to its maximum, then gain.
5. **Time.** The frame is stamped ``t_mid + offset + jitter`` (the application is not told the
   offset), and some frames never arrive.

Static-world optical flow. A point at normalised coordinates ``(x, y)`` and inverse depth
``rho`` seen by a camera moving with linear velocity ``v`` and angular velocity ``w`` (both in
the optical frame) moves at

    x' = -rho (v_x - x v_z) - a_x + x a_z,   y' = -rho (v_y - y v_z) - a_y + y a_z,
    a = w x (x, y, 1),

so pixel ``(u, v)`` moves at ``(fx x', fy y')``; sky (no depth) has ``rho = 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera, make_pose, quat_to_rot, so3_exp, undistort_points
from autonomy.lens import CameraModel
from autonomy.options import OptionError, option, validate
from drivers.camera.exposure import STEP_RATE, TARGET_LEVEL, Exposure, ExposureLaw, mean_level

#: EuRoC MAV cam0 (an MT9M034 behind a wide-angle lens), Kalibr radial-tangential
#: coefficients from the dataset's ``mav0/cam0/sensor.yaml`` (Burri et al. 2016).
EUROC_CAM0_RADTAN = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)

#: The radiometric anchor: a white surface lit at this illuminance saturates the sensor at
#: unity gain after :data:`REFERENCE_EXPOSURE_S` (an office scene at the RealSense D455's
#: default colour exposure).
REFERENCE_LUX = 400.0
#: The D455 colour sensor's default manual exposure, 156 in UVC units of 100 us (librealsense
#: device JSON ``controls-color-autoexposure-manual``).
REFERENCE_EXPOSURE_S = 0.0156
#: Most warped copies averaged for one blurred frame, and their spacing along the longest
#: blur streak, pixels (bilinear sampling fills the gaps).
MAX_BLUR_SAMPLES = 12
BLUR_SAMPLE_SPACING = 1.5
#: Pixel stride of the grid the optical flow is computed on.
FLOW_STRIDE = 4


@dataclass(frozen=True)
class SensorOptions:
    """The simulated camera's sensor, lens and timing: config table ``[sim_camera]``, used by
    the ``realistic`` profile (``[sim] profile``); sources in docs/simulator.md."""

    enabled: bool = option(True, doc="false: the realistic profile with an exact camera (the "
                           "world and IMU stay realistic), to measure what the sensor costs")
    time_offset_ms: float = option(15.0, ge=-40.0, le=40.0, doc="camera clock behind the IMU's: "
                                   "frames are stamped this late, unknown to the application")
    timestamp_jitter_ms: float = option(1.0, ge=0.0, le=10.0, doc="standard deviation of the "
                                        "frame stamps' jitter, ms")
    drop_probability: float = option(0.01, ge=0.0, lt=1.0, doc="chance that a frame never "
                                     "arrives")
    motion_blur: bool = option(True, doc="blur by the motion during the exposure")
    rolling_shutter_ms: float = option(0.0, ge=0.0, le=50.0, doc="readout time from the first "
                                       "row to the last; 0 is a global shutter (a D455's colour "
                                       "sensor; an OAK's IMX378 is rolling)")
    distortion: tuple[float, ...] = option(EUROC_CAM0_RADTAN, doc="radial-tangential lens "
                                           "(k1 k2 p1 p2 [k3]) drawn into the image; [] for a "
                                           "pinhole")
    corner_illumination: float = option(0.7, gt=0.0, le=1.0, doc="vignetting: relative "
                                        "illumination at the image corners")
    full_well_electrons: float = option(6000.0, gt=0.0, doc="electrons at saturation")
    read_noise_electrons: float = option(3.0, ge=0.0, doc="read noise, electrons rms")
    exposure_min_ms: float = option(0.1, gt=0.0, doc="shortest auto-exposure time, ms")
    exposure_max_ms: float = option(8.0, gt=0.0, doc="longest auto-exposure time, ms (the "
                                    "vehicle presets' auto_exposure_limit_us)")
    gain_max: float = option(16.0, ge=1.0, doc="highest analogue gain")
    exposure_target: float = option(TARGET_LEVEL, gt=0.0, lt=1.0, doc="mean image level the "
                                    "auto-exposure aims at, share of full scale")
    exposure_rate: float = option(STEP_RATE, gt=0.0, le=1.0, doc="auto-exposure step: the exposure "
                                  "moves by (target / mean)^rate per frame")
    exposure_delay_frames: int = option(2, ge=0, le=10, doc="frames before a new exposure "
                                        "takes effect")
    illuminance_mine: float = option(50.0, gt=0.0, doc="light on the mine's surfaces, lux")
    illuminance_sewer: float = option(100.0, gt=0.0, doc="light on the sewer's surfaces, lux")
    illuminance_dome: float = option(10000.0, gt=0.0, doc="daylight in the dome, lux")
    mount_rotation_error_deg: float = option(0.5, ge=0.0, le=10.0, doc="true camera mounting "
                                             "off the configured one by this angle, degrees")
    mount_translation_error_mm: float = option(5.0, ge=0.0, le=100.0, doc="true camera "
                                               "position off the configured one, mm")

    def __post_init__(self) -> None:
        validate(self)
        if self.exposure_min_ms > self.exposure_max_ms:
            raise OptionError("exposure_min_ms", f"must not exceed exposure_max_ms "
                              f"({self.exposure_max_ms}), got {self.exposure_min_ms}")
        if len(self.distortion) not in (0, 4, 5):
            raise OptionError("distortion", "radial-tangential takes 4 or 5 coefficients "
                              f"(k1 k2 p1 p2 [k3]) or none, got {len(self.distortion)}")

    def for_profile(self, profile: str) -> "SensorOptions | None":
        """The sensor a camera of the simulator's ``profile`` looks through: these options in
        ``realistic`` unless switched off (``enabled``), None (an exact camera) otherwise."""
        return self if profile == "realistic" and self.enabled else None

    def exposure_law(self) -> ExposureLaw:
        """The auto-exposure's control law within these limits."""
        return ExposureLaw(self.exposure_target, self.exposure_rate,
                           self.exposure_min_ms * 1e-3, self.exposure_max_ms * 1e-3,
                           self.gain_max)

    def illuminance(self, world: str) -> float:
        """The light level of ``world``, lux."""
        lux = getattr(self, f"illuminance_{world}", None)
        if lux is None:
            raise ValueError(f"no illuminance for world {world!r}; [sim_camera] has "
                             "illuminance_mine, illuminance_sewer and illuminance_dome")
        return lux


def camera_twist(state, T_B_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(v_C, w_C)``: the optical frame's linear and angular velocity, in the optical frame,
    of a camera mounted at ``T_B_C`` on a vehicle in ``state`` (a ``VehicleState``)."""
    R_W_B = quat_to_rot(state.q_W_B)
    w_B = np.asarray(state.angular_velocity_B, dtype=float)
    v_B = R_W_B.T @ np.asarray(state.velocity, dtype=float) + np.cross(w_B, T_B_C[:3, 3])
    R_C_B = T_B_C[:3, :3].T
    return R_C_B @ v_B, R_C_B @ w_B


def image_velocity(x: np.ndarray, y: np.ndarray, depth: np.ndarray, v_C, w_C
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(dx/dt, dy/dt)``, normalised image units per second, of the static-world points at
    normalised coordinates ``(x, y)`` and z-``depth`` (NaN: infinitely far) seen from a camera
    moving with ``(v_C, w_C)`` (module docstring)."""
    rho = np.where(np.isfinite(depth), 1.0 / np.maximum(np.nan_to_num(depth, nan=1.0), 1e-3),
                   0.0).astype(np.float32)
    wx, wy, wz = (float(c) for c in w_C)
    vx, vy, vz = (float(c) for c in v_C)
    ax, ay, az = wy - wz * y, wz * x - wx, wx * y - wy * x
    return (-rho * (vx - x * vz) - ax + x * az, -rho * (vy - y * vz) - ay + y * az)


class Lens:
    """Where each pixel of the distorted image of ``camera`` (its intrinsics) looks in a wide
    pinhole render, through radial-tangential ``distortion``; :attr:`render_camera` is the
    pinhole the renderer must draw, just wide enough for every distorted pixel's ray.
    ``map_u, map_v`` (float32, the image's shape) are those render pixels."""

    def __init__(self, camera: PinholeCamera, distortion: tuple[float, ...]):
        self.model = CameraModel(camera, "radtan" if distortion else "none", distortion)
        grid = np.stack(np.meshgrid(np.arange(camera.width, dtype=float),
                                    np.arange(camera.height, dtype=float)), -1).reshape(-1, 2)
        rays = undistort_points(camera, distortion, grid) if distortion else \
            (grid - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
        if not np.isfinite(rays).all():
            raise ValueError(f"the lens {distortion} cannot be inverted over a "
                             f"{camera.width}x{camera.height} image")
        u, v = camera.fx * rays[:, 0] + camera.cx, camera.fy * rays[:, 1] + camera.cy
        pad_u = math.ceil(max(0.0, -u.min(), u.max() - (camera.width - 1))) + 1
        pad_v = math.ceil(max(0.0, -v.min(), v.max() - (camera.height - 1))) + 1
        self.render_camera = PinholeCamera(camera.width + 2 * pad_u, camera.height + 2 * pad_v,
                                           camera.fx, camera.fy, camera.cx + pad_u,
                                           camera.cy + pad_v)
        shape = (camera.height, camera.width)
        self.map_u = (u + pad_u).reshape(shape).astype(np.float32)
        self.map_v = (v + pad_v).reshape(shape).astype(np.float32)
        # distorted radius of each pixel over the corners', for vignetting
        r = np.hypot((grid[:, 0] - camera.cx) / camera.fx, (grid[:, 1] - camera.cy) / camera.fy)
        self.radius = (r / r.max()).reshape(shape).astype(np.float32)

    def image(self, wide: np.ndarray, map_u=None, map_v=None, out=None) -> np.ndarray:
        """The image of a wide render (bilinear), through the lens or the maps given, into
        ``out`` if given."""
        return cv2.remap(wide, self.map_u if map_u is None else map_u,
                         self.map_v if map_v is None else map_v, cv2.INTER_LINEAR, dst=out,
                         borderMode=cv2.BORDER_REPLICATE)

    def depth(self, wide: np.ndarray) -> np.ndarray:
        """The true depth of every image pixel (nearest render pixel: no blending across
        edges)."""
        return cv2.remap(wide, self.map_u, self.map_v, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_REPLICATE)


class AutoExposure:
    """The camera's auto-exposure (:class:`~drivers.camera.exposure.ExposureLaw`, the one the
    vehicle's drivers run), each new setting taking effect ``delay`` frames after the frame it
    was computed from."""

    def __init__(self, options: SensorOptions):
        self.options = options
        self.law = options.exposure_law()
        self._queue: list[float] = []  # exposure time x gain of the coming frames, seconds

    def current(self, radiance_mean: float, scene_scale: float) -> Exposure:
        """The exposure of the next frame. The first frame starts converged (the camera streams
        before the flight), from the mean radiance and the scene's ``lux / 400`` scale."""
        if not self._queue:
            level = max(radiance_mean * scene_scale / REFERENCE_EXPOSURE_S, 1e-6)
            self._queue = [self.law.clip(self.options.exposure_target / level)] * \
                (self.options.exposure_delay_frames + 1)
        return self.law.split(self._queue[0])

    def update(self, measured_mean: float) -> None:
        """Steer by the mean level of the frame just taken (share of full scale), which the
        setting :meth:`current` returned took."""
        self._queue = self._queue[1:] + [self.law.step(self._queue[0], measured_mean)]


@dataclass(frozen=True)
class Capture:
    """One frame as the camera delivers it: its stamp (``None`` when the frame is dropped),
    the image, the true depth aligned with it, and how it was exposed."""

    stamp: float | None
    image: np.ndarray
    depth: np.ndarray
    exposure: Exposure


class CameraSensor:
    """The realistic camera of one world (module docstring): ``capture`` a render.

    Cost: one remap from the render straight into the image per blur sample (the lens and
    the motion in one map), the flow on a grid :data:`FLOW_STRIDE` times coarser (it is smooth
    but at depth edges, where the warp is approximate anyway), and the noise drawn from a bank
    made once, each row of the image at its own random offset in every frame (one offset for
    the whole image made each frame's noise the last one's moved whole, which the tracker
    follows: docs/simulator.md). Every full-frame intermediate lives in a buffer
    made once: a fresh megabyte-sized array per step would be fresh pages from the kernel,
    whose faults cost more than the arithmetic.

    ``rng`` draws the noise, the jitter and the lost frames; ``vehicle_rng`` (default ``rng``)
    the mounting error, which a vehicle keeps from flight to flight.
    """

    def __init__(self, options: SensorOptions, camera: PinholeCamera, world: str,
                 period: float, rng: np.random.Generator,
                 vehicle_rng: np.random.Generator | None = None):
        if options.time_offset_ms * 1e-3 + 3 * options.timestamp_jitter_ms * 1e-3 >= period:
            raise ValueError(f"a camera time offset of {options.time_offset_ms} ms (+3 sigma "
                             f"jitter) must stay under the frame period {period * 1e3:.1f} ms")
        self.options, self.camera, self.period = options, camera, period
        self.lens = Lens(camera, tuple(options.distortion))
        self.scene_scale = options.illuminance(world) / REFERENCE_LUX
        self.exposure = AutoExposure(options)
        self._rng = rng
        c = options.corner_illumination
        # one factor per channel, so that the products need no broadcasting (numpy's is slow)
        self._vignette = np.repeat((1.0 - (1.0 - c) * self.lens.radius ** 2)[..., None], 3, 2)
        wide = self.render_camera
        coarse_u = self.lens.map_u[::FLOW_STRIDE, ::FLOW_STRIDE]
        coarse_v = self.lens.map_v[::FLOW_STRIDE, ::FLOW_STRIDE]
        self._coarse = (coarse_u, coarse_v, (coarse_u - wide.cx) / wide.fx,
                        (coarse_v - wide.cy) / wide.fy)
        # each pixel's readout instant per second of readout, from the middle row
        self._row_offset = (self.lens.map_v - wide.cy) / camera.height
        bank = 2 * camera.height * camera.width * 3
        self._noise = rng.standard_normal(bank, dtype=np.float32)
        self._noise_image = np.empty((camera.height, camera.width * 3), np.float32)
        if vehicle_rng is not None:
            # A vehicle's generator is another flight's: past a bank of its own, its draws are
            # that flight's mounting, so a vehicle seed equal to the run's gives the run's.
            vehicle_rng.standard_normal(bank, dtype=np.float32)
        self._vehicle_rng = vehicle_rng
        shape = (camera.height, camera.width)
        self._map_u, self._map_v = np.empty(shape, np.float32), np.empty(shape, np.float32)
        self._sample = np.empty((*shape, 4), np.uint8)  # one warped copy of the render
        self._total = np.empty((*shape, 4), np.float32)  # the copies' sum
        self._radiance = np.empty((*shape, 3), np.float32)
        self._scratch = np.empty((*shape, 3), np.float32)

    @property
    def render_camera(self) -> PinholeCamera:
        """The pinhole the renderer must draw for :meth:`capture`."""
        return self.lens.render_camera

    def mount_error(self) -> np.ndarray:
        """A 4x4 rigid transform ``T_C_true``: where the camera truly is in the frame of its
        configured mounting, off by the options' rotation and translation errors in random
        directions (drawn once per flight)."""
        o = self.options
        draws = [self._rng.standard_normal(3) for _ in range(2)]  # the flight's stream moves on
        if self._vehicle_rng is not None:
            draws = [self._vehicle_rng.standard_normal(3) for _ in range(2)]
        axis, direction = _unit(draws[0]), _unit(draws[1])
        return make_pose(so3_exp(axis * math.radians(o.mount_rotation_error_deg)),
                         direction * o.mount_translation_error_mm * 1e-3)

    def capture(self, t_mid: float, rgb: np.ndarray, depth: np.ndarray, v_C, w_C) -> Capture:
        """The frame exposed around ``t_mid`` of a render (``rgb`` uint8, three channels or
        four with an opaque alpha, as :meth:`Renderer.render
        <drivers.sim.render.Renderer.render>` gives with ``alpha``; ``depth``) of
        :attr:`render_camera` at the pose of ``t_mid``, the camera moving with ``(v_C, w_C)``
        (optical frame, :func:`camera_twist`)."""
        o = self.options
        # OpenCV remaps four channels fastest
        rgba = rgb if rgb.shape[2] == 4 else cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA)
        exposure = self.exposure.current(mean_level(rgba[..., :3]), self.scene_scale)
        image = self._expose(self._through_lens(rgba, depth, v_C, w_C, exposure.time_s),
                             exposure)
        self.exposure.update(mean_level(image))
        jitter = float(np.clip(self._rng.normal(0.0, o.timestamp_jitter_ms * 1e-3),
                               -self.period / 4, self.period / 4))
        dropped = self._rng.random() < o.drop_probability
        stamp = None if dropped else t_mid + o.time_offset_ms * 1e-3 + jitter
        return Capture(stamp, image, self.lens.depth(depth), exposure)

    def _through_lens(self, rgba, depth, v_C, w_C, exposure_s: float) -> np.ndarray:
        """The image (float32, 0..1, a buffer reused by the next frame) of the render seen
        through the lens, each pixel the mean over the instants it integrated light (module
        docstring, steps 1 and 2)."""
        o = self.options
        readout = o.rolling_shutter_ms * 1e-3
        span = exposure_s if o.motion_blur else 0.0
        self._total.fill(0.0)
        if not (span or readout):
            self._add_copy(rgba, self.lens.map_u, self.lens.map_v)
            return self._radiance_of(1)
        coarse_du, coarse_dv = self._flow(depth, v_C, w_C)
        longest = float(np.sqrt(coarse_du ** 2 + coarse_dv ** 2).max()) * span
        samples = int(np.clip(math.ceil(longest / BLUR_SAMPLE_SPACING), 1, MAX_BLUR_SAMPLES))
        size = (self.camera.width, self.camera.height)
        du = cv2.resize(coarse_du, size, interpolation=cv2.INTER_LINEAR)
        dv = cv2.resize(coarse_dv, size, interpolation=cv2.INTER_LINEAR)
        base_u, base_v = self.lens.map_u, self.lens.map_v
        if readout:  # the maps at each row's readout instant
            base_u = base_u - du * (self._row_offset * readout)
            base_v = base_v - dv * (self._row_offset * readout)
        for k in range(samples):
            step = span * ((k + 0.5) / samples - 0.5)
            cv2.scaleAdd(du, -step, base_u, dst=self._map_u)
            cv2.scaleAdd(dv, -step, base_v, dst=self._map_v)
            self._add_copy(rgba, self._map_u, self._map_v)
        return self._radiance_of(samples)

    def _add_copy(self, rgba: np.ndarray, map_u: np.ndarray, map_v: np.ndarray) -> None:
        """Add the render warped by the maps to the copies' sum."""
        cv2.accumulate(self.lens.image(rgba, map_u, map_v, out=self._sample), self._total)

    def _radiance_of(self, samples: int) -> np.ndarray:
        """The mean of the ``samples`` copies summed, colour channels only, 0..1, into the
        radiance buffer (a contiguous copy first: numpy is several times slower on the
        strided view)."""
        colour = cv2.cvtColor(self._total, cv2.COLOR_RGBA2RGB, dst=self._radiance)
        return np.multiply(colour, np.float32(1.0 / (255.0 * samples)), out=self._radiance)

    def _flow(self, depth: np.ndarray, v_C, w_C) -> tuple[np.ndarray, np.ndarray]:
        """The image's velocity in render pixels per second on the coarse grid."""
        coarse_u, coarse_v, x, y = self._coarse
        coarse_depth = cv2.remap(depth, coarse_u, coarse_v, cv2.INTER_NEAREST,
                                 borderMode=cv2.BORDER_REPLICATE)
        dx, dy = image_velocity(x, y, coarse_depth, v_C, w_C)
        wide = self.render_camera
        return dx * np.float32(wide.fx), dy * np.float32(wide.fy)

    def _expose(self, radiance: np.ndarray, exposure: Exposure) -> np.ndarray:
        """8-bit values of the image's radiance (module docstring, steps 3 and 4); works in
        ``radiance``'s buffer."""
        o = self.options
        electrons_at_unity = (self.scene_scale * exposure.time_s / REFERENCE_EXPOSURE_S
                              * o.full_well_electrons)
        gain = np.multiply(self._vignette, np.float32(electrons_at_unity), out=self._scratch)
        electrons = np.multiply(radiance, gain, out=radiance)
        # each row from its own place in the bank: no shift maps one frame's noise on the next
        noise, length = self._noise_image, self._noise_image.shape[1]
        starts = self._rng.integers(0, self._noise.size - length + 1, noise.shape[0])
        for row, start in enumerate(starts.tolist()):
            noise[row] = self._noise[start:start + length]
        noise = noise.reshape(radiance.shape)
        deviation = np.add(electrons, np.float32(o.read_noise_electrons ** 2),
                           out=self._scratch)
        np.sqrt(deviation, out=deviation)
        electrons += np.multiply(deviation, noise, out=deviation)
        return cv2.convertScaleAbs(np.maximum(electrons, 0.0, out=electrons),
                                   alpha=255.0 * exposure.gain / o.full_well_electrons)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
