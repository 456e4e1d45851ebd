"""The motion-primitive planner: choose a forward arc every round, or stop (Lee et al., 2024).

Each round (about 12 Hz) the planner places the library of forward arcs (primitives.py) in the
start frame ``S`` of the present pose (origin at the body, x along its heading, z up) and checks
every point of every primitive against the depth history (history.py), in one vectorised call
per frame. A primitive is safe when all of these are:

- its arc and its stopping extension (the vehicle can stop after the whole arc);
- the branch "follow the arc for one planning period, then brake": the stop that will be
  followed if the next round finds nothing safe, checked now, this round.

Among the safe primitives it takes the one of least cost (dimensionless terms):

    J = -w_p (|s - g| - |e - g|) / (v T)                   progress toward the goal g
        + w_s [((w - w0) / w_max)² + ((c - c0) / c_max)²]    change from the previous choice
        + w_c max(0, 1 - clearance / clearance_wanted)       nearness of observed surfaces

with ``s`` the start, ``e`` the arc's end, ``v T`` the arc's horizontal length, ``(w, c)`` its
yaw rate and vertical speed and ``(w0, c0)`` those of the previous arc chosen, ``clearance``
the least distance along the primitive between the far side of the robot's sphere and the
surface observed behind it.

When nothing is safe, or there is no depth, it returns the stop checked in the previous round
(the previous arc's one-period-then-brake branch, continued in time from that round), or, with
no such stop or once it has run out, braking from the present velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from autonomy.geometry import PinholeCamera, make_pose, rot_z, yaw_of
from autonomy.messages import MetricDepth
from autonomy.options import OptionError, option
from autonomy.planning.history import DepthHistory, as_pose
from autonomy.planning.primitives import (
    Primitive, PrimitiveOptions, forward_arc, library, stop_primitive,
)


@dataclass(frozen=True)
class PlannerOptions(PrimitiveOptions):
    """Every planner setting, flat (one ``[planner]`` table): the library's shape (the fields of
    :class:`PrimitiveOptions`, inherited), the collision check and the cost."""

    period_s: float = option(1.0 / 12.0, gt=0.0, le=1.0, doc="time between planning rounds, "
                             "seconds: the stop checked each round follows the arc this long")
    robot_radius: float = option(1.0, gt=0.0, le=10.0, doc="radius of the sphere about each "
                                 "point that must be free, metres")
    history_frames: int = option(8, ge=1, le=64, doc="newest depth frames kept for checking")
    history_s: float = option(2.0, gt=0.0, le=60.0, doc="oldest depth frame used, seconds "
                              "before the planning time")
    min_confidence: float = option(0.3, ge=0.0, le=1.0, doc="depth pixels less confident than "
                                   "this are unknown")
    max_range: float = option(10.0, gt=0.0, le=100.0, doc="depth trusted up to this distance, "
                              "metres; farther space is unknown, farther pixels count as this")
    progress_weight: float = option(1.0, ge=0.0, le=100.0, doc="cost weight of progress toward "
                                    "the goal")
    smoothness_weight: float = option(0.3, ge=0.0, le=100.0, doc="cost weight of changing yaw "
                                      "rate and vertical speed from the previous choice")
    clearance_weight: float = option(0.5, ge=0.0, le=100.0, doc="cost weight of passing near "
                                     "observed surfaces")
    clearance_wanted: float = option(2.0, gt=0.0, le=100.0, doc="clearance beyond the robot "
                                     "radius that costs nothing, metres")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.period_s >= self.duration_s:
            raise OptionError("period_s", f"must be < duration_s ({self.duration_s:g}), "
                              f"got {self.period_s:g}")
        if self.max_range <= self.robot_radius:
            raise OptionError("max_range", f"must be > robot_radius ({self.robot_radius:g}), "
                              f"got {self.max_range:g}")

    @property
    def primitives(self) -> PrimitiveOptions:
        """The library's shape alone, as :class:`PrimitiveOptions`."""
        return PrimitiveOptions(**{f.name: getattr(self, f.name)
                                   for f in fields(PrimitiveOptions)})


