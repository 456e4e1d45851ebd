"""Serve the simulated vehicle over MAVLink: quadrotor + IMU model + mock PX4, one physics loop.

Physics runs at the IMU rate (``dt = 1 / ImuOptions.rate_hz``); each tick steps the vehicle,
samples the IMU over that step, and lets the mock PX4 read its link, fly and send. Two clocks:

- ``realtime``: ticks are paced by the wall clock (``MonotonicClock``), for outside MAVLink
  clients (MAVSDK, QGroundControl, the companion on another machine). A late tick is run at
  once, without sleeping, until the loop has caught up.
- ``lockstep``: a ``SimClock`` is advanced one tick at a time, as fast as the CPU allows;
  everything sleeping on that clock in the same event loop wakes in simulated time, so a run
  is deterministic and can be much faster than real time.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drivers.clock import MonotonicClock, SimClock
from drivers.mavlink import px4_protocol
from drivers.mavlink.link import mavlink, open_link
from drivers.sim.baro import Barometer, BaroOptions, baro_generator
from drivers.sim.faults import PACKET_LOSS, FaultSchedule, FaultyLink
from drivers.sim.imu import ImuModel, ImuOptions, flight_generators
from drivers.sim.options import CLOCK_MODES
from drivers.sim.mock_px4 import HOME_ALTITUDE_M, MockPx4, Px4Options
from drivers.sim.quadrotor import Collision, Quadrotor, VehicleOptions

log = logging.getLogger(__name__)

#: How the simulator's own flights (``companion sim fly``, :mod:`drivers.sim.host`) link the
#: application to the mock PX4: loopback UDP, or a serial port (the mock serving a
#: pseudo-terminal, the application opening its other side as ``serial://`` at
#: :data:`SERIAL_BAUD`: the code a flight controller on a UART goes through).
LINKS = ("udp", "serial")
#: The serial link's rate: a Pixracer's TELEM port as the paper's vehicle sets it.
SERIAL_BAUD = 921600


class StopSignal(Protocol):
    """Anything with ``is_set()``: ``asyncio.Event`` or ``threading.Event``."""

    def is_set(self) -> bool: ...


@dataclass(frozen=True)
class ServeSummary:
    """How a served run ended."""

    sim_time: float               # simulated seconds flown
    steps: int                    # physics ticks
    collision: Collision | None   # the collision that ended the flight, if any
    pty_path: str | None          # the pseudo-terminal served on, for url "pty"


def start_position(world) -> np.ndarray:
    """Where the vehicle starts: the first route's start of the world, else the origin."""
    routes = getattr(world, "routes", ()) if world is not None else ()
    return np.array(routes[0].start, dtype=float) if routes else np.zeros(3)


class SimulatedVehicle:
    """The vehicle, its IMU and the mock PX4 on one link, stepped together.

    ``faults`` injects the link and flight-controller faults of :mod:`drivers.sim.faults`
    (link cut or lossy, IMU gap, repeated or reordered, TIMESYNC silent, a forced disarm, a
    reboot). The vehicle stands at ``start`` (x, y, z in the world frame; default
    :func:`start_position`) heading ``start_yaw``, radians. ``seed`` draws the IMU's and the
    barometer's noise and the link's losses; ``vehicle_seed`` (default ``seed``) the IMU's
    scale and misalignment, which a vehicle keeps from flight to flight.
    """

    def __init__(self, link, world, *, seed: int = 0, vehicle_seed: int | None = None,
                 vehicle_options: VehicleOptions | None = None,
                 imu_options: ImuOptions | None = None, px4_options: Px4Options | None = None,
                 baro_options: BaroOptions | None = None,
                 start=None, start_yaw: float = 0.0, faults: FaultSchedule | None = None):
        self.imu_options = imu_options or ImuOptions().for_profile("ideal")
        self.dt = 1.0 / self.imu_options.rate_hz
        clearance = getattr(world, "obstacle_clearance", None) if world is not None else None
        _, estimator_seed, link_seed = np.random.SeedSequence(seed).spawn(3)
        self.vehicle = Quadrotor(vehicle_options or VehicleOptions(), clearance,
                                 position=start_position(world) if start is None else start,
                                 yaw=start_yaw)
        self.imu = ImuModel(self.imu_options, *flight_generators(
            seed, seed if vehicle_seed is None else vehicle_seed))
        self.link = FaultyLink(link, np.random.default_rng(link_seed))
        self.faults = faults or FaultSchedule()
        self._rebooted = False
        self.px4 = MockPx4(self.link, self.vehicle, px4_options or Px4Options(),
                           rng=np.random.default_rng(estimator_seed),
                           physics_rate_hz=self.imu_options.rate_hz)
        self.barometer = Barometer(baro_options or BaroOptions().for_profile("ideal"),
                                   baro_generator(seed), HOME_ALTITUDE_M)
        self.steps = 0

    @property
    def time(self) -> float:
        return self.vehicle.state.time

    def tick(self) -> None:
        """One physics step of dt, its IMU sample, then the flight controller at the new time."""
        truth = self.vehicle.step(self.dt)
        gyro, accel = self.imu.measure(truth, self.dt, thrust=self.vehicle.thrust)
        state = self.vehicle.state
        air_data = self.barometer.sample(state.time, state.position[2], state.velocity)
        self.steps += 1
        self._apply_faults()
        self.px4.update(state.time, gyro, accel, air_data)

    def _apply_faults(self) -> None:
        state, faults, px4 = self.vehicle.state, self.faults, self.px4
        faults.update(state.time, state.position, state.velocity,
                      landing=px4.mode == px4_protocol.AUTO_LAND)
        active = lambda kind: faults.active(kind, state.time)  # noqa: E731
        self.link.cut = active("link_cut")
        self.link.loss = PACKET_LOSS if active("packet_loss") else 0.0
        if active("disarm") and self.vehicle.armed:
            px4.force_disarm("a ground station's forced disarm (fault)")
        if active("px4_reboot") and not self._rebooted:
            self._rebooted = True
            px4.reboot()
        px4.imu_delivery = "repeat" if active("imu_repeat") else \
            "reorder" if active("imu_reorder") else None
        for stream, kind in ((mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, "imu_gap"),
                             (mavlink.MAVLINK_MSG_ID_TIMESYNC, "timesync_stop")):
            if active(kind):
                px4.suppressed_streams.add(stream)
            else:
                px4.suppressed_streams.discard(stream)


