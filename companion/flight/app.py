"""The flight application: one asyncio process from camera and IMU to PX4 setpoints.

DESIGN.md, "The process"; docs/architecture.md draws the flow of one frame to one setpoint.
Stages, each a few short coroutines on one event loop, exchanging messages over channels
(:class:`~companion.flight.context.Channels`):

- the MAVLink driver (:class:`drivers.mavlink.autopilot.Autopilot`): heartbeats, TIMESYNC,
  HIGHRES_IMU, commands;
- perception (:mod:`~companion.flight.perception`): per camera frame the VINS and the depth
  source, then metric depth into the planner's history;
- navigation (:mod:`~companion.flight.navigation`): the route, the behaviours at corners and
  dead ends and the planner, every ``[planner] period_s``;
- command (:mod:`~companion.flight.command`): setpoints and ODOMETRY to PX4, and the
  setpoint watchdog thread;
- health (:mod:`~companion.flight.health`): loop lag and the failsafe checks;
- the mission's steps (:mod:`~companion.flight.steps`): preflight to landing.

Heavy work runs on workers (:mod:`~companion.flight.workers`): inline in lockstep, a thread
per stage in real time.

Frames: the VINS world ``W`` is fixed at its static initialisation; PX4's local frame ``L``
(ENU here, NED on the wire) is its own. They are tied once, on the ground, by the yaw and
position of the two estimates at the same instant
(:func:`autonomy.geometry.yaw_alignment`); goals are given in ``L``, planned in ``W``, and
setpoints and odometry go back to ``L``.
"""

from __future__ import annotations

import asyncio
import logging
import math

import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.navigation.behaviours import GOAL_STOP_REASON
from autonomy.navigation.mission import GROUND_STATES, FlightState
from autonomy.navigation.route import Route
from autonomy.planning.planner import Planner
from autonomy.vins.estimator import Vins
from companion.flight.command import Command
from companion.flight.context import FlightContext
from companion.flight.go import OperatorGate
from companion.flight.health import Health
from companion.flight.navigation import Navigation
from companion.flight.perception import DepthSource, Perception
from companion.flight.steps import MissionSteps
from companion.flight.workers import make_workers
from companion.report import show

log = logging.getLogger(__name__)

#: The workers heavy stages run on.
WORKERS = ("vins", "network", "planner")


