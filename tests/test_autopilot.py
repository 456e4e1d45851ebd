"""The companion's PX4 driver against the mock PX4 over real loopback UDP (or a serial port: the
mock on a pseudo-terminal).

The simulator is served in the test's own event loop, in lockstep on a SimClock that the
Autopilot sleeps on too, so simulated time is exact and runs faster than real time; the link
loss test runs both in real time (a restarted simulator boots at time zero again). Every test
has a wall-clock timeout, so a regression fails instead of hanging.
"""

import asyncio
import logging
import math
import os
import re
import socket
import threading
import time
import tty
from dataclasses import replace

import numpy as np
import pytest

from autonomy.geometry import GRAVITY
from autonomy.options import OptionError
from drivers.clock import MonotonicClock, SimClock
from drivers.mavlink import px4_protocol
from drivers.mavlink.autopilot import (Autopilot, CommandDenied, CommandTimeout,
                                       CompanionStatus, MavlinkOptions, NotConnected)
from drivers.mavlink.imu_stream import ImuStamper, updated_pressure
from drivers.mavlink.link import mavlink, open_link
from drivers.mavlink.odometry import pose_covariance_to_mavlink
from drivers.mavlink.provision import ProvisionError, Provisioned, provision
from drivers.mavlink.signing import load_key
from drivers.mavlink.timesync import RESET_AFTER_OUTLIERS, TimesyncFilter
from drivers.sim.baro import isa_pressure
from drivers.sim.imu import ImuOptions
from drivers.sim.mock_px4 import HOME_ALTITUDE_M, Px4Options
from drivers.sim.serve import serve

DT = 0.005  # the simulator's physics and IMU period
KEY = "ab" * 32
WALL_TIMEOUT = 90.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def until(clock, predicate, timeout: float, step: float = 0.01) -> bool:
    """Wait on ``clock`` until ``predicate()`` holds (True) or ``timeout`` passes (False)."""
    deadline = clock.now() + timeout
    while not predicate():
        if clock.now() >= deadline:
            return False
        await clock.sleep(step)
    return True


class Flight:
    """A served simulator and an Autopilot on one clock; ``truth`` records the IMU samples
    the mock PX4 was given: (time at the end of the step, gyro FLU, accel FLU).

    ``serial_name``: the link is a serial port, the mock serving a pseudo-terminal that this
    path (a symbolic link, as udev's /dev/serial/by-id names) points to."""

    def __init__(self, clock, options: MavlinkOptions, serial_name=None, **serve_kwargs):
        self.clock, self.options, self.serve_kwargs = clock, options, serve_kwargs
        self.serial_name = serial_name
        self.port = free_udp_port()
        self.sim = None
        self.truth = []
        self.autopilot = None

    def _ready(self, sim) -> None:
        self.sim = sim
        update = sim.px4.update

        def recording_update(t, gyro=None, accel=None, air_data=None):
            self.truth.append((t, np.array(gyro), np.array(accel)))
            update(t, gyro, accel, air_data)
        sim.px4.update = recording_update

    async def start_server(self) -> None:
        """Serve on the flight's port until ``self.stop`` is set (the task is ``server``)."""
        kwargs = dict(self.serve_kwargs)
        if isinstance(self.clock, SimClock):
            kwargs.update(clock_mode="lockstep", sim_clock=self.clock)
        self.stop = asyncio.Event()
        url = "pty" if self.serial_name else f"udpin://127.0.0.1:{self.port}"
        self.server = asyncio.create_task(serve(url, None, stop=self.stop, duration=600.0,
                                                on_ready=self._ready, **kwargs))
        await asyncio.sleep(0)  # the link is open once serve first yields
        if self.serial_name:  # "plugged in"
            self.serial_name.unlink(missing_ok=True)
            self.serial_name.symlink_to(self.sim.px4.link.pty_path)

    @property
    def url(self) -> str:
        """Where a companion reaches the served simulator."""
        return (f"serial://{self.serial_name}:921600" if self.serial_name
                else f"udpout://127.0.0.1:{self.port}")

    async def serve(self, main) -> None:
        """Run ``await main(self)`` against the served simulator, then stop serving."""
        await self.start_server()
        try:
            await main(self)
        finally:
            self.stop.set()
            await asyncio.gather(self.server, return_exceptions=True)

    async def fly(self, body) -> None:
        await self.serve(lambda flight: flight.with_autopilot(self.options, body))

    async def with_autopilot(self, options: MavlinkOptions, body) -> None:
        """Run ``await body(self)`` with ``self.autopilot`` open on ``options`` and running."""
        self.autopilot = Autopilot.open(replace(options, url=self.url), self.clock)
        runner = asyncio.create_task(self.autopilot.run())
        try:
            await body(self)
            assert not runner.done(), "Autopilot.run() ended"
        finally:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
            self.autopilot.close()

    async def connected(self, timeout=5.0) -> bool:
        return await until(self.clock, lambda: self.autopilot.connected, timeout)


def fly(body, options=None, clock=None, serial_name=None, **serve_kwargs):
    """Run ``await body(flight)`` against a served simulator (lockstep unless a clock)."""
    flight = Flight(clock or SimClock(), options or MavlinkOptions(), serial_name,
                    **serve_kwargs)
    asyncio.run(asyncio.wait_for(flight.fly(body), WALL_TIMEOUT))
    return flight


