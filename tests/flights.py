"""What every simulated flight's summary must show, shared by the flight tests."""

from __future__ import annotations

from autonomy.navigation.mission import DEPTH_UNUSED_STATES
from companion.config import load_config
from companion.launch import simulated

SUMMARY_KEYS = {"reached_goal", "collisions", "flight_time_s", "path_length_m",
                "min_clearance_m", "failsafes", "depth_rate_hz", "loop_lag_ms_p99", "backoffs",
                "navigation_end", "position_error_m", "vins_time_offset",
                "vins_correction_m", "failsafe_stop_m", "landing_glide_m"}

#: A short mission: 5 m along the dome's first leg from its first start (-23, -15), at
#: take-off height, clear of the trunks by 2.2 m. Take-off, a few seconds of navigation and
#: the landing: every phase of a flight, for the tests of what is not the route (the link,
#: the go, the clock, the soak).
SHORT_DOME_GOAL = (-19.14, -11.82, 1.5)

_LOCKSTEP_FLIGHTS: dict[tuple[simulated.SimMission, tuple[str, ...]], dict] = {}


def fly(world: str, *, faults=(), goal=None, depth="estimated", overrides=()) -> dict:
    """The lockstep flight's summary, with the default config but for ``overrides``
    (``section.key=value``); a lockstep flight is deterministic, so one flown already is not
    flown again (several tests read the same fault's flight)."""
    mission = simulated.SimMission(world=world, faults=tuple(faults), goal=goal, depth=depth)
    key = (mission, tuple(overrides))
    if key not in _LOCKSTEP_FLIGHTS:
        _LOCKSTEP_FLIGHTS[key] = simulated.run(load_config(None, overrides), mission)
    return _LOCKSTEP_FLIGHTS[key]


def assert_safe_landing(summary: dict) -> None:
    """Whatever happened: no collision, landed and disarmed, no crash of the application; and
    once PX4 flew the vehicle on its own, the application never commanded it again (its
    depth rests from then on: ``DEPTH_UNUSED_STATES``)."""
    assert summary["collisions"] == 0, (summary["collision"], summary["floor_contact"])
    assert summary["final_state"] == "landed", summary["transitions"]
    resting = {state.value for state in DEPTH_UNUSED_STATES}
    states = [t["to"] for t in summary["transitions"]]
    first = next(k for k, state in enumerate(states) if state in resting)  # "landed" is one
    assert set(states[first:]) <= resting, states
