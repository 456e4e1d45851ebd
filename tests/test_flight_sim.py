"""The whole stack flown in the simulator over real MAVLink (issue 6's acceptance).

Every flight runs the product: the mock PX4 on loopback UDP, the rendered camera, the VINS on
its images and the IMU from HIGHRES_IMU, the synthetic network on the rendered depth, the
rescaler, the planner on the rescaled depth, setpoints and odometry back to PX4. Nothing of the
stack sees ground truth; the summary's truth fields (collisions, clearance, closest approach)
come from the simulator's side.

Flights are deterministic in lockstep; the event-loop stall runs in real time, the one fault
lockstep cannot show (the simulator would stall with the loop).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from companion import cli, simfly
from companion.config import Config
from drivers.sim.faults import Fault
from drivers.sim.world import build_world

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

SUMMARY_KEYS = {"reached_goal", "collisions", "flight_time_s", "path_length_m",
                "min_clearance_m", "failsafes", "depth_rate_hz", "loop_lag_ms_p99"}


def fly(world: str, *, faults=(), goal=None, clock="lockstep") -> dict:
    mission = simfly.SimMission(world=world, faults=tuple(faults), goal=goal, clock=clock)
    return simfly.run(Config(), mission)


def assert_safe_landing(summary: dict) -> None:
    """Whatever happened: no collision, landed and disarmed, no crash of the application."""
    assert summary["collisions"] == 0, summary["collision"]
    assert summary["final_state"] == "landed", summary["transitions"]


# ---------------------------------------------------------------- acceptance: reach the goal

_FLIGHTS: dict[str, dict] = {}


def first_pair(world: str) -> dict:
    """The first start/goal pair of ``world``, flown once per session (deterministic)."""
    if world not in _FLIGHTS:
        _FLIGHTS[world] = fly(world)
    return _FLIGHTS[world]


@pytest.mark.parametrize("world", ["dome", "sewer", "mine"])
def test_first_pair_of_each_world_is_flown_without_collision(world):
    summary = first_pair(world)
    assert_safe_landing(summary)
    assert summary["min_clearance_m"] > Config().vehicle.collision_radius
    assert summary["path_length_m"] > 10.0  # it set off along the route
    assert summary["depth_rate_hz"] > 10.0  # metric depth for most frames of a 20 Hz camera


@pytest.mark.xfail(strict=True, reason="issue 6 open: the dome flight's VINS resets in cruise "
                   "(a failsafe lands it); sewer and mine stop at their first narrow passage "
                   "(3 m hallway, 3-4 m tunnel), where no arc is proved free with a 1 m radius")
@pytest.mark.parametrize("world", ["dome", "sewer", "mine"])
def test_first_pair_of_each_world_reaches_its_goal(world):
    summary = first_pair(world)
    assert summary["reached_goal"] and summary["failsafes"] == [], summary["failsafes"]
    assert summary["closest_to_goal_m"] <= Config().flight.goal_tolerance + 1.0


# ---------------------------------------------------------------- failsafes

@pytest.mark.parametrize("fault, reason", [
    ("camera_freeze@1", "camera silent"),
    ("imu_gap@1+2", "IMU silent"),
    ("network_nan@1", "no metric depth"),
    ("camera_blackout@1+1.5", "VINS lost"),
])
def test_a_failure_in_cruise_ends_in_stop_hold_and_landing(fault, reason):
    summary = fly("dome", faults=[Fault.parse(fault)])
    assert_safe_landing(summary)
    assert summary["failsafes"] and reason in summary["failsafes"][0], summary["failsafes"]
    states = [t["to"] for t in summary["transitions"]]
    assert states[-4:] == ["failsafe_stop", "holding", "landing", "landed"], states
    assert not summary["reached_goal"]


def test_a_network_outputting_nan_is_named_in_the_summary():
    summary = fly("dome", faults=[Fault.parse("network_nan@1")])
    assert "non_finite" in summary["failsafes"][0] or "NaN" in summary["failsafes"][0], \
        summary["failsafes"]
    assert summary["depth_failures"]


def test_a_vins_reset_after_a_blackout_is_counted():
    summary = fly("dome", faults=[Fault.parse("camera_blackout@1+1.5")])
    assert summary["vins_resets"] >= 1


def test_link_cut_lets_px4_hold_and_the_companion_lands_once_it_is_back():
    summary = fly("dome", faults=[Fault.parse("link_cut@1+3")])
    assert_safe_landing(summary)
    # the IMU stream stops first (VINS lost), the heartbeats' timeout follows
    assert "MAVLink link lost" in summary["failsafes"], summary["failsafes"]
    states = [t["to"] for t in summary["transitions"]]
    assert "link_lost" in states and states[-3:] == ["holding", "landing", "landed"], states


def test_a_dead_end_is_a_no_safe_primitive_failsafe():
    world = build_world("mine", 0)
    start = world.routes[0].start
    # the route starts at the blind end of a tunnel: ask for a goal through its end wall
    corners = world.find_path(start[:2], world.routes[0].goal[:2], 1.0)
    back = start[:2] - (corners[1] - start[:2]) / np.linalg.norm(corners[1] - start[:2]) * 10.0
    summary = fly("mine", goal=(float(back[0]), float(back[1]), 1.5))
    assert_safe_landing(summary)
    assert summary["failsafes"] == ["no safe primitive"]
    assert summary["path_length_m"] < 5.0  # it never went anywhere


def test_an_event_loop_stall_is_caught_by_the_watchdog_in_real_time():
    summary = fly("dome", faults=[Fault.parse("loop_stall@1+1.5")], clock="realtime")
    assert_safe_landing(summary)
    assert summary["watchdog_setpoints"] > 0
    assert any(r.startswith(("event loop stalled", "setpoint deadline missed"))
               for r in summary["failsafes"]), summary["failsafes"]


# ---------------------------------------------------------------- the command

def test_sim_fly_json_prints_the_summary_and_exits_by_the_outcome(capsys, tmp_path):
    plot = tmp_path / "flight.png"
    status = cli.main(["sim", "fly", "--world", "dome", "--fault", "camera_freeze@0.5",
                       "--json", "--plot", str(plot)])
    summary = json.loads(capsys.readouterr().out)
    assert SUMMARY_KEYS <= set(summary)
    assert summary["failsafes"][0] == "camera silent"
    assert status == 0  # a faulted flight that landed safely is a success
    assert plot.stat().st_size > 1000


@pytest.mark.parametrize("argv, words", [
    (["--pair", "99"], "pairs 0..5"),
    (["--fault", "gremlins"], "unknown fault"),
    (["--fault", "loop_stall"], "needs --clock realtime"),
])
def test_sim_fly_refuses_a_bad_mission_clearly(capsys, argv, words):
    assert cli.main(["sim", "fly", "--no-plot", *argv]) == 1
    assert words in capsys.readouterr().err


def test_sim_fly_rejects_a_malformed_goal(capsys):
    assert cli.main(["sim", "fly", "--goal", "1,2"]) == 2
    assert "expected X,Y,Z" in capsys.readouterr().err
