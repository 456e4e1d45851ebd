"""The mission's steps, in order (DESIGN.md, "Flight behaviour"): preflight, the VINS's static
initialisation, the operator's go (:mod:`companion.flight.go`), arming and take-off, entering
Offboard (then the offset swing while the camera's time offset is unknown:
:class:`~autonomy.navigation.behaviours.OffsetSwing`), navigating until the goal is reached
or a failsafe stops the vehicle, and coming down. Each step waits on the other stages'
channels and moves the mission's state machine (:class:`autonomy.navigation.mission.Mission`);
a step that fails on the ground aborts, one that fails in the air lands."""

from __future__ import annotations

import logging

from autonomy.navigation.behaviours import facing, offset_unknown
from autonomy.navigation.mission import MISSION_TIMEOUT, SITE_SEEKING_FAILSAFES, FlightState
from companion.flight.context import FlightContext
from companion.flight.go import OperatorGate
from companion.flight.navigation import Navigation
from companion.flight.perception import Perception
from drivers.mavlink import px4_protocol

log = logging.getLogger(__name__)

#: How often a waiting step polls, seconds.
POLL_S = 0.01
#: PX4 takes Offboard only after a second of setpoints (> 2 Hz); wait a little longer.
OFFBOARD_STREAM_S = 1.2
#: How far under the take-off height counts as there, metres.
TAKEOFF_HEIGHT_MARGIN = 0.25
#: The navigation phase: from Offboard until the vehicle is at rest, landing at the goal, or
#: after a failsafe, holding or gliding to a landing site (not counted as navigation).
NAVIGATION_PHASE = frozenset({FlightState.NAVIGATING, FlightState.ALIGNING,
                              FlightState.STOPPING, FlightState.FAILSAFE_STOP})


class ClimbWatch:
    """PX4's take-off to ``target_z`` (local frame, metres) as its messages report it."""

    def __init__(self, target_z: float):
        self.target_z = target_z
        self.seen_armed = False

    def over(self, autopilot) -> bool:
        """The climb is over: PX4 stopped the motors during it, or it is in the air, holding
        (AUTO_LOITER, where its take-off ends) within ``TAKEOFF_HEIGHT_MARGIN`` of the
        target. Either only once a HEARTBEAT has said armed: until then (they come at 1 Hz)
        the mode and landed state read are those from before the arm, Hold, and a local
        position that drifted up on the ground read as a finished climb. A take-off 15 s
        after the VINS initialised then ended at once, as "disarmed in the air"."""
        self.seen_armed = self.seen_armed or autopilot.armed
        if not self.seen_armed:
            return False
        state = autopilot.state
        return not autopilot.armed or (
            state is not None and autopilot.in_air
            and autopilot.mode == px4_protocol.AUTO_LOITER
            and state.position_L[2] >= self.target_z - TAKEOFF_HEIGHT_MARGIN)


