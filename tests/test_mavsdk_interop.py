"""Acceptance: MAVSDK, a MAVLink client written by others, flies the mock PX4 over loopback UDP.

The simulator serves in real time in a background thread (its own event loop), as
`companion sim serve` would; MAVSDK connects with the connection string a user would type.
Every wait has a timeout, so a regression fails fast instead of hanging. What MAVSDK reads is
in its telemetry_impl.cpp: ATTITUDE for the Euler attitude, SYS_STATUS's
MAV_SYS_STATUS_PREARM_CHECK health bit for ``health().is_armable``.
"""

import asyncio
import math
import time

import pytest

mavsdk = pytest.importorskip("mavsdk.asyncio")

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync, ActionError  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.param import ParamAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from mavsdk.autopilot import Autopilot  # noqa: E402
from mavsdk.vehicle import Vehicle  # noqa: E402

from drivers.mavlink import px4_protocol  # noqa: E402
from drivers.mavlink.link import mavlink, open_link  # noqa: E402


async def first(generator, predicate=lambda _: True, timeout=10.0):
    """The first item of an async generator that satisfies ``predicate``, within ``timeout``."""
    async def search():
        async for item in generator:
            if predicate(item):
                return item
    try:
        return await asyncio.wait_for(search(), timeout)
    finally:
        await generator.aclose()


async def count_imu(telemetry: TelemetryAsync, samples: int, timeout=10.0):
    """Rate of IMU messages (per second of the vehicle's own timestamps) over ``samples``."""
    stamps = []

    async def collect():
        async for imu in telemetry.subscribe_imu():
            stamps.append(imu.timestamp_us)
            if len(stamps) >= samples:
                return
    await asyncio.wait_for(collect(), timeout)
    return (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-6)


async def connect(drone: Mavsdk, port: int):
    """The autopilot MAVSDK discovers on the served port, as a ground station."""
    await drone.add_any_connection(f"udpout://127.0.0.1:{port}")
    system = await drone.first_autopilot(timeout_s=10.0)
    assert system is not None, "MAVSDK discovered no autopilot"
    return system


def ground_station() -> Mavsdk:
    return Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))


async def fly(port: int) -> None:
    async with ground_station() as drone:
        system = await connect(drone, port)
        assert await system.autopilot_type() == Autopilot.PX4
        assert await system.vehicle_type() == Vehicle.MULTICOPTER

        telemetry, action, offboard = (TelemetryAsync(system), ActionAsync(system),
                                       OffboardAsync(system))
        await asyncio.wait_for(telemetry.set_rate_imu(200.0), 10)
        assert await count_imu(telemetry, 200) == pytest.approx(200, rel=0.05)

        # ATTITUDE: the vehicle stands facing east, 90 degrees from north
        euler = await first(telemetry.subscribe_attitude_euler())
        assert euler.yaw_deg == pytest.approx(90.0, abs=2.0)
        assert abs(euler.roll_deg) < 2.0 and abs(euler.pitch_deg) < 2.0

        await first(telemetry.subscribe_health(), lambda health: health.is_armable)
        await asyncio.wait_for(action.arm(), 10)
        await first(telemetry.subscribe_armed(), lambda armed: armed)

        # MAVSDK's offboard example: one setpoint, then start at once (offboardCheck.cpp
        # asks for a setpoint younger than COM_OF_LOSS_T, not for a stream of some length)
        up_and_north = VelocityNedYaw(1.0, 0.0, -1.0, 0.0)
        await offboard.set_velocity_ned(up_and_north)
        await asyncio.wait_for(offboard.start(), 10)
        await first(telemetry.subscribe_flight_mode(), lambda mode: mode == FlightMode.OFFBOARD)
        moved = await first(telemetry.subscribe_position_velocity_ned(),
                            lambda pv: pv.position.north_m > 1.0 and pv.position.down_m < -1.0)
        assert moved.velocity.north_m_s > 0.5

        await asyncio.wait_for(offboard.stop(), 10)
        await first(telemetry.subscribe_flight_mode(), lambda mode: mode == FlightMode.HOLD)


def test_mavsdk_flies_the_mock_px4_over_udp(served_vehicle):
    port, _ = served_vehicle
    asyncio.run(asyncio.wait_for(fly(port), 60))


def leave_in_offboard_without_setpoints(port: int) -> None:
    """A ground station that sends one setpoint, switches the disarmed vehicle to OFFBOARD and
    goes silent: COM_OF_LOSS_T later PX4 refuses to arm in that mode."""
    with open_link(f"udpout://127.0.0.1:{port}", source_system=255, source_component=190) as gcs:
        def answer(kind, send):
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                send()
                time.sleep(0.05)
                found = [m for m in gcs.receive_pending() if m.get_type() == kind]
                if found:
                    return found[-1]
            raise AssertionError(f"no {kind} from the served vehicle")

        answer("HEARTBEAT", lambda: gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS,
                                                           mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        gcs.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, px4_protocol.TYPE_MASK_VELOCITY_YAW_RATE,
            0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        ack = answer("COMMAND_ACK", lambda: gcs.mav.command_long_send(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            px4_protocol.OFFBOARD.main, 0, 0, 0, 0, 0))
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED


async def check_not_armable(port: int) -> None:
    async with ground_station() as drone:
        system = await connect(drone, port)
        telemetry = TelemetryAsync(system)
        await first(telemetry.subscribe_flight_mode(), lambda mode: mode == FlightMode.OFFBOARD)
        health = await first(telemetry.subscribe_health(),
                             lambda health: health.is_gyrometer_calibration_ok)
        assert not health.is_armable
        with pytest.raises(ActionError):
            await asyncio.wait_for(ActionAsync(system).arm(), 10)


def test_mavsdk_health_is_not_armable_when_px4_would_refuse(served_vehicle):
    port, _ = served_vehicle
    leave_in_offboard_without_setpoints(port)
    time.sleep(1.2)  # COM_OF_LOSS_T (1 s) without a setpoint
    asyncio.run(asyncio.wait_for(check_not_armable(port), 30))


async def read_parameters(port: int) -> tuple:
    async with ground_station() as drone:
        param = ParamAsync(await connect(drone, port))
        return (await asyncio.wait_for(param.get_param_int("EKF2_HGT_REF"), 10),
                await asyncio.wait_for(param.get_param_float("COM_OF_LOSS_T"), 10))


def test_mavsdk_reads_px4_parameters_bytewise(served_vehicle):
    port, _ = served_vehicle
    height_reference, loss_timeout = asyncio.run(asyncio.wait_for(read_parameters(port), 30))
    assert height_reference == 3  # Vision; a C-cast reading of the bytes would not give 3
    assert math.isclose(loss_timeout, 1.0)
