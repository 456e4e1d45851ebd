"""Navigation: every ``[planner] period_s`` (a fixed rate: a round's compute comes out of the
period, not on top of it), the route's next waypoint, the behaviours at corners and dead ends
(:mod:`autonomy.navigation.behaviours`) and the planner's arcs, on the newest VINS state; the
plan goes out on the ``plan`` channel, the braking branch it checked on ``checked_stop`` (the
watchdog's fallback).

A round (docs/flight.md): record the trail; pass waypoints or reach the goal; then the first
behaviour that applies: backing off along the trail, turning at a corner, the parallax glide
after a turn, the approach glide to a stop waypoint, and else the planner's arcs. A round with
no safe arc starts the no-path clock, and at rest turns once toward the waypoint, then backs
off. Decisions are autonomy's; this stage runs them and the planner (on its worker).
"""

from __future__ import annotations

import logging
import math
from functools import partial

import numpy as np

from autonomy.messages import Odometry
from autonomy.navigation.behaviours import (BACKOFF_REASON, DEPTH_STOP_REASON,
                                            FLOWN_GROUND_REASONS, GOAL_STOP_REASON,
                                            PARALLAX_REASON, TURN_HOLD_REASON,
                                            TURN_STOP_REASON, Backoff, Blocked,
                                            NoPathClock, OffsetSwing, ParallaxGlide, Step,
                                            approach_targets, depth_lapsed, must_turn,
                                            on_glide, pause_turn, still_turning, view_starved)
from autonomy.navigation.failsafes import age
from autonomy.navigation.mission import (FAILSAFE_OFFBOARD_STATES, IN_PLACE_STATES,
                                        FlightState)
from autonomy.navigation.route import Route, heading_error
from autonomy.navigation.trail import Trail
from autonomy.planning.planner import Plan, Planner
from companion.flight.context import FlightContext
from companion.flight.perception import Perception
from drivers.clock import Rate

log = logging.getLogger(__name__)

#: From the take-off until navigating: the vehicle climbs its take-off column and holds on
#: top (yawing there while the camera's time offset is learnt).
CLIMBING_STATES = frozenset({FlightState.TAKING_OFF, FlightState.ENTERING_OFFBOARD,
                             FlightState.CALIBRATING})