class FlightApp:
    """The whole stack against one autopilot, camera and depth source (module docstring).

    ``waypoints_L``: (N, 3) points in PX4's local frame (ENU), the last one the goal.
    ``depth``: a :class:`~companion.flight.perception.DepthSource` (the network and the
    rescaler, :class:`~companion.flight.perception.NetworkDepth`, or in simulation the true
    depth). ``workers`` maps :data:`WORKERS` to a worker.
    """

    @classmethod
    def from_config(cls, config, *, autopilot, camera, pinhole: PinholeCamera, T_B_C,
                    depth: DepthSource, waypoints_L, clock, lockstep: bool,
                    go_given_by: str = "", notifier=None,
                    latency: dict[str, float] | None = None,
                    exact_tracks=None) -> "FlightApp":
        """The application with its VINS, planner and workers built from ``config``: the
        camera's frames follow the ideal ``pinhole`` (rectified, drivers.camera.calibration)
        from a camera mounted at ``T_B_C``; the ``[vins_imu]`` noise model; workers inline in
        lockstep (charging ``latency``, seconds per worker, to the simulated clock), threads
        otherwise (closed when :meth:`run` ends). ``go_given_by`` non-empty:
        the operator's go is already given (``sim fly``), else ``[go]`` says how it comes.
        ``exact_tracks``: a simulated flight's tracks replaced by the truth's
        (:class:`drivers.sim.truth_tracks.TruthTracks`; None: the tracker's)."""
        vins = Vins(pinhole, (0.0,) * 4, T_B_C, config.vins_imu, config.vins,
                    frontend=config.vins_frontend, static=config.vins_init)
        return cls(config, autopilot=autopilot, camera=camera, depth=depth, vins=vins,
                   T_B_C=T_B_C, planner=Planner(pinhole, config.planner),
                   waypoints_L=waypoints_L, clock=clock, notifier=notifier,
                   workers=make_workers(lockstep, WORKERS, clock, latency),
                   gate=OperatorGate(config.go, autopilot, go_given_by),
                   exact_tracks=exact_tracks)

    def __init__(self, config, *, autopilot, camera, depth: DepthSource, vins: Vins,
                 T_B_C: np.ndarray, planner: Planner, waypoints_L, clock, workers: dict,
                 gate: OperatorGate, notifier=None, exact_tracks=None):
        options = config.flight
        self.context = FlightContext(options, clock, autopilot, workers)
        self.perception = Perception(self.context, camera, vins, depth, planner, T_B_C,
                                     exact_tracks)
        self.navigation = Navigation(self.context, self.perception, planner,
                                     Route(waypoints_L, math.radians(options.corner_turn_deg)))
        self.command = Command(self.context, self.perception, self.navigation)
        self.health = Health(self.context, self.perception, self.navigation,
                             self.command.watchdog, notifier)
        self.gate = gate
        self.steps = MissionSteps(self.context, self.perception, self.navigation, gate,
                                  notifier)

    @property
    def channels(self):
        """The stages' channels, for taps (a recorder, a live view, a test)."""
        return self.context.channels

    @property
    def pinhole(self) -> PinholeCamera:
        """The rectified camera every stage sees."""
        return self.perception.planner.camera

    @property
    def T_B_C(self) -> np.ndarray:
        """The camera's mounting on the body."""
        return self.perception.T_B_C

    @property
    def mission(self):
        return self.context.mission

    @property
    def autopilot(self):
        return self.context.autopilot

    async def run(self) -> dict:
        """Fly the mission to its end (landed or aborted) and return the summary."""
        c = self.context
        self.gate.open()
        watchdog = self.command.watchdog
        watchdog.start()
        tasks = [asyncio.create_task(self._guard(name, coroutine), name=name)
                 for name, coroutine in (
                     ("autopilot", c.autopilot.run()), ("perception", self.perception.run()),
                     ("planner", self.navigation.run()),
                     ("setpoints", self.command.send_setpoints()),
                     ("odometry", self.command.send_odometry()),
                     ("monitor", self.health.run()))]
        try:
            await self.steps.fly()
        finally:
            watchdog.close()
            self.gate.close()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for worker in c.workers.values():
                worker.close()
        return self.summary()

    async def _guard(self, name: str, coroutine) -> None:
        """Run one task; an error in it is a failsafe (logged with its traceback once), never
        an exception out of the application. The watchdog covers a dead setpoint task."""
        c = self.context
        try:
            await coroutine
        except asyncio.CancelledError:
            raise
        except Exception as error:  # noqa: BLE001 - every failure must end in the safe state
            log.exception("%s task failed", name)
            c.mission.failsafe(c.clock.now(), f"{name} failed: {error}")
            if c.state == FlightState.FAILSAFE_STOP:
                c.channels.plan.publish(c.channels.checked_stop.value)  # immutable: safe
            elif not c.mission.done and c.state in GROUND_STATES:
                c.abort(f"{name} failed: {error}")

    def stop_requested(self, reason: str) -> None:
        """An operator's stop (SIGTERM from systemd): on the ground the mission ends; in the
        air it is a failsafe (stop, hold, land) at the next check."""
        self.health.stop_reason = reason
        if self.context.state in GROUND_STATES:
            self.context.abort(reason)

    def summary(self) -> dict:
        """The run in plain numbers for JSON (the simulator adds the ground truth)."""
        c = self.context
        s, mission, now = c.stats, c.mission, c.clock.now()
        navigation = ((s.navigation_end or now) - s.navigation_start
                      if s.navigation_start is not None else 0.0)
        return {
            "final_state": mission.state.value,
            "reached_goal": any(t.reason == GOAL_STOP_REASON for t in mission.transitions),
            "failsafes": list(mission.failsafes),
            "transitions": [{"t": round(t.t, 3), "from": t.source.value, "to": t.target.value,
                             "reason": t.reason} for t in mission.transitions],
            "flight_time_s": ((s.landed_t or now) - s.takeoff_t
                              if s.takeoff_t is not None else 0.0),
            "navigation_time_s": navigation,
            "frames": s.frames,
            "frames_out_of_order": s.frames_out_of_order,
            "frames_stale": s.frames_stale,
            # frames the driver replaced, untaken, by a newer one (the VINS busy), and frames
            # the camera never delivered (its counter's gaps)
            "camera_frames_dropped": self.perception.camera.dropped,
            "camera_frames_lost": self.perception.camera.lost,
            # from a frame's stamp to the VINS loop taking it: what skipped frames cost
            "frame_age_ms": percentiles_ms(s.frame_age_s),
            # the VINS takes every frame; the depth stage the newest when its network is free
            "vins_frames": c.channels.vins.published,
            "depth_frames": c.channels.depth.published,
            # metric depth frames the planner got per second of navigation
            "depth_rate_hz": s.depth_ok / navigation if navigation > 0 else 0.0,
            "depth_failures": dict(s.depth_reasons),
            "depth_fallbacks": s.depth_fallbacks,
            "planning_rounds": s.planning_rounds,
            "stop_rounds": s.stop_rounds,
            "backoffs": s.backoffs,
            "vins_resets": self.perception.vins.resets,
            # keyframes given a zero-velocity prior on the ground before the take-off (all of
            # them when there was none; autonomy/vins/stillness.py)
            "vins_still_keyframes": (self.perception.vins.zero_velocity_keyframes
                                     if s.vins_still_keyframes_at_takeoff is None
                                     else s.vins_still_keyframes_at_takeoff),
            "vins_barometer": barometer_summary(self.perception.vins),
            "vins_time_offset": time_offset_summary(self.perception.vins.time_offset),
            "vins_gyro_alignment": gyro_alignment_summary(self.perception.vins.gyro_alignment),
            # the accelerometer's z sensitivity error read at rest and divided out (a fraction;
            # None unless [vins] rest_accel_scale_share: autonomy/vins/accel_scale.py)
            "vins_rest_accel_scale_error": self.perception.vins.rest_accel_scale_error,
            "vins_correction_m": correction_summary(s.vins_corrections_m),
            "watchdog_setpoints": self.command.watchdog.fired,
            "loop_lag_ms_p99": percentiles_ms(s.loop_lag_s, (99,))["p99"],
            "waypoints_passed": self.navigation.route.index,
            "navigation_end": s.navigation_end_L,
            # on, and the messages it refused: unsigned, bad_signature
            "mavlink_signing": c.autopilot.signing,
            # what the autopilot driver dropped and why: IMU samples, TIMESYNC samples, ...
            "autopilot_counters": c.autopilot.stats(),
        }


