"""The flight application: one asyncio process from camera and IMU to PX4 setpoints.

DESIGN.md, "The process". Tasks on one event loop, each a short coroutine:

- the MAVLink driver (:class:`drivers.mavlink.autopilot.Autopilot`): heartbeats, TIMESYNC,
  HIGHRES_IMU, commands;
- perception, per camera frame: the VINS (front-end and back-end) and the depth network side by
  side on their own workers, then the metric depth stage, whose output goes into the planner's
  depth history;
- the planner every ``[planner] period_s`` on the newest VINS state;
- the setpoint sender at ``setpoint_rate_hz``: the plan sampled now (velocity corrected toward
  the plan's position, acceleration as feed-forward), turned into PX4's local frame; the
  :class:`~companion.watchdog.SetpointWatchdog` thread replaces it by the stop when it is late;
- ODOMETRY to PX4 at ``odometry_rate_hz``;
- the monitor at ``monitor_rate_hz``: event-loop lag and the failsafe checks;
- the mission (:mod:`companion.mission`): preflight, initialisation, take-off, offboard,
  navigation through the waypoints (stopping, gliding and turning at corners: docs/flight.md),
  landing.

Frames: the VINS world ``W`` is fixed at its static initialisation; PX4's local frame ``L``
(ENU here, NED on the wire) is its own. They are tied once, on the ground, by the yaw and
position of the two estimates at the same instant
(:func:`autonomy.geometry.yaw_alignment`); goals are given in
``L``, planned in ``W``, and setpoints and odometry go back to ``L``.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from autonomy.depth.stage import MetricDepthStage
from autonomy.geometry import invert_pose, rot_to_quat, yaw_alignment, yaw_of
from autonomy.messages import Frame, MetricDepth, Odometry, RelativeDepth
from autonomy.planning.planner import Plan, Planner, Setpoint
from autonomy.vins.estimator import FrameUpdate, Vins
from autonomy.vins.health import HealthState
from autonomy.vins.preintegration import ImuNoise
from companion.eval.numbers import show
from companion.mission import (GUARDED_STATES, OFFBOARD_STATES, FlightOptions, FlightState,
                               Mission, stop_waypoints)
from companion.watchdog import SetpointWatchdog
from companion.workers import make_workers
from drivers.mavlink import px4
from drivers.mavlink.autopilot import CompanionStatus

log = logging.getLogger(__name__)

#: Longest wait for the IMU to reach a frame's time before the frame is processed anyway, s.
IMU_WAIT_S = 0.05
#: How often a waiting step polls, seconds.
POLL_S = 0.01
#: Oldest VINS state the setpoints' tracking correction uses, seconds.
TRACKING_MAX_AGE_S = 0.2
#: After a turn at a corner: how long without metric depth before gliding for parallax (s),
#: how far back along the approach (m), and the reason its plans carry.
PARALLAX_WAIT_S = 0.3
PARALLAX_GLIDE_M = 0.5
#: The flown trail, the take-off climb included: a position every TRAIL_SPACING_M of flight,
#: TRAIL_LENGTH of them (6 m, more than [flight] backoff_distance may be); a glide back to one
#: of them goes over ground just flown.
TRAIL_SPACING_M = 0.1
TRAIL_LENGTH = 60
PARALLAX_REASON = "gliding for parallax"
BACKOFF_REASON = "backing off along the trail"
#: From the take-off to Offboard: the vehicle climbs its take-off column and holds on top.
CLIMBING_STATES = frozenset({FlightState.TAKING_OFF, FlightState.ENTERING_OFFBOARD})


@dataclass
class CornerState:
    """What the application keeps about the route's stop waypoints (corners, the goal), and
    about the way back from a dead end."""

    pending: bool = False  # one was just passed: stop and turn before going on
    trail: deque = field(default_factory=lambda: deque(maxlen=TRAIL_LENGTH))  # flown, W
    climbing: deque = field(default_factory=lambda: deque(maxlen=TRAIL_LENGTH))  # take-off?
    parallax_moves: list = field(default_factory=list)  # glides back and forth, after turning
    backoff_moves: list = field(default_factory=list)  # glides back along the trail, blocked
    backoffs: int = 0  # backings-off toward the present waypoint

    def record(self, position_W: np.ndarray, climbing: bool = False) -> None:
        """Add a flown position to the trail (``climbing``: on the take-off climb), loops
        erased: a position back within TRAIL_SPACING_M of an older one (a glide back and
        forth) cuts the trail there, so the trail is the way back without detours."""
        trail = self.trail
        for k in range(len(trail) - 1, -1, -1):
            if np.linalg.norm(position_W - trail[k]) < TRAIL_SPACING_M:
                while len(trail) > k + 1:
                    trail.pop()
                    self.climbing.pop()
                return
        trail.append(position_W.copy())
        self.climbing.append(climbing)

    def way_back(self, position_W: np.ndarray, distance: float) -> list[np.ndarray]:
        """Points of the trail back from ``position_W`` about every PARALLAX_GLIDE_M of it,
        ending where it has run ``distance`` back, or at its oldest point above the take-off
        column (backing off never descends it): the straight glides between them stay within
        centimetres of the trail."""
        points, run, previous, since_point = [], 0.0, position_W, 0.0
        for point, climbing in zip(reversed(self.trail), reversed(self.climbing)):
            if climbing:
                break
            step = float(np.linalg.norm(point - previous))
            run, since_point, previous = run + step, since_point + step, point
            if since_point >= PARALLAX_GLIDE_M or run >= distance:
                points.append(point.copy())
                since_point = 0.0
            if run >= distance:
                break
        if points and run < distance and since_point > 0.0:
            points.append(previous.copy())  # the trail ran out: its oldest point
        return points


@dataclass
class FlightStats:
    """What the run measured, for the summary."""

    frames: int = 0
    depth_ok: int = 0
    depth_reasons: dict = field(default_factory=dict)
    network_errors: int = 0
    planning_rounds: int = 0
    stop_rounds: int = 0
    backoffs: int = 0
    loop_lag_s: list = field(default_factory=list)
    navigation_start: float | None = None
    navigation_end: float | None = None
    navigation_end_L: dict | None = None  # t and the VINS position in PX4's local frame then
    takeoff_t: float | None = None
    landed_t: float | None = None
    vins_reinitialisations_at_takeoff: int = 0
    vins_rebuilds_seen: int = 0


class FlightApp:
    """The whole stack against one autopilot, camera and depth network (module docstring).

    ``waypoints_L``: (N, 3) points in PX4's local frame (ENU), the last one the goal.
    ``depth_source(frame) -> relative disparity`` is the network (or the simulator's stand-in).
    ``metric_source(frame) -> MetricDepth``, when given, replaces the network and the rescaler
    (the simulator's true depth: the ground-truth-depth baseline of the evaluation).
    ``workers`` maps "vins", "network", "planner" to a worker (:mod:`companion.workers`).
    """

    @classmethod
    def from_config(cls, config, *, autopilot, camera, depth_source, T_B_C, waypoints_L, clock,
                    lockstep: bool, notifier=None, metric_source=None) -> "FlightApp":
        """The application with its VINS, planner and workers built from ``config``: an
        undistorted ``[camera]`` mounted at ``T_B_C``, the ``[imu]`` noise model; workers
        inline in lockstep, threads otherwise (closed when :meth:`run` ends)."""
        pinhole = config.camera.pinhole()
        imu = config.imu
        noise = ImuNoise(imu.gyro_noise_density, imu.accel_noise_density,
                         imu.gyro_bias_random_walk, imu.accel_bias_random_walk)
        vins = Vins(pinhole, (0.0,) * 4, T_B_C, noise, config.vins,
                    frontend=config.vins_frontend, static=config.vins_init)
        return cls(config, autopilot=autopilot, camera=camera, depth_source=depth_source,
                   vins=vins, T_B_C=T_B_C, planner=Planner(pinhole, config.planner),
                   waypoints_L=waypoints_L, clock=clock, notifier=notifier,
                   workers=make_workers(lockstep, ("vins", "network", "planner")),
                   metric_source=metric_source)

    def __init__(self, config, *, autopilot, camera, depth_source: Callable[[Frame], np.ndarray],
                 vins: Vins, T_B_C: np.ndarray, planner: Planner, waypoints_L, clock,
                 workers: dict, notifier=None,
                 metric_source: Callable[[Frame], MetricDepth] | None = None):
        self.options: FlightOptions = config.flight
        self._home_z = 0.0
        self.autopilot, self.camera, self.clock = autopilot, camera, clock
        self.depth_source, self.vins, self.planner = depth_source, vins, planner
        self.metric_source = metric_source
        self.T_B_C = np.asarray(T_B_C, dtype=float)
        self.stage = MetricDepthStage(config.rescale, config.depth)
        self.waypoints_L = _checked_waypoints(waypoints_L)
        #: Waypoints the vehicle stops at: the goal, and corners sharper than
        #: ``corner_turn_deg`` (approached slowly; at rest it faces the next leg).
        self.stop_at = stop_waypoints(self.waypoints_L, math.radians(
            self.options.corner_turn_deg))
        self.workers = workers
        self.notifier = notifier  # systemd (companion.service.SystemdNotifier) or None
        self.mission = Mission(clock.now())
        self.stats = FlightStats()
        self.T_L_W: np.ndarray | None = None
        self.waypoint = 0
        self.plan: Plan | None = None
        self.checked_stop: Plan | None = None
        self.last_frame_t: float | None = None
        self.last_depth_t: float | None = None
        self.last_fit_t: float | None = None  # newest depth rescaled by its own frame's fit
        self.last_depth_reason = ""
        self.last_update: FrameUpdate | None = None
        self.odometry: Odometry | None = None  # newest VINS state, see _refresh_odometry
        self.no_path_since: float | None = None
        self.stop_reason = ""
        self.turned_for_path = False
        self.corner = CornerState()
        self.watchdog = SetpointWatchdog(clock.now, self._watchdog_stop,
                                         self.options.setpoint_deadline_s,
                                         1.0 / self.options.setpoint_rate_hz)

    # ------------------------------------------------------------------ running

    async def run(self) -> dict:
        """Fly the mission to its end (landed or aborted) and return the summary."""
        self.watchdog.start()
        tasks = [asyncio.create_task(self._guard(name, coroutine), name=name)
                 for name, coroutine in (
                     ("autopilot", self.autopilot.run()), ("perception", self._perceive()),
                     ("planner", self._plan_loop()), ("setpoints", self._send_setpoints()),
                     ("odometry", self._send_odometry()), ("monitor", self._monitor()))]
        try:
            await self._fly()
        finally:
            self.watchdog.close()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for worker in self.workers.values():
                worker.close()
        return self.summary()

    async def _guard(self, name: str, coroutine) -> None:
        """Run one task; an error in it is a failsafe (logged with its traceback once), never
        an exception out of the application. The watchdog covers a dead setpoint task."""
        try:
            await coroutine
        except asyncio.CancelledError:
            raise
        except Exception as error:  # noqa: BLE001 - every failure must end in the safe state
            log.exception("%s task failed", name)
            self.mission.failsafe(self.clock.now(), f"{name} failed: {error}")
            if self.mission.state == FlightState.FAILSAFE_STOP:
                self.plan = self.checked_stop  # immutable: safe whatever failed
            elif not self.mission.done and self.mission.state in (
                    FlightState.PREFLIGHT, FlightState.INITIALISING):
                self._abort(f"{name} failed: {error}")

    def stop_requested(self, reason: str) -> None:
        """An operator's stop (SIGTERM from systemd): on the ground the mission ends; in the
        air it is a failsafe (stop, hold, land) at the next check."""
        self.stop_reason = reason
        if self.mission.state in (FlightState.PREFLIGHT, FlightState.INITIALISING):
            self._abort(reason)

    async def _fly(self) -> None:
        steps = (self._preflight, self._initialise, self._take_off, self._enter_offboard,
                 self._navigate, self._come_down)
        for step in steps:
            if self.mission.done:
                return
            await step()

    # ------------------------------------------------------------------ mission steps

    async def _preflight(self) -> None:
        o = self.options
        ready = await self._wait(lambda: self._preflight_problem() == "", o.preflight_timeout_s)
        if not ready:
            self._abort(f"preflight: {self._preflight_problem()}")
            return
        self._go(FlightState.INITIALISING, "link, IMU and camera up")
        if self.notifier is not None:
            self.notifier.ready("preflight passed")

    def _preflight_problem(self) -> str:
        autopilot = self.autopilot
        if not autopilot.connected:
            return "no heartbeat from the flight controller"
        if not autopilot.time_synced:
            return "no TIMESYNC answer from the flight controller"
        if autopilot.last_imu_t is None:
            return "no HIGHRES_IMU from the flight controller"
        if self.last_frame_t is None:
            return "no camera frame"
        return ""

    async def _initialise(self) -> None:
        ready = await self._wait(lambda: self.T_L_W is not None, self.options.init_timeout_s)
        if not ready:
            reason = self.last_update.health.reason if self.last_update else "no frames"
            self._abort(f"VINS did not initialise: {reason}")
            return
        self._go(FlightState.TAKING_OFF, "VINS initialised; frames aligned")

    async def _take_off(self) -> None:
        o, autopilot = self.options, self.autopilot
        if not await autopilot.arm():
            self._abort("arming denied")
            return
        self.stats.takeoff_t = self.clock.now()
        self.stats.vins_reinitialisations_at_takeoff = self.vins.reinitialisations
        if not await autopilot.takeoff(o.takeoff_altitude):
            self._go(FlightState.LANDING, "take-off denied")
            return

        def up() -> bool:
            state = autopilot.state
            return (state is not None and autopilot.in_air and autopilot.mode == px4.AUTO_LOITER
                    and state.position_L[2] >= self._home_z + o.takeoff_altitude - 0.25)
        if not await self._wait(up, o.takeoff_timeout_s):
            self._go(FlightState.LANDING, "take-off did not reach its height")
            return
        self._go(FlightState.ENTERING_OFFBOARD, "at take-off height")

    async def _enter_offboard(self) -> None:
        # PX4 takes Offboard only after a second of a setpoint stream (> 2 Hz); the setpoint
        # task streams zero velocity in this state.
        await self.clock.sleep(1.2)
        if not await self.autopilot.set_mode(px4.OFFBOARD):
            self._go(FlightState.LANDING, "PX4 refused Offboard")
            return
        self.stats.navigation_start = self.clock.now()
        self._go(FlightState.NAVIGATING, "Offboard")

    async def _navigate(self) -> None:
        o = self.options
        deadline = self.clock.now() + o.mission_timeout_s
        while self.mission.state in (FlightState.NAVIGATING, FlightState.ALIGNING,
                                     FlightState.STOPPING, FlightState.FAILSAFE_STOP):
            if self.clock.now() > deadline:
                self.mission.failsafe(self.clock.now(), "mission timeout")
            await self._navigation_step()
            await self.clock.sleep(POLL_S)
        self.stats.navigation_end = self.clock.now()
        position = self._position_L()
        if position is not None:
            self.stats.navigation_end_L = {"t": self.stats.navigation_end,
                                           "position_L": position}

    async def _navigation_step(self) -> None:
        state, now = self.mission.state, self.clock.now()
        if state in (FlightState.STOPPING, FlightState.FAILSAFE_STOP):
            if self._stopped() or self.mission.elapsed(now) > self.options.stop_timeout_s:
                await self._after_stop(state)
        elif state == FlightState.ALIGNING and abs(self._heading_error()) < math.radians(
                self.options.align_done_deg):
            self._go(FlightState.NAVIGATING, "facing the next waypoint")

    async def _after_stop(self, state: FlightState) -> None:
        if state == FlightState.STOPPING:
            self._go(FlightState.LANDING, "stopped at the goal")
            return
        self._go(FlightState.HOLDING, "stopped after a failsafe")
        await self.autopilot.hold()

    async def _come_down(self) -> None:
        o = self.options
        if self.mission.state == FlightState.LINK_LOST:
            await self._wait(lambda: self.autopilot.connected, o.land_timeout_s)
            if not self.autopilot.connected:
                self._go(FlightState.ABORTED, "link never came back; PX4's failsafe flies")
                return
            self._go(FlightState.HOLDING, "link back")
            await self.autopilot.hold()
        if self.mission.state == FlightState.HOLDING:
            await self.clock.sleep(o.hold_before_land_s)
            self._go(FlightState.LANDING, "hold time over")
        if not await self.autopilot.land():
            log.warning("land command not acknowledged; waiting for PX4 anyway")
        if await self._wait(lambda: not self.autopilot.armed, o.land_timeout_s):
            self.stats.landed_t = self.clock.now()
            self._go(FlightState.LANDED, "disarmed on the ground")
        else:
            self._go(FlightState.ABORTED, "did not land in time")

    # ------------------------------------------------------------------ perception

    async def _perceive(self) -> None:
        while True:
            frame = await self.camera.next_frame()
            self.last_frame_t = frame.t
            self.stats.frames += 1
            await self._wait_for_imu(frame.t)
            network = self.workers["network"]
            source = self.metric_source if self.metric_source is not None else self._infer
            update, depth = await asyncio.gather(self.workers["vins"].run(self._track, frame),
                                                 network.run(source, frame))
            self._after_vins(update)
            if self.metric_source is None:  # rescale with the sparse map of this very frame
                depth = await network.run(self._metric_depth, frame.t, depth, update)
            await self._after_depth(depth, update)

    async def _wait_for_imu(self, t: float) -> None:
        give_up = self.clock.now() + IMU_WAIT_S
        while (self.autopilot.last_imu_t is None or self.autopilot.last_imu_t < t) \
                and self.clock.now() < give_up:
            await self.clock.sleep(0.002)

    def _feed_imu(self) -> None:
        for sample in self.autopilot.take_imu():
            try:
                self.vins.add_imu(sample)
            except ValueError as error:
                log.debug("IMU sample refused: %s", error)

    def _track(self, frame: Frame) -> FrameUpdate:
        """The VINS on one frame, with the IMU up to it (on the VINS worker)."""
        self._feed_imu()
        return self.vins.add_frame(frame.t, self.vins.track(frame.image))

    def _infer(self, frame: Frame) -> np.ndarray | None:
        try:
            return self.depth_source(frame)
        except (ValueError, RuntimeError) as error:
            self.stats.network_errors += 1
            log.warning("depth network failed on frame t=%.3f: %s", frame.t, error)
            return None

    def _after_vins(self, update: FrameUpdate) -> None:
        self.last_update = update
        if update.sparse_map is not None:
            self.stage.add_sparse_map(update.sparse_map)
        if self.T_L_W is None and update.T_W_B is not None and self.autopilot.state is not None:
            self.T_L_W = yaw_alignment(self.autopilot.state.T_L_B, update.T_W_B)
            self._home_z = float(self.autopilot.state.position_L[2])

    def _metric_depth(self, t: float, disparity, update: FrameUpdate) -> MetricDepth | None:
        if disparity is None:
            return None
        return self.stage.process(RelativeDepth(t, disparity))

    async def _after_depth(self, metric: MetricDepth | None, update: FrameUpdate) -> None:
        if metric is None:
            self._depth_failed("depth network failed")
            return
        if not metric.ok or update.T_W_B is None:
            self._depth_failed(metric.diagnostics.reason or "no VINS pose for the frame")
            return
        # on the planner's worker: the history is only touched there, in order with planning
        await self.workers["planner"].run(self.planner.add_depth, metric,
                                          update.T_W_B @ self.T_B_C)
        self.last_depth_t = metric.t
        if not metric.held:
            self.last_fit_t = metric.t
        if self.stats.navigation_start is not None and self.stats.navigation_end is None:
            self.stats.depth_ok += 1

    def _depth_failed(self, reason: str) -> None:
        self.last_depth_reason = reason
        kind = reason.split(":")[0]  # counted by kind, without the frame's own numbers
        self.stats.depth_reasons[kind] = self.stats.depth_reasons.get(kind, 0) + 1

    # ------------------------------------------------------------------ planning

    async def _plan_loop(self) -> None:
        period = self.planner.options.period_s
        while True:
            if self.mission.state == FlightState.NAVIGATING:
                await self._plan_round()
            elif self.mission.state in CLIMBING_STATES:
                await self._record_climb()
            await self.clock.sleep(period)

    async def _record_climb(self) -> None:
        """Keep the take-off column in the trail: the first turn, toward the first waypoint,
        has no flown leg behind it, and gliding down the column is the parallax move then."""
        odometry = await self._refresh_odometry()
        if odometry is not None:
            self.corner.record(odometry.T_W_B[:3, 3], climbing=True)

    async def _plan_round(self) -> None:
        odometry = await self._refresh_odometry()
        if odometry is None or self.T_L_W is None:
            return
        now = self.clock.now()
        self.corner.record(odometry.T_W_B[:3, 3])
        self._advance_waypoints(odometry.T_W_B[:3, 3])
        if self.mission.state != FlightState.NAVIGATING:
            return
        goal_W = self._to_W(self.waypoints_L[self.waypoint])
        if self._backing_off(odometry, now):
            return
        if self.corner.pending or (abs(self._heading_error()) > math.radians(
                self.options.align_threshold_deg) and not self._gliding()):
            await self._turn_at_corner()
            return
        if self._move_for_parallax(odometry, now):
            return
        if await self._approach(odometry, goal_W):
            return
        plan, checked_stop = await self.workers["planner"].run(self._plan_with_stop, odometry,
                                                               goal_W)
        if self.mission.state != FlightState.NAVIGATING:
            return  # a failsafe took over while planning
        self.plan, self.checked_stop = plan, checked_stop
        self.stats.planning_rounds += 1
        if plan.kind != "stop":
            self.no_path_since, self.turned_for_path = None, False
            return
        self.stats.stop_rounds += 1
        self.no_path_since = self.no_path_since if self.no_path_since is not None else now
        if not self._stopped():
            return
        if not self.turned_for_path and abs(self._heading_error()) > math.radians(
                self.options.align_done_deg):
            # blocked, at rest and not facing the waypoint: one turn in place for a new view
            # (the arcs only turn while moving on), then the no-path clock starts again
            self.turned_for_path, self.no_path_since = True, None
            self._go(FlightState.ALIGNING, "no safe primitive; turning to face the waypoint")
        elif now - self.no_path_since >= self.options.no_path_timeout_s / 2.0:
            self._back_off()

    def _gliding(self) -> bool:
        """Is the vehicle on a checked glide to a stop waypoint? Its heading does not matter
        then (near the point, the bearing to it swings wildly)."""
        return self.plan is not None and self.plan.reason == "approach"

    def _on_glide(self, reason: str, now: float) -> bool:
        """Is the plan a glide for ``reason`` that has not ended yet?"""
        plan = self.plan
        return plan is not None and plan.reason == reason and now < plan.end_time

    def _back_off(self) -> None:
        """Blocked at rest and facing the waypoint (or turned toward it already): a dead end
        for forward arcs, such as a wall beside a door the arcs drifted past. Glide back
        ``backoff_distance`` along the flown trail, heading held, and plan again from there:
        the camera sees the place from farther back, where the arcs have room to line up
        with the opening. At most ``max_backoffs`` times a waypoint; then the no-path clock
        runs on to the failsafe."""
        o, corner = self.options, self.corner
        if corner.backoffs >= o.max_backoffs:
            return
        moves = corner.way_back(self.odometry.T_W_B[:3, 3], o.backoff_distance)
        if not moves:
            return
        corner.backoffs += 1
        self.stats.backoffs += 1
        corner.backoff_moves = moves
        self.no_path_since, self.turned_for_path = None, False
        log.warning("no safe primitive; backing off %.1f m along the flown trail (%d of %d)",
                    o.backoff_distance, corner.backoffs, o.max_backoffs)

    def _backing_off(self, odometry: Odometry, now: float) -> bool:
        """Fly the glides of :meth:`_back_off`, one trail point after the other: unchecked,
        as the ground is the vehicle's own trail (behind the camera, no frame sees it).
        True while doing so."""
        if self._on_glide(BACKOFF_REASON, now):
            return True
        moves = self.corner.backoff_moves
        if not moves:
            return False
        glide = self.planner.glide(odometry.t, odometry.T_W_B, moves.pop(0), BACKOFF_REASON)
        if glide is not None:
            self.plan = self.checked_stop = glide
        return True

    async def _approach(self, odometry: Odometry, goal_W: np.ndarray) -> bool:
        """Near a stop waypoint (a corner, the goal) and slow: glide straight to it when the
        planner finds that safe (True), else plan arcs as usual (False). A corner is glided to
        exactly; the goal only to half ``goal_tolerance`` short of it, or failing that 0.9 of
        it (horizontally, at its height), since a goal near a wall may leave no room for the
        sphere on the point."""
        o = self.options
        position = odometry.T_W_B[:3, 3]
        offset = goal_W - position
        distance = float(np.hypot(offset[0], offset[1]))
        if not self.stop_at[self.waypoint] or distance > o.approach_distance or float(
                np.linalg.norm(odometry.velocity_W)) > self.planner.tiers[-1].speed \
                + o.stopped_speed:
            return False
        plan = None
        for short in ((0.0,) if self.waypoint < len(self.waypoints_L) - 1 else (0.5, 0.9)):
            target = goal_W.copy()
            if short > 0.0 and distance > 0.0:
                target[:2] -= offset[:2] * (min(distance, short * o.goal_tolerance) / distance)
            plan = await self.workers["planner"].run(self.planner.approach, odometry.t,
                                                     odometry.T_W_B, target)
            if plan is not None:
                break
        if plan is None:
            return False
        self.plan = self.checked_stop = plan
        self.stats.planning_rounds += 1
        self.no_path_since, self.turned_for_path = None, False
        return True

    def _move_for_parallax(self, odometry: Odometry, now: float) -> bool:
        """After turning in place at a corner the view is new, and a monocular VINS has no
        landmarks in it until the camera moves sideways: no anchors, no metric depth, no arc
        checked. Then glide back to the newest point of the trail just flown half a metre off
        (the straight line to it stays within centimetres of ground the vehicle was on a
        moment ago) and return to the corner: the camera, facing the next leg, moves across
        its view. At the first turn, right after take-off, that point is down the take-off
        column, and the camera moves across its view vertically. True while doing so."""
        moves = self.corner.parallax_moves
        if not moves:
            return False
        started = len(moves) < 2
        if not started and self._age(self.last_fit_t, now) <= PARALLAX_WAIT_S:
            moves.clear()  # anchors came back by themselves (a held fit does not count)
            return False
        if started and self._on_glide(PARALLAX_REASON, now):
            return True
        target = moves.pop(0)
        glide = self.planner.glide(odometry.t, odometry.T_W_B, target, PARALLAX_REASON)
        if glide is not None:
            self.plan = self.checked_stop = glide
        log.info("no depth after turning; gliding %s along the flown trail",
                 "back" if moves else "to the turning point")
        return True

    async def _turn_at_corner(self) -> None:
        """At a corner (a stop waypoint just passed, or the next waypoint far off the
        heading): come to rest on the stop checked at the last round, then turn in place to
        face the next waypoint; the arcs would sweep wide. A stop by choice: the no-path clock
        does not run."""
        self.no_path_since = None
        if not self._stopped():
            self.plan = await self.workers["planner"].run(
                self._stop_plan, "stopping to turn to the next waypoint")
            return
        corner, position = self.corner, self.odometry.T_W_B[:3, 3]
        corner.pending = False
        back = next((p for p in reversed(corner.trail)
                     if np.linalg.norm(p - position) >= PARALLAX_GLIDE_M), None)
        if back is not None:
            corner.parallax_moves = [back.copy(), position.copy()]
        if abs(self._heading_error()) > math.radians(self.options.align_done_deg):
            self._go(FlightState.ALIGNING, "at a corner; turning to face the next waypoint")

    def _plan_with_stop(self, odometry: Odometry, goal_W: np.ndarray) -> tuple[Plan, Plan]:
        """This round's plan, and the braking branch it checked (for the watchdog thread to
        follow); on the planner's worker."""
        args = (odometry.t, odometry.T_W_B, odometry.velocity_W)
        return (self.planner.plan(*args, goal_W, stop_at_goal=self.stop_at[self.waypoint]),
                self.planner.stop_plan(*args, "setpoint deadline"))

    def _advance_waypoints(self, position_W: np.ndarray) -> None:
        """Pass every waypoint within ``waypoint_tolerance``, or stop at the goal within
        ``goal_tolerance`` and ``height_tolerance``: horizontal distances and, for the goal,
        the height (as PX4's acceptance radius and altitude acceptance). A waypoint guides
        the route; the planner may pass it higher, over what lies below."""
        o = self.options
        while True:
            offset = self._to_W(self.waypoints_L[self.waypoint]) - position_W
            distance = float(np.hypot(offset[0], offset[1]))
            last = self.waypoint == len(self.waypoints_L) - 1
            if last and distance <= o.goal_tolerance \
                    and abs(float(offset[2])) <= o.height_tolerance:
                self._stop_at_goal()
                return
            tolerance = o.corner_tolerance if self.stop_at[self.waypoint] else \
                o.waypoint_tolerance
            if last or distance > tolerance:
                return
            self.corner.pending = self.stop_at[self.waypoint]
            self.corner.backoffs = 0
            self.waypoint += 1
            log.info("waypoint %d of %d", self.waypoint + 1, len(self.waypoints_L))

    def _stop_at_goal(self) -> None:
        self.plan = self._stop_plan("goal reached")
        self._go(FlightState.STOPPING, "goal reached")

    def _stop_plan(self, reason: str) -> Plan | None:
        """The stop checked at the last planning round while it lasts (braking from the
        newest state's velocity after it, or when there was no round)."""
        odometry = self.odometry
        if odometry is None:
            return self.plan
        return self.planner.stop_plan(odometry.t, odometry.T_W_B, odometry.velocity_W, reason)

    async def _refresh_odometry(self) -> Odometry | None:
        """The VINS state at the newest IMU sample, kept in :attr:`odometry`. On the VINS
        worker: the estimator is touched by one thread only, in order with its frames."""
        self.odometry = await self.workers["vins"].run(self._estimate)
        return self.odometry

    def _estimate(self) -> Odometry | None:
        self._feed_imu()
        return self.vins.odometry()

    def _heading_error(self) -> float:
        """Angle from the body's heading to the next waypoint, radians in (-pi, pi]."""
        odometry = self.odometry
        if odometry is None or self.T_L_W is None:
            return 0.0
        to_goal = self._to_W(self.waypoints_L[self.waypoint]) - odometry.T_W_B[:3, 3]
        error = math.atan2(to_goal[1], to_goal[0]) - yaw_of(odometry.T_W_B[:3, :3])
        return math.atan2(math.sin(error), math.cos(error))

    def _stopped(self) -> bool:
        odometry = self.odometry
        return odometry is not None and float(np.linalg.norm(odometry.velocity_W)) < \
            self.options.stopped_speed

    def _to_W(self, point_L) -> np.ndarray:
        T_W_L = invert_pose(self.T_L_W)
        return T_W_L[:3, :3] @ np.asarray(point_L, dtype=float) + T_W_L[:3, 3]

    # ------------------------------------------------------------------ setpoints and odometry

    async def _send_setpoints(self) -> None:
        period = 1.0 / self.options.setpoint_rate_hz
        while True:
            commanding = self.mission.state in OFFBOARD_STATES and self.T_L_W is not None
            self.watchdog.arm(commanding)
            if commanding:
                now = self.clock.now()
                self._send(self._tracked(self._command(now), now))
                self.watchdog.fed(now)
            await self.clock.sleep(period)

    def _command(self, now: float) -> Setpoint:
        state = self.mission.state
        if state == FlightState.ALIGNING:
            rate = math.radians(self.options.align_yaw_rate_deg)
            return _still(math.copysign(rate, self._heading_error()))
        if state == FlightState.ENTERING_OFFBOARD or self.plan is None:
            return _still()
        return self.plan.setpoint(now)

    def _tracked(self, setpoint: Setpoint, now: float) -> Setpoint:
        """``setpoint`` with its velocity corrected toward the plan's position:
        ``v + k (p_plan - p)``, ``p`` the newest VINS position carried to ``now`` on its
        velocity, the correction at most ``max_tracking_speed``. Without it the autopilot's
        velocity loop lets the vehicle run on (in braking, its integrator keeps a creep for
        seconds) off the primitive the planner checked. Unchanged without a fresh VINS state
        or a plan position."""
        o, odometry = self.options, self.odometry
        if setpoint.position_W is None or odometry is None or o.tracking_gain == 0.0 \
                or not 0.0 <= now - odometry.t <= TRACKING_MAX_AGE_S:
            return setpoint
        position = odometry.T_W_B[:3, 3] + odometry.velocity_W * (now - odometry.t)
        correction = o.tracking_gain * (setpoint.position_W - position)
        size = float(np.linalg.norm(correction))
        if not math.isfinite(size):
            return setpoint
        if size > o.max_tracking_speed:
            correction *= o.max_tracking_speed / size
        return setpoint._replace(velocity_W=setpoint.velocity_W + correction)

    def _send(self, setpoint: Setpoint, T_L_W: np.ndarray | None = None) -> None:
        """``setpoint`` (frame W) to PX4 in frame L; zero velocity if it is not finite."""
        R_L_W = (self.T_L_W if T_L_W is None else T_L_W)[:3, :3]
        try:
            self.autopilot.send_velocity(R_L_W @ setpoint.velocity_W, setpoint.yaw_rate,
                                         R_L_W @ setpoint.acceleration_W)
        except ValueError as error:  # a non-finite command never leaves: send the stop
            log.error("setpoint refused (%s); sending zero velocity", error)
            self.autopilot.send_velocity(np.zeros(3), 0.0)

    def _watchdog_stop(self, now: float) -> None:
        """From the watchdog thread: the stop checked at the last planning round (or the
        present stop plan), zero velocity without one. Reads only immutable plans."""
        plan, T_L_W = self.plan, self.T_L_W
        if plan is not None and plan.kind != "stop":
            plan = self.checked_stop
        if plan is None or T_L_W is None:
            self.autopilot.send_velocity(np.zeros(3), 0.0)
            return
        self._send(plan.setpoint(now), T_L_W)

    async def _send_odometry(self) -> None:
        period = 1.0 / self.options.odometry_rate_hz
        while True:
            odometry = await self._refresh_odometry() if self.T_L_W is not None else None
            if odometry is not None and np.isfinite(odometry.T_W_B).all():
                health = self.last_update.health if self.last_update else None
                T_L_B = self.T_L_W @ odometry.T_W_B
                self.autopilot.send_odometry(
                    odometry.t, T_L_B[:3, 3], rot_to_quat(T_L_B[:3, :3]),
                    self.T_L_W[:3, :3] @ odometry.velocity_W, odometry.angular_velocity_B,
                    odometry.pose_covariance, reset_counter=self.vins.resets,
                    quality=_quality(health.state if health else HealthState.LOST))
            await self.clock.sleep(period)

    # ------------------------------------------------------------------ monitoring

    async def _monitor(self) -> None:
        period = 1.0 / self.options.monitor_rate_hz
        while True:
            expected = self.clock.now() + period
            await self.clock.sleep(period)
            lag = max(0.0, self.clock.now() - expected)
            self.stats.loop_lag_s.append(lag)
            self._check(lag)
            self.autopilot.set_status(self._mav_state())
            if self.notifier is not None:  # the loop is alive: systemd's watchdog is fed
                self.notifier.watchdog()

    def _check(self, lag: float) -> None:
        now, state = self.clock.now(), self.mission.state
        if state in OFFBOARD_STATES | {FlightState.HOLDING} and not self.autopilot.connected:
            self.mission.failsafe(now, "MAVLink link lost")
            self._go(FlightState.LINK_LOST, "no heartbeat from the flight controller")
            return
        if state not in GUARDED_STATES:
            return
        reason = self._failsafe_reason(now, lag)
        if reason and self.mission.failsafe(now, reason):
            self.plan = self._stop_plan(reason)

    def _failsafe_reason(self, now: float, lag: float) -> str:
        o = self.options
        checks = (
            (bool(self.stop_reason), self.stop_reason),
            (lag > o.max_loop_lag_s, f"event loop stalled ({1e3 * lag:.0f} ms late)"),
            (self.watchdog.in_charge, "setpoint deadline missed (watchdog sent the stop)"),
            (self._age(self.last_frame_t, now) > o.camera_timeout_s, "camera silent"),
            (self._age(self.autopilot.last_imu_t, now) > o.imu_timeout_s, "IMU silent"),
            (self._vins_problem() != "", self._vins_problem()),
            (self._age(self.last_depth_t, now) > o.depth_timeout_s
             and not self._on_flown_ground(),
             f"no metric depth ({self.last_depth_reason or 'none yet'})"),
            (self.no_path_since is not None and now - self.no_path_since > o.no_path_timeout_s,
             "no safe primitive"),
        )
        return next((reason for failed, reason in checks if failed), "")

    def _on_flown_ground(self) -> bool:
        """Turning in place at a corner, gliding for parallax after it, or backing off along
        the trail: the vehicle stays on ground it has flown, so depth may lapse (new depth is
        what the first two are for)."""
        now, corner = self.clock.now(), self.corner
        return self.mission.state == FlightState.ALIGNING or bool(
            corner.parallax_moves or corner.backoff_moves) or self._on_glide(
            PARALLAX_REASON, now) or self._on_glide(BACKOFF_REASON, now)

    def _vins_problem(self) -> str:
        update = self.last_update
        if update is None:
            return ""
        if update.health.state == HealthState.LOST:
            return f"VINS lost ({update.health.reason})"
        if self.vins.reinitialisations > self.stats.vins_reinitialisations_at_takeoff:
            return "VINS reset in flight"
        rebuilds = self.vins.backend.resets
        if rebuilds > self.stats.vins_rebuilds_seen:
            # the smoother refused an update and went on from its last good keyframe: the
            # estimate stays continuous (DEGRADED for a while), so the flight goes on
            self.stats.vins_rebuilds_seen = rebuilds
            log.warning("VINS smoother rebuilt (%s)", self.vins.backend.last_failure)
        return ""

    @staticmethod
    def _age(t: float | None, now: float) -> float:
        return math.inf if t is None else now - t

    def _mav_state(self) -> CompanionStatus:
        """What the companion's HEARTBEAT tells PX4 and the ground station."""
        state = self.mission.state
        if self.mission.failsafes and state != FlightState.LANDED:
            return CompanionStatus.CRITICAL
        if state == FlightState.ABORTED:
            return CompanionStatus.EMERGENCY
        if state in (FlightState.PREFLIGHT, FlightState.INITIALISING, FlightState.LANDED):
            return CompanionStatus.STANDBY
        return CompanionStatus.ACTIVE

    # ------------------------------------------------------------------ helpers

    async def _wait(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        deadline = self.clock.now() + timeout_s
        while not condition():
            if self.clock.now() >= deadline or self.mission.done:
                return False
            await self.clock.sleep(POLL_S)
        return True

    def _go(self, state: FlightState, reason: str) -> None:
        self.mission.go(self.clock.now(), state, reason)

    def _abort(self, reason: str) -> None:
        self._go(FlightState.ABORTED, reason)

    def summary(self) -> dict:
        """The run in plain numbers for JSON (the simulator adds the ground truth)."""
        s, mission = self.stats, self.mission
        navigation = ((s.navigation_end or self.clock.now()) - s.navigation_start
                      if s.navigation_start is not None else 0.0)
        lag = np.asarray(s.loop_lag_s) if s.loop_lag_s else np.zeros(1)
        return {
            "final_state": mission.state.value,
            "reached_goal": any(t.reason == "goal reached" for t in mission.transitions),
            "failsafes": list(mission.failsafes),
            "transitions": [{"t": round(t.t, 3), "from": t.source.value, "to": t.target.value,
                             "reason": t.reason} for t in mission.transitions],
            "flight_time_s": ((s.landed_t or self.clock.now()) - s.takeoff_t
                              if s.takeoff_t is not None else 0.0),
            "navigation_time_s": navigation,
            "frames": s.frames,
            # metric depth frames the planner got per second of navigation
            "depth_rate_hz": s.depth_ok / navigation if navigation > 0 else 0.0,
            "depth_failures": dict(s.depth_reasons),
            "planning_rounds": s.planning_rounds,
            "stop_rounds": s.stop_rounds,
            "backoffs": s.backoffs,
            "vins_resets": self.vins.resets,
            "watchdog_setpoints": self.watchdog.fired,
            "loop_lag_ms_p99": float(1e3 * np.percentile(lag, 99)),
            "waypoints_passed": self.waypoint,
            "navigation_end": s.navigation_end_L,
        }

    def _position_L(self) -> list[float] | None:
        """The VINS estimate of the vehicle's position in PX4's local frame, metres (None
        before the frames are tied)."""
        if self.odometry is None or self.T_L_W is None:
            return None
        return [round(float(v), 3) for v in (self.T_L_W @ self.odometry.T_W_B)[:3, 3]]


def format_flight(summary: dict) -> str:
    """The application's own summary (real or simulated flight) as a few lines."""
    return "\n".join([
        f"  final state       {summary['final_state']}",
        f"  failsafes         {', '.join(summary['failsafes']) or 'none'}",
        f"  flight time       {show(summary.get('flight_time_s'), '.1f', ' s')}",
        f"  depth rate        {show(summary.get('depth_rate_hz'), '.1f', ' Hz')}",
        f"  loop lag p99      {show(summary.get('loop_lag_ms_p99'), '.1f', ' ms')}",
        f"  planning rounds   {summary['planning_rounds']} ({summary['stop_rounds']} stops, "
        f"{summary['backoffs']} backings-off)",
        f"  VINS resets       {summary['vins_resets']}",
    ])


def _still(yaw_rate: float = 0.0) -> Setpoint:
    """Hold the position (zero velocity and acceleration), turning at ``yaw_rate``."""
    return Setpoint(np.zeros(3), yaw_rate, np.zeros(3))


def _quality(state: HealthState) -> int:
    """ODOMETRY.quality (0: invalid, 100: best) from the VINS health."""
    return {HealthState.OK: 100, HealthState.DEGRADED: 50}.get(state, 0)


def _checked_waypoints(waypoints) -> np.ndarray:
    points = np.asarray(waypoints, dtype=float)
    if points.ndim == 1:
        points = points.reshape(1, -1)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"waypoints must be (N, 3) points, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("waypoints must be finite numbers")
    return points
