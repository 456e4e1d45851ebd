"""The motion-primitive library: forward arcs, each with a stopping extension, and a stop.

Primitives live in the start frame ``S``: origin at the body's position when planning,
gravity-aligned, x along the body's heading (yaw only), y left, z up. A forward arc holds a
constant horizontal speed ``v``, yaw rate ``w`` and vertical speed ``c`` for ``duration``:

    psi(t) = w t
    x(t)   = v sin(w t) / w,   y(t) = v (1 - cos(w t)) / w     (x = v t, y = 0 for w = 0)
    z(t)   = c t

Its stopping extension brakes from the arc's final velocity ``u`` to rest at a constant
deceleration over ``stop_duration`` ``T``, heading held: ``p(tau) = p_end + u (tau - tau² /
(2 T))``, so it ends ``u T / 2`` beyond the arc. A primitive is safe only when the arc and its
extension are, so the vehicle can always stop after following any part of the arc (Lee et al.,
Section III). The stop primitive is that braking from the vehicle's present velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.options import OptionError, option, validate


@dataclass(frozen=True)
class PrimitiveOptions:
    """The shape of the library: the paper flies 2 m/s, 2 s arcs; 15 yaw rates x 5 vertical
    speeds make its 75 primitives."""

    speed: float = option(2.0, gt=0.0, le=20.0, doc="horizontal speed along every arc, m/s")
    duration_s: float = option(2.0, gt=0.0, le=10.0, doc="length of an arc in time, seconds")
    yaw_rates: int = option(15, ge=1, le=101, doc="yaw rates in the library, spread evenly "
                            "over [-max_yaw_rate, max_yaw_rate] (odd keeps a straight arc)")
    max_yaw_rate_deg: float = option(45.0, ge=0.0, le=360.0, doc="largest yaw rate of an arc, "
                                     "degrees per second")
    vertical_speeds: int = option(5, ge=1, le=21, doc="vertical speeds in the library, spread "
                                  "evenly over [-max_vertical_speed, max_vertical_speed]")
    max_vertical_speed: float = option(0.5, ge=0.0, le=5.0, doc="largest climb or sink rate of "
                                       "an arc, m/s")
    speed_tiers: int = option(3, ge=1, le=5, doc="speeds of the library: speed, speed r, "
                              "speed r², ... (r: tier_ratio); a slower tier is tried only when "
                              "no arc of the faster ones is safe (a narrow passage, a corner)")
    tier_ratio: float = option(0.5, gt=0.0, lt=1.0, doc="each speed tier's speed over the next "
                               "faster one's")
    stop_duration_s: float = option(2.0, gt=0.0, le=10.0, doc="time to brake to rest, seconds")
    sample_spacing: float = option(0.25, gt=0.0, le=5.0, doc="largest distance between the "
                                   "points an arc is checked at, metres")

    def __post_init__(self) -> None:
        validate(self)
        if self.yaw_rates > 1 and self.max_yaw_rate_deg == 0.0:
            raise OptionError("max_yaw_rate_deg", f"must be > 0 for {self.yaw_rates} yaw rates")


@dataclass(frozen=True, eq=False)
class Primitive:
    """One primitive in the start frame: its commands and the points it passes through.

    ``points_S`` (N, 3) are the arc's positions at times ``t`` (N,), from the start (t = 0)
    to the arc's end; ``stop_points_S`` (M, 3) the stopping extension after it, ending at rest.
    ``heading`` is the yaw at the arc's end, radians. The stop primitive has an arc of no
    length; its ``speed``, ``vertical_speed`` and ``heading`` are those of the velocity it
    brakes from, so ``end_velocity_S`` is that velocity for every primitive.
    """

    speed: float
    yaw_rate: float
    vertical_speed: float
    t: np.ndarray
    points_S: np.ndarray
    stop_points_S: np.ndarray
    heading: float

    @property
    def duration(self) -> float:
        """Time along the arc, seconds, before the stopping extension begins."""
        return float(self.t[-1])

    @property
    def end_velocity_S(self) -> np.ndarray:
        """The velocity at the arc's end, m/s in the start frame."""
        return np.array([self.speed * math.cos(self.heading),
                         self.speed * math.sin(self.heading), self.vertical_speed])


    def motion_S(self, tau: float, stop_duration: float):
        """``(position, velocity, acceleration, yaw_rate)`` at ``tau`` seconds after the start
        (clamped to 0 below), in the start frame: along the arc (module docstring) for
        ``tau < duration``, then braking over ``stop_duration``, at rest after. On the arc
        ``v = (v cos w tau, v sin w tau, c)`` and ``a = v w (-sin w tau, cos w tau, 0)``;
        braking from the end velocity ``u``, ``s = tau - duration``: ``p = p_end + u (s -
        s² / 2T)``, ``v = u (1 - s / T)``, ``a = -u / T``."""
        tau = max(0.0, tau)
        if tau < self.duration:
            heading = self.yaw_rate * tau
            cos, sin = math.cos(heading), math.sin(heading)
            x, y = _arc_xy(self.speed, self.yaw_rate, np.array([tau]))
            position = np.array([x[0], y[0], self.vertical_speed * tau])
            velocity = np.array([self.speed * cos, self.speed * sin, self.vertical_speed])
            return (position, velocity, self.speed * self.yaw_rate * np.array([-sin, cos, 0.0]),
                    self.yaw_rate)
        u = self.end_velocity_S
        s = min(tau - self.duration, stop_duration)
        position = self.points_S[-1] + u * (s - s * s / (2.0 * stop_duration))
        if s >= stop_duration:
            return position, np.zeros(3), np.zeros(3), 0.0
        return position, u * (1.0 - s / stop_duration), -u / stop_duration, 0.0