class MissionSteps:
    """The steps (module docstring); ``gate`` gives the operator's go; ``notifier`` is
    systemd's (READY=1 after preflight)."""

    def __init__(self, context: FlightContext, perception: Perception,
                 navigation: Navigation, gate: OperatorGate, notifier=None):
        self.context, self.perception, self.navigation = context, perception, navigation
        self.gate, self.notifier = gate, notifier

    async def fly(self) -> None:
        steps = (self._preflight, self._initialise, self._await_go, self._take_off,
                 self._enter_offboard, self._swing, self._navigate, self._come_down)
        for step in steps:
            if self.context.mission.done:
                return
            await step()

    async def _wait(self, condition, timeout_s: float) -> bool:
        return await self.context.wait(condition, timeout_s, POLL_S)

    async def _preflight(self) -> None:
        c = self.context
        if not await self._wait(lambda: self.preflight_problem() == "",
                                c.options.preflight_timeout_s):
            c.abort(f"preflight: {self.preflight_problem()}")
            return
        c.go(FlightState.INITIALISING, "link, IMU and camera up")
        if self.notifier is not None:
            self.notifier.ready("preflight passed")

    def preflight_problem(self) -> str:
        autopilot = self.context.autopilot
        if not autopilot.connected:
            return f"no heartbeat from the flight controller: {autopilot.link_problem}"
        if not autopilot.time_synced:
            return "no TIMESYNC answer from the flight controller"
        if autopilot.last_imu_t is None:
            return "no HIGHRES_IMU from the flight controller"
        if self.perception.last_frame_t is None:
            return "no camera frame"
        return ""

    async def _initialise(self) -> None:
        c = self.context
        if not await self._wait(lambda: c.T_L_W is not None, c.options.init_timeout_s):
            update = c.channels.vins.value
            c.abort(f"VINS did not initialise: {update.health.reason if update else 'no frames'}")
            return

    async def _await_go(self) -> None:
        """Wait, disarmed, for the operator's go (no time limit: a vehicle on the ground may
        wait); a preflight problem that arises meanwhile aborts."""
        c, gate = self.context, self.gate
        if not gate.options.required or gate.given_by:
            given = f"; go from {gate.given_by}" if gate.given_by else ""
            c.go(FlightState.TAKING_OFF, f"VINS initialised; frames aligned{given}")
            return
        gate.start_waiting()
        c.go(FlightState.AWAITING_GO, "VINS initialised; frames aligned; waiting for the "
                                      f"{gate.describe()}")
        if self.notifier is not None:
            self.notifier.status(f"disarmed, waiting for the {gate.describe()}")
        await self._wait(lambda: gate.poll() or self.preflight_problem(), float("inf"))
        if c.mission.done:  # an operator's stop while waiting
            return
        if self.preflight_problem():
            c.abort(f"while waiting for the go: {self.preflight_problem()}")
            return
        if self.notifier is not None:
            self.notifier.status(f"go from {gate.given_by}; flying")
        c.go(FlightState.TAKING_OFF, f"go from {gate.given_by}")

    async def _take_off(self) -> None:
        c = self.context
        o, autopilot = c.options, c.autopilot
        if not await autopilot.arm():
            c.abort("arming denied")
            return
        c.stats.takeoff_t = c.clock.now()
        c.stats.vins_reinitialisations_at_takeoff = self.perception.vins.reinitialisations
        c.stats.vins_still_keyframes_at_takeoff = self.perception.vins.zero_velocity_keyframes
        if not await autopilot.takeoff(o.takeoff_altitude):
            c.go(FlightState.LANDING, "take-off denied")
            return
        watch = ClimbWatch(c.channels.alignment.value.home_z + o.takeoff_altitude)
        if not await self._wait(lambda: watch.over(autopilot), o.takeoff_timeout_s):
            c.go(FlightState.LANDING, "take-off did not reach its height")
            return
        if not autopilot.armed:
            c.motors_stopped()
            return
        c.go(FlightState.ENTERING_OFFBOARD, "at take-off height")

    async def _enter_offboard(self) -> None:
        c = self.context
        # the setpoint task streams zero velocity in this state
        await c.clock.sleep(OFFBOARD_STREAM_S)
        if not await c.autopilot.set_mode(px4_protocol.OFFBOARD):
            c.go(FlightState.LANDING, "PX4 refused Offboard")
            return
        c.stats.navigation_start = c.clock.now()
        if self._offset_unknown() and c.options.offset_swing_deg > 0.0:
            c.go(FlightState.CALIBRATING, "Offboard; swinging in place until the camera's time "
                                          "offset is known")
        else:
            c.go(FlightState.NAVIGATING, "Offboard")

    def _offset_unknown(self) -> bool:
        """Is the camera's time offset still to be shown (:func:`offset_unknown`), by the
        newest VINS update (none yet: unknown)?"""
        update = self.context.channels.vins.value
        return update is None or offset_unknown(
            update.time_offset, self.perception.vins.options.time_offset_max_sigma_s)

    async def _swing(self) -> None:
        """The offset swing (CALIBRATING; the setpoints are the command stage's) until it is
        over (:class:`~autonomy.navigation.behaviours.OffsetSwing`), the offset known or not:
        navigation needs it no more than flights before the swing did. A failsafe meanwhile
        ends it, and its stop is :meth:`_navigate`'s. The mission timeout starts after it."""
        c = self.context
        while c.state == FlightState.CALIBRATING and not self._swing_over():
            await c.clock.sleep(POLL_S)

    def _swing_over(self) -> bool:
        """Is the swing over? Then on to navigating, saying whether the offset was shown."""
        c, swing = self.context, self.navigation.swing
        elapsed = c.mission.elapsed(c.clock.now())
        if not swing.over(elapsed, known=not self._offset_unknown()):
            return False
        if swing.end_s is not None:  # known once, if no longer quite (its sigma grows)
            offset = c.channels.vins.value.time_offset
            c.go(FlightState.NAVIGATING, f"the camera's time offset known: "
                                         f"{offset.seconds * 1e3:.1f} ms")
            return True
        log.warning("the camera's time offset still unknown after the swing's %.1f s", elapsed)
        c.go(FlightState.NAVIGATING, "the offset swing timed out, the camera's time offset "
                                     "unknown")
        return True

    async def _navigate(self) -> None:
        c = self.context
        deadline = c.clock.now() + c.options.mission_timeout_s
        while c.state in NAVIGATION_PHASE:
            if c.clock.now() > deadline and c.mission.failsafe(c.clock.now(), MISSION_TIMEOUT):
                self.navigation.stop(MISSION_TIMEOUT)
            await self._navigation_step()
            await c.clock.sleep(POLL_S)
        c.stats.navigation_end = c.clock.now()
        self._note_navigation_end()

    def _note_navigation_end(self) -> None:
        """Where the VINS put the vehicle when navigation ended or, when it was restarting
        then (a stop flown on PX4's estimate may end first), at its first position after,
        during the hold: the simulator scores the VINS's drift there."""
        c = self.context
        position = self.navigation.position_L()
        if c.stats.navigation_end_L is None and position is not None:
            c.stats.navigation_end_L = {"t": c.clock.now(), "position_L": position}

    def _holding(self) -> bool:
        """The hold's wait condition: never over early (PX4 disarming the vehicle ends it
        through the mission: Health); meanwhile :meth:`_note_navigation_end`."""
        self._note_navigation_end()
        return False

    async def _navigation_step(self) -> None:
        c = self.context
        state, now = c.state, c.clock.now()
        if state in (FlightState.STOPPING, FlightState.FAILSAFE_STOP):
            if self.navigation.stopped() or c.mission.elapsed(now) > c.options.stop_timeout_s:
                await self._after_stop(state)
        elif state == FlightState.ALIGNING:
            error = self.navigation.heading_error()
            if facing(error, c.options):
                looking = self.navigation.no_path.aim != 0.0
                c.go(FlightState.NAVIGATING,
                     "facing the look aside" if looking else "facing the next waypoint")
            elif self.navigation.turn_paused(error):
                c.go(FlightState.NAVIGATING, "few VINS landmarks; the turn paused for parallax")

    async def _after_stop(self, state: FlightState) -> None:
        c = self.context
        if state == FlightState.STOPPING:
            c.go(FlightState.LANDING, "stopped at the goal")
            return
        if await self._glide_to_landing_site() or c.state != FlightState.FAILSAFE_STOP:
            return  # gliding; or the link or the motors were lost meanwhile (Health)
        on_px4 = ", on PX4's estimate (the VINS failed)" if self.navigation.stopping_on_px4 else ""
        c.go(FlightState.HOLDING, f"stopped after a failsafe{on_px4}")
        await c.autopilot.hold()

    async def _glide_to_landing_site(self) -> bool:
        """After a failsafe that leaves the vehicle sound (``SITE_SEEKING_FAILSAFES``), at rest
        on the VINS: glide to a landing site seen clear (docs/flight.md, "Where it lands").
        False when it does not: it then lands where it is."""
        c, navigation = self.context, self.navigation
        if c.mission.stopped_by not in SITE_SEEKING_FAILSAFES \
                or c.mission.stopped_from == FlightState.STOPPING \
                or navigation.stopping_on_px4 or navigation.glide_cut or not navigation.stopped():
            return False  # (stopping at the goal: it lands there)
        distance = await navigation.to_landing_site()
        if distance is None:
            if c.state == FlightState.FAILSAFE_STOP and not navigation.glide_cut:
                log.warning("no landing site seen clear ahead: landing where the stop ended")
            return False
        c.go(FlightState.TO_LANDING_SITE,
             f"stopped after a failsafe; gliding {distance:.1f} m to a landing site seen clear")
        return True

    def _glide_end(self) -> str:
        """Why the glide to a landing site ended."""
        navigation = self.navigation
        if navigation.glide_cut:
            return f"{navigation.glide_cut}: the glide to the landing site cut short"
        if navigation.stopping_on_px4:
            return "the VINS failed: stopped short of the landing site, on PX4's estimate"
        if navigation.at_landing_site():
            return "at the landing site"
        return "the glide to the landing site ran out of time"

    async def _come_down(self) -> None:
        c = self.context
        o, autopilot = c.options, c.autopilot
        if c.state == FlightState.TO_LANDING_SITE:
            await self._wait(lambda: c.state != FlightState.TO_LANDING_SITE
                             or self.navigation.at_landing_site(), self.navigation.glide_left())
            if c.state == FlightState.TO_LANDING_SITE:
                c.go(FlightState.HOLDING, self._glide_end())
                await autopilot.hold()
        if c.state == FlightState.LINK_LOST:
            await self._wait(lambda: autopilot.connected, o.land_timeout_s)
            if not autopilot.connected:
                c.go(FlightState.ABORTED, "link never came back; PX4's failsafe flies")
                return
            c.go(FlightState.HOLDING, "link back")
            await autopilot.hold()
        if c.state == FlightState.HOLDING:
            await self._wait(self._holding, o.hold_before_land_s)
            if c.mission.done:
                return
            c.go(FlightState.LANDING, "hold time over")
        if c.mission.done:  # PX4 disarmed the vehicle during the hold command (Health)
            return
        if not await autopilot.land():
            log.warning("land command not acknowledged; waiting for PX4 anyway")
        if await self._wait(lambda: not autopilot.armed, o.land_timeout_s):
            c.stats.landed_t = c.clock.now()
            c.go(FlightState.LANDED, "disarmed on the ground")
        else:
            c.go(FlightState.ABORTED, "did not land in time")

