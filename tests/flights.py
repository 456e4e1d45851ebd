"""What every simulated flight's summary must show, shared by the flight tests."""

from __future__ import annotations

from companion.config import Config
from companion.launch import simulated

SUMMARY_KEYS = {"reached_goal", "collisions", "flight_time_s", "path_length_m",
                "min_clearance_m", "failsafes", "depth_rate_hz", "loop_lag_ms_p99", "backoffs",
                "navigation_end", "position_error_m", "vins_time_offset",
                "vins_correction_m", "failsafe_stop_m", "landing_glide_m"}

#: A short mission: 4 m east of the dome's first start (-23, -15) at take-off height, 3 m from
#: the nearest trunk. Take-off, a few seconds of navigation and the landing: every phase of a
#: flight, for the tests of what is not the route (the link, the go, the clock).
SHORT_DOME_GOAL = (-19.0, -15.0, 1.5)

_LOCKSTEP_FLIGHTS: dict[simulated.SimMission, dict] = {}


def fly(world: str, *, faults=(), goal=None, depth="estimated") -> dict:
    """The lockstep flight's summary; a lockstep flight is deterministic, so one flown already
    is not flown again (several tests read the same fault's flight)."""
    mission = simulated.SimMission(world=world, faults=tuple(faults), goal=goal, depth=depth)
    if mission not in _LOCKSTEP_FLIGHTS:
        _LOCKSTEP_FLIGHTS[mission] = simulated.run(Config(), mission)
    return _LOCKSTEP_FLIGHTS[mission]


def assert_safe_landing(summary: dict) -> None:
    """Whatever happened: no collision, landed and disarmed, no crash of the application."""
    assert summary["collisions"] == 0, summary["collision"]
    assert summary["final_state"] == "landed", summary["transitions"]