def serve_flight(main, **serve_kwargs) -> None:
    """Run ``await main(flight)`` against a simulator served in lockstep, no companion open."""
    flight = Flight(SimClock(), MavlinkOptions(), **serve_kwargs)
    asyncio.run(asyncio.wait_for(flight.serve(main), WALL_TIMEOUT))


async def stream_velocity(flight: Flight, velocity_L, seconds: float, rate_hz=20.0):
    """Send a velocity setpoint at ``rate_hz`` for ``seconds`` on the flight's clock."""
    end = flight.clock.now() + seconds
    while flight.clock.now() < end:
        flight.autopilot.send_velocity(velocity_L, 0.0)
        await flight.clock.sleep(1.0 / rate_hz)


# -------------------------------------------------------------------- options and pure parts

def test_options_default_to_an_onboard_computer_talking_to_px4():
    options = MavlinkOptions()
    assert (options.system_id, options.component_id) == (1, 191)
    assert (options.target_system, options.target_component) == (1, 1)
    assert options.imu_rate_hz == 200.0 and load_key(options) is None


@pytest.mark.parametrize("changes, key", [
    ({"signing_key": "abc"}, "signing_key"),
    ({"signing_key": "zz" * 32}, "signing_key"),
    ({"url": "udp://127.0.0.1:14540"}, "url"),
    ({"imu_rate_hz": 0.0}, "imu_rate_hz"),
    ({"component_id": 256}, "component_id"),
])
def test_bad_options_name_the_field(changes, key):
    with pytest.raises(OptionError) as error:
        MavlinkOptions(**changes)
    assert error.value.key == key


def test_timesync_filter_averages_ignores_one_outlier_and_follows_a_clock_jump():
    f = TimesyncFilter()
    for k, error in enumerate([0.002, -0.002, 0.001, -0.001]):
        remote = 10.0 + k
        assert f.add(remote + 5.0 - 0.001 + error, remote, remote + 5.0 + 0.001 + error)
    assert f.offset == pytest.approx(5.0, abs=1e-9)
    assert not f.add(20.0, 14.0 - 1.0, 20.001)  # one sample 1 s off: ignored
    assert f.offset == pytest.approx(5.0, abs=1e-9)
    assert not f.add(20.0, 15.0, 20.5)          # a 0.5 s round trip: too loose to use
    assert f.rejected_rtt == 1
    for k in range(RESET_AFTER_OUTLIERS):       # PX4 rebooted: its clock restarted
        f.add(30.0 + k, 0.1 + k, 30.001 + k)
    assert f.offset == pytest.approx(29.9005, abs=1e-6) and f.resets == 1
    assert f.to_local(1.0) == pytest.approx(30.9005) and f.to_remote(30.9005) == \
        pytest.approx(1.0)


def test_imu_stamper_holds_each_sample_from_the_previous_stamp_in_flu():
    stamper = ImuStamper(200.0)
    assert stamper.push(1.000, (0.1, 0.2, 0.3), (1, 2, 3), offset=10.0) is None  # first
    sample = stamper.push(1.005, (0.1, 0.2, 0.3), (1.0, 2.0, -9.8), offset=10.0)
    assert sample.t == pytest.approx(11.000)
    np.testing.assert_allclose(sample.gyro, [0.1, -0.2, -0.3])
    np.testing.assert_allclose(sample.accel, [1.0, -2.0, 9.8])
    assert stamper.push(1.005, (0, 0, 0), (0, 0, 0), offset=10.0) is None   # not later
    assert stamper.push(1.050, (0, 0, 0), (0, 0, 0), offset=10.0) is None   # a gap
    assert stamper.push(1.055, (0, 0, 0), (0, 0, 0), offset=10.0).t == pytest.approx(11.050)
    assert stamper.push(1.060, (math.nan, 0, 0), (0, 0, 0), offset=10.0) is None
    assert stamper.push(1.065, (0, 0, 0), (0, 0, 0), offset=None) is None
    assert dict(stamper.counts) == {"first": 1, "backwards": 1, "gap": 1, "invalid": 1,
                                    "no_time": 1}


def test_imu_stamper_passes_a_new_pressure_on_in_pascals_and_leaves_out_one_no_barometer_reads():
    """PX4 sends hPa (MAVLink's unit) since 2023, pascals before: the size says which. A
    pressure neither can be is left out of its sample, which is kept."""
    stamper = ImuStamper(200.0)
    stamper.push(1.000, (0, 0, 0), (0, 0, 0), offset=0.0)
    assert stamper.push(1.005, (0, 0, 0), (0, 0, 0), 0.0, 955.9).pressure_pa == \
        pytest.approx(95590.0)
    assert stamper.push(1.010, (0, 0, 0), (0, 0, 0), 0.0, 95590.0).pressure_pa == 95590.0
    assert stamper.push(1.015, (0, 0, 0), (0, 0, 0), 0.0, None).pressure_pa is None
    for k, bad in enumerate((0.0, math.nan, -955.9, 5000.0, 2e5)):
        sample = stamper.push(1.020 + 0.005 * k, (0, 0, 0), (0, 0, 0), 0.0, bad)
        assert sample is not None and sample.pressure_pa is None
    assert stamper.counts["bad_pressure"] == 5
    # HIGHRES_IMU's abs_pressure counts only where fields_updated marks it new
    assert updated_pressure(0b111111 | (1 << 9), 955.9) == 955.9
    assert updated_pressure(0b111111 | (1 << 12), 955.9) is None


