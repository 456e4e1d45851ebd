"""The failsafes flown in the simulator over real MAVLink (issue 6's acceptance): a failure in
cruise (a frozen camera, an IMU gap, a network outputting NaN, a blacked-out camera, a camera
repeating its last image, a cut link, a dead end) ends in the stop, PX4 Hold and a landing,
with the reason named.

Every flight runs the product, as in test_flight_sim.py; flights are deterministic in lockstep,
so one flown for several tests is flown once (:func:`flights.fly`).
"""

from __future__ import annotations

import dataclasses
import itertools
import time

import numpy as np
import pytest

from companion.config import Config
from companion.launch import simulated
from drivers.mavlink.autopilot import MavlinkOptions
from drivers.sim.mock_px4 import Px4Options

from drivers.sim.faults import Fault
from drivers.sim.world import build_world
from flights import SHORT_DOME_GOAL, assert_safe_landing, fly

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


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


def test_a_failure_during_the_offset_swing_ends_in_stop_hold_and_landing():
    """The swing before navigating (CALIBRATING, docs/flight.md) is guarded as navigation is:
    a camera that freezes during it (the swing held on for 10 s by an offset that never
    shows) stops the vehicle, which holds and lands without navigating."""
    summary = fly("dome", faults=[Fault.parse("camera_freeze@takeoff:3")], overrides=[
        "vins.estimate_time_offset=true", "flight.offset_swing_deg=10",
        "vins.time_offset_max_sigma_s=1e-7"])
    assert_safe_landing(summary)
    assert summary["failsafes"] and "camera silent" in summary["failsafes"][0], \
        summary["failsafes"]
    states = [t["to"] for t in summary["transitions"]]
    assert states[-5:] == ["calibrating", "failsafe_stop", "holding", "landing", "landed"], \
        states


def test_after_an_imu_gap_near_an_obstacle_the_vins_restarts_where_the_vehicle_is():
    """The fault matrix's IMU gap near the trunk (issue 27): the vehicle brakes in the 2 s
    gap, so the last sample held across it put the VINS 53 degrees off level; the restart
    from there ran away (78 resets, 15.6 m off when it landed). Now it restarts relocalised on
    the map (autonomy/vins/imu_gap.py): 1 reset, 0.02 m off at the landing. Relocalising
    needs every frame of the gap: when each frame waited out the IMU's timeout, the VINS saw
    one in 0.29 s, its tracks broke between them, and this flight came back 1.55 m off
    (docs/reliability.md). Flown with the mock's step take-off and the gap 0.8 s after the
    vehicle nears the trunk, where the window's landmarks stay in view (the next test is a gap
    where they do not). Where that is follows the flight's timing: with the mock's TIMESYNC
    answer a tick late (until 2026-12-05) it was 0.5 s; on the corrected clock 0.6 s ended
    0.07 m off, and 0.5 s and 0.4 s, the map lost, 0.90 and 1.64 m; since the camera exposes
    on its own grid (2026-12-05, twentieth session) 0.8 s ends 0.03 m off, 0.7 s 0.21 m and
    0.6 s 0.54 m."""
    summary = fly("dome", faults=[Fault.parse("imu_gap@obstacle:0.8+2")], goal=(-11, -15, 1.5),
                  overrides=("px4.smooth_takeoff=false",))
    assert_safe_landing(summary)
    assert summary["failsafes"] == ["IMU silent"], summary["failsafes"]
    assert summary["vins_resets"] <= 4, summary["vins_resets"]
    assert summary["position_error_m"] < 0.5, summary["position_error_m"]


def test_after_an_imu_gap_that_loses_the_map_the_vins_restarts_where_it_last_saw_it():
    """The same gap on the flight PX4's own take-off times (the mock's default): it falls
    just after a turn. The gap's first two frames see 7 of the window's 119 landmarks, enough
    for PnP; from then on 3, too few, and nothing else in view is metric (docs/vins.md, "An IMU
    gap in flight"). The VINS restarts standing still where the second of those frames put
    it: 0.84 m off at the landing, where the estimate from before the gap, 1.5 m behind the
    vehicle once it had braked, left it 1.41 m off."""
    summary = fly("dome", faults=[Fault.parse("imu_gap@obstacle:0.5+2")], goal=(-11, -15, 1.5))
    assert_safe_landing(summary)
    assert summary["failsafes"] == ["IMU silent"], summary["failsafes"]
    assert summary["vins_resets"] <= 4, summary["vins_resets"]
    assert summary["position_error_m"] < 1.0, summary["position_error_m"]


