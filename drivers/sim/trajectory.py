"""PX4's jerk-limited setpoint smoothing on one axis, for the mock's take-off.

PX4 does not climb to its take-off height on a velocity step: the take-off is an auto flight
task whose position target, the take-off waypoint, goes through ``PositionSmoothing``
(``src/modules/flight_mode_manager/tasks/Auto/FlightTaskAuto.cpp``, ``update`` and
``_updateTrajConstraints``). Every control step it asks for the fastest vertical speed from
which it can still stop at the target,

    v_sp = min(v_max, computeMaxSpeedFromDistance(j_max, a_max, |z_target - z|, 0)),

(``src/lib/motion_planning/PositionSmoothing.cpp``, ``_getMaxZSpeed``) and lets
``VelocitySmoothing`` reach it by a time-optimal S-curve that never exceeds the jerk ``j_max``
or the acceleration ``a_max`` (``src/lib/motion_planning/VelocitySmoothing.cpp``): jerk
``±j_max`` for ``T1``, none for ``T2``, ``∓j_max`` for ``T3``. Below ``MPC_LAND_ALT1`` the
take-off's limits are ``v_max = MPC_TKO_SPEED`` and ``a_max = min(MPC_ACC_UP_MAX,
MPC_TKO_SPEED / MPC_TKO_RAMP_T)``, the jerk ``MPC_JERK_AUTO``, and the trajectory's position is
held at the vehicle's own height every step, so the vehicle flies the smoothed velocity.

This module is that arithmetic, in float64 where PX4's is float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace


def max_speed_from_distance(jerk: float, accel: float, distance: float,
                            final_speed: float = 0.0) -> float:
    """The fastest speed from which a vehicle limited to ``jerk`` and ``accel`` still slows to
    ``final_speed`` within ``distance``: the positive root of
    ``v_f² = v² - 2 a (d - v 2 a / j)``, never below ``final_speed`` (PX4's
    ``math::trajectory::computeMaxSpeedFromDistance``, ``TrajMath.hpp``)."""
    b = 4.0 * accel * accel / jerk
    c = -2.0 * accel * abs(distance) - final_speed * final_speed  # PX4 passes fabs()
    return max(0.5 * (-b + math.sqrt(b * b - 4.0 * c)), final_speed)


@dataclass
class AxisState:
    """Jerk, acceleration, velocity and position on the axis."""

    j: float = 0.0
    a: float = 0.0
    v: float = 0.0
    x: float = 0.0


class VelocitySmoothing:
    """PX4's ``VelocitySmoothing`` on one axis: :meth:`update_durations` plans the S-curve from
    the present state to a new velocity setpoint, :meth:`update_traj` moves along it."""

    def __init__(self, max_jerk: float, max_accel: float, max_vel: float,
                 state: AxisState | None = None):
        for name, value in (("max_jerk", max_jerk), ("max_accel", max_accel),
                            ("max_vel", max_vel)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive, got {value!r}")
        self.max_jerk, self.max_accel, self.max_vel = max_jerk, max_accel, max_vel
        self.state = state or AxisState()
        self._start = replace(self.state)
        self._local_time = 0.0
        self._direction = 0
        self._durations = (0.0, 0.0, 0.0)

    def force_position(self, x: float) -> None:
        """Move the trajectory to ``x``, keeping its velocity and acceleration (PX4's
        ``VelocitySmoothing::setCurrentPosition``, which ``PositionSmoothing::forceSetPosition``
        calls per axis)."""
        self.state.x = x
        self._start.x = x

    def update_durations(self, velocity_setpoint: float) -> None:
        """Plan the time-optimal S-curve from the present state to ``velocity_setpoint``
        (clamped to ``±max_vel``)."""
        target = min(max(velocity_setpoint, -self.max_vel), self.max_vel)
        self._local_time = 0.0
        self._start = replace(self.state)
        self._direction = self._direction_to(target)
        if self._direction == 0:
            self._durations = (0.0, 0.0, 0.0)
            return
        jerk = self._direction * self.max_jerk
        a0, delta_v = self.state.a, target - self.state.v
        t1 = self._t1(a0, delta_v, jerk)
        t3 = max(a0 / jerk + t1, 0.0)
        self._durations = (t1, self._t2(t1, t3, a0, delta_v, jerk), t3)

    def update_traj(self, dt: float) -> AxisState:
        """Advance ``dt`` seconds along the planned S-curve; the new state."""
        self._local_time += dt
        remaining = self._local_time
        t1, t2, t3 = self._durations
        s = self._start
        state = _evaluate(self._direction * self.max_jerk, s.a, s.v, s.x, min(remaining, t1))
        remaining -= t1
        for jerk, span in ((0.0, t2), (-self._direction * self.max_jerk, t3)):
            if remaining > 0.0:
                state = _evaluate(jerk, state.a, state.v, state.x, min(remaining, span))
                remaining -= span
        if remaining > 0.0:
            state = _evaluate(0.0, 0.0, state.v, state.x, remaining)
        self.state = state
        return state

    def _direction_to(self, target: float) -> int:
        """The sign of the first jerk: toward ``target`` from the velocity the trajectory
        has once its acceleration is brought to zero."""
        a, v = self.state.a, self.state.v
        if abs(a) > 0.0:
            jerk = -math.copysign(self.max_jerk, a)
            t = -a / jerk
            v = v + a * t + 0.5 * jerk * t * t
        direction = _sign(target - v)
        return direction if direction != 0 else _sign(a)

    def _t1(self, a0: float, delta_v: float, jerk: float) -> float:
        """Time of increasing acceleration (``computeT1``), cut where ``max_accel`` is met."""
        delta = 2.0 * a0 * a0 + 4.0 * jerk * delta_v
        t1 = 0.0
        if delta >= 0.0:
            root = math.sqrt(delta)
            for candidate in ((-a0 + 0.5 * root) / jerk, (-a0 - 0.5 * root) / jerk):
                if candidate >= 0.0 and a0 / jerk + candidate >= 0.0:
                    t1 = candidate
                    break
        reached = a0 + jerk * t1
        if reached > self.max_accel:
            t1 = (self.max_accel - a0) / jerk
        elif reached < -self.max_accel:
            t1 = (-self.max_accel - a0) / jerk
        return max(t1, 0.0)

    @staticmethod
    def _t2(t1: float, t3: float, a0: float, delta_v: float, jerk: float) -> float:
        """Time at constant acceleration (``computeT2``)."""
        den = a0 + jerk * t1
        if abs(den) <= 1e-12:
            return 0.0
        t2 = (-0.5 * t1 * t1 * jerk - t1 * t3 * jerk - t1 * a0 + 0.5 * t3 * t3 * jerk
              - t3 * a0 + delta_v) / den
        return max(t2, 0.0)


def _evaluate(jerk: float, a0: float, v0: float, x0: float, t: float) -> AxisState:
    return AxisState(jerk, a0 + jerk * t, v0 + a0 * t + 0.5 * jerk * t * t,
                     x0 + v0 * t + 0.5 * a0 * t * t + jerk * t * t * t / 6.0)


def _sign(value: float) -> int:
    return (value > 0.0) - (value < 0.0)