def test_pose_covariance_goes_to_ned_position_and_euler_angles():
    # q_L_B identity: level, facing east (x of frame L), so PX4's yaw is +90 degrees
    sigma = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # roll, pitch, yaw, forward, left, up
    upper = pose_covariance_to_mavlink(sigma, (1.0, 0.0, 0.0, 0.0))
    full = np.zeros((6, 6))
    full[np.triu_indices(6)] = upper
    # forward (east) is NED y, left (north) is NED x, up is -down
    np.testing.assert_allclose(np.diag(full), [5.0, 4.0, 6.0, 1.0, 2.0, 3.0], atol=1e-12)
    assert math.isnan(pose_covariance_to_mavlink(None, (1, 0, 0, 0))[0])
    assert math.isnan(pose_covariance_to_mavlink(np.full((6, 6), np.nan), (1, 0, 0, 0))[0])
    with pytest.raises(ValueError, match="6x6"):
        pose_covariance_to_mavlink(np.eye(3), (1, 0, 0, 0))


# -------------------------------------------------------------------- over the link

def test_connects_and_streams_imu_at_200hz_in_flu_on_the_companion_clock():
    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        assert await until(flight.clock, lambda: autopilot.imu_rate_hz > 190.0, 5.0)
        assert flight.sim.px4.message_rate_hz(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU) == 200.0
        autopilot.take_imu()
        await flight.clock.sleep(1.0)
        samples = autopilot.take_imu()
        assert len(samples) == pytest.approx(200, abs=2)
        np.testing.assert_allclose(np.diff([s.t for s in samples]), DT, atol=1e-5)
        theta = autopilot.timesync.offset
        # the simulator's boot time is the SimClock's time: the IMU is stamped on the camera's
        # clock to well under a millisecond (half a tick off costs a flight ~1 % of its scale)
        assert abs(theta) <= 1e-4
        truth = {round(t / DT): (gyro, accel) for t, gyro, accel in flight.truth}
        for sample in samples:
            # the sample holding over [t, t + DT) is the one the IMU integrated up to t + DT
            gyro, accel = truth[round((sample.t - theta + DT) / DT)]
            np.testing.assert_allclose(sample.gyro, gyro, atol=1e-5)
            np.testing.assert_allclose(sample.accel, accel, atol=1e-4)
        assert np.mean([s.accel[2] for s in samples]) == pytest.approx(GRAVITY, abs=0.05)
        assert autopilot.last_imu_t == samples[-1].t
        # PX4's 20 Hz barometer rides along, in the samples whose interval it was sent in
        pressures = [s.pressure_pa for s in samples if s.pressure_pa is not None]
        assert len(pressures) == pytest.approx(20, abs=1)
        assert np.mean(pressures) == pytest.approx(isa_pressure(HOME_ALTITUDE_M), abs=2.0)
        assert autopilot.landed and not autopilot.in_air and not autopilot.armed
        assert autopilot.mode == px4_protocol.AUTO_LOITER
    fly(body)


def test_timesync_converges_both_ways():
    async def body(flight):
        assert await flight.connected()
        assert await until(flight.clock,
                           lambda: flight.sim.px4.timesync_offset_ns is not None, 3.0)
        await flight.clock.sleep(2.0)
        assert abs(flight.autopilot.timesync.offset) <= 1e-4
        assert abs(flight.sim.px4.timesync_offset_ns) <= DT * 1e9
        assert flight.autopilot.stats()["timesync_answered"] >= 1
        assert flight.autopilot.time_synced
        state = flight.autopilot.state
        assert state is not None and abs(state.t - flight.clock.now()) < 0.1
        np.testing.assert_allclose(state.T_L_B[:3, 3], state.position_L)
    fly(body)


def test_heartbeat_shows_the_companion_status():
    received = []

    async def body(flight):
        assert await flight.connected()
        # listen in on the mock's side of the link for our heartbeats
        receive = flight.sim.px4.link.receive_pending

        def spy():
            messages = receive()
            received.extend(m for m in messages if m.get_type() == "HEARTBEAT")
            return messages
        flight.sim.px4.link.receive_pending = spy
        flight.autopilot.set_status(CompanionStatus.CRITICAL)
        await flight.clock.sleep(0.05)
    fly(body)
    heartbeat = received[-1]
    assert heartbeat.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert heartbeat.system_status == mavlink.MAV_STATE_CRITICAL
    assert (heartbeat.get_srcSystem(), heartbeat.get_srcComponent()) == (1, 191)


