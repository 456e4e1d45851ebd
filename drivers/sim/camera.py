"""The simulated camera: frames rendered from the simulated vehicle's true pose, on the clock.

:class:`CameraHead` is the camera on the airframe: where it truly sits, what the renderer must
draw, and, in the ``realistic`` profile, the sensor between the light and the frame
(:mod:`drivers.sim.sensor`: motion blur, lens, vignetting, exposure and noise, a late and
jittery stamp, lost frames). ``sim record`` shoots through it at its own ticks;
:class:`SimCamera` is the driver ``sim fly`` reads.

:meth:`SimCamera.next_frame` waits for the next exposure of a ``rate_hz`` camera (mid-exposure
on the grid ``k / rate_hz``), renders the world at the vehicle's true pose at that instant and
hands the frame over at its stamp, on the companion's clock, with ``truth_depth`` (the
renderer's depth, aligned with the image, for the synthetic network and for scoring) and
``truth_pose`` (that pose, for the flight recording). A
consumer slower than the camera gets the newest frame and the ones it missed are counted in
``dropped`` (as a real driver with a one-frame buffer); frames the camera itself lost are
counted in ``lost``. In lockstep the render happens while simulated time stands still, so the
frame shows exactly the pose at its exposure. Faults (:mod:`drivers.sim.faults`):
``camera_freeze`` delivers nothing, ``camera_blackout`` black images, ``camera_stale`` the last
frame before it began (its image, depth and number) at each new stamp.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace

import numpy as np

from autonomy.geometry import PinholeCamera, make_pose, quat_to_rot
from autonomy.lens import CameraModel
from autonomy.messages import Frame
from drivers.camera.options import CameraOptions
from drivers.sim.quadrotor import VehicleState
from drivers.sim.sensor import Capture, CameraSensor, Exposure, SensorOptions, camera_twist

#: The default camera mounting (``[camera]`` mount_*): optical frame looking along body x,
#: 10 cm ahead of the body origin and 5 cm above it.
T_BODY_CAMERA = CameraOptions().T_B_C()

#: The exposure reported for an ideal camera's frames: an instant, no gain.
INSTANT = Exposure(0.0, 1.0)
#: A tick this close to an instant of the frame grid, in frame periods, falls on it.
GRID_TOLERANCE = 1e-6


class CameraHead:
    """The camera of ``pinhole`` intrinsics at ``rate_hz``, configured at mounting ``T_B_C``;
    ``sensor`` (the realistic profile's ``[sim_camera]``) or None for an ideal camera: exact
    pose, instant exposure, exact stamps. A sensor needs the ``world`` it flies in (its light)
    and ``rng``, which draws its noise, lost frames and (unless ``vehicle_rng`` does) mounting
    error. ``numbered``: the device numbers its frames (``Frame.counter``, the exposure's index
    on the camera's grid), as a RealSense or an OAK does."""

    def __init__(self, pinhole: PinholeCamera, rate_hz: float, T_B_C=T_BODY_CAMERA,
                 sensor: SensorOptions | None = None, world: str = "",
                 rng: np.random.Generator | None = None,
                 vehicle_rng: np.random.Generator | None = None, numbered: bool = True):
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"camera rate must be a positive number of Hz, got {rate_hz}")
        self.pinhole, self.period, self.numbered = pinhole, 1.0 / rate_hz, numbered
        self.T_B_C_configured = np.asarray(T_B_C, dtype=float)
        self.sensor = None if sensor is None else CameraSensor(
            sensor, pinhole, world, self.period,
            rng if rng is not None else np.random.default_rng(), vehicle_rng)
        #: Where the camera truly is: the configured mounting, off by a calibration error.
        self.T_B_C = self.T_B_C_configured if self.sensor is None else \
            self.T_B_C_configured @ self.sensor.mount_error()

    @property
    def render_camera(self) -> PinholeCamera:
        """The pinhole the renderer must draw (wider than the image behind a lens)."""
        return self.pinhole if self.sensor is None else self.sensor.render_camera

    @property
    def model(self) -> CameraModel:
        """The lens of the delivered frames, as a factory calibration states it."""
        return CameraModel(self.pinhole) if self.sensor is None else self.sensor.lens.model

    def shoot(self, renderer, t_mid: float, state) -> Capture:
        """The frame exposed around ``t_mid`` by a vehicle in ``state`` (a ``VehicleState`` at
        ``t_mid``), drawn by ``renderer`` (of :attr:`render_camera`)."""
        T_W_C = make_pose(quat_to_rot(state.q_W_B), state.position) @ self.T_B_C
        if self.sensor is None:
            rgb, depth = renderer.render(T_W_C)
            return Capture(t_mid, rgb, depth, INSTANT)
        rgba, depth = renderer.render(T_W_C, alpha=True)
        return self.sensor.capture(t_mid, rgba, depth, *camera_twist(state, self.T_B_C))


class SimCamera:
    """Frames of ``head`` drawn by ``renderer`` from the pose of ``sim`` (a
    :class:`~drivers.sim.serve.SimulatedVehicle`), on ``clock``."""

    def __init__(self, sim, renderer, clock, head: CameraHead):
        self.sim, self.renderer, self.clock, self.head = sim, renderer, clock, head
        self.period = head.period
        self._next_index = math.ceil(clock.now() / self.period)
        # the shutter's newest exposure: (index on the grid, time, the vehicle's state then)
        self._exposed: tuple[int, float, VehicleState] | None = None
        self._shutter: asyncio.Task | None = None
        self.delivered = 0
        self.dropped = 0
        self.lost = 0
        self._last: Frame | None = None  # what a stale camera repeats
        self._held: Frame | None = None  # a frame_reorder fault's frame, until the next one
        self._again: list[Frame] = []  # frames delivered again or late, next in line

    async def next_frame(self) -> Frame:
        """The next frame whose exposure is at or after now (waiting for its stamp); under a
        ``frame_repeat`` or ``frame_reorder`` fault, frames come twice or in swapped pairs."""
        if self._again:
            return self._again.pop(0)
        while True:
            index, t_exposed, state = await self._newest_exposure()
            self.dropped += index - self._next_index
            self._next_index = index + 1
            if self.sim.faults.active("camera_freeze", self.sim.time):
                continue
            capture = self.head.shoot(self.renderer, t_exposed, state)
            if capture.stamp is None:
                self.lost += 1
                continue
            if capture.stamp > self.clock.now():  # a late stamp: the frame arrives then
                await self.clock.sleep(capture.stamp - self.clock.now())
            self.delivered += 1
            truth = make_pose(quat_to_rot(state.q_W_B), state.position)
            counter = self._next_index - 1 if self.head.numbered else None
            frame = self._deliver(replace(self._picture(capture, counter), truth_pose=truth))
            if frame is not None:
                return frame

    async def _newest_exposure(self) -> tuple[int, float, VehicleState]:
        """``(index on the grid, time, the vehicle's state then)`` of the newest exposure not
        yet delivered: one the shutter took while the reader was busy, else the next one,
        waited for (taken at the tick it falls on, so that in lockstep the frame is rendered
        and handed over while simulated time stands still)."""
        if self._shutter is None:
            self._shutter = asyncio.ensure_future(self._run_shutter())
        if self._exposed is not None and self._exposed[0] >= self._next_index:
            return self._exposed
        if self.clock.now() < (self._next_index - GRID_TOLERANCE) * self.period:
            await self._sleep_until(self._next_index)
        return self._exposure_now()  # on the tick of the instant (the shutter may come after)

    async def _run_shutter(self) -> None:
        """The camera's own clock: at each instant ``k / rate_hz`` of the grid, the vehicle's
        state is what that frame will show, whether or not anyone reads it then. A reader late
        for a frame gets the newest one exposed, as old as it is, not one exposed when it asked
        (a real camera does not wait for its reader)."""
        while True:
            await self._sleep_until(self._next_exposure_index())
            self._exposed = self._exposure_now()

    async def _sleep_until(self, index: int) -> None:
        """Until the tick that falls on the grid's instant ``index``: within
        :data:`GRID_TOLERANCE` of a period, which a clock stepped by adding its ticks misses by
        rounding (a sleep of nothing would wait for the next tick)."""
        await self.clock.sleep((index - GRID_TOLERANCE) * self.period - self.clock.now())

    def _next_exposure_index(self) -> int:
        newest = -1 if self._exposed is None else self._exposed[0]
        return max(newest + 1, self._next_index)

    def _exposure_now(self) -> tuple[int, float, VehicleState]:
        """The exposure at the newest grid instant at or before now (a tick falls on or just
        after it), taken now."""
        now = self.clock.now()
        return math.floor(now / self.period + GRID_TOLERANCE), now, self.sim.vehicle.state

    async def stop(self) -> None:
        """Stop the shutter (the simulator is stopping)."""
        if self._shutter is not None:
            self._shutter.cancel()
            await asyncio.gather(self._shutter, return_exceptions=True)

    def _picture(self, capture, counter: int | None) -> Frame:
        """The capture, numbered ``counter``, as the image faults leave it: stale (the last
        frame again, its number too, under the new stamp) or black."""
        faults, t = self.sim.faults, self.sim.time
        if faults.active("camera_stale", t) and self._last is not None:
            return replace(self._last, t=capture.stamp)
        self._last = Frame(capture.stamp, capture.image, capture.depth, counter=counter)
        if faults.active("camera_blackout", t):
            return replace(self._last, image=np.zeros_like(capture.image))
        return self._last

    def _deliver(self, frame: Frame) -> Frame | None:
        """``frame`` now, or None while a ``frame_reorder`` fault holds it back to follow the
        next; a held frame comes after the one that overtook it, and under ``frame_repeat``
        every frame comes twice."""
        faults, t = self.sim.faults, self.sim.time
        if faults.active("frame_reorder", t) and self._held is None:
            self._held = frame
            return None
        if self._held is not None:
            self._again.append(self._held)
            self._held = None
        if faults.active("frame_repeat", t):
            self._again.append(frame)
        return frame
