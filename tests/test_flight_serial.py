"""A whole mission flown over a serial link, as on the paper's vehicle (a Jetson Orin on a
Pixracer's TELEM port at 921600 baud): the mock PX4 serves a pseudo-terminal and the application
opens its other end as ``serial:///dev/pts/N:921600``, through the pyserial code a flight
controller on a UART goes through. The mission is short (take-off, 5 m across the dome,
landing): what the link must carry is every phase's traffic, not a long route (the whole
routes are flown over UDP in test_flight_sim.py). In its own module, so pytest-xdist flies it on a worker of
its own beside the other flights."""

from __future__ import annotations

from companion.config import Config
from companion.launch import simulated
from flights import SHORT_DOME_GOAL, assert_safe_landing


def test_a_lockstep_mission_over_a_921600_baud_serial_link_reaches_the_goal():
    summary = simulated.run(Config(), simulated.SimMission(world="dome", goal=SHORT_DOME_GOAL,
                                                             link="serial"))
    assert_safe_landing(summary)
    assert summary["reached_goal"] and summary["failsafes"] == []
    load = summary["mavlink"]
    assert load["where"].startswith("/dev/pts/") and load["where"].endswith(" at 921600 baud")
    # both ways the stream (HIGHRES_IMU at 200 Hz, odometry, attitude, setpoints, TIMESYNC)
    # fits the 92 kB/s of the line with room to spare, and nothing arrived garbled
    assert load["received_bytes_per_s"] < 0.5 * load["capacity_bytes_per_s"]
    assert load["sent_bytes_per_s"] < 0.5 * load["capacity_bytes_per_s"]
    assert load["bad_data"] == {"received": 0, "sent": 0}