def test_arm_take_off_offboard_velocity_in_enu_hold_land():
    async def body(flight):
        autopilot, clock = flight.autopilot, flight.clock
        assert await flight.connected()
        assert not await autopilot.set_mode(px4_protocol.OFFBOARD)
        error = autopilot.last_command_error
        assert isinstance(error, CommandDenied)
        assert error.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert "Offboard is currently not available" in str(error)
        assert await autopilot.arm()
        assert await autopilot.takeoff(3.0)
        assert await until(clock, lambda: autopilot.in_air, 2.0)
        assert await until(clock, lambda: autopilot.state.position_L[2] > 2.8
                           and autopilot.mode == px4_protocol.AUTO_LOITER, 10.0)
        await clock.sleep(3.0)  # the climb overshoots a little, then holds
        assert flight.sim.vehicle.state.position[2] == pytest.approx(3.0, abs=0.3)
        start = autopilot.state.position_L.copy()
        await stream_velocity(flight, (0.0, 0.0, 0.0), 1.2)  # PX4 wants a stream first
        streaming = asyncio.create_task(stream_velocity(flight, (1.0, 0.0, 0.0), 4.0))
        assert await autopilot.set_mode(px4_protocol.OFFBOARD)
        assert await until(clock, lambda: autopilot.mode == px4_protocol.OFFBOARD, 2.0)
        await streaming
        moved = autopilot.state.position_L - start
        assert moved[0] > 2.0 and abs(moved[1]) < 0.3 and abs(moved[2]) < 0.3  # east
        assert flight.sim.vehicle.state.position[0] > 2.0
        assert autopilot.state.velocity_L[0] > 0.5
        assert await autopilot.hold()
        assert await until(clock, lambda: autopilot.mode == px4_protocol.AUTO_LOITER, 1.0)
        assert await autopilot.land()
        assert await until(clock, lambda: autopilot.landed, 15.0)
        assert await autopilot.disarm()
        assert await until(clock, lambda: not autopilot.armed, 2.0)
    fly(body)


async def _take_off_to_offboard(flight, height: float) -> None:
    """Arm, take off to ``height`` and switch to Offboard, streaming zero velocity."""
    autopilot, clock = flight.autopilot, flight.clock
    assert await flight.connected()
    assert await autopilot.arm()
    assert await autopilot.takeoff(height)
    assert await until(clock, lambda: autopilot.mode == px4_protocol.AUTO_LOITER
                       and autopilot.state.position_L[2] > height - 0.2, 15.0)
    await stream_velocity(flight, (0.0, 0.0, 0.0), 1.2)  # PX4 wants a stream first
    streaming = asyncio.create_task(stream_velocity(flight, (0.0, 0.0, 0.0), 0.5))
    assert await autopilot.set_mode(px4_protocol.OFFBOARD)
    await streaming


def test_a_disarm_after_a_touch_down_is_told_from_one_in_the_air():
    """PX4 says landed once it disarms, in the air too (its land detector), so only what it
    said while armed tells them apart: its auto-disarm after Offboard velocity flew the
    vehicle down onto the ground reads as on the ground; a forced disarm 6 m up, whose landed
    state turns to the ground with the disarm while the vehicle still falls (1.1 s, longer than
    the HEARTBEAT period), reads as in the air."""
    async def down_onto_the_ground(flight):
        autopilot = flight.autopilot
        await _take_off_to_offboard(flight, 2.0)
        assert not autopilot.disarmed_on_the_ground
        streaming = asyncio.create_task(stream_velocity(flight, (0.0, 0.0, -1.0), 8.0))
        assert await until(flight.clock, lambda: not autopilot.armed, 8.0)
        assert autopilot.mode == px4_protocol.OFFBOARD and flight.sim.vehicle.landed
        assert autopilot.disarmed_on_the_ground
        streaming.cancel()

    async def killed_in_the_air(flight):
        autopilot = flight.autopilot
        await _take_off_to_offboard(flight, 6.0)
        assert await autopilot.disarm(force=True)
        # PX4 says landed at once: heard within a heartbeat period, the vehicle still falling
        assert await until(flight.clock, lambda: not autopilot.armed and autopilot.landed, 1.0)
        assert flight.sim.vehicle.state.position[2] > 0.5
        assert not autopilot.disarmed_on_the_ground

    fly(down_onto_the_ground)
    fly(killed_in_the_air)


def test_acceleration_feed_forward_lets_the_vehicle_brake_as_commanded():
    """A braking ramp 1.5 m/s -> 0 over 1.5 s: the velocity loop alone lags it (at the ramp's
    end the vehicle is still moving, further on); the ramp's deceleration sent as feed-forward
    keeps the vehicle much nearer to it."""
    ramp_s, speed, rate_hz = 1.5, 1.5, 30.0

    async def brake(flight, feed_forward: bool) -> tuple[float, float]:
        """(distance beyond the ramp's 1.125 m, speed left) at the ramp's end."""
        autopilot, clock = flight.autopilot, flight.clock
        await stream_velocity(flight, (speed, 0.0, 0.0), 3.0)  # steady at cruise
        start, t0 = flight.sim.vehicle.state.position[0], clock.now()
        while clock.now() < t0 + ramp_s:
            left = 1.0 - (clock.now() - t0) / ramp_s
            autopilot.send_velocity((speed * left, 0.0, 0.0), 0.0,
                                    (-speed / ramp_s, 0.0, 0.0) if feed_forward else None)
            await clock.sleep(1.0 / rate_hz)
        state = flight.sim.vehicle.state
        return state.position[0] - start - speed * ramp_s / 2.0, state.velocity[0]

    async def body(flight):
        await _take_off_to_offboard(flight, 3.0)
        beyond, still_moving = await brake(flight, feed_forward=False)
        assert beyond > 0.4 and still_moving > 0.4  # the loop's lag
        beyond_ff, still_moving_ff = await brake(flight, feed_forward=True)
        assert beyond_ff < 0.5 * beyond and still_moving_ff < 0.5 * still_moving
    fly(body)