def test_the_wall_clock_stepping_an_hour_back_and_forth_mid_flight_changes_nothing(monkeypatch):
    """The companion's clock jumping (issue 27): NTP stepping the host's clock, or an Orin
    without an RTC battery setting it late. The application times everything on the
    monotonic clock; the wall clock is read for log records, file names and MAVLink
    signing's first timestamp (pymavlink counts up from it). Here every 500 reads of
    ``time.time`` in the process step it an hour forward or back (about 60 steps in the
    flight); the signed flight is the same to the bit as with a steady clock."""
    key = bytes(range(32)).hex()
    config = dataclasses.replace(Config(), mavlink=MavlinkOptions(signing_key=key),
                                 px4=Px4Options(signing_key=key))
    mission = simulated.SimMission(world="dome", goal=SHORT_DOME_GOAL)
    steady = simulated.run(config, mission)
    wall, reads = time.time, itertools.count()
    monkeypatch.setattr(time, "time",
                        lambda: wall() + (-3600.0 if next(reads) // 500 % 2 else 3600.0))
    stepped = simulated.run(config, mission)
    monkeypatch.undo()
    assert next(reads) > 10_000  # the clock was read, and stepped, throughout the flight
    assert steady["final_state"] == "landed" and steady["reached_goal"]
    for field in ("final_state", "failsafes", "collisions", "mavlink_signing", "flight_time_s",
                "position_error_m", "vins_resets", "transitions"):
        assert stepped[field] == steady[field], field


#: A camera without frame numbers (a V4L2 webcam through OpenCV): the application cannot tell
#: its stale buffer from a new frame.
UNNUMBERED = ("sim.camera_counter=false",)


def test_a_camera_repeating_its_last_frame_is_refused_and_falls_silent():
    """A driver whose buffer stopped updating delivers its last frame, numbered as before,
    under fresh stamps: refused and counted from the first, so the camera falls silent to the
    failsafes (camera_timeout_s) while the VINS still holds its landmarks."""
    summary = fly("dome", faults=[Fault.parse("camera_stale@1")], depth="truth")
    assert_safe_landing(summary)
    assert summary["failsafes"] == ["camera silent"], summary["failsafes"]
    assert summary["frames_stale"] > 20, summary["frames_stale"]
    assert summary["frames_out_of_order"] == 0
    assert not summary["reached_goal"]
    assert summary["position_error_m"] < 0.5, summary["position_error_m"]


def test_an_unnumbered_camera_repeating_its_image_leaves_the_vins_blind_and_stops_the_flight():
    """The features stay tracked, standing still, while the vehicle moves: the landmarks leave
    the VINS, whose pose is then the IMU's alone. On true depth nothing else stops the flight
    (estimated depth loses its anchors first), so it is the blind VINS's own failsafe."""
    summary = fly("dome", faults=[Fault.parse("camera_stale@1")], depth="truth",
                  overrides=UNNUMBERED)
    assert_safe_landing(summary)
    assert summary["frames_stale"] == 0
    assert len(summary["failsafes"]) == 1 and \
        summary["failsafes"][0].startswith("VINS blind (< 5 landmarks for 3."), \
        summary["failsafes"]
    assert not summary["reached_goal"]


def test_the_stop_after_a_blind_vins_is_flown_on_px4s_estimate_not_the_drifting_vins():
    """The blind VINS of the test above is many metres off by the landing. Its stop, tracked
    on that drifting position, flew 3.9 m and never came to rest by the VINS's reckoning (the
    stop's timeout ended it); at zero velocity on PX4's estimate it brakes within the
    braking distance from cruise and is at rest well before the timeout."""
    summary = fly("dome", faults=[Fault.parse("camera_stale@1")], depth="truth",
                  overrides=UNNUMBERED)
    transitions = summary["transitions"]
    stop = next(k for k, t in enumerate(transitions) if t["to"] == "failsafe_stop")
    stopping_s = transitions[stop + 1]["t"] - transitions[stop]["t"]
    assert stopping_s < Config().flight.stop_timeout_s - 0.5, stopping_s
    assert summary["failsafe_stop_m"] < 2.0, summary["failsafe_stop_m"]


def test_a_vins_failing_during_another_failsafes_stop_hands_that_stop_to_px4():
    """The IMU gap above fails the IMU first ("IMU silent"), so its stop starts tracked on the
    VINS; the VINS then restarts during the stop (a reset in flight), and the rest of the stop
    is flown as zero velocity on PX4's estimate, as after a VINS failure alone. Measured: at
    rest after 1.4 s and 1.0 m, where the stop tracked on the restarting VINS took 2.1 s and
    1.3 m. The VINS's drift is scored at its first position after the restart."""
    summary = fly("dome", faults=[Fault.parse("imu_gap@obstacle:0.5+2")], goal=(-11, -15, 1.5))
    assert summary["failsafes"] == ["IMU silent"], summary["failsafes"]
    held = next(t for t in summary["transitions"] if t["to"] == "holding")
    assert held["reason"] == "stopped after a failsafe, on PX4's estimate (the VINS failed)", \
        held
    assert summary["position_error_m"] is not None


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


def test_px4_disarming_the_vehicle_in_the_air_ends_the_mission_without_another_command():
    """The motors stop in cruise (a forced disarm; a crash does the same in the simulator):
    the mission ends there, named, and the companion neither lands nor re-arms a vehicle that
    is no longer flying."""
    summary = fly("dome", faults=[Fault.parse("disarm@1")], depth="truth")
    assert summary["failsafes"] == ["PX4 disarmed the vehicle in the air"], summary["failsafes"]
    assert summary["final_state"] == "aborted", summary["transitions"]
    states = [t["to"] for t in summary["transitions"]]
    aborted = states.index("aborted")
    assert states[aborted - 1] == "failsafe_stop", states
    assert not {"holding", "landing", "taking_off"} & set(states[aborted - 1:]), states
    assert not summary["reached_goal"]


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


def test_px4_disarming_the_vehicle_during_the_take_off_ends_the_mission_at_once():
    """The motors stop 0.5 s into the climb: the mission ends in ABORTED as soon as PX4's
    heartbeat says so, with no landing command (it used to wait out the take-off timeout,
    20 s, then command a landing of the falling vehicle: found by the fault matrix)."""
    from companion.tools.fault_matrix import MATRIX_GOAL

    summary = fly("dome", faults=[Fault.parse("disarm@takeoff:0.5")], goal=MATRIX_GOAL)
    assert summary["failsafes"] == ["PX4 disarmed the vehicle in the air"], summary["failsafes"]
    states = [t["to"] for t in summary["transitions"]]
    assert states[-2:] == ["taking_off", "aborted"], states
    aborted_t = summary["transitions"][-1]["t"]
    assert aborted_t - summary["fault_moments"]["takeoff"] < 2.0  # a heartbeat or two