@dataclass(frozen=True, eq=False)
class Plan:
    """What to fly from time ``t``: ``primitive`` in the start frame whose pose is ``T_W_S``.

    ``kind``: "arc" (a forward arc, its stopping extension after it) or "stop" (braking; the
    previous round's checked branch, whose ``t`` and ``T_W_S`` are that round's, or braking
    from the velocity at ``t``). ``reason``: "" for an arc, else why it stops. ``safe_count``:
    primitives found safe this round. ``clearance``: metres between the robot's sphere and the
    observed surfaces along the primitive (inf where none was measured, NaN for an unchecked
    stop). ``stop_duration_s``: the braking time.
    """

    t: float
    T_W_S: np.ndarray
    primitive: Primitive
    kind: str
    reason: str
    safe_count: int
    clearance: float
    stop_duration_s: float

    def setpoint(self, t: float) -> tuple[np.ndarray, float]:
        """``(velocity_W (3,), yaw_rate)`` commanded at time ``t``, m/s and rad/s about z up.

        With ``tau = t - self.t`` (0 before the start), arc duration ``D``, braking time ``T``
        and the primitive's speed ``v``, yaw rate ``w``, vertical speed ``c``:
        ``v_S = (v cos w tau, v sin w tau, c)``, yaw rate ``w`` for ``tau < D``; then
        ``v_S = u (1 - (tau - D) / T)`` with ``u`` the arc's final velocity, yaw rate 0, until
        rest at ``D + T``; zero after. ``velocity_W = R_W_S v_S``.
        """
        if not math.isfinite(t):
            raise ValueError(f"setpoint time must be finite, got {t!r}")
        p = self.primitive
        tau = max(0.0, t - self.t)
        if tau < p.duration:
            heading = p.yaw_rate * tau
            v_S = np.array([p.speed * math.cos(heading), p.speed * math.sin(heading),
                            p.vertical_speed])
            yaw_rate = p.yaw_rate
        else:
            left = max(0.0, 1.0 - (tau - p.duration) / self.stop_duration_s)
            v_S, yaw_rate = p.end_velocity_S * left, 0.0
        return self.T_W_S[:3, :3] @ v_S, float(yaw_rate)

    @property
    def end_time(self) -> float:
        """When the plan comes to rest."""
        return self.t + self.primitive.duration + self.stop_duration_s