def test_external_vision_odometry_reaches_px4():
    async def body(flight):
        autopilot = flight.autopilot
        assert not autopilot.send_odometry(0.0, (0, 0, 0), (1, 0, 0, 0))  # no time yet
        assert autopilot.stats()["odometry_no_time"] == 1
        assert await flight.connected()
        assert await until(flight.clock, lambda: autopilot.timesync.offset is not None, 1.0)
        shifted = np.array([1.0, 2.0, 0.0])  # vision says the vehicle is 1 m east, 2 north
        for _ in range(20):
            assert autopilot.send_odometry(flight.clock.now(), shifted, (1, 0, 0, 0),
                                           np.zeros(3), np.zeros(3), np.eye(6) * 1e-4,
                                           quality=80)
            await flight.clock.sleep(0.05)
        assert flight.sim.px4.external_vision_active
        np.testing.assert_allclose(flight.sim.px4.estimate.position, shifted, atol=0.1)
        await flight.clock.sleep(0.1)
        np.testing.assert_allclose(autopilot.state.position_L, shifted, atol=0.1)
    fly(body)


def test_imu_rate_far_below_the_request_is_asked_again():
    async def body(flight):
        assert await flight.connected()
        await flight.clock.sleep(8.0)
        assert flight.autopilot.imu_rate_hz == pytest.approx(100.0, rel=0.05)
        assert flight.autopilot.stats()["imu_interval_requests"] >= 2
        assert flight.autopilot.take_imu()  # samples still come, at the rate PX4 can give
    # a flight controller whose IMU runs at 100 Hz cannot send 200 Hz
    fly(body, imu_options=ImuOptions(rate_hz=100.0))


def test_link_loss_is_detected_and_the_imu_rate_requested_again_after_it():
    clock = MonotonicClock()

    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        first_sim = flight.sim
        imu_rate = lambda: flight.sim.px4.message_rate_hz(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU)
        assert await until(clock, lambda: imu_rate() == 200.0, 3.0)
        flight.stop.set()  # the served vehicle goes away
        await flight.server
        assert await until(clock, lambda: not autopilot.connected, 5.0)
        assert autopilot.link_losses == 1
        await flight.start_server()  # and comes back, booted afresh
        assert flight.sim is not first_sim and imu_rate() == 50.0
        assert await flight.connected(5.0)
        assert await until(clock, lambda: imu_rate() == 200.0, 3.0)
        autopilot.take_imu()
        assert await until(clock, lambda: len(autopilot.take_imu()) > 0, 2.0)
    fly(body, clock=clock)


def test_a_serial_adapter_unplugged_is_a_lost_link_at_once_and_reopened_when_back(tmp_path):
    """USB unplugged: the vehicle's end of the serial line goes away (our reads find the
    end: EIO on a USB adapter). That is a lost link at once, not after the link timeout, and
    never an exception out of run(); the port is closed and tried again every second, and when
    the adapter is back under its name (udev's by-id link) the link comes back up."""
    clock = MonotonicClock()

    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        flight.stop.set()  # unplugged
        await flight.server
        unplugged = clock.now()
        assert await until(clock, lambda: not autopilot.connected, 0.5)
        assert clock.now() - unplugged < 0.5 < autopilot.options.link_timeout_s
        assert autopilot.link_losses == 1 and autopilot.stats()["device_lost"] == 1
        assert autopilot.link_problem == (
            f"serial port {flight.serial_name} at 921600 baud lost: end of file (its other "
            "side closed); reopening it every 1 s")
        await flight.start_server()  # plugged back in: a new device under the same name
        assert await flight.connected(3.0)
        assert autopilot.link_losses == 1 and autopilot.link_problem == ""
        autopilot.take_imu()
        assert await until(clock, lambda: len(autopilot.take_imu()) > 0, 2.0)
    fly(body, clock=clock, serial_name=tmp_path / "usb-Pixracer-if00")


def at_wrong_baud(data: bytes, sent_baud: int, read_baud: int) -> bytes:
    """What a UART reading at ``read_baud`` makes of ``data`` sent at ``sent_baud`` (8N1, the
    line idle high): from each start bit it finds (a low level) it samples eight data bits in
    the middle of its own bit times, then looks for the next one after the stop bit."""
    bits = [1]
    for byte in data:
        bits += [0] + [(byte >> i) & 1 for i in range(8)] + [1]
    bits += [1] * 10
    level = lambda t: bits[min(int(t * sent_baud / read_baud), len(bits) - 1)]  # noqa: E731
    received, t, end = [], 0.0, len(bits) * read_baud / sent_baud
    while t < end:
        if level(t):
            t += 0.25  # the receiver looks for a start bit four times a bit
            continue
        received.append(sum(level(t + 1.5 + i) << i for i in range(8)))
        t += 9.5
    return bytes(received)


ARMED, DISARMED = "armed", "disarmed"
ON_GROUND, IN_AIR = mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_IN_AIR