def barometer_summary(vins) -> dict | None:
    """What the VINS made of the flight controller's barometer (None when it was not used:
    ``[vins] barometer_sigma_m`` 0): the keyframes it gave a height, the pressures it left out
    as no barometer's, and the samples it took as steps of pressure, not climbs (docs/vins.md,
    "The barometer")."""
    if vins.options.barometer_sigma_m <= 0.0:
        return None
    return {"keyframes": vins.barometer_keyframes, "refused": vins.refused_pressures,
            "steps": vins.backend.barometer_steps}


def percentiles_ms(seconds: list, percents=(50, 95)) -> dict:
    """``{"p50": ..., "p95": ...}``: the ``percents`` of ``seconds`` in milliseconds (zero
    when there are none)."""
    values = np.asarray(seconds) if seconds else np.zeros(1)
    return {f"p{percent}": float(1e3 * np.percentile(values, percent)) for percent in percents}


def correction_summary(corrections_m: list) -> dict:
    """How far the VINS's smoother moved its keyframes from the IMU's propagation while
    navigating (:attr:`~autonomy.vins.estimator.FrameUpdate.correction_m`): ``median``,
    ``p95`` and ``max`` metres over ``keyframes`` (None for each without one)."""
    if not corrections_m:
        return {"keyframes": 0, "median": None, "p95": None, "max": None}
    values = np.asarray(corrections_m)
    return {"keyframes": len(values), "median": float(np.median(values)),
            "p95": float(np.percentile(values, 95)), "max": float(values.max())}


def time_offset_summary(offset) -> dict:
    """The camera-IMU time offset the VINS ended on (a
    :class:`~autonomy.vins.time_offset.TimeOffset`): ``seconds``, ``sigma_s`` (None while
    nothing showed it, or fixed), ``estimated`` (online, ``[vins] estimate_time_offset``)."""
    return {"seconds": offset.seconds, "sigma_s": offset.sigma, "estimated": offset.estimating}


def gyro_alignment_summary(estimate) -> dict | None:
    """The gyro's misalignment the VINS ended on (a
    :class:`~autonomy.vins.gyro_alignment.GyroAlignmentEstimate`, None when it corrects none):
    ``column`` (the response to the yaw rate: x, y, z), ``sigma`` (None without frame pairs: a
    calibration given, not estimated), ``pairs``, and ``matrix``, ``matrix_sigma`` (the whole
    matrix by rows; None when only the yaw column is corrected)."""
    return None if estimate is None else estimate.as_dict()


def format_flight(summary: dict) -> str:
    """The application's own summary (real or simulated flight) as a few lines."""
    return "\n".join([*_flight_lines(summary), *_recording_lines(summary.get("recording"))])


def _recording_lines(recording: dict | None) -> list[str]:
    if recording is None:
        return []
    dropped = sum(sum(reasons.values()) for reasons in recording["dropped"].values())
    problem = f"; stopped: {recording['error']}" if recording["error"] else ""
    return [f"  recording         {recording['path']} ({recording['messages']} messages, "
            f"{recording['bytes'] / 1e6:.0f} MB, {dropped} dropped{problem})"]