async def serve(url: str, world=None, *, seed: int = 0, vehicle_seed: int | None = None,
                clock_mode: str = "realtime",
                vehicle_options: VehicleOptions | None = None,
                imu_options: ImuOptions | None = None, px4_options: Px4Options | None = None,
                baro_options: BaroOptions | None = None, duration: float | None = None,
                stop: StopSignal | None = None,
                sim_clock: SimClock | None = None, stop_on_collision: bool = False,
                on_ready=None, start=None, start_yaw: float = 0.0,
                faults: FaultSchedule | None = None) -> ServeSummary:
    """Serve the vehicle on ``url`` until ``duration`` simulated seconds, ``stop`` is set, or
    (with ``stop_on_collision``) a collision; returns a :class:`ServeSummary`.

    ``world`` is a ``drivers.sim.world.World`` (anything with ``obstacle_clearance`` and
    ``routes``) or None for open space. ``sim_clock`` is advanced in lockstep mode (one is made
    if not given). ``on_ready(sim)`` is called with the :class:`SimulatedVehicle` once the link
    is open (e.g. to print the pty path). ``start``, ``start_yaw``, ``faults``, ``seed``,
    ``vehicle_seed`` and the options go to the :class:`SimulatedVehicle`.
    """
    if clock_mode not in CLOCK_MODES:
        raise ValueError(f"clock_mode must be one of {', '.join(CLOCK_MODES)}, got {clock_mode!r}")
    if duration is not None and not duration > 0:
        raise ValueError(f"duration must be positive seconds, got {duration!r}")
    link = open_link(url, source_system=(px4_options or Px4Options()).system_id,
                     source_component=(px4_options or Px4Options()).component_id)
    try:
        sim = SimulatedVehicle(link, world, seed=seed, vehicle_seed=vehicle_seed,
                               vehicle_options=vehicle_options,
                               imu_options=imu_options, px4_options=px4_options,
                               baro_options=baro_options, start=start, start_yaw=start_yaw,
                               faults=faults)
        if link.pty_path is not None:
            log.info("serving MAVLink on pseudo-terminal %s", link.pty_path)
        if on_ready is not None:
            on_ready(sim)
        run = _run_realtime if clock_mode == "realtime" else _run_lockstep
        await run(sim, lambda: _finished(sim, duration, stop, stop_on_collision), sim_clock)
        return ServeSummary(sim.time, sim.steps, sim.vehicle.collision, link.pty_path)
    finally:
        link.close()


def _finished(sim: SimulatedVehicle, duration, stop, stop_on_collision) -> bool:
    if duration is not None and sim.time >= duration - 0.5 * sim.dt:
        return True
    if stop is not None and stop.is_set():
        return True
    return stop_on_collision and sim.vehicle.collision is not None


async def _run_realtime(sim: SimulatedVehicle, finished, _sim_clock) -> None:
    clock = MonotonicClock()
    start_wall, start_sim = clock.now(), sim.time
    while not finished():
        sim.tick()
        await clock.sleep(start_wall + (sim.time - start_sim) - clock.now())


#: Ticks between yields to the event loop in lockstep when nobody sleeps on the clock.
LOCKSTEP_YIELD_EVERY = 10


async def _run_lockstep(sim: SimulatedVehicle, finished, sim_clock) -> None:
    clock = sim_clock or SimClock(sim.time)
    await asyncio.sleep(0)  # let tasks started before us begin at the first simulated instant
    while not finished():
        sim.tick()
        # asked before advancing: advance_to wakes (and so removes) the sleepers now due
        sleepers = clock.next_deadline is not None
        clock.advance_to(sim.time)
        if sleepers or sim.steps % LOCKSTEP_YIELD_EVERY == 0:
            await asyncio.sleep(0)