def disarm_read(script) -> bool:
    """What the driver makes of PX4's last disarm (``disarmed_on_the_ground``) after PX4's end
    of a serial line wrote ``script`` to it: HEARTBEATs (``ARMED``, ``DISARMED``), landed
    states (``ON_GROUND``, ``IN_AIR``) and pauses (seconds, a float), in that order."""
    clock = MonotonicClock()
    master, slave = os.openpty()
    tty.setraw(slave)
    px4 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def message(step):
        if step in (ARMED, DISARMED):
            base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
                mavlink.MAV_MODE_FLAG_SAFETY_ARMED if step == ARMED else 0)
            return px4.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                        base_mode, 0, mavlink.MAV_STATE_ACTIVE)
        return px4.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, step)

    async def main():
        options = MavlinkOptions(url=f"serial://{os.ttyname(slave)}:921600")
        autopilot = Autopilot.open(options, clock)
        runner = asyncio.create_task(autopilot.run())
        try:
            for step in script:
                if isinstance(step, float):
                    await clock.sleep(step)
                    continue
                read = autopilot.link.messages_received
                os.write(master, message(step).pack(px4))
                # each read in a poll of its own, as PX4's messages come
                assert await until(clock, lambda: autopilot.link.messages_received > read, 2.0)
            return autopilot.disarmed_on_the_ground
        finally:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
            autopilot.close()

    try:
        return asyncio.run(asyncio.wait_for(main(), WALL_TIMEOUT))
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("script, on_the_ground", [
    # PX4's auto-disarm: on the ground while armed, a heartbeat still armed, then disarmed
    ([ARMED, IN_AIR, ON_GROUND, ARMED, ON_GROUND, DISARMED], True),
    # a disarm in the air: PX4 says landed only after it, so after its last armed heartbeat
    ([ARMED, IN_AIR, ON_GROUND, DISARMED], False),
    # ... however many of its heartbeats are lost (within the link's timeout)
    ([ARMED, IN_AIR, ON_GROUND, 0.6, ON_GROUND, 0.6, DISARMED], False),
    # armed on the ground and disarmed there before a take-off
    ([DISARMED, ON_GROUND, ARMED, ON_GROUND, ARMED, DISARMED], True),
    # landed once, then bounced back into the air before the disarm
    ([ARMED, ON_GROUND, ARMED, IN_AIR, ON_GROUND, DISARMED], False),
    # a touch-down's disarm forgotten once PX4 is armed again, and flown in the air
    ([ARMED, ON_GROUND, ARMED, DISARMED, ARMED, IN_AIR, ON_GROUND, DISARMED], False),
    # armed on the ground, then the link lost (3.5 s): what PX4 said before says nothing of
    # a disarm heard after (it may have taken off and been killed meanwhile)
    ([ARMED, ON_GROUND, ARMED, 3.5, ON_GROUND, DISARMED], False),
])
def test_the_driver_tells_a_disarm_on_the_ground_from_one_in_the_air(script, on_the_ground):
    assert disarm_read(script) is on_the_ground


def test_a_silent_serial_link_says_whether_bytes_came_and_what_to_check(caplog):
    """A serial link to PX4 never up: the log says once, after the link timeout, what came
    instead of MAVLink and what to check, and :attr:`link_problem` (which the preflight quotes)
    says it as it is now: no bytes at all (the wrong port or cable), bytes that do not parse
    (PX4's heartbeats sent at 57600 baud read at 921600), MAVLink from another system."""
    clock = MonotonicClock()
    master, slave = os.openpty()  # PX4's end of the line, raw
    tty.setraw(slave)
    path = os.ttyname(slave)
    px4 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeats = b"".join(px4.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                               mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0).pack(px4)
                          for _ in range(5))

    async def main():
        options = MavlinkOptions(url=f"serial://{path}:921600", link_timeout_s=0.2)
        autopilot = Autopilot.open(options, clock)
        runner = asyncio.create_task(autopilot.run())
        try:
            await clock.sleep(0.4)
            silent = autopilot.link_problem
            os.write(master, at_wrong_baud(heartbeats, 57600, 921600))
            await clock.sleep(0.05)
            garbled = autopilot.link_problem
            other = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
            os.write(master, other.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                                    mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0
                                                    ).pack(other))
            await clock.sleep(0.05)
            return silent, garbled, autopilot.link_problem, autopilot.stats()
        finally:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
            autopilot.close()

    with caplog.at_level(logging.WARNING, logger="drivers.mavlink.autopilot"):
        try:
            silent, garbled, foreign, stats = asyncio.run(asyncio.wait_for(main(), WALL_TIMEOUT))
        finally:
            os.close(master)
            os.close(slave)
    seconds = r"in \d+\.\d s: "
    assert re.match(f"no MAVLink from {path} at 921600 baud {seconds}no bytes at all: check "
                    r"the TELEM port and its wiring .* and the baud rate \(PX4 SER_TELn_BAUD\)$",
                    silent), silent
    assert re.match(f"no MAVLink from {path} at 921600 baud {seconds}"
                    r"\d+ bytes arrived but none parse as MAVLink: check the baud rate \(PX4 "
                    r"SER_TELn_BAUD must be 921600\) and the TELEM port \(MAV_n_CONFIG",
                    garbled), garbled
    assert stats["bad_data"] > 0
    assert re.match(f"MAVLink arrives from {path} at 921600 baud but no HEARTBEAT from system 1 "
                    f"component 1 {seconds}check \\[mavlink\\] target_system", foreign), foreign
    logged = [r.getMessage() for r in caplog.records if "no MAVLink from" in r.getMessage()]
    assert len(logged) == 1 and "no bytes at all" in logged[0]


class Px4StandIn(threading.Thread):
    """A flight controller in its own thread, as on the vehicle: HEARTBEAT at 1 Hz and a
    flood of small messages (100 every 10 ms), so that while nobody reads our socket its
    buffer fills within tens of milliseconds and whatever comes after, HEARTBEATs too, is
    dropped."""

    def __init__(self, port: int):
        super().__init__(name="px4-stand-in", daemon=True)
        self.port, self.quiet = port, threading.Event()

    def run(self) -> None:
        link = open_link(f"udpout://127.0.0.1:{self.port}", source_system=1, source_component=1)
        next_heartbeat = 0.0
        try:
            while not self.quiet.is_set():
                if time.monotonic() >= next_heartbeat:
                    link.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR,
                                            mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
                    next_heartbeat = time.monotonic() + 1.0
                for _ in range(100):
                    link.mav.system_time_send(0, 0)
                time.sleep(0.01)
        finally:
            link.close()


