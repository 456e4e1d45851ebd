"""The simulated camera: frames rendered from the simulated vehicle's true pose, on the clock.

A driver like any other camera driver: :meth:`SimCamera.next_frame` waits for the next frame
time of a ``rate_hz`` camera and returns a :class:`~autonomy.messages.Frame` stamped on the
companion's clock. It renders the world at the vehicle's true pose at that instant, through the
camera mounting ``T_B_C`` (``[camera]`` mount_*), and fills ``truth_depth`` (the
renderer's depth, for the synthetic network and for scoring).

Frames come on a fixed grid ``k / rate_hz``; a consumer slower than the camera gets the newest
frame and the ones it missed are counted in ``dropped`` (as a real driver with a one-frame
buffer). In lockstep the render happens while simulated time stands still, so the frame shows
exactly the pose at its stamp. Faults (:mod:`drivers.sim.faults`): ``camera_freeze`` delivers
nothing, ``camera_blackout`` delivers black images.
"""

from __future__ import annotations

import math

import numpy as np

from autonomy.geometry import make_pose, quat_to_rot
from autonomy.messages import Frame
from drivers.sim.record import T_BODY_CAMERA


class SimCamera:
    """Frames of ``renderer`` from the pose of ``sim`` (a :class:`~drivers.sim.serve.
    SimulatedVehicle`) at ``rate_hz``, on ``clock``, the camera mounted at ``T_B_C``."""

    def __init__(self, sim, renderer, rate_hz: float, clock, T_B_C=T_BODY_CAMERA):
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"camera rate must be a positive number of Hz, got {rate_hz}")
        self.sim, self.renderer, self.clock = sim, renderer, clock
        self.T_B_C = np.asarray(T_B_C, dtype=float)
        self.period = 1.0 / rate_hz
        self._next_index = math.ceil(clock.now() / self.period)
        self.delivered = 0
        self.dropped = 0

    async def next_frame(self) -> Frame:
        """The next frame at or after now (waiting for its time)."""
        while True:
            due = self._next_index * self.period
            await self.clock.sleep(due - self.clock.now())
            now = self.clock.now()
            missed = max(0, math.floor(now / self.period + 1e-9) - self._next_index)
            self.dropped += missed
            self._next_index += missed + 1
            if self.sim.faults.active("camera_freeze", self.sim.time):
                continue
            self.delivered += 1
            return self._render(now)

    def _render(self, t: float) -> Frame:
        state = self.sim.vehicle.state
        T_W_C = make_pose(quat_to_rot(state.q_W_B), state.position) @ self.T_B_C
        rgb, depth = self.renderer.render(T_W_C)
        if self.sim.faults.active("camera_blackout", self.sim.time):
            rgb = np.zeros_like(rgb)
        return Frame(t, rgb, depth)
