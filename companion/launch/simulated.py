"""``companion sim fly``: the whole stack against the simulated vehicle, over real MAVLink.

The simulator host (:mod:`drivers.sim.host`) serves the mock PX4 on loopback UDP, or (``link``
serial) on a pseudo-terminal the application opens as a serial port at 921600 baud, through the
code a flight controller on a UART goes through; the application
(:class:`companion.flight.app.FlightApp`) connects to it as it would to a real flight
controller, sees the world through the simulated camera, estimates its state with the
VINS and its depth with the network (the synthetic stand-in of ``[synthetic_depth]`` unless
``[depth_network] model`` names an ONNX file) and the rescaler, and flies the planner's arcs
to the goal.

The mission: a world's start/goal pair (``pair``), flown through the corners of the route's
collision-free path as waypoints (what an operator would give as a mission), or one ``goal``.
Waypoints and goals are in PX4's local frame, which in the simulator is the world frame (ENU).

Ground truth stays on the simulator's side and is used only for the summary: the flown path,
its clearance from the obstacles, collisions, the distance to the goal at the end.

Clocks: ``lockstep`` (default) runs the simulator and the application on one event loop and one
:class:`~drivers.clock.SimClock`, heavy stages inline (deterministic, as fast as the CPU
allows); ``realtime`` runs the simulator in its own thread on the wall clock and the application
on the main thread with its stages in worker threads, as on the vehicle.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import json
import logging
import math
from pathlib import Path
from typing import Callable

import numpy as np

from autonomy.navigation.mission import FlightState
from companion.flight.app import FlightApp, format_flight
from companion.flight.perception import NetworkDepth
from companion.recording.session import open_recording, recorded, recording_metadata
from companion.report import format_split, show
from drivers.camera.calibration import CalibratedCamera, grid_stamps
from drivers.mavlink.autopilot import Autopilot
from drivers.mavlink.signing import load_key
from drivers.sim.faults import FaultSchedule
from drivers.sim.host import (DEPTH_SOURCES, LockstepSimulator, SimError, SimMission,
                              ThreadedSimulator, TruthDepth, TruthTrack, empty_disk,
                              fill_disk_when_due, mission_waypoints, simulated_network,
                              stall_when_due)
from drivers.sim.serve import LINKS
from drivers.sim.truth_tracks import TRACK_SOURCES, replacement_for
from drivers.sim.world import World, build_world

log = logging.getLogger(__name__)

#: How much further than ``[flight] goal_tolerance`` the true closest approach may be when the
#: application says it reached the goal: the VINS's drift over a flight, metres.
GOAL_DRIFT_ALLOWANCE = 1.0

#: How often ``--go-after`` looks whether the mission waits for the go yet, seconds.
WAITING_POLL_S = 0.05

__all__ = ["DEPTH_SOURCES", "SimError", "SimMission", "check_track_source", "run", "fly",
           "format_summary"]


def check_track_source(config, tracks: str) -> None:
    """SimError unless ``config`` can fly the VINS on ``tracks`` (a key of
    :data:`~drivers.sim.truth_tracks.TRACK_SOURCES`): anything but the tracker's needs the
    ideal profile."""
    if tracks not in TRACK_SOURCES:
        raise SimError(f"tracks must be one of {', '.join(TRACK_SOURCES)}, got {tracks!r}")
    if tracks != "tracker" and config.sim.profile != "ideal":
        raise SimError("truth tracks need the ideal profile ([sim] profile = \"ideal\"): the "
                       "realistic camera's lens, mounting error and late stamps are not the "
                       "configured camera the truth is projected through (--config "
                       "config/sim.toml flies the ideal profile)")


def run(config, mission: SimMission, *, plot: Path | None = None,
        progress: Callable[[str], None] | None = None, record: bool = False,
        live: str | None = None) -> dict:
    """Fly ``mission`` to its end and return the summary (module docstring); ``record``: into
    an MCAP file as ``[recorder]`` says, ``live``: served to Foxglove on ``HOST:PORT``
    (docs/recording.md). A signing key (``[mavlink]``, ``[px4]``) that cannot be used is a
    :class:`~drivers.mavlink.signing.SigningKeyError` before the simulator starts."""
    if mission.clock not in ("lockstep", "realtime"):
        raise SimError(f"clock must be lockstep or realtime, got {mission.clock!r}")
    if mission.depth not in DEPTH_SOURCES:
        raise SimError(f"depth must be one of {', '.join(DEPTH_SOURCES)}, "
                       f"got {mission.depth!r}")
    check_track_source(config, mission.tracks)
    if mission.link not in LINKS:
        raise SimError(f"link must be one of {', '.join(LINKS)}, got {mission.link!r}")
    for table in (config.mavlink, config.px4):
        load_key(table)  # a key that cannot be used stops here, before the simulator starts
    unestimated = realistic_errors_not_estimated(config)
    if unestimated:
        log.warning("%s", unestimated)
    camera = config.camera
    if camera.calibration != "config" or camera.distortion_model != "none":
        raise SimError("the simulator renders an ideal pinhole camera: [camera] calibration "
                       "must be config and distortion_model none (got "
                       f"{camera.calibration}, {camera.distortion_model})")
    summary = asyncio.run(fly(config, mission, plot=plot, progress=progress, record=record,
                              live=live))
    # The flight's stages refer to one another through their shared context, so a finished
    # flight (its world, renderer, depth history, smoother) is freed only by the cycle
    # collector, whose full pass comes rarely: without this, a process flying mission after
    # mission (eval nav's workers, `sim soak`) carried about 90 MB per past flight, up to
    # 370 MB more after nine (`companion sim soak`, docs/reliability.md).
    gc.collect()
    return summary


def realistic_errors_not_estimated(config) -> str:
    """What of the realistic vehicle's errors the configured VINS leaves unestimated, which a
    real vehicle's configuration estimates ("" when none, or on the ideal profile): the
    camera's time offset (the Orin presets' ``estimate_time_offset``) and the gyro's yaw
    response (their first flight's ``estimate_gyro_alignment``, carried after it)."""
    if config.sim.profile != "realistic":
        return ""
    vins = config.vins
    missing = [what for what, estimated in (
        ("the camera's time offset ([vins] estimate_time_offset)", vins.estimate_time_offset),
        ("the gyro's yaw response ([vins] estimate_gyro_alignment or gyro_alignment)",
         vins.estimate_gyro_alignment or any(vins.gyro_alignment)))
        if not estimated]
    if not missing:
        return ""
    return (f"the realistic profile's vehicle is flown without estimating {' or '.join(missing)}"
            ", as no real vehicle's configuration flies: its errors are then the VINS's; "
            "--config config/sim-realistic.toml flies it as the Orin presets do")


async def fly(config, mission: SimMission, *, plot: Path | None = None,
              progress: Callable[[str], None] | None = None,
              go_given_by: str = "sim fly", record: bool = False,
              live: str | None = None) -> dict:
    """Fly ``mission`` on the running loop and return the summary (module docstring). The
    command line is the operator's go (``go_given_by``); "" waits for one as ``[go]`` says.
    ``record`` and ``live``: as :func:`run`."""
    if mission.go_after_s is not None:  # the go comes later, as a ground station's would
        if not (mission.go_after_s >= 0.0):
            raise SimError(f"--go-after must be 0 seconds or more, got {mission.go_after_s}")
        config = dataclasses.replace(config, go=dataclasses.replace(
            config.go, required=True, socket="", rc_channel=0))
        go_given_by = ""
    world = build_world(mission.world, mission.seed, config.sim.profile)
    # the route's corners are planned in the ideal world, so that its thin obstacles (the
    # realistic profile's) are the flight's to see and avoid, not the route's
    start, waypoints, start_yaw = mission_waypoints(build_world(mission.world, mission.seed),
                                                    mission, config.flight.takeoff_altitude)
    faults = FaultSchedule(mission.faults, world.obstacle_clearance)
    if faults.has("loop_stall") and mission.clock != "realtime":
        raise SimError("a loop_stall fault needs --clock realtime: in lockstep the simulator "
                       "shares the stalled loop, so simulated time stalls with it")
    if faults.has("disk_full") and not record:
        raise SimError("a disk_full fault fills the recording's disk: it needs a recorded "
                       "flight (drop --no-record, or set [recorder] enabled = true)")
    side = (LockstepSimulator if mission.clock == "lockstep" else ThreadedSimulator)(
        config, world, mission, (start, start_yaw), faults, waypoints[-1], progress)
    sim, camera, clock = await side.start()
    camera = CalibratedCamera(camera, side.calibration(), grid_stamps(config.camera))
    stall = asyncio.create_task(stall_when_due(faults, sim))
    try:
        depth = TruthDepth(config.planner.max_range) if mission.depth == "truth" else \
            NetworkDepth(simulated_network(config, mission.seed, faults, lambda: sim.time),
                         config.rescale, config.depth)
        exact_tracks = replacement_for(mission.tracks, config.camera.pinhole(),
                                       config.camera.T_B_C())
        app = build_app(config, clock, side.companion_url(), camera, depth, waypoints,
                        lockstep=mission.clock == "lockstep", go_given_by=go_given_by,
                        exact_tracks=exact_tracks)
        go_later = asyncio.create_task(give_go_after(app.gate, clock, mission.go_after_s))
        try:
            metadata = recording_metadata(config,
                                          mission=json.dumps(dataclasses.asdict(mission)))
            recording = open_recording(config.recorder, clock=clock, to_file=record, live=live,
                                       metadata=metadata)
            disk = asyncio.create_task(fill_disk_when_due(faults, sim, recording and
                                                          recording.path))
            try:
                summary = await recorded(app, recording)
            finally:
                disk.cancel()
                empty_disk(disk.result() if disk.done() and not disk.cancelled() else None)
            summary["mavlink"] = _link_load(app.autopilot.link, sim)
        finally:
            go_later.cancel()
            app.autopilot.close()
    finally:
        stall.cancel()
        await side.stop()
    summary.update(_truth_summary(config, world, mission, sim, side.track, waypoints, summary))
    # when each moment a fault can start at came (simulated seconds): a fault whose moment
    # never came was never injected
    summary["fault_moments"] = {moment: round(t, 3) for moment, t in faults.moment_since.items()}
    if plot is not None:
        _plot(world, mission, side.track, (start, waypoints), plot, summary)
        summary["plot"] = str(plot)
    return summary


async def give_go_after(gate, clock, seconds: float | None) -> None:
    """The operator's go ``seconds`` of the flight's clock after the mission starts waiting
    for it (``sim fly --go-after``; nothing when None): the vehicle stands on the ground
    meanwhile, as one does while its operator checks the field."""
    if seconds is None:
        return
    while not gate.waiting:
        await clock.sleep(WAITING_POLL_S)
    await clock.sleep(seconds)
    if not gate.command(f"sim fly --go-after {seconds:g}"):
        log.warning("--go-after: the mission no longer waited for the go when it came")


def build_app(config, clock, url: str, camera, depth, waypoints, *,
              lockstep: bool, go_given_by: str = "sim fly", exact_tracks=None) -> FlightApp:
    """The application wired to a camera, a depth source and the autopilot at ``url``; in
    lockstep with the realistic profile, each stage's compute takes ``[sim_latency]``'s time
    in simulated time. ``exact_tracks``: as :meth:`FlightApp.from_config`."""
    autopilot = Autopilot.open(dataclasses.replace(config.mavlink, url=url), clock)
    realistic = lockstep and config.sim.profile == "realistic"
    return FlightApp.from_config(config, autopilot=autopilot, camera=camera,
                                 pinhole=config.camera.pinhole(), T_B_C=config.camera.T_B_C(),
                                 depth=depth, waypoints_L=waypoints, clock=clock,
                                 lockstep=lockstep, go_given_by=go_given_by,
                                 latency=config.sim_latency.per_stage() if realistic else None,
                                 exact_tracks=exact_tracks)


def _link_load(link, sim) -> dict:
    """The MAVLink bytes each way per simulated second, beside what the link can carry at most
    (a serial port: baud / 10, a byte being 10 bits on the wire with 8N1; else None), and the
    bytes or frames that did not parse at each end (a link that drops bytes garbles frames)."""
    seconds = max(sim.time, sim.dt)
    capacity = link.address.baud / 10 if link.address.scheme == "serial" else None
    return {"where": link.address.where,
            "received_bytes_per_s": round(link.traffic.bytes / seconds),
            "sent_bytes_per_s": round(sim.px4.link.traffic.bytes / seconds),
            "capacity_bytes_per_s": capacity,
            "bad_data": {"received": link.bad_data_count,
                         "sent": sim.px4.link.bad_data_count}}


def _truth_summary(config, world: World, mission: SimMission, sim, track: TruthTrack,
                   waypoints, summary: dict) -> dict:
    goal = waypoints[-1]
    truth = track.score(world, goal, summary.get("navigation_end"))
    collision = sim.vehicle.collision
    floor = _floor_contact(track, summary["transitions"])
    return {
        "world": world.name, "seed": mission.seed, "pair": mission.pair, "depth": mission.depth,
        "goal": [round(float(v), 3) for v in goal],
        "faults": [dataclasses.asdict(f) for f in mission.faults],
        "collisions": (collision is not None) + (floor is not None),
        "collision": None if collision is None else _event(collision.time, collision.position),
        "floor_contact": floor,
        **truth,
        "failsafe_stop_m": _path_length_in(track, summary["transitions"], "failsafe_stop"),
        "landing_glide_m": _path_length_in(track, summary["transitions"], "to_landing_site"),
        # the application's own judgement, confirmed by the truth (with room for VINS drift)
        "reached_goal": bool(summary["reached_goal"] and truth["closest_to_goal_m"] is not None
                             and truth["closest_to_goal_m"]
                             <= config.flight.goal_tolerance + GOAL_DRIFT_ALLOWANCE),
    }


def _event(t: float, position) -> dict:
    return {"t": round(t, 3), "position": [round(float(v), 3) for v in position]}


def _floor_contact(track: TruthTrack, transitions: list[dict]) -> dict | None:
    """Where and when the vehicle first came down on the floor, armed, between the switch to
    Offboard and the landing (an arc or a stop flown into it: no obstacle's collision radius
    counts the floor, and the least clearance leaves out the path below 0.3 m, the take-off's
    and the landing's), None if it did not. A collision as much as a wall is."""
    start = offboard_switch_time(transitions)
    if start is None:
        return None
    end = next((t["t"] for t in transitions if t["t"] >= start and t["to"] in _DOWN), math.inf)
    contact = track.first_floor_contact(start, end)
    return None if contact is None else _event(*contact)


def offboard_switch_time(transitions: list[dict]) -> float | None:
    """When the flight switched to Offboard (the transition out of ENTERING_OFFBOARD, to the
    offset swing or to navigating), from a summary's ``transitions``; None if it never did."""
    return next((t["t"] for t in transitions
                 if t["from"] == FlightState.ENTERING_OFFBOARD.value), None)


#: The states in which the vehicle is meant to come down, or is down.
_DOWN = frozenset(state.value for state in (FlightState.LANDING, FlightState.LANDED,
                                              FlightState.ABORTED))


def _path_length_in(track: TruthTrack, transitions: list[dict], state: str) -> float | None:
    """Metres flown in truth during the first time in ``state``, from its start to the next
    state (None when never in it): the failsafe's stop, which must be short, and the glide to
    a landing site after it."""
    for k, transition in enumerate(transitions):
        if transition["to"] == state:
            end = transitions[k + 1]["t"] if k + 1 < len(transitions) else math.inf
            return round(track.path_length_between(transition["t"], end), 3)
    return None


def _plot(world, mission: SimMission, track: TruthTrack, route, out: Path,
          summary: dict) -> None:
    """The top view of the flight (:func:`companion.tools.plot.top_view`): the true path
    coloured by time over the world, the ``route``'s start and waypoints, where it met a
    surface or came down on the floor (the summary's ``collision`` and ``floor_contact``)."""
    from companion.tools.eval.provenance import code_revision
    from companion.tools.plot import flight_caption, top_view

    start, waypoints = route
    top_view(world, np.array(track.positions), times=track.t, start=start, goal=waypoints[-1],
             waypoints=waypoints[:-1],
             collisions=tuple(event["position"] for event in (summary.get("collision"),
                                                              summary.get("floor_contact"))
                              if event is not None), out=out,
             title=f"{world.name} pair {mission.pair}: "
                   f"{'reached' if summary['reached_goal'] else 'not reached'}",
             caption=f"Flown: {flight_caption(mission)}; code revision {code_revision()}.")


def _format_load(load: dict) -> str:
    carried = (f"{load['received_bytes_per_s'] / 1e3:.1f} kB/s in, "
               f"{load['sent_bytes_per_s'] / 1e3:.1f} kB/s out")
    if load["capacity_bytes_per_s"] is not None:
        carried += f" of {load['capacity_bytes_per_s'] / 1e3:.1f} kB/s each way"
    bad = load["bad_data"]
    return f"{load['where']}: {carried}; bad data {bad['received']} in, {bad['sent']} out"


def _floor_line(summary: dict) -> str:
    floor = summary.get("floor_contact")
    return "" if floor is None else f" (on the floor at t={floor['t']:.1f} s)"


def format_summary(summary: dict) -> str:
    """A simulated flight's summary as a few lines for a person."""
    lines = [f"{summary['world']} pair {summary['pair']} (seed {summary['seed']}) -> goal "
             f"{summary['goal']}",
             f"  reached goal      {'yes' if summary['reached_goal'] else 'no'}"
             f" (closest {show(summary.get('closest_to_goal_m'), '.2f', ' m')})",
             f"  collisions        {summary['collisions']}{_floor_line(summary)}",
             f"  path length       {show(summary.get('path_length_m'), '.1f', ' m')}",
             f"  min clearance     {show(summary.get('min_clearance_m'), '.2f', ' m')}",
             f"  VINS error        {show(summary.get('position_error_m'), '.2f', ' m')}"
             f"{format_split(summary.get('position_error_split'))}",
             f"  MAVLink           {_format_load(summary['mavlink'])}"]
    lines += format_flight(summary).splitlines()
    if summary.get("plot"):
        lines.append(f"  plot              {summary['plot']}")
    return "\n".join(lines)