def test_a_stalled_event_loop_is_not_taken_for_a_lost_link():
    """While our own loop is blocked nobody reads the link: PX4's HEARTBEATs are lost in our
    socket's full buffer, not on the wire, and that time must not count as PX4's silence.
    A real silence after it is still caught within the link timeout."""
    clock, port = MonotonicClock(), free_udp_port()
    options = MavlinkOptions(url=f"udpin://127.0.0.1:{port}", command_retries=0)
    stand_in = Px4StandIn(port)

    async def body(autopilot):
        assert await until(clock, lambda: autopilot.connected, 5.0)
        await clock.sleep(0.5)
        time.sleep(2.0 * options.link_timeout_s)  # the loop stalls (a blocking call)
        await clock.sleep(0.2)
        assert autopilot.connected and autopilot.link_losses == 0
        stand_in.quiet.set()  # now PX4 does go silent
        assert await until(clock, lambda: not autopilot.connected,
                           options.link_timeout_s + 1.0)
        assert autopilot.link_losses == 1

    async def main():
        autopilot = Autopilot.open(options, clock)
        runner = asyncio.create_task(autopilot.run())
        stand_in.start()
        try:
            await body(autopilot)
        finally:
            stand_in.quiet.set()
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
            autopilot.close()
            stand_in.join(2.0)
    asyncio.run(asyncio.wait_for(main(), WALL_TIMEOUT))


def test_signing_on_both_ends_works_with_a_watchdog_thread_sending_too():
    async def body(flight):
        autopilot = flight.autopilot
        assert autopilot.link.signing_enabled
        assert await flight.connected()
        assert await until(flight.clock, lambda: autopilot.imu_rate_hz > 190.0, 5.0)
        watchdog = threading.Thread(
            target=lambda: [autopilot.send_velocity((0.0, 0.0, 0.0)) for _ in range(300)])
        watchdog.start()
        assert await autopilot.arm()
        while watchdog.is_alive():
            await flight.clock.sleep(0.01)
        await flight.clock.sleep(0.05)
        assert flight.sim.vehicle.armed
        assert flight.sim.px4.link.bad_data_count == 0  # every signed frame arrived whole
    fly(body, MavlinkOptions(signing_key=KEY), px4_options=Px4Options(signing_key=KEY))


def test_a_wrong_key_is_rejected_both_ways():
    async def body(flight):
        assert not await flight.connected(3.0)
        assert flight.sim.px4.link.bad_data_count > 0
        assert flight.autopilot.stats()["bad_data"] > 0
        assert flight.autopilot.signing["bad_signature"] > 0
        assert "PX4 (system 1 component 1) on udpout://127.0.0.1" in \
            flight.autopilot.link_problem
        assert "signs with another key" in flight.autopilot.link_problem
        assert not await flight.autopilot.arm()
        assert isinstance(flight.autopilot.last_command_error, NotConnected)
        with pytest.raises(NotConnected, match="no HEARTBEAT"):
            await flight.autopilot.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    fly(body, MavlinkOptions(signing_key="cd" * 32), px4_options=Px4Options(signing_key=KEY))


def test_px4_requiring_signing_ignores_an_unsigned_companion():
    async def body(flight):
        assert await flight.connected()  # we hear PX4 (its signatures are not checked) ...
        assert not await flight.autopilot.arm()  # ... but it does not listen to us
        assert isinstance(flight.autopilot.last_command_error, CommandTimeout)
        assert "no COMMAND_ACK" in str(flight.autopilot.last_command_error)
        assert not flight.sim.vehicle.armed
        assert flight.sim.px4.link.bad_data_count > 0
    fly(body, px4_options=Px4Options(signing_key=KEY))


def test_a_signing_companion_refuses_a_px4_without_a_key_and_says_so():
    async def body(flight):
        assert not await flight.connected(3.0)
        assert flight.autopilot.signing["unsigned"] > 0
        assert "does not sign" in flight.autopilot.link_problem
        assert "companion signing provision" in flight.autopilot.link_problem
    fly(body, MavlinkOptions(signing_key=KEY))


def test_after_provisioning_px4_ignores_an_unsigned_companion_and_flies_a_signed_one():
    key = bytes.fromhex(KEY)

    async def unsigned(flight):
        assert await flight.connected()  # PX4's signed messages are not checked without a key
        assert not await flight.autopilot.arm()
        assert isinstance(flight.autopilot.last_command_error, CommandTimeout)

    async def signed(flight):
        assert await flight.connected()
        assert await flight.autopilot.arm() and await flight.autopilot.takeoff(1.0)
        assert await until(flight.clock, lambda: flight.autopilot.in_air, 3.0)
        assert flight.autopilot.signing == {"on": True, "unsigned": 0, "bad_signature": 0}

    async def main(flight):
        options = MavlinkOptions(url=flight.url)
        assert await provision(options, flight.clock, key, timeout_s=2.0) == \
            Provisioned(had_key=False, already=False)
        assert flight.sim.px4.signing_key == key
        assert await provision(options, flight.clock, key, timeout_s=2.0) == \
            Provisioned(had_key=True, already=True)
        await flight.with_autopilot(MavlinkOptions(), unsigned)
        assert not flight.sim.vehicle.armed
        await flight.with_autopilot(MavlinkOptions(signing_key=KEY), signed)
    serve_flight(main)