class Planner:
    """Checks the library against the newest depth frames and chooses, every round."""

    def __init__(self, camera: PinholeCamera, options: PlannerOptions | None = None):
        if not isinstance(camera, PinholeCamera):
            raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
        o = options or PlannerOptions()
        self.camera = camera
        self.options = o
        self.history = DepthHistory(robot_radius=o.robot_radius, min_confidence=o.min_confidence,
                                    max_range=o.max_range, max_frames=o.history_frames,
                                    max_age_s=o.history_s)
        shape = o.primitives
        self.library = library(shape)
        branch_shape = replace(shape, duration_s=o.period_s)
        self.branches = [forward_arc(a.speed, a.yaw_rate, a.vertical_speed, branch_shape)
                         for a in self.library]
        # Every point checked per primitive: arc (less its start, the vehicle's own sphere),
        # extension, then the branch's point at one period and its braking.
        groups = [np.vstack([a.points_S[1:], a.stop_points_S, b.points_S[-1:], b.stop_points_S])
                  for a, b in zip(self.library, self.branches)]
        self._points_S = np.vstack(groups)
        self._starts = np.cumsum([0] + [len(g) for g in groups[:-1]])
        self._ends_S = np.array([a.points_S[-1] for a in self.library])
        self._yaw_rates = np.array([a.yaw_rate for a in self.library])
        self._vertical = np.array([a.vertical_speed for a in self.library])
        self._previous: Plan | None = None
        self._checked_stop: Plan | None = None

    def reset(self) -> None:
        """Forget the depth history, the previous choice and its checked stop."""
        self.history.clear()
        self._previous = None
        self._checked_stop = None

    def add_depth(self, depth: MetricDepth, T_W_C) -> bool:
        """Keep a metric depth frame taken with the camera at ``T_W_C``; False (and nothing
        kept) when it has no depth."""
        if not isinstance(depth, MetricDepth):
            raise TypeError(f"depth must be a MetricDepth, got {type(depth).__name__}")
        if depth.depth is None:
            return False
        if depth.confidence is None:
            raise ValueError("MetricDepth has a depth image but no confidence")
        self.history.add(depth.depth, depth.confidence, T_W_C, self.camera, depth.t)
        return True

    def plan(self, t: float, T_W_B, velocity_W, goal_W) -> Plan:
        """The plan for the round at time ``t`` with the body at ``T_W_B`` moving at
        ``velocity_W`` (m/s), heading for ``goal_W`` (module docstring)."""
        t = _finite_time(t)
        T_W_S = _start_pose(T_W_B)
        velocity = _vector(velocity_W, "velocity_W")
        goal = _vector(goal_W, "goal_W")
        if not any(ft >= t - self.options.history_s for ft in self.history.times):
            return self._stop(t, T_W_S, velocity, "no depth")
        safe, clearance = self.check(t, T_W_S)
        count = int(safe.sum())
        if count == 0:
            return self._stop(t, T_W_S, velocity, "no safe primitive")
        R, start = T_W_S[:3, :3], T_W_S[:3, 3]
        cost = np.where(safe, self._cost(start, R, goal, clearance), np.inf)
        i = int(np.argmin(cost))
        chosen = float(clearance[i])
        plan = Plan(t, T_W_S, self.library[i], "arc", "", count, chosen,
                    self.options.stop_duration_s)
        self._previous = plan
        self._checked_stop = Plan(t, T_W_S, self.branches[i], "stop", "", count, chosen,
                                  self.options.stop_duration_s)
        return plan

    def check(self, t: float, T_W_S) -> tuple[np.ndarray, np.ndarray]:
        """``(safe, clearance)`` of every primitive of ``library`` (and its branch) placed at
        the start frame ``T_W_S``, against the frames no older than ``t - history_s``:
        ``safe`` (P,) bool; ``clearance`` (P,) the least clearance along it (metres between
        the sphere's far side and the surface behind it; inf where only rays judged it)."""
        R, start = T_W_S[:3, :3], T_W_S[:3, 3]
        result = self.history.check(self._points_S @ R.T + start, start_W=start, now=t)
        safe = np.logical_and.reduceat(result.free, self._starts)
        return safe, np.fmin.reduceat(result.clearance, self._starts)

    def stop_plan(self, t: float, T_W_B, velocity_W, reason: str) -> Plan:
        """The stop for the application's failsafes: the stop checked at the last round,
        continued, while it has not run out; else braking from ``velocity_W``."""
        if not isinstance(reason, str) or not reason:
            raise ValueError(f"a stop needs a reason, got {reason!r}")
        return self._stop(_finite_time(t), _start_pose(T_W_B),
                          _vector(velocity_W, "velocity_W"), reason)

    def _stop(self, t: float, T_W_S: np.ndarray, velocity: np.ndarray, reason: str) -> Plan:
        stop = self._checked_stop
        if stop is not None and stop.t <= t < stop.end_time:
            return replace(stop, reason=reason, safe_count=0)
        self._checked_stop = None
        velocity_S = T_W_S[:3, :3].T @ velocity
        return Plan(t, T_W_S, stop_primitive(velocity_S, self.options.primitives), "stop",
                    reason, 0, math.nan, self.options.stop_duration_s)

    def _cost(self, start: np.ndarray, R: np.ndarray, goal: np.ndarray,
              clearance: np.ndarray) -> np.ndarray:
        """The cost ``J`` of the module docstring for every primitive."""
        o = self.options
        ends = self._ends_S @ R.T + start
        progress = np.linalg.norm(start - goal) - np.linalg.norm(ends - goal, axis=1)
        cost = -o.progress_weight * progress / (o.speed * o.duration_s)
        if self._previous is not None:
            change = np.zeros(len(cost))
            if o.max_yaw_rate_deg > 0.0:
                w0 = self._previous.primitive.yaw_rate
                change += ((self._yaw_rates - w0) / math.radians(o.max_yaw_rate_deg)) ** 2
            if o.max_vertical_speed > 0.0:
                c0 = self._previous.primitive.vertical_speed
                change += ((self._vertical - c0) / o.max_vertical_speed) ** 2
            cost += o.smoothness_weight * change
        near = np.clip(1.0 - clearance / o.clearance_wanted, 0.0, 1.0)
        return cost + o.clearance_weight * near


def _finite_time(t) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float, np.floating)) or not math.isfinite(t):
        raise ValueError(f"planning time must be a finite number, got {t!r}")
    return float(t)


def _vector(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v


def _start_pose(T_W_B) -> np.ndarray:
    """The start frame: origin at the body, rotated by the body's yaw only."""
    T = as_pose(T_W_B, "T_W_B")
    return make_pose(rot_z(yaw_of(T[:3, :3])), T[:3, 3])