def tier_speeds(options: PrimitiveOptions | None = None) -> list[float]:
    """The horizontal speed of each tier, fastest first: ``speed r^k`` (r: ``tier_ratio``)."""
    o = options or PrimitiveOptions()
    return [o.speed * o.tier_ratio**k for k in range(o.speed_tiers)]


def library(options: PrimitiveOptions | None = None, speed: float | None = None
            ) -> list[Primitive]:
    """Every forward arc of one tier (``speed``, default the fastest), yaw rate varying
    fastest, from right turns (negative yaw rate, clockwise seen from above) to left turns.
    The same yaw rates at every speed: a slower arc turns on a tighter circle, ``v / w``."""
    o = options or PrimitiveOptions()
    yaw_rates = _spread(math.radians(o.max_yaw_rate_deg), o.yaw_rates)
    vertical_speeds = _spread(o.max_vertical_speed, o.vertical_speeds)
    v = o.speed if speed is None else speed
    return [forward_arc(v, w, c, o) for c in vertical_speeds for w in yaw_rates]


def forward_arc(speed: float, yaw_rate: float, vertical_speed: float,
                options: PrimitiveOptions, duration: float | None = None) -> Primitive:
    """The arc with these commands for ``duration`` seconds (default ``duration_s``), sampled
    at most ``sample_spacing`` apart, and its stopping extension."""
    o = options
    duration = o.duration_s if duration is None else float(duration)
    if not (math.isfinite(duration) and duration > 0.0):
        raise ValueError(f"an arc's duration must be > 0 s, got {duration!r}")
    step_length = math.hypot(speed, vertical_speed)
    t = _sample_times(duration, step_length, o.sample_spacing)
    points = np.column_stack([*_arc_xy(speed, yaw_rate, t), vertical_speed * t])
    heading = yaw_rate * duration
    velocity = np.array([speed * math.cos(heading), speed * math.sin(heading), vertical_speed])
    stop = braking_points(points[-1], velocity, o)
    return Primitive(speed, yaw_rate, vertical_speed, t, points, stop, heading)


def stop_primitive(velocity_S, options: PrimitiveOptions | None = None) -> Primitive:
    """Braking to rest from ``velocity_S`` (m/s, start frame) at the present position: the
    action followed whenever no arc is safe."""
    o = options or PrimitiveOptions()
    velocity = np.asarray(velocity_S, dtype=float).reshape(3)
    if not np.isfinite(velocity).all():
        raise ValueError(f"velocity must be 3 finite numbers, got {velocity_S!r}")
    stop = braking_points(np.zeros(3), velocity, o)
    heading = math.atan2(velocity[1], velocity[0]) if velocity[:2].any() else 0.0
    return Primitive(math.hypot(velocity[0], velocity[1]), 0.0, float(velocity[2]), np.zeros(1),
                     np.zeros((1, 3)), stop, heading)


def braking_points(start: np.ndarray, velocity: np.ndarray,
                   options: PrimitiveOptions) -> np.ndarray:
    """Points of braking from ``velocity`` at ``start`` to rest in ``stop_duration_s`` at a
    constant deceleration, ``start + velocity (tau - tau² / (2 T))``, the first point after
    ``start`` to the point of rest, at most ``sample_spacing`` apart."""
    duration = options.stop_duration_s
    tau = _sample_times(duration, float(np.linalg.norm(velocity)), options.sample_spacing)[1:]
    travelled = tau - tau**2 / (2.0 * duration)
    return start + travelled[:, None] * velocity


def _spread(limit: float, count: int) -> np.ndarray:
    """``count`` values evenly over [-limit, limit]; 0 alone for a count of 1."""
    return np.linspace(-limit, limit, count) if count > 1 else np.zeros(1)


def _sample_times(duration: float, speed: float, spacing: float) -> np.ndarray:
    """Times from 0 to ``duration`` inclusive, evenly spaced, at most ``spacing`` metres of
    travel apart at ``speed`` (the fastest speed along the way); 2 times at least."""
    steps = max(1, math.ceil(speed * duration / spacing))
    return np.linspace(0.0, duration, steps + 1)


def _arc_xy(speed: float, yaw_rate: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal position along a constant-speed, constant-yaw-rate arc from rest heading
    along x; the straight line as the limit of a vanishing yaw rate."""
    if abs(yaw_rate) < 1e-9:
        return speed * t, np.zeros_like(t)
    angle = yaw_rate * t
    return speed * np.sin(angle) / yaw_rate, speed * (1.0 - np.cos(angle)) / yaw_rate