def test_a_px4_key_is_replaced_only_with_the_old_key_and_never_while_armed():
    old, new = bytes.fromhex(KEY), bytes(range(32))

    async def main(flight):
        options = MavlinkOptions(url=flight.url)
        with pytest.raises(ProvisionError, match="already signs with another key: give that "
                                                 "key with --current-key-file"):
            await provision(options, flight.clock, new, timeout_s=1.0)
        with pytest.raises(ProvisionError, match="signs with neither"):
            await provision(options, flight.clock, new, current_key=bytes(32 * [5]),
                            timeout_s=1.0)
        assert flight.sim.px4.signing_key == old
        flight.sim.vehicle.arm()
        with pytest.raises(ProvisionError, match="PX4 is armed"):
            await provision(options, flight.clock, new, current_key=old, timeout_s=1.0)
        flight.sim.vehicle.disarm()
        assert await provision(options, flight.clock, new, current_key=old, timeout_s=2.0) == \
            Provisioned(had_key=True, already=False)
        assert flight.sim.px4.signing_key == new
    serve_flight(main, px4_options=Px4Options(signing_key=KEY))


def test_provisioning_a_silent_link_says_what_came_instead():
    async def main():
        url = f"udpout://127.0.0.1:{free_udp_port()}"
        with pytest.raises(ProvisionError, match="no HEARTBEAT from PX4 .*: no MAVLink from "
                                                 "udpout.* no bytes at all"):
            await provision(MavlinkOptions(url=url), MonotonicClock(), bytes(32), timeout_s=0.3)
    asyncio.run(main())


def test_bad_setpoints_and_odometry_raise_and_send_nothing():
    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        for velocity, yaw_rate in [((math.nan, 0, 0), 0.0), ((0, 0, 0), math.inf),
                                   ((1, 2), 0.0)]:
            with pytest.raises(ValueError):
                autopilot.send_velocity(velocity, yaw_rate)
        with pytest.raises(ValueError, match="acceleration_L"):
            autopilot.send_velocity((0, 0, 0), 0.0, (0, math.inf, 0))
        with pytest.raises(ValueError, match="position_L"):
            autopilot.send_odometry(flight.clock.now(), (0, math.nan, 0), (1, 0, 0, 0))
        with pytest.raises(ValueError, match="unit quaternion"):
            autopilot.send_odometry(flight.clock.now(), (0, 0, 0), (2, 0, 0, 0))
        for quality in (101, -2, 50.0, True):  # MAVLink's range: -1 failed .. 100 best
            with pytest.raises(ValueError, match="quality"):
                autopilot.send_odometry(flight.clock.now(), (0, 0, 0), (1, 0, 0, 0),
                                        quality=quality)
        with pytest.raises(ValueError, match="altitude"):
            await autopilot.takeoff(-1.0)
        await flight.clock.sleep(0.1)
        assert not flight.sim.px4.external_vision_active
        assert "SET_POSITION_TARGET" not in " ".join(s.text for s in autopilot.statustexts)
    fly(body)


def test_garbage_and_other_systems_are_ignored():
    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        address = ("127.0.0.1", autopilot.link._connection.port.getsockname()[1])
        stranger = open_link(f"udpout://{address[0]}:{address[1]}", source_system=42,
                             source_component=1)
        impostor = open_link(f"udpout://{address[0]}:{address[1]}", source_system=1,
                             source_component=100)
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
                for n in range(50):
                    raw.sendto(bytes([0xFD, n, 0, 0, 0]) + bytes(range(n)), address)
                    raw.sendto(np.random.default_rng(n).bytes(200), address)
            stranger.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR,
                                        mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
            impostor.mav.timesync_send(0, 12345)
            await flight.clock.sleep(0.5)
        finally:
            stranger.close()
            impostor.close()
        stats = autopilot.stats()
        assert stats["bad_data"] > 0 and stats["foreign"] >= 2
        assert autopilot.connected and autopilot.link_losses == 0
        assert autopilot.take_imu()
    fly(body)


def test_a_statustext_in_chunks_is_joined_and_an_endless_one_is_cut():
    """A text in MAVLink 2 chunks (``id``, ``chunk_seq``) is one text once its short last
    chunk comes; a sender that never ends one (full chunks of one id, again and again) gets
    texts cut at PX4's longest, 3 chunks, instead of a list of chunks that only grows (seen
    in the fuzzing review)."""
    async def body(flight):
        autopilot = flight.autopilot
        assert await flight.connected()
        px4 = flight.sim.px4.link.mav
        warning = mavlink.MAV_SEVERITY_WARNING
        for seq in range(30):  # more would overflow the socket's receive buffer
            px4.statustext_send(warning, b"x" * 50, 9, seq)
        for seq, chunk in enumerate((b"a" * 50, b"b" * 50, b"end")):
            px4.statustext_send(warning, chunk, 7, seq)
        await flight.clock.sleep(0.5)
        texts = [status.text for status in autopilot.statustexts]
        assert texts[-1] == "a" * 50 + "b" * 50 + "end"
        assert texts[:-1] == ["x" * 150 + " [cut]"] * 10
    fly(body)
