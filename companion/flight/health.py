"""Health: at ``monitor_rate_hz``, the event loop's lag and the failsafe checks
(:func:`autonomy.navigation.failsafes.failsafe_reason`), the companion's status in its
HEARTBEAT, and systemd's watchdog fed while the loop is alive."""

from __future__ import annotations

import logging

from autonomy.navigation.failsafes import (Vitals, age, failsafe_reason, vins_failed,
                                           vins_problem)
from autonomy.navigation.mission import (DISARMED_STATES, FAILSAFE_OFFBOARD_STATES,
                                         GUARDED_STATES, OFFBOARD_STATES,
                                         SITE_SEEKING_FAILSAFES, FlightState)
from companion.flight.context import FlightContext
from companion.flight.navigation import Navigation
from companion.flight.perception import Perception
from companion.flight.watchdog import SetpointWatchdog
from drivers.mavlink.autopilot import CompanionStatus

log = logging.getLogger(__name__)


def companion_status(state: FlightState, failsafes) -> CompanionStatus:
    """What the companion's HEARTBEAT tells PX4 and the ground station."""
    if failsafes and state != FlightState.LANDED:
        return CompanionStatus.CRITICAL
    if state == FlightState.ABORTED:
        return CompanionStatus.EMERGENCY
    if state in DISARMED_STATES:
        return CompanionStatus.STANDBY
    return CompanionStatus.ACTIVE


class Health:
    """The stage (module docstring). ``stop_reason`` is an operator's stop, set by
    :meth:`companion.flight.app.FlightApp.stop_requested`."""

    def __init__(self, context: FlightContext, perception: Perception,
                 navigation: Navigation, watchdog: SetpointWatchdog, notifier=None):
        self.context, self.perception, self.navigation = context, perception, navigation
        self.watchdog, self.notifier = watchdog, notifier
        self.stop_reason = ""

    async def run(self) -> None:
        c = self.context
        period = 1.0 / c.options.monitor_rate_hz
        while True:
            expected = c.clock.now() + period
            await c.clock.sleep(period)
            lag = max(0.0, c.clock.now() - expected)
            c.stats.loop_lag_s.append(lag)
            self.check(lag)
            c.autopilot.set_status(companion_status(c.state, c.mission.failsafes))
            if self.notifier is not None:  # the loop is alive: systemd's watchdog is fed
                self.notifier.watchdog()

    def check(self, lag: float) -> None:
        """One check: the link and the motors in the air, then the failsafe rules while
        guarded."""
        c = self.context
        now, state = c.clock.now(), c.state
        in_the_air = state in OFFBOARD_STATES | {FlightState.HOLDING}
        if in_the_air and not c.autopilot.connected:
            c.mission.failsafe(now, "MAVLink link lost")
            c.go(FlightState.LINK_LOST, "no heartbeat from the flight controller")
            return
        if in_the_air and not c.autopilot.armed:
            c.motors_stopped()
            return
        flown_on_vins = (state in GUARDED_STATES and state != FlightState.ALIGNING
                         or state == FlightState.TO_LANDING_SITE)
        c.blind.update(now, self.navigation.landmarks(), flown_on_vins, c.options)
        if state in FAILSAFE_OFFBOARD_STATES:
            self._check_after_failsafe(self.vitals(now, lag))
            return
        if state not in GUARDED_STATES:
            return
        vitals = self.vitals(now, lag)
        reason = failsafe_reason(vitals, c.options)
        if reason and c.mission.failsafe(now, reason):
            self.navigation.stop(reason, vins_failed(vitals))

    def _check_after_failsafe(self, vitals: Vitals) -> None:
        """During a failsafe's stop and the glide to a landing site after it. The glide is
        for a sound vehicle after a mission-level failsafe: any other failure since (an
        operator's stop, a silent sensor, a stalled loop) rules it out, or ends it at once in
        Hold. Both are tracked on the VINS: if the VINS fails under them, the rest is flown
        on PX4's estimate."""
        c, navigation = self.context, self.navigation
        if c.mission.stopped_by in SITE_SEEKING_FAILSAFES and not navigation.glide_cut:
            reason = failsafe_reason(vitals, c.options)
            if reason and reason not in SITE_SEEKING_FAILSAFES:
                navigation.glide_cut = reason
        if not navigation.stopping_on_px4 and vins_failed(vitals):
            navigation.stop_on_px4()

    def vitals(self, now: float, lag: float) -> Vitals:
        c, perception = self.context, self.perception
        return Vitals(
            stop_requested=self.stop_reason, loop_lag_s=lag,
            watchdog_in_charge=self.watchdog.in_charge,
            camera_age_s=age(perception.last_frame_t, now),
            imu_age_s=age(c.autopilot.last_imu_t, now),
            vins_problem=self._vins_problem(),
            depth_age_s=age(perception.last_depth_t, now),
            depth_reason=perception.last_depth_reason, blind_s=c.blind.blind_s,
            blind_expired=c.vins_blind,
            on_flown_ground=self.navigation.on_flown_ground(),
            no_path_expired=self.navigation.no_path.expired(now, c.options))

    def _vins_problem(self) -> str:
        c, vins = self.context, self.perception.vins
        update = c.channels.vins.value
        if update is None:
            return ""
        problem = vins_problem(update.health.state, update.health.reason,
                               vins.reinitialisations,
                               c.stats.vins_reinitialisations_at_takeoff)
        rebuilds = vins.backend.resets
        if not problem and rebuilds > c.stats.vins_rebuilds_seen:
            # the smoother refused an update and went on from its last good keyframe: the
            # estimate stays continuous (DEGRADED for a while), so the flight goes on
            c.stats.vins_rebuilds_seen = rebuilds
            log.warning("VINS smoother rebuilt (%s)", vins.backend.last_failure)
        return problem