def _flight_lines(summary: dict) -> list[str]:
    return [
        f"  final state       {summary['final_state']}",
        f"  failsafes         {', '.join(summary['failsafes']) or 'none'}",
        f"  flight time       {show(summary.get('flight_time_s'), '.1f', ' s')}",
        *_camera_lines(summary),
        f"  depth rate        {show(summary.get('depth_rate_hz'), '.1f', ' Hz')}",
        f"  loop lag p99      {show(summary.get('loop_lag_ms_p99'), '.1f', ' ms')}",
        f"  planning rounds   {summary['planning_rounds']} ({summary['stop_rounds']} stops, "
        f"{summary['backoffs']} backings-off)",
        f"  VINS resets       {summary['vins_resets']}{_still_keyframes(summary)}",
        *_barometer_lines(summary.get("vins_barometer")),
        *_time_offset_lines(summary.get("vins_time_offset")),
        *_gyro_alignment_lines(summary.get("vins_gyro_alignment")),
        *_rest_accel_scale_lines(summary.get("vins_rest_accel_scale_error")),
        *_signing_lines(summary.get("mavlink_signing")),
    ]


def _camera_lines(summary: dict) -> list[str]:
    """The frames taken, skipped and lost, and their age (absent from recordings made
    before they were counted)."""
    if "camera_frames_dropped" not in summary:
        return []
    age = summary["frame_age_ms"]
    return [f"  camera frames     {summary['frames']} taken, "
            f"{summary['camera_frames_dropped']} skipped while busy, "
            f"{summary['camera_frames_lost']} lost by the camera; "
            f"age {age['p50']:.0f} ms median, {age['p95']:.0f} ms p95"]


def _still_keyframes(summary: dict) -> str:
    """The keyframes given a zero-velocity prior (absent from recordings made before it)."""
    still = summary.get("vins_still_keyframes")
    return "" if still is None else f" ({still} keyframes standing still before the take-off)"


def _barometer_lines(barometer: dict | None) -> list[str]:
    if barometer is None:
        return []
    steps = barometer.get("steps")  # absent from recordings made before it was counted
    return [f"  VINS barometer    a height on {barometer['keyframes']} keyframes, "
            f"{barometer['refused']} pressures refused"
            + ("" if steps is None else f", {steps} steps of pressure taken out")]


def _signing_lines(signing: dict | None) -> list[str]:
    if signing is None:
        return []
    if not signing["on"]:
        return ["  MAVLink signing   off"]
    return [f"  MAVLink signing   on: {signing['unsigned']} unsigned and "
            f"{signing['bad_signature']} badly signed messages ignored"]


def _gyro_alignment_lines(alignment: dict | None) -> list[str]:
    """The gyro's misalignment the VINS estimated (its response to the yaw rate, or the whole
    matrix by rows), and how to start the next flight of this vehicle from it: the estimate
    learns it in flight, too late for the first corner (docs/vins.md, "The gyro's response to
    yaw")."""
    if alignment is None or not alignment["pairs"]:
        return []
    if alignment.get("matrix") is None:
        values, sigma, what = alignment["column"], max(alignment["sigma"]), "yaw response"
    else:
        values = [v for row in alignment["matrix"] for v in row]
        sigma = max(max(row) for row in alignment["matrix_sigma"])
        what = "misalignment (rows)"
    numbers = ", ".join(f"{c:.4f}" for c in values)
    return [f"  gyro {what} [{numbers}] (sigma at most {sigma:.4f}, "
            f"{alignment['pairs']} frame pairs); to start the next flight from it: "
            f"--set 'vins.gyro_alignment=[{numbers}]'"]


def _rest_accel_scale_lines(error: float | None) -> list[str]:
    return [] if error is None else [
        f"  accel z at rest   {error:+.3%} sensitivity error, divided out "
        "([vins] rest_accel_scale_share)"]


def _time_offset_lines(offset: dict | None) -> list[str]:
    """The offset the VINS estimated, and how to start the next flight from it: the
    estimate starts from ``[vins] time_offset_s`` and moves only with enough rotation, so a
    camera's offset is best learned once and then given (docs/vins.md, time offset)."""
    if offset is None or not offset["estimated"] or offset["sigma_s"] is None:
        return []
    return [f"  camera-IMU offset {1e3 * offset['seconds']:.1f} ms "
            f"(sigma {1e3 * offset['sigma_s']:.1f} ms); to start the next flight from it: "
            f"--set vins.time_offset_s={offset['seconds']:.4f}"]
