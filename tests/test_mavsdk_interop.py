"""Acceptance: MAVSDK, a MAVLink client written by others, flies the mock PX4 over loopback UDP.

The simulator serves in real time in a background thread (its own event loop), as
`companion sim serve` would; MAVSDK connects with the connection string a user would type.
Every wait has a timeout, so a regression fails fast instead of hanging.
"""

import asyncio
import socket
import threading

import pytest

mavsdk = pytest.importorskip("mavsdk.asyncio")

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from mavsdk.autopilot import Autopilot  # noqa: E402
from mavsdk.vehicle import Vehicle  # noqa: E402

from drivers.sim.serve import serve  # noqa: E402


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def served_vehicle():
    """The simulator serving udpin://127.0.0.1:PORT in real time; yields the port."""
    port = free_udp_port()
    stop = threading.Event()
    outcome = {}

    def run():
        try:
            outcome["summary"] = asyncio.run(serve(f"udpin://127.0.0.1:{port}", None,
                                                   clock_mode="realtime", stop=stop,
                                                   duration=120.0))
        except BaseException as error:  # reported by the test, not lost in the thread
            outcome["error"] = error

    thread = threading.Thread(target=run, name="sim-serve", daemon=True)
    thread.start()
    yield port
    stop.set()
    thread.join(timeout=10)
    assert not thread.is_alive(), "the served simulator did not stop"
    assert "error" not in outcome, outcome.get("error")
    assert outcome["summary"].collision is None


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


async def fly(port: int) -> None:
    configuration = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(configuration) as drone:
        await drone.add_any_connection(f"udpout://127.0.0.1:{port}")
        system = await drone.first_autopilot(timeout_s=10.0)
        assert system is not None, "MAVSDK discovered no autopilot"
        assert await system.autopilot_type() == Autopilot.PX4
        assert await system.vehicle_type() == Vehicle.MULTICOPTER

        telemetry, action, offboard = (TelemetryAsync(system), ActionAsync(system),
                                       OffboardAsync(system))
        await asyncio.wait_for(telemetry.set_rate_imu(200.0), 10)
        assert await count_imu(telemetry, 200) == pytest.approx(200, rel=0.05)

        await asyncio.wait_for(action.arm(), 10)
        await first(telemetry.subscribe_armed(), lambda armed: armed)

        up_and_north = VelocityNedYaw(1.0, 0.0, -1.0, 0.0)
        await offboard.set_velocity_ned(up_and_north)  # MAVSDK streams it at 20 Hz from now
        await asyncio.sleep(1.3)                         # PX4 wants > 1 s of stream first
        await asyncio.wait_for(offboard.start(), 10)
        await first(telemetry.subscribe_flight_mode(), lambda mode: mode == FlightMode.OFFBOARD)
        moved = await first(telemetry.subscribe_position_velocity_ned(),
                            lambda pv: pv.position.north_m > 1.0 and pv.position.down_m < -1.0)
        assert moved.velocity.north_m_s > 0.5

        await asyncio.wait_for(offboard.stop(), 10)
        await first(telemetry.subscribe_flight_mode(), lambda mode: mode == FlightMode.HOLD)


def test_mavsdk_flies_the_mock_px4_over_udp(served_vehicle):
    asyncio.run(asyncio.wait_for(fly(served_vehicle), 60))
