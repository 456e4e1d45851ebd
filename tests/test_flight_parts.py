"""The flight application's parts on their own: faults, the truth's scoring, the watchdog,
frame alignment, the simulated camera (the navigation decisions: test_navigation.py)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from autonomy.geometry import make_pose, rot_z, yaw_alignment
from autonomy.vins.health import HealthState
from companion.flight.command import odometry_quality
from companion.flight.steps import ClimbWatch
from companion.flight.watchdog import SetpointWatchdog
from drivers.clock import SimClock
from drivers.mavlink import px4_protocol
from drivers.sim.host import FrameSlot, TruthDepth, TruthTrack, free_udp_port
from drivers.mavlink.link import open_link
from drivers.sim.faults import FaultyLink, Fault, FaultSchedule
from drivers.sim.world import build_world


# ---------------------------------------------------------------- faults

def test_fault_parse_reads_kind_start_and_duration():
    assert Fault.parse("imu_gap") == Fault("imu_gap", 1.0, math.inf)
    assert Fault.parse("link_cut@2.5") == Fault("link_cut", 2.5, math.inf)
    assert Fault.parse("camera_freeze@1+0.5") == Fault("camera_freeze", 1.0, 0.5)
    assert Fault.parse("px4_reboot@landing:0.5") == Fault("px4_reboot", 0.5, math.inf, "landing")
    for fault in (Fault("imu_gap", 2.0, 0.5, "takeoff"), Fault("link_cut", 0.0),
                  Fault("disarm", 0.1 + 0.2, 1 / 3, "obstacle")):
        assert Fault.parse(str(fault)) == fault


@pytest.mark.parametrize("text, words", [
    ("gremlins", "unknown fault"),
    ("imu_gap@soon", "expected kind[@[moment:]after_s[+duration_s]]"),
    ("imu_gap@later:1", "unknown moment 'later'"),
    ("imu_gap@-1", "after_s must be"),
    ("imu_gap@1+0", "duration_s must be > 0"),
])
def test_fault_parse_rejects_bad_text_clearly(text, words):
    with pytest.raises(ValueError, match=re.escape(words)):
        Fault.parse(text)


def test_fault_clock_starts_when_the_vehicle_first_cruises():
    schedule = FaultSchedule((Fault("imu_gap", after_s=1.0, duration_s=0.5),))
    schedule.update(5.0, (0.0, 0.0, 1.5), (0.5, 0.0, 0.0))  # hovering: no cruise yet
    assert not schedule.active("imu_gap", 7.0)
    schedule.update(10.0, (0.0, 0.0, 1.5), (0.0, 1.5, 0.0))  # cruising from t = 10
    assert not schedule.active("imu_gap", 10.9)
    assert schedule.active("imu_gap", 11.0)
    assert schedule.active("imu_gap", 11.4)
    assert not schedule.active("imu_gap", 11.5)
    assert not schedule.active("link_cut", 11.2)


def test_each_moment_comes_when_the_true_flight_reaches_it():
    """Take-off: 0.3 m above where it stood; cruise: over 1 m/s; near an obstacle: within
    2 m of one, in cruise; landing: PX4 landing after cruise (not the take-off's descent)."""
    wall_x = 10.0
    schedule = FaultSchedule(tuple(Fault("imu_gap", 0.0, 0.1, moment) for moment in
                                   ("takeoff", "cruise", "obstacle", "landing")),
                             clearance=lambda points: wall_x - points[:, 0])
    flight = [(0.0, (0, 0, 0.0), (0, 0, 0), True),    # on the ground, Land mode: not yet
              (1.0, (0, 0, 0.2), (0, 0, 1), False),
              (1.5, (0, 0, 0.4), (0, 0, 1), False),   # take-off
              (3.0, (0, 0, 1.5), (1.5, 0, 0), False),  # cruise
              (7.0, (7.5, 0, 1.5), (1.5, 0, 0), False),
              (8.5, (8.5, 0, 1.5), (1.5, 0, 0), False),  # 1.5 m from the wall
              (9.0, (9.0, 0, 1.5), (0, 0, 0), True)]   # landing
    for t, position, velocity, landing in flight:
        schedule.update(t, np.array(position, dtype=float), velocity, landing)
    assert schedule.moment_since == {"takeoff": 1.5, "cruise": 3.0, "obstacle": 8.5,
                                     "landing": 9.0}


def test_a_lossy_link_loses_about_the_share_asked_each_way():
    class Wire:
        def __init__(self):
            self.sent = []

        def send(self, message):
            self.sent.append(message)

        def receive_pending(self):
            return list(range(1000))

    wire = Wire()
    link = FaultyLink(wire, np.random.default_rng(1))
    link.loss = 0.5
    received = link.receive_pending()
    for k in range(1000):
        link.send(k)
    assert 430 < len(received) < 570 and 430 < len(wire.sent) < 570
    assert received == sorted(received)  # lost, never reordered
    link.loss = 0.0
    assert len(link.receive_pending()) == 1000


def _received(link, seconds=0.5) -> list[str]:
    deadline, names = time.monotonic() + seconds, []
    while time.monotonic() < deadline:
        names += [m.get_type() for m in link.receive_pending()]
        time.sleep(0.01)
    return names


def test_a_cut_link_neither_sends_nor_delivers():
    port = free_udp_port()
    with open_link(f"udpin://127.0.0.1:{port}") as server_raw, \
            open_link(f"udpout://127.0.0.1:{port}") as client:
        server = FaultyLink(server_raw)
        client.mav.heartbeat_send(6, 8, 0, 0, 0)
        assert "HEARTBEAT" in _received(server)
        server.send(server.mav.heartbeat_encode(6, 8, 0, 0, 0))
        assert "HEARTBEAT" in _received(client)
        server.cut = True
        client.mav.heartbeat_send(6, 8, 0, 0, 0)
        server.send(server.mav.heartbeat_encode(6, 8, 0, 0, 0))
        assert _received(server) == [] and _received(client) == []
        server.cut = False
        client.mav.heartbeat_send(6, 8, 0, 0, 0)
        assert "HEARTBEAT" in _received(server)


def test_the_truth_scores_the_flight_and_the_vins_error_when_navigation_ended():
    world = build_world("dome", 0)
    track = TruthTrack()
    track.t = [0.0, 2.0, 6.0, 9.0]
    track.positions = [np.array(p) for p in ((0.0, 0.0, 0.0), (0.0, 0.0, 1.5), (4.0, 3.0, 1.5),
                                             (4.0, 3.0, 0.0))]
    goal = np.array([4.0, 4.0, 1.5])
    # navigation ended at t = 6 with the vehicle believing itself 0.5 m higher than it was
    score = track.score(world, goal, {"t": 6.0, "position_L": [4.0, 3.0, 2.0]})
    assert score["path_length_m"] == pytest.approx(8.0)
    assert score["closest_to_goal_m"] == pytest.approx(1.0)
    assert score["position_error_m"] == pytest.approx(0.5)
    # split over the 5 m flown from the start: all of it height, none scale or heading
    split = score["position_error_split"]
    assert split["distance_m"] == pytest.approx(5.0) and split["height_m"] == pytest.approx(0.5)
    assert split["scale"] == pytest.approx(1.0) and split["across_m"] == pytest.approx(0.0)
    # believing itself 10 % farther along the same bearing: all of it along the path
    split = track.score(world, goal, {"t": 6.0, "position_L": [4.4, 3.3, 1.5]})[
        "position_error_split"]
    assert split["scale"] == pytest.approx(1.1) and split["along_m"] == pytest.approx(0.5)
    assert split["bearing_deg"] == pytest.approx(0.0, abs=1e-9)
    unscored = track.score(world, goal)  # no estimate (never tied)
    assert unscored["position_error_m"] is None and unscored["position_error_split"] is None


def _transition(t, source, target):
    return {"t": t, "from": source, "to": target, "reason": "test"}


def test_a_vehicle_come_down_on_the_floor_while_navigating_is_a_collision():
    """The floor is no obstacle of the world's (the collision radius never meets it) and the
    least clearance leaves out the path below 0.3 m, so an arc flown into the floor showed
    nowhere: between the switch to Offboard and the landing, its first contact armed is a
    collision. The take-off before, the landing after, PX4's own landing and a fall once
    disarmed are not."""
    from companion.launch.simulated import _floor_contact

    track = TruthTrack()
    track.t = [0.0, 3.0, 8.0, 9.0, 12.0, 15.0]
    track.positions = [np.array(p) for p in ((0, 0, 0.0), (0, 0, 1.5), (5, 0, 0.6),
                                             (6, 0, 0.0), (6, 0, 0.0), (6, 0, 0.0))]
    track.armed = [False, True, True, True, True, False]
    track.px4_landing = [False] * 6
    flown = [_transition(2.0, "taking_off", "entering_offboard"),
             _transition(4.0, "entering_offboard", "navigating"),
             _transition(13.0, "holding", "landing"), _transition(14.0, "landing", "landed")]
    assert _floor_contact(track, flown) == {"t": 9.0, "position": [6.0, 0.0, 0.0]}
    assert track.first_floor_contact(10.0, 20.0)[0] == 12.0
    assert track.first_floor_contact(0.5, 8.5) is None  # from the ground up and back at 0.6 m
    landed = [*flown[:2], _transition(8.5, "navigating", "landing")]
    assert _floor_contact(track, landed) is None  # came down in the landing, as meant
    assert _floor_contact(track, flown[:1]) is None  # never reached Offboard
    aborted = [*flown[:2], _transition(8.8, "navigating", "aborted")]
    assert _floor_contact(track, aborted) is None  # PX4 disarmed it: the app gave up
    track.px4_landing = [False, False, False, True, True, True]  # PX4 landed it (link lost)
    assert _floor_contact(track, flown) is None
    track.px4_landing = [False] * 6
    track.armed = [False, True, True, False, False, False]  # disarmed in the air: it fell
    assert _floor_contact(track, flown) is None


def test_truth_depth_is_fully_confident_and_its_empty_sky_is_far():
    from autonomy.messages import Frame
    depth = np.array([[2.0, np.nan], [5.0, 7.0]], np.float32)
    frame = Frame(1.5, np.zeros((2, 2, 3), np.uint8), truth_depth=depth)
    source = TruthDepth(10.0)
    metric = source.infer(frame)
    assert source.metric(metric, None) is metric  # nothing to rescale
    assert metric.ok and metric.t == 1.5 and metric.diagnostics.method == "truth"
    np.testing.assert_array_equal(metric.depth, [[2.0, 10.0], [5.0, 7.0]])
    np.testing.assert_array_equal(metric.confidence, 1.0)


# ---------------------------------------------------------------- watchdog

class _Now:
    """A clock the test moves by hand (read from the watchdog's thread)."""

    def __init__(self):
        self.value = 0.0

    def __call__(self) -> float:
        return self.value


def _wait_until(condition, seconds=2.0) -> bool:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    return condition()


@contextlib.contextmanager
def _running_watchdog(now: _Now, send_stop, deadline_s: float):
    """A started watchdog sending at 100 Hz, closed (its thread joined) afterwards."""
    watchdog = SetpointWatchdog(now, send_stop, deadline_s=deadline_s, period_s=0.01)
    watchdog.start()
    try:
        yield watchdog
    finally:
        watchdog.close()


def test_watchdog_sends_the_stop_when_setpoints_go_stale_and_yields_when_they_resume():
    now, sent = _Now(), []
    with _running_watchdog(now, sent.append, deadline_s=0.2) as watchdog:
        watchdog.arm(True)
        watchdog.fed(0.0)
        now.value = 0.1
        time.sleep(0.15)
        assert sent == [] and not watchdog.in_charge
        now.value = 0.5  # the loop stalled: no setpoint since t = 0
        assert _wait_until(lambda: len(sent) >= 3)
        assert watchdog.in_charge and watchdog.episodes == 1
        watchdog.fed(0.5)  # the loop is back
        assert not watchdog.in_charge
        count = len(sent)
        time.sleep(0.1)
        assert len(sent) == count


def test_watchdog_stays_quiet_when_disarmed_and_survives_a_failing_send():
    now = _Now()
    calls = []

    def failing(t):
        calls.append(t)
        raise OSError("link gone")
    with _running_watchdog(now, failing, deadline_s=0.1) as watchdog:
        watchdog.fed(0.0)
        now.value = 1.0
        time.sleep(0.1)
        assert calls == []  # not armed
        watchdog.arm(True)
        watchdog.fed(1.0)
        now.value = 2.0
        assert _wait_until(lambda: len(calls) >= 2)  # kept trying after the error
        assert watchdog.fired == 0
    assert not any(t.name == "setpoint-watchdog" for t in threading.enumerate())


def test_watchdog_armed_again_after_a_pause_waits_for_the_next_setpoint():
    """The link lost in offboard: the application stops commanding, then commands again when
    it is back. The setpoint from before the pause is not a late loop; the deadline runs
    from the first setpoint after it (the fault matrix's packet loss at take-off fired one
    stop between the loop's arm and its next setpoint)."""
    now, sent = _Now(), []
    with _running_watchdog(now, sent.append, deadline_s=0.1) as watchdog:
        watchdog.arm(True)
        watchdog.fed(0.0)
        watchdog.arm(False)  # the link lost: no setpoints for a while
        now.value = 5.0
        watchdog.arm(True)  # the link back; the loop has not sent yet
        time.sleep(0.1)
        assert sent == [] and watchdog.fired == 0
        watchdog.fed(5.0)
        now.value = 5.5  # and now the loop is late
        assert _wait_until(lambda: len(sent) >= 1)


# ---------------------------------------------------------------- frames

def test_a_late_setpoint_on_a_glide_through_a_point_brakes_on_the_glide_to_rest_there():
    """Backing off glides on through one trail point after another (Backoff): the loop
    stalled, the watchdog must not fly on past the point and along the glide's stopping
    extension off the trail, but come to rest on the point, as the round checked."""
    from autonomy.geometry import PinholeCamera
    from autonomy.navigation.behaviours import BACKOFF_REASON
    from autonomy.planning.planner import Planner, PlannerOptions
    from companion.flight.command import Command

    planner = Planner(PinholeCamera.from_hfov(160, 120, math.radians(90.0)), PlannerOptions())
    here, point = make_pose(np.eye(3), [0.0, 0.0, 1.5]), np.array([0.0, 0.5, 1.5])
    through = planner.glide(0.0, here, point, BACKOFF_REASON, stop_at_goal=False)
    to_rest = planner.glide(0.0, here, point, BACKOFF_REASON)
    sent = []
    command = Command.__new__(Command)  # the parts the watchdog's stop reads
    command.navigation = SimpleNamespace(stopping_on_px4=False)
    command.context = SimpleNamespace(
        T_L_W=np.eye(4), autopilot=SimpleNamespace(
            send_velocity=lambda velocity, yaw_rate, acceleration=None: sent.append(velocity)),
        channels=SimpleNamespace(plan=SimpleNamespace(value=through),
                                 checked_stop=SimpleNamespace(value=to_rest)))
    for now in (0.5, 1.5, 3.0):
        command._watchdog_stop(now)
    np.testing.assert_allclose(sent, [to_rest.setpoint(t).velocity_W for t in (0.5, 1.5, 3.0)])
    assert np.linalg.norm(sent[-1]) == 0.0  # at rest on the point


def test_yaw_alignment_maps_the_body_pose_from_vins_world_to_px4_local():
    T_W_B = make_pose(rot_z(0.3), np.array([1.0, 2.0, 0.1]))
    T_L_B = make_pose(rot_z(1.9), np.array([-4.0, 7.0, 0.0]))
    T_L_W = yaw_alignment(T_L_B, T_W_B)
    assert np.allclose(T_L_W @ T_W_B, T_L_B, atol=1e-12)
    assert np.allclose(T_L_W[:3, :3], rot_z(1.6))


# ---------------------------------------------------------------- odometry to PX4

@pytest.mark.parametrize("state, settling, blind, quality", [
    (HealthState.OK, False, False, 100), (HealthState.DEGRADED, False, False, 50),
    (HealthState.LOST, False, False, -1), (HealthState.INITIALISING, False, False, 0),
    # just reset: the new smoother's state is its prior, not for PX4 to fuse
    (HealthState.DEGRADED, True, False, 0), (HealthState.LOST, True, False, -1),
    # blind past the timeout: PX4 (EKF2_EV_QMIN >= 1) must not hold position on its drift
    (HealthState.OK, False, True, -1), (HealthState.DEGRADED, False, True, -1)])
def test_odometry_quality_tells_px4_when_not_to_fuse_the_vins(state, settling, blind, quality):
    from autonomy.vins.health import Health

    assert odometry_quality(Health(state, "", settling=settling), blind) == quality
    assert odometry_quality(None, False) == -1  # no VINS update yet


# ---------------------------------------------------------------- the summary

def test_the_simulated_summary_splits_the_vins_error_over_the_path():
    """`sim fly`'s summary gives the VINS error with its split (the path's scale, bearing,
    height), and the bare error where the flight has none (never tied, or flew nowhere)."""
    from companion.launch.simulated import format_summary

    summary = {"world": "sewer", "pair": 0, "seed": 1, "goal": [80.0, 2.5, 1.5],
               "reached_goal": True, "closest_to_goal_m": 0.48, "collisions": 0,
               "path_length_m": 87.1, "min_clearance_m": 1.1, "position_error_m": 2.07,
               "mavlink": {"where": "udp", "received_bytes_per_s": 9e3, "sent_bytes_per_s": 2e3,
                           "capacity_bytes_per_s": None,
                           "bad_data": {"received": 0, "sent": 0}},
               "final_state": "landed", "failsafes": [], "flight_time_s": 63.3,
               "depth_rate_hz": 9.9, "loop_lag_ms_p99": 5.0, "planning_rounds": 522,
               "stop_rounds": 0, "backoffs": 0, "vins_resets": 0,
               "position_error_split": {"distance_m": 81.2, "scale": 0.9808, "bearing_deg": -0.86,
                                        "along_m": -1.56, "across_m": -1.22, "height_m": 0.38,
                                        "start_m": 0.0}}
    line = next(line for line in format_summary(summary).splitlines() if "VINS error" in line)
    assert line == ("  VINS error        2.07 m (path scale 0.9808: -1.56 m along; bearing "
                    "-0.86°: -1.22 m across; height +0.38 m)")
    summary["position_error_split"] = None
    line = next(line for line in format_summary(summary).splitlines() if "VINS error" in line)
    assert line == "  VINS error        2.07 m"


#: A flight summary's lines every flight has, for the tests of the lines that follow them.
FLIGHT = {"final_state": "landed", "failsafes": [], "flight_time_s": 60.0,
          "depth_rate_hz": 14.0, "loop_lag_ms_p99": 3.0, "planning_rounds": 600,
          "stop_rounds": 9, "backoffs": 0, "vins_resets": 0}


def test_the_summary_counts_the_frames_taken_skipped_and_lost_and_their_age():
    """What the camera gave the VINS: skipped frames (the VINS busy past a frame's period)
    make every later frame older and the tracks' steps longer; a recording made before the
    counts has no such line."""
    from companion.flight.app import format_flight

    camera = {"frames": 1198, "camera_frames_dropped": 4, "camera_frames_lost": 12,
              "frame_age_ms": {"p50": 2.2, "p95": 31.6}}
    lines = format_flight({**FLIGHT, **camera}).splitlines()
    assert [line for line in lines if "camera frames" in line] == [
        "  camera frames     1198 taken, 4 skipped while busy, 12 lost by the camera; "
        "age 2 ms median, 32 ms p95"]
    assert not any("camera frames" in line for line in format_flight(FLIGHT).splitlines())


def test_the_summary_ends_with_the_estimated_time_offset_and_how_to_start_from_it():
    from autonomy.vins.time_offset import TimeOffset
    from companion.flight.app import format_flight, time_offset_summary

    def offset_line(offset: TimeOffset) -> list[str]:
        summary = {**FLIGHT, "vins_time_offset": time_offset_summary(offset)}
        return [line for line in format_flight(summary).splitlines() if "offset" in line]

    estimated = TimeOffset(seconds=0.01742, sigma=0.0004, estimating=True, updates=80)
    assert time_offset_summary(estimated) == {"seconds": 0.01742, "sigma_s": 0.0004,
                                              "estimated": True}
    assert offset_line(estimated) == [
        "  camera-IMU offset 17.4 ms (sigma 0.4 ms); to start the next flight from it: "
        "--set vins.time_offset_s=0.0174"]
    # nothing to tell: a fixed offset, or an estimate the motion never showed
    assert offset_line(TimeOffset(seconds=0.015)) == []
    assert offset_line(TimeOffset(seconds=0.0, estimating=True)) == []


def test_the_summary_says_what_the_vins_made_of_the_barometer_where_it_used_it():
    import math

    import numpy as np

    from autonomy.geometry import PinholeCamera
    from autonomy.vins import ImuNoise, Vins, VinsOptions
    from companion.flight.app import barometer_summary, format_flight

    def vins(sigma: float) -> Vins:
        estimator = Vins(PinholeCamera.from_hfov(64, 48, math.radians(90.0)), (), np.eye(4),
                         ImuNoise.icm42688p(), VinsOptions(barometer_sigma_m=sigma))
        estimator.barometer_keyframes, estimator.refused_pressures = 412, 2
        return estimator

    assert barometer_summary(vins(0.0)) is None
    assert barometer_summary(vins(0.2)) == {"keyframes": 412, "refused": 2, "steps": 0}
    lines = format_flight({**FLIGHT, "vins_barometer": barometer_summary(vins(0.2))})
    assert ("  VINS barometer    a height on 412 keyframes, 2 pressures refused, 0 steps of "
            "pressure taken out") in lines.splitlines()
    # a recording made before the steps were counted
    older = format_flight({**FLIGHT, "vins_barometer": {"keyframes": 412, "refused": 2}})
    assert "  VINS barometer    a height on 412 keyframes, 2 pressures refused" in \
        older.splitlines()
    assert "barometer" not in format_flight(FLIGHT)


def test_the_summary_ends_with_the_estimated_gyro_alignment_and_how_to_start_from_it():
    from autonomy.vins.gyro_alignment import GyroAlignmentEstimate
    from companion.flight.app import format_flight, gyro_alignment_summary

    def alignment_lines(estimate) -> list[str]:
        summary = {**FLIGHT, "vins_gyro_alignment": gyro_alignment_summary(estimate)}
        return [line for line in format_flight(summary).splitlines() if "gyro" in line]

    estimated = GyroAlignmentEstimate((0.0197, 0.0193, -0.0018), (0.0026, 0.0030, 0.0012), 670)
    assert gyro_alignment_summary(estimated) == {"column": [0.0197, 0.0193, -0.0018],
                                                 "sigma": [0.0026, 0.0030, 0.0012],
                                                 "pairs": 670, "matrix": None,
                                                 "matrix_sigma": None}
    assert alignment_lines(estimated) == [
        "  gyro yaw response [0.0197, 0.0193, -0.0018] (sigma at most 0.0030, 670 frame "
        "pairs); to start the next flight from it: "
        "--set 'vins.gyro_alignment=[0.0197, 0.0193, -0.0018]'"]
    whole = GyroAlignmentEstimate(
        (0.0197, 0.0193, -0.0018), (0.0026, 0.0030, 0.0012), 1300,
        ((0.002, -0.021, 0.0197), (0.01, 0.003, 0.0193), (-0.027, 0.016, -0.0018)),
        ((0.003, 0.004, 0.0026), (0.004, 0.003, 0.0030), (0.005, 0.0061, 0.0012)))
    numbers = "0.0020, -0.0210, 0.0197, 0.0100, 0.0030, 0.0193, -0.0270, 0.0160, -0.0018"
    assert alignment_lines(whole) == [
        f"  gyro misalignment (rows) [{numbers}] (sigma at most 0.0061, 1300 frame pairs); "
        f"to start the next flight from it: --set 'vins.gyro_alignment=[{numbers}]'"]
    # nothing to tell: no alignment, a calibration given and not estimated, no pair yet
    assert gyro_alignment_summary(None) is None and alignment_lines(None) == []
    assert alignment_lines(GyroAlignmentEstimate((0.02, 0.0, 0.0))) == []


# ---------------------------------------------------------------- simulated camera

class _Vehicle:
    def __init__(self, faults):
        from drivers.sim.quadrotor import Quadrotor
        self.vehicle = Quadrotor(position=(0.0, 0.0, 1.5))
        self.faults = FaultSchedule(faults)
        self.time = 0.0

    def turn_to(self, t: float) -> None:
        """At time ``t``, yawing at 1 rad/s, so each frame sees a different view."""
        from drivers.sim.quadrotor import Quadrotor
        self.time = t
        self.vehicle = Quadrotor(position=(0.0, 0.0, 1.5), yaw=t)


def _sim_camera_frames(faults, count: int, busy_s: float = 0.0):
    """``count`` frames of a 20 Hz simulated camera yawing at 1 rad/s, cruising (the faults'
    clock running) from t = 0, read by a consumer busy ``busy_s`` of simulated time after
    each frame."""
    from drivers.sim.camera import CameraHead, SimCamera
    from drivers.sim.render import Renderer
    from drivers.sim.world import build_world
    from drivers.camera.options import CameraOptions

    options = CameraOptions(width=64, height=48, rate_hz=20.0)
    world = build_world("dome", 0)
    sim = _Vehicle(faults)
    clock = SimClock(0.0)

    async def main():
        frames = []
        with Renderer(world, options.pinhole()) as renderer:
            camera = SimCamera(sim, renderer, clock, CameraHead(options.pinhole(),
                                                                options.rate_hz))
            sim.faults.update(0.0, (0.0, 0.0, 1.5), (2.0, 0.0, 0.0))

            async def advance():
                for k in range(1, 141):
                    sim.turn_to(k * 0.005)
                    clock.advance_to(sim.time)
                    await asyncio.sleep(0)
            runner = asyncio.create_task(advance())
            for _ in range(count):
                frames.append(await camera.next_frame())
                if busy_s:
                    await clock.sleep(busy_s)
            await camera.stop()
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
        return frames, camera

    return asyncio.run(main())


def test_sim_camera_delivers_frames_on_its_grid_and_injects_freeze_stale_and_blackout():
    frames, camera = _sim_camera_frames((Fault("camera_freeze", 0.0, 0.2),
                                         Fault("camera_stale", 0.3, 0.1),
                                         Fault("camera_blackout", 0.4, 0.1)), 8)
    times = np.array([f.t for f in frames])
    grid = np.arange(0.2, 0.56, 0.05)  # nothing while frozen, before 0.2 s
    # each frame is stamped at its exposure: the tick that falls on its grid time (the first
    # one a tick later: the clock had not ticked when the consumer first asked)
    assert np.all((times >= grid - 1e-9) & (times <= grid + 0.005 + 1e-9)), times
    assert camera.delivered == 8
    bright = [float(f.image.mean()) for f in frames]
    black = [0.4 <= t < 0.5 for t in times]
    assert [b == 0.0 for b in bright] == black
    assert min(b for b, dark in zip(bright, black) if not dark) > 20.0
    assert all(f.truth_depth.shape == (48, 64) for f in frames)
    # stale from 0.3 s to 0.4 s: the 0.25 s frame again, image and depth, with fresh stamps
    repeated = [np.array_equal(f.image, before.image)
                and np.array_equal(f.truth_depth, before.truth_depth, equal_nan=True)
                for before, f in zip(frames, frames[1:])]
    assert repeated == [0.3 <= t < 0.4 for t in times[1:]], times
    # numbered by exposure on the grid, as a RealSense or OAK numbers its frames; the stale
    # frames carry the number of the frame they repeat, so the application can refuse them
    counters = [f.counter for f in frames]
    assert counters == [round(t / 0.05) if not 0.3 <= t < 0.4 else 5 for t in times], counters


def test_a_busy_reader_gets_the_newest_frame_exposed_on_the_grid_with_its_pose_then():
    """A consumer busy 80 ms after each frame of a 20 Hz camera comes late. A real camera does
    not wait for it: it gets the newest frame exposed, at its grid time (the tick that falls
    on it, or the next one) and showing the pose then (yawing at 1 rad/s), not a frame
    exposed when it asked; the frames it never took are counted as dropped."""
    frames, camera = _sim_camera_frames((), 5, busy_s=0.08)
    times = np.array([f.t for f in frames])
    # read at 0.005 (the first tick), 0.085, 0.165, 0.245 and 0.325 s
    grid = np.array([0.0, 0.05, 0.15, 0.2, 0.3])
    assert np.all((times >= grid - 1e-9) & (times <= grid + 0.005 + 1e-9)), times
    yaws = [math.atan2(f.truth_pose[1, 0], f.truth_pose[0, 0]) for f in frames]
    assert np.allclose(yaws, times, atol=1e-9)  # the pose at the exposure, not at the read
    assert [f.counter for f in frames] == [0, 1, 3, 4, 6]
    assert camera.dropped == 2


def test_the_real_time_simulators_frame_slot_counts_frames_replaced_untaken_and_the_lost():
    """In real time the simulator's camera runs in its own thread and hands its frames to
    the application's loop through a newest-frame slot, as a real driver does: frames put
    from that thread while the application was busy are replaced, counted as dropped, and
    the camera's own count of lost frames comes with each frame."""
    async def scenario():
        slot = FrameSlot(asyncio.get_running_loop())
        thread = threading.Thread(target=lambda: [slot.put(k, lost=k // 2) for k in range(4)])
        thread.start()
        await asyncio.to_thread(thread.join)
        newest = await slot.next_frame()
        waiting = asyncio.ensure_future(slot.next_frame())
        await asyncio.sleep(0)
        return newest, waiting.done(), slot.dropped, slot.lost
    assert asyncio.run(scenario()) == (3, False, 3, 1)


def test_sim_camera_delivers_frames_twice_or_in_swapped_pairs_under_those_faults():
    """Repeated from 0 to 0.1 s (each frame, same stamp and image, twice), swapped pairs from
    0.2 s to just before the 0.3 s frame; in order, once each, before and after."""
    frames, _ = _sim_camera_frames((Fault("frame_repeat", 0.0, 0.1),
                                    Fault("frame_reorder", 0.2, 0.09)), 11)
    times = [round(round(f.t / 0.05) * 0.05, 2) for f in frames]  # on the grid
    assert times == [0.0, 0.0, 0.05, 0.05, 0.1, 0.15, 0.25, 0.2, 0.3, 0.35, 0.4], times
    assert frames[1].image is frames[0].image
    assert not np.array_equal(frames[6].image, frames[7].image)
    assert [f.counter for f in frames] == [0, 0, 1, 1, 2, 3, 5, 4, 6, 7, 8]


# ---------------------------------------------------------------- the real vehicle's wiring

def test_the_real_vehicles_app_runs_the_users_network_and_rescales_with_the_frames_map(
        tmp_path):
    """`companion fly`'s application (launch/real.py): a real ONNX session on each frame's
    RGB image, a real MAVLink link; the stage has no fit without the frame's sparse map; the
    VINS and the planner work on the camera's rectified pinhole, mounted where calibrated."""
    from dataclasses import replace

    from autonomy.depth.network import DepthNetwork, NetworkOptions
    from autonomy.messages import Frame
    from companion.config import Config
    from companion.launch.real import build_app
    from companion.tools.testmodel import build_test_model
    from drivers.camera.calibration import CalibratedCamera, resolve
    from drivers.clock import MonotonicClock
    from drivers.mavlink.autopilot import Autopilot

    model = tmp_path / "model.onnx"
    model.write_bytes(build_test_model())
    config = Config()
    config = replace(config, camera=replace(config.camera, distortion_model="radtan",
                                            distortion=(-0.28, 0.07, 0.0, 0.0), fx=300.0,
                                            rectified_hfov_deg=100.0, mount_pitch_deg=10.0))
    calibration = resolve(config.camera)
    size = (config.camera.height, config.camera.width)
    network = DepthNetwork.open(NetworkOptions(model=str(model)), size)
    clock = MonotonicClock()
    autopilot = Autopilot.open(
        replace(config.mavlink, url=f"udpout://127.0.0.1:{free_udp_port()}"), clock)
    app = build_app(config, [(5.0, 0.0, 1.5)], autopilot=autopilot,
                    camera=CalibratedCamera(None, calibration), network=network, clock=clock)
    try:
        assert app.perception.vins.camera == calibration.rectified != config.camera.pinhole()
        assert np.allclose(app.perception.T_B_C, config.camera.T_B_C())
        assert app.navigation.planner.camera == calibration.rectified
        depth = app.perception.depth
        dark, bright = (depth.infer(Frame(0.0, np.full(size + (3,), v, np.uint8)))
                        for v in (60, 180))
        assert dark.disparity.shape == size and np.isfinite(dark.disparity).all()
        assert bright.disparity.mean() > dark.disparity.mean()  # the test model's monotony
        metric = depth.metric(dark, None)
        assert not metric.ok and "no VINS sparse map" in metric.diagnostics.reason
    finally:
        for worker in app.context.workers.values():
            worker.close()
        autopilot.close()


def reported(armed: bool, mode, in_air: bool, z: float):
    """What the autopilot driver holds from PX4's last messages."""
    return SimpleNamespace(armed=armed, mode=mode, in_air=in_air,
                           state=SimpleNamespace(position_L=np.array([0.0, 0.0, z])))


def test_the_climb_is_over_only_on_what_px4_reports_after_the_arm():
    """Until a HEARTBEAT says armed (1 Hz), the driver still holds the state from before the
    arm: Hold, and here a position that drifted up on the ground. That is neither a finished
    climb nor a disarm in the air (it read as both: the take-off ended at once)."""
    watch = ClimbWatch(target_z=1.5)
    assert not watch.over(reported(False, px4_protocol.AUTO_LOITER, True, 1.6))
    assert not watch.over(reported(True, px4_protocol.AUTO_TAKEOFF, True, 0.8))
    assert watch.over(reported(True, px4_protocol.AUTO_LOITER, True, 1.3))


def test_motors_stopped_after_the_arm_end_the_climb():
    watch = ClimbWatch(target_z=1.5)
    assert not watch.over(reported(True, px4_protocol.AUTO_TAKEOFF, True, 0.4))
    assert watch.over(reported(False, px4_protocol.AUTO_TAKEOFF, True, 0.4))


@pytest.mark.parametrize("on_the_ground, reason, cause", [
    (False, "PX4 disarmed the vehicle in the air", "a ground station's forced disarm"),
    (True, "PX4 disarmed the vehicle on the ground", "COM_DISARM_LAND's auto-disarm"),
])
def test_motors_stopped_name_where_px4_disarmed_the_vehicle(on_the_ground, reason, cause):
    """The summary names a disarm in the air apart from PX4's auto-disarm once the vehicle
    came down (flown into the floor: it used to read as a disarm in the air); either way
    the mission ends."""
    from autonomy.navigation.mission import FlightOptions, FlightState
    from companion.flight.context import FlightContext

    context = FlightContext(FlightOptions(), SimpleNamespace(now=lambda: 5.0),
                            SimpleNamespace(disarmed_on_the_ground=on_the_ground), {})
    context.motors_stopped()
    assert context.mission.failsafes == [reason]
    assert context.state == FlightState.ABORTED
    assert cause in context.mission.transitions[-1].reason


# ---------------------------------------------------------------- the glide to a landing site

@pytest.mark.parametrize("failure, reason", [
    ({"stop_requested": "stop requested (SIGTERM)"}, "stop requested (SIGTERM)"),
    ({"camera_age_s": 0.6}, "camera silent"),
])
def test_a_failure_during_the_glide_to_a_landing_site_cuts_it_short(failure, reason):
    """SIGTERM, or a sensor falling silent, after a mission timeout while the vehicle glides to
    its landing site: it holds and lands now (the glide is for a sound vehicle, and systemd's
    stop timeout allows a stop, Hold and a landing, not a glide). A failure during the stop
    rules the glide out the same way."""
    from autonomy.navigation.failsafes import BlindClock
    from autonomy.navigation.mission import FlightOptions, FlightState
    from companion.flight.health import Health
    from companion.flight.navigation import Navigation
    from companion.flight.steps import MissionSteps
    from test_navigation import vitals

    context = SimpleNamespace(clock=SimpleNamespace(now=lambda: 10.0),
                              state=FlightState.TO_LANDING_SITE, options=FlightOptions(),
                              autopilot=SimpleNamespace(connected=True, armed=True),
                              blind=BlindClock(), mission=SimpleNamespace(
                                  stopped_by="mission timeout"),
                              channels=SimpleNamespace(plan=SimpleNamespace(value=None)))
    navigation = Navigation.__new__(Navigation)  # the parts the check and the glide's end read
    navigation.context, navigation.glide_cut, navigation._vins_failed = context, "", False
    navigation.landmarks = lambda: 50
    navigation.stopped = lambda: False  # still gliding
    health = Health(context, None, navigation, None)
    measured = {"no_path_expired": True}  # the mission's own failure does not cut it
    health.vitals = lambda now, lag: vitals(**measured)
    steps = MissionSteps(context, None, navigation, None)
    health.check(0.0)
    assert not navigation.at_landing_site()  # gliding on
    measured.update(failure)
    health.check(0.0)
    assert navigation.at_landing_site()
    assert steps._glide_end() == f"{reason}: the glide to the landing site cut short"


def test_a_frame_waits_out_a_silent_imu_once_and_the_next_frames_do_not_while_it_stays_silent():
    """A frame waits for the IMU to reach it, up to ``imu_timeout_s``; once a wait has run
    out, the next frames go straight on while the IMU's newest stamp stays where it was (each
    waiting the whole time out, the VINS saw one frame in 0.29 s through an IMU gap and lost
    the tracks it relocalises on), and wait again once the IMU moves."""
    from companion.flight.perception import IMU_POLL_S, Perception

    clock = SimClock(10.0)
    autopilot = SimpleNamespace(last_imu_t=9.0)
    context = SimpleNamespace(clock=clock, autopilot=autopilot,
                              options=SimpleNamespace(imu_timeout_s=0.25))
    perception = SimpleNamespace(context=context, _imu_silent_since=math.nan)

    async def wait_for(t: float, imu_arrives_at: float | None = None) -> float:
        """Simulated seconds the frame at ``t`` waited, the clock moved as the lockstep host
        moves it (to each sleeper's deadline)."""
        start = clock.now()
        waiting = asyncio.ensure_future(Perception._wait_for_imu(perception, t))
        while not waiting.done():
            await asyncio.sleep(0)
            deadline = clock.next_deadline
            if deadline is not None:
                clock.advance_to(deadline)
            if imu_arrives_at is not None and clock.now() >= imu_arrives_at:
                autopilot.last_imu_t = t
        return clock.now() - start

    async def frames():
        silent = await wait_for(10.0)  # the IMU stopped at 9.0: the whole time out
        still_silent = [await wait_for(10.0 + 0.05 * k) for k in range(1, 4)]
        autopilot.last_imu_t = 9.9  # back, behind the frame: waited for again
        back = await wait_for(10.5, imu_arrives_at=clock.now() + 0.02)
        return silent, still_silent, back

    silent, still_silent, back = asyncio.run(frames())
    assert silent == pytest.approx(0.25, abs=2 * IMU_POLL_S)
    assert still_silent == [0.0, 0.0, 0.0]
    assert back == pytest.approx(0.02, abs=2 * IMU_POLL_S)