class Navigation:
    """The stage (module docstring)."""

    def __init__(self, context: FlightContext, perception: Perception, planner: Planner,
                 route: Route):
        self.context, self.perception, self.planner, self.route = (context, perception,
                                                                   planner, route)
        self.trail = Trail()
        self.corner_pending = False  # a stop waypoint was just passed: stop and turn
        self.parallax, self.backoff, self.no_path = ParallaxGlide(), Backoff(), NoPathClock()
        self._vins_failed = False  # the failsafe's stop is flown on PX4's estimate
        self.glide_cut = ""  # a failure after the failsafe that rules out or ends the glide
        self.turn_began: float | None = None  # |heading error| as a corner's turn began
        self.regained_after: float | None = None  # the fit that lapsed at the last regaining
        self.swing = OffsetSwing(context.options)  # before navigating, for the time offset

    # ------------------------------------------------------------------ for the other stages

    @property
    def plan(self) -> Plan | None:
        return self.context.channels.plan.value

    def heading_error(self) -> float:
        """Angle from the body's heading to the one aimed at, radians (0 without a state): the
        next waypoint's bearing, or while blocked looking aside, that turned by the look."""
        c = self.context
        odometry = c.channels.odometry.value
        if odometry is None or c.T_L_W is None:
            return 0.0
        return heading_error(odometry.T_W_B, self.route.next_W(c.T_L_W), self.no_path.aim)

    def landmarks(self) -> int | None:
        """The VINS's landmarks at its newest update (None before the first)."""
        update = self.context.channels.vins.value
        return None if update is None else update.health.landmarks

    def turn_paused(self, heading_error: float) -> bool:
        """Pause a corner's turn in place (its parallax glide armed) for the glide
        (:func:`~autonomy.navigation.behaviours.pause_turn`)."""
        if self.turn_began is None or not self.parallax.active:
            return False
        return pause_turn(self.turn_began - abs(heading_error), self.landmarks())

    @property
    def stopping_on_px4(self) -> bool:
        """A failsafe's stop, or the glide to a landing site after it, after the VINS failed:
        flown as zero velocity on PX4's own estimate, untracked (:meth:`stop`)."""
        return self._vins_failed and self.context.state in FAILSAFE_OFFBOARD_STATES

    async def to_landing_site(self) -> float | None:
        """At rest after a failsafe: fly the planner's glide to a landing site seen clear
        (:meth:`~autonomy.planning.planner.Planner.landing_glide`); its horizontal length,
        metres, or None when no site passes."""
        c = self.context
        odometry = c.channels.odometry.value
        if odometry is None or c.T_L_W is None:
            return None
        floor_z = c.channels.alignment.value.home_z - float(c.T_L_W[2, 3])  # the take-off's
        glide = await c.workers["planner"].run(self.planner.landing_glide, odometry.t,
                                               odometry.T_W_B, floor_z)
        if glide is None or c.state != FlightState.FAILSAFE_STOP or self.stopping_on_px4 \
                or self.glide_cut:
            return None  # none, or the link, the motors, the VINS or the vehicle failed meanwhile
        self._follow(glide)
        end = glide.setpoint(glide.end_time).position_W
        return float(np.hypot(*(end - odometry.T_W_B[:3, 3])[:2]))

    def at_landing_site(self) -> bool:
        """The landing site's glide is over and the vehicle at rest (or, the VINS having
        failed on the way, at rest on PX4's estimate), or a failure cut it short."""
        if self.glide_cut:
            return True
        plan = self.plan
        over = self.stopping_on_px4 or plan is None or self.context.clock.now() >= plan.end_time
        return over and self.stopped()

    def glide_left(self) -> float:
        """Seconds the landing site's glide has left, plus ``stop_timeout_s`` to come to rest."""
        plan, now = self.plan, self.context.clock.now()
        left = 0.0 if plan is None else max(0.0, plan.end_time - now)
        return left + self.context.options.stop_timeout_s

    def stopped(self) -> bool:
        """At rest: slower than ``stopped_speed`` by the VINS, or by PX4's estimate while
        :attr:`stopping_on_px4`."""
        if self.stopping_on_px4:
            state = self.context.autopilot.state
            velocity = None if state is None else state.velocity_L
        else:
            odometry = self.context.channels.odometry.value
            velocity = None if odometry is None else odometry.velocity_W
        return velocity is not None and float(np.linalg.norm(velocity)) < \
            self.context.options.stopped_speed

    def on_flown_ground(self) -> bool:
        """Braking to a corner's turn on the stop checked before it, turning in place there
        (or swinging for the camera's time offset on top of the take-off column), gliding for
        parallax after it, backing off along the trail, or braking at the goal: the vehicle
        stays on ground it has flown or checked, so depth may lapse (new depth is what the
        turn and the glides are for; at the goal none is needed)."""
        now, plan = self.context.clock.now(), self.plan
        return self.context.state in IN_PLACE_STATES or self.parallax.active \
            or self.backoff.active \
            or any(on_glide(plan, reason, now) for reason in FLOWN_GROUND_REASONS)

    def stop_plan(self, reason: str) -> Plan | None:
        """The stop checked at the last planning round, or the newer glide to rest a
        behaviour holds on ``checked_stop``, while it lasts (braking from the newest state's
        velocity after it, or when there was neither)."""
        c = self.context
        odometry = c.channels.odometry.value
        if odometry is None:
            return self.plan
        return self.planner.stop_plan(odometry.t, odometry.T_W_B, odometry.velocity_W, reason,
                                      c.channels.checked_stop.value)

    def stop(self, reason: str, vins_failed: bool = False) -> None:
        """Fly :meth:`stop_plan` from now on. With the VINS failed (lost, reset, or blind:
        :func:`~autonomy.navigation.failsafes.vins_failed`) its position and velocity are no
        longer the vehicle's, and a stop tracked on them follows their drift: the stop is
        then zero velocity, untracked, braked by PX4 on its own estimate (the plan is still
        published, for the record of what the VINS believed)."""
        self._vins_failed = False
        if vins_failed:
            self.stop_on_px4()
        self.context.channels.plan.publish(self.stop_plan(reason))

    def stop_on_px4(self) -> None:
        """Fly the failsafe's stop, from now on, as zero velocity on PX4's estimate: the VINS
        failed at the failsafe or during its stop (:meth:`stop`)."""
        self._vins_failed = True
        log.warning("the VINS has failed: stopping on PX4's estimate (zero velocity, "
                    "untracked)")

    # ------------------------------------------------------------------ the loop

    async def run(self) -> None:
        c = self.context
        rate = Rate(c.clock, self.planner.options.period_s)
        while True:
            if c.state == FlightState.NAVIGATING:
                await self._round()
            elif c.state in CLIMBING_STATES:
                await self._record_climb()
            await rate.sleep()

    async def _record_climb(self) -> None:
        """Keep the take-off column in the trail: the first turn, toward the first waypoint,
        has no flown leg behind it, and gliding down the column is the parallax move then."""
        odometry = await self.perception.odometry()
        if odometry is not None:
            self.trail.record(odometry.T_W_B[:3, 3], climbing=True)

    async def _round(self) -> None:
        c = self.context
        odometry = await self.perception.odometry()
        if odometry is None or c.T_L_W is None:
            return
        now, position = c.clock.now(), odometry.T_W_B[:3, 3]
        self.trail.record(position)
        if c.state != FlightState.NAVIGATING:
            return  # a failsafe took over while the odometry was read: its stop is in charge
        self._advance(position)
        if c.state != FlightState.NAVIGATING:
            return
        if self._back_off_step(odometry, now):
            return
        # the glide first: a corner's turn paused for it turns on after it, when still due
        if self._parallax_step(odometry, now):
            return
        if must_turn(self.corner_pending, self.heading_error(), self.plan, c.options):
            await self._turn_at_corner()
            return
        if await self._regain_depth(odometry, now):
            return
        if await self._approach(odometry):
            return
        await self._plan_arcs(odometry, now)

    def _advance(self, position_W: np.ndarray) -> None:
        c, route = self.context, self.route
        progress = route.advance(position_W, c.T_L_W, c.options)
        if progress.passed:
            self.corner_pending = progress.corner
            self.backoff.count = 0
            log.info("waypoint %d of %d", route.index + 1, len(route.waypoints_L))
        if progress.goal_reached:
            self.stop(GOAL_STOP_REASON)
            c.go(FlightState.STOPPING, GOAL_STOP_REASON)

    def _follow(self, glide: Plan | None) -> None:
        """Fly ``glide`` (none: nothing changes); a glide ends at rest, so it is also the
        watchdog's fallback."""
        if glide is None:
            return
        self.context.channels.plan.publish(glide)
        self.context.channels.checked_stop.publish(glide)

    def _back_off_step(self, odometry: Odometry, now: float) -> bool:
        """Fly this round's glide of a backing-off (:class:`Backoff`). True while doing so.
        A glide through its point carries, as the watchdog's stop, the glide that comes to
        rest on the point."""
        slowest = self.planner.tiers[-1].speed
        step = self.backoff.step(self.plan, now, odometry.T_W_B[:3, 3], slowest,
                                 slowest * self.planner.options.stop_duration_s / 2.0)
        if isinstance(step, Step):
            return step == Step.KEEP
        glide = partial(self.planner.glide, odometry.t, odometry.T_W_B, step.target,
                        BACKOFF_REASON)
        to_rest = glide() or self.stop_plan(BACKOFF_REASON)  # None: at the way's end already
        self.context.channels.plan.publish(to_rest if step.stop else glide(stop_at_goal=False))
        self.context.channels.checked_stop.publish(to_rest)
        return True

    def _parallax_step(self, odometry: Odometry, now: float) -> bool:
        """Glide back along the trail after a turn and return to the turning point, unless a
        fresh fit and the VINS's landmarks came back first. True while doing so."""
        starved = view_starved(age(self.perception.last_fit_t, now), self.landmarks())
        step = self.parallax.step(self.plan, now, starved)
        if isinstance(step, Step):
            return step == Step.KEEP
        self.no_path.restart()
        self._follow(self.planner.glide(odometry.t, odometry.T_W_B, step, PARALLAX_REASON))
        log.info("no depth or few landmarks after turning; gliding %s along the flown trail",
                 "back" if self.parallax.active else "to the turning point")
        return True

    async def _turn_at_corner(self) -> None:
        """Come to rest on the stop checked at the last round, then turn in place to face the
        next waypoint. A stop by choice: the no-path clock does not run."""
        c = self.context
        self.no_path.restart()
        if not self.stopped():
            await self._brake(TURN_STOP_REASON)
            return
        self.corner_pending = False
        self.parallax.start(self.trail, c.channels.odometry.value.T_W_B[:3, 3])
        error = self.heading_error()
        if still_turning(error, c.options):
            self.turn_began = abs(error)
            self._turn_in_place("at a corner; turning to face the next waypoint")

    def _turn_in_place(self, reason: str) -> None:
        """Turn in place (ALIGNING) for ``reason``, holding where the turn begins: the stop in
        force through the turn, after it until the next plan, and for a failsafe during it
        brakes afresh from the present velocity (:meth:`Planner.stop_afresh`), not on the stop
        checked before, whose path runs on ahead of where the vehicle came to rest."""
        c = self.context
        odometry = c.channels.odometry.value
        if odometry is not None:
            hold = self.planner.stop_afresh(odometry.t, odometry.T_W_B, odometry.velocity_W,
                                            TURN_HOLD_REASON)
            c.channels.plan.publish(hold)
            c.channels.checked_stop.publish(hold)
        c.go(FlightState.ALIGNING, reason)

    async def _brake(self, reason: str) -> None:
        """Fly :meth:`stop_plan` for ``reason``, a stop by choice, unless a failsafe's stop
        took over while it was computed."""
        c = self.context
        stop = await c.workers["planner"].run(self.stop_plan, reason)
        if c.state == FlightState.NAVIGATING:
            c.channels.plan.publish(stop)

    async def _regain_depth(self, odometry: Odometry, now: float) -> bool:
        """The fit lapsed on the arcs (:func:`~autonomy.navigation.behaviours.depth_lapsed`):
        come to rest on the stop checked at the last round, then glide for parallax; once per
        lapse (a fit that came and lapsed again gets another). True while braking, and when
        the glide is armed."""
        c, fit_t = self.context, self.perception.last_fit_t
        if fit_t is None or fit_t == self.regained_after \
                or not depth_lapsed(age(fit_t, now), c.options):
            return False
        if not self.stopped():
            await self._brake(DEPTH_STOP_REASON)
            return True
        self.regained_after = fit_t
        self.parallax.start(self.trail, odometry.T_W_B[:3, 3])
        log.warning("no metric depth for %.1f s on the arcs; at rest, gliding for parallax",
                    age(fit_t, now))
        return self.parallax.active

    async def _approach(self, odometry: Odometry) -> bool:
        """Glide straight to a near stop waypoint when the planner finds that safe (True)."""
        c, route = self.context, self.route
        targets = approach_targets(
            route.next_W(c.T_L_W), odometry.T_W_B[:3, 3],
            float(np.linalg.norm(odometry.velocity_W)), stop_here=route.stops_next,
            is_goal=route.at_last, slowest_speed=self.planner.tiers[-1].speed,
            options=c.options)
        for target in targets:
            plan = await c.workers["planner"].run(self.planner.approach, odometry.t,
                                                  odometry.T_W_B, target)
            if c.state != FlightState.NAVIGATING:
                return True  # a failsafe took over while planning: its stop is in charge
            if plan is not None:
                self._follow(plan)
                c.stats.planning_rounds += 1
                self.no_path.reset()
                return True
        return False

    async def _plan_arcs(self, odometry: Odometry, now: float) -> None:
        c = self.context
        plan, checked_stop = await c.workers["planner"].compute(
            self._plan_with_stop, odometry, self.route.next_W(c.T_L_W))
        if c.state != FlightState.NAVIGATING:
            return  # a failsafe took over while planning
        c.channels.plan.publish(plan)
        c.channels.checked_stop.publish(checked_stop)
        c.stats.planning_rounds += 1
        if plan.kind != "stop":
            self.no_path.reset()
            return
        c.stats.stop_rounds += 1
        blocked = self.no_path.blocked(now, self.stopped(), self.heading_error(), c.options)
        if blocked == Blocked.TURN:
            # at rest and not facing the waypoint: one turn in place for a new view (the arcs
            # only turn while moving on), then the no-path clock starts again
            self._turn_in_place("no safe primitive; turning to face the waypoint")
        elif blocked == Blocked.BACK_OFF:
            self._back_off(odometry)

    def _back_off(self, odometry: Odometry) -> None:
        """Blocked at rest and facing the waypoint: a dead end for forward arcs, such as a wall
        beside a door the arcs drifted past. Glide back ``backoff_distance`` along the flown
        trail, heading held, and plan again from there, where the arcs have room to line up
        with the opening. With no way back left, look aside instead."""
        o = self.context.options
        if not self.backoff.start(self.trail, odometry.T_W_B[:3, 3], o):
            self._look_aside()
            return
        self.context.stats.backoffs += 1
        self.no_path.reset()
        log.warning("no safe primitive; backing off %.1f m along the flown trail (%d of %d)",
                    o.backoff_distance, self.backoff.count, o.max_backoffs)

    def _look_aside(self) -> None:
        """Blocked at rest, facing the waypoint, with no way back: turn in place to look to one
        side of it, then the other (:class:`NoPathClock`); after both, the no-path failsafe
        comes."""
        plan = self.plan
        aim = self.no_path.look_aside(None if plan is None else plan.candidates)
        if aim is None:
            return
        side = "left" if aim > 0.0 else "right"
        self._turn_in_place(f"no safe primitive and no way back; looking "
                            f"{math.degrees(abs(aim)):.0f} deg {side} of the waypoint")

    def _plan_with_stop(self, odometry: Odometry, goal_W: np.ndarray) -> tuple[Plan, Plan]:
        """This round's plan, and the braking branch it checked; on the planner's worker."""
        args = (odometry.t, odometry.T_W_B, odometry.velocity_W)
        return (self.planner.plan(*args, goal_W, stop_at_goal=self.route.stops_next),
                self.planner.stop_plan(*args, "setpoint deadline"))

    def position_L(self) -> list[float] | None:
        """The VINS estimate of the vehicle's position in PX4's local frame, metres (None
        before the frames are tied)."""
        c = self.context
        odometry = c.channels.odometry.value
        if odometry is None or c.T_L_W is None:
            return None
        return [round(float(v), 3) for v in (c.T_L_W @ odometry.T_W_B)[:3, 3]]

