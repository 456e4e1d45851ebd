"""Command: the offboard setpoints at ``setpoint_rate_hz`` and ODOMETRY at
``odometry_rate_hz`` to PX4, and the setpoint watchdog.

A setpoint is the ``plan`` channel's plan sampled now, its velocity corrected toward the plan's
position (:func:`tracked`), turned into PX4's local frame; zero velocity while entering
Offboard and in a failsafe's stop after the VINS failed; a turn in place while aligning, the
offset swing while calibrating. The :class:`~companion.flight.watchdog.
SetpointWatchdog` thread replaces a late setpoint by the ``checked_stop`` channel's plan, from
outside the event loop.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from autonomy.geometry import rot_to_quat
from autonomy.messages import Odometry
from autonomy.navigation.behaviours import turn_rate
from autonomy.navigation.mission import OFFBOARD_STATES, FlightState
from autonomy.planning.planner import Setpoint
from autonomy.vins.health import Health, HealthState
from companion.flight.context import FlightContext
from companion.flight.navigation import Navigation
from companion.flight.perception import Perception
from companion.flight.watchdog import SetpointWatchdog

log = logging.getLogger(__name__)

#: Oldest VINS state the setpoints' tracking correction uses, seconds.
TRACKING_MAX_AGE_S = 0.2


def still(yaw_rate: float = 0.0) -> Setpoint:
    """Hold the position (zero velocity and acceleration), turning at ``yaw_rate``."""
    return Setpoint(np.zeros(3), yaw_rate, np.zeros(3))


def tracked(setpoint: Setpoint, odometry: Odometry | None, now: float, options) -> Setpoint:
    """``setpoint`` with its velocity corrected toward the plan's position:
    ``v + k (p_plan - p)``, ``p`` the newest VINS position carried to ``now`` on its velocity,
    the correction at most ``max_tracking_speed``. Without it the autopilot's velocity loop
    lets the vehicle run on (in braking, its integrator keeps a creep for seconds) off the
    primitive the planner checked. Unchanged without a VINS state at most
    :data:`TRACKING_MAX_AGE_S` old or a plan position."""
    o = options
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


#: ODOMETRY.quality of odometry that has failed (MAVLink: -1 failed, 0 unknown, 1..100).
FAILED_QUALITY = -1


def odometry_quality(health: Health | None, blind: bool) -> int:
    """ODOMETRY.quality from the VINS health: 100 OK, 50 DEGRADED, 0 (unknown) while it
    initialises or settles after a reset, and -1 (failed) without a health, when LOST or
    once blind past ``blind_timeout_s``: its pose is then IMU propagation that drifts without
    bound, and PX4 (``EKF2_EV_QMIN`` >= 1) must not hold position on it after the failsafe
    (docs/operations.md). Settling: a smoother restarted in the air from the IMU's propagation
    across an IMU gap ran away, resetting again and again at tens of m/s while DEGRADED, and
    PX4 fusing it flew the vehicle 8 m past its goal (the fault matrix, docs/reliability.md)."""
    if blind or health is None or health.state == HealthState.LOST:
        return FAILED_QUALITY
    if health.settling:
        return 0
    return {HealthState.OK: 100, HealthState.DEGRADED: 50}.get(health.state, 0)


class Command:
    """The stage (module docstring)."""

    def __init__(self, context: FlightContext, perception: Perception,
                 navigation: Navigation):
        self.context, self.perception, self.navigation = context, perception, navigation
        o = context.options
        self.watchdog = SetpointWatchdog(context.clock.now, self._watchdog_stop,
                                         o.setpoint_deadline_s, 1.0 / o.setpoint_rate_hz)

    async def send_setpoints(self) -> None:
        c = self.context
        period = 1.0 / c.options.setpoint_rate_hz
        while True:
            commanding = c.state in OFFBOARD_STATES and c.T_L_W is not None
            self.watchdog.arm(commanding)
            if commanding:
                now = c.clock.now()
                setpoint = tracked(self._command(now), c.channels.odometry.value, now,
                                   c.options)
                self._send(setpoint)
                c.channels.setpoints.publish(setpoint)
                self.watchdog.fed(now)
            await c.clock.sleep(period)

    def _command(self, now: float) -> Setpoint:
        state, plan = self.context.state, self.context.channels.plan.value
        if state == FlightState.ALIGNING:
            return still(turn_rate(self.navigation.heading_error(), self.context.options))
        if state == FlightState.CALIBRATING:
            return still(self.navigation.swing.rate(self.context.mission.elapsed(now)))
        if state == FlightState.ENTERING_OFFBOARD or plan is None \
                or self.navigation.stopping_on_px4:
            return still()
        return plan.setpoint(now)

    def _send(self, setpoint: Setpoint, T_L_W: np.ndarray | None = None) -> None:
        """``setpoint`` (frame W) to PX4 in frame L; zero velocity if it is not finite."""
        autopilot = self.context.autopilot
        R_L_W = (self.context.T_L_W if T_L_W is None else T_L_W)[:3, :3]
        try:
            autopilot.send_velocity(R_L_W @ setpoint.velocity_W, setpoint.yaw_rate,
                                    R_L_W @ setpoint.acceleration_W)
        except ValueError as error:  # a non-finite command never leaves: send the stop
            log.error("setpoint refused (%s); sending zero velocity", error)
            autopilot.send_velocity(np.zeros(3), 0.0)

    def _watchdog_stop(self, now: float) -> None:
        """From the watchdog thread: the stop checked at the last planning round (or the
        present stop plan), zero velocity without one. Reads only immutable plans."""
        channels = self.context.channels
        plan, T_L_W = channels.plan.value, self.context.T_L_W
        if plan is not None and plan.kind != "stop":
            plan = channels.checked_stop.value
        if plan is None or T_L_W is None or self.navigation.stopping_on_px4:
            self.context.autopilot.send_velocity(np.zeros(3), 0.0)
            return
        self._send(plan.setpoint(now), T_L_W)

    async def send_odometry(self) -> None:
        c = self.context
        period = 1.0 / c.options.odometry_rate_hz
        while True:
            odometry = await self.perception.odometry() if c.T_L_W is not None else None
            if odometry is not None and np.isfinite(odometry.T_W_B).all():
                self._send_odometry(odometry)
            await c.clock.sleep(period)

    def _send_odometry(self, odometry: Odometry) -> None:
        c = self.context
        update = c.channels.vins.value
        T_L_W = c.T_L_W
        T_L_B = T_L_W @ odometry.T_W_B
        c.autopilot.send_odometry(
            odometry.t, T_L_B[:3, 3], rot_to_quat(T_L_B[:3, :3]),
            T_L_W[:3, :3] @ odometry.velocity_W, odometry.angular_velocity_B,
            odometry.pose_covariance, reset_counter=self.perception.vins.resets,
            quality=odometry_quality(update.health if update else None, c.vins_blind))
