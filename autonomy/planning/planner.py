"""The motion-primitive planner: choose a forward arc every round, or stop (Lee et al., 2024).

Each round (about 12 Hz) the planner places the library of forward arcs (primitives.py) in the
start frame ``S`` of the present pose (origin at the body, x along its heading, z up) and checks
every point of every primitive against the depth history (history.py), in one vectorised call
per frame. A primitive is safe when all of these are:

- its arc and its stopping extension (the vehicle can stop after the whole arc);
- the branch "follow the arc for one planning period, then brake": the stop that will be
  followed if the next round finds nothing safe, checked now, this round.

The library comes in speed tiers (``speed``, ``speed / 2``, ``speed / 4``): the fastest is
checked first, and a slower one only when no arc of the faster ones is safe. A slower arc
needs less room ahead (its stopping extension is ``u T / 2``) and turns on a tighter circle
(``v / w``), so a narrow passage or a corner is flown slowly instead of not at all, while open
space costs one tier's check per round.

Among the safe primitives of the tier it takes the one of least cost (dimensionless terms):

    J = -w_p (|s - g|_k - |e - g|_k) / (v T)               progress toward the goal g
        + w_s [((w - w0) / w_max)² + ((c - c0) / c_max)²]    change from the previous choice
        + w_c max(0, 1 - clearance / clearance_wanted)       nearness of observed surfaces

with ``s`` the start, ``e`` the arc's end, ``v T`` the arc's horizontal length, ``(w, c)`` its
yaw rate and vertical speed and ``(w0, c0)`` those of the previous arc chosen, ``clearance``
the least distance along the primitive between the far side of the robot's sphere and the
surface observed behind it. ``|d|_k = sqrt(dx² + dy² + (k dz)²)`` counts a metre of height
as the ``k = v / c_max`` metres of ground the tier covers while it climbs or sinks that metre
(``height_gap_in_time``; else ``k = 1``): a height gap is closed before the goal is reached,
not after. With plain distance a gap of 1.8 m, 10 m out, was worth 0.16 m of progress, less
than the clearance term's pull away from the floor: a sewer flight rode at 3.3 m through a
room and came to the 3 m hallway's door too high to enter it (docs/planner.md, "Height").

**Hemmed in.** A vehicle may stand nearer than ``robot_radius`` to a wall: stopped at a
corner waypoint that hugs the inside of the turn, or put there by the estimate's error. Then
every arc begins inside the robot's sphere and none can be safe, however open the way ahead.
When no arc of the slowest tier is safe and the robot's sphere about its straight arc's first
point (a step ahead) meets an observed surface, that tier is checked again with spheres
:data:`ESCAPE_STEP_M` smaller each time, down to ``escape_radius``, and the first with a safe
arc is used: the arcs flown keep the most room any arc can, never less than
``escape_radius``, and the clearance cost turns them away from the wall. A vehicle blocked
farther ahead is not hemmed in and stops as before. The plan's candidates say which sphere
was used.

**The speed wave.** With ``speed_swing`` the chosen arc and its checked stop are flown along
the same path up to ``speed_swing`` m/s slower, and back, every ``speed_swing_period_s``
(speed_wave.py): never faster than the tier checked, so the check holds; the accelerations
let the VINS see its scale, which a steady cruise lets walk. With ``height_swing`` they are
flown swinging ``height_swing`` metres up and down about it every ``height_swing_period_s``
(height_wave.py), fading out over the braking, without slowing down the path. Each arc is
then checked about the line the wave swings about, at the wave's crest and trough: every point
``height_swing`` = ``A`` above and below it, with spheres of ``sqrt(r² + A²)`` for the robot's
``r``. Any point within ``r`` of the vertical segment between them lies within that of one of
its ends, so every sphere of the flown path lies inside the two checked, for twice the points
(the glides, flown level, keep the robot's sphere). The wave never costs speed: where no arc of
a tier clears the crest and the trough but one clears the level path (a low pipe), that tier's
arc and its stop are flown level, checked with the robot's own sphere.

When nothing is safe, or there is no depth, it returns the stop checked in the previous round
(the previous arc's one-period-then-brake branch, continued in time from that round), or, with
no such stop, braking from the present velocity, which the following rounds continue in the
same way. A stop that has come to rest goes on holding its end point (the application steers
toward the plan's position) while the vehicle is within a robot radius of it; farther off, a
new braking begins where the vehicle is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple, Sequence

import numpy as np

from autonomy.geometry import PinholeCamera, make_pose, rot_z, yaw_of
from autonomy.messages import MetricDepth
from autonomy.options import OptionError, option
from autonomy.planning.height_wave import HeightWave
from autonomy.planning.history import DepthHistory, as_pose, check_camera
from autonomy.planning.landing import candidate_sites, column_points
from autonomy.planning.primitives import (
    Primitive, PrimitiveOptions, forward_arc, library, stop_primitive, tier_speeds,
)
from autonomy.planning.speed_wave import SpeedWave


#: The reason an approach glide's plan carries (:meth:`Planner.approach`).
APPROACH_REASON = "approach"

#: The reason a landing site's glide carries (:meth:`Planner.landing_glide`).
LANDING_REASON = "landing site"

#: Steps of the sphere's radius a hemmed-in vehicle's arcs are checked with, metres.
ESCAPE_STEP_M = 0.1


@dataclass(frozen=True)
class PlannerOptions(PrimitiveOptions):
    """Every planner setting, flat (one ``[planner]`` table): the library's shape (the fields of
    :class:`PrimitiveOptions`, inherited), the collision check and the cost."""

    period_s: float = option(1.0 / 12.0, gt=0.0, le=1.0, doc="time between planning rounds, "
                             "seconds: the stop checked each round follows the arc this long")
    robot_radius: float = option(1.0, gt=0.0, le=10.0, doc="radius of the sphere about each "
                                 "point that must be free, metres")
    escape_radius: float = option(0.6, gt=0.0, le=10.0, doc="a vehicle already nearer than "
                                  "robot_radius to a surface flies the arcs that keep the most "
                                  "room, down to this radius (at robot_radius: never), metres")
    history_frames: int = option(8, ge=1, le=64, doc="newest depth frames kept for checking")
    history_s: float = option(2.0, gt=0.0, le=60.0, doc="oldest depth frame used, seconds "
                              "before the planning time")
    min_confidence: float = option(0.3, ge=0.0, le=1.0, doc="depth pixels less confident than "
                                   "this are unknown")
    max_range: float = option(10.0, gt=0.0, le=100.0, doc="depth trusted up to this distance, "
                              "metres; farther space is unknown, farther pixels count as this")
    near_tail_share: float = option(0.0, ge=0.0, le=1.0, doc="a low-confidence pixel nearer "
                                    "than every confident one (the rescaling's straight tail "
                                    "past the nearest landmark) counts as this share of its "
                                    "depth, 0.9 measured; 0: unknown (docs/planner.md, the "
                                    "near tail)")
    far_tail_share: float = option(0.0, ge=0.0, le=1.0, doc="a low-confidence pixel farther "
                                   "than every confident one (the rescaling's straight tail "
                                   "past the farthest landmark) counts as this share of its "
                                   "depth where that exceeds the farthest confident depth; 0: "
                                   "as the farthest confident depth (docs/planner.md, the far "
                                   "tail)")
    progress_weight: float = option(1.0, ge=0.0, le=100.0, doc="cost weight of progress toward "
                                    "the goal")
    smoothness_weight: float = option(0.3, ge=0.0, le=100.0, doc="cost weight of changing yaw "
                                      "rate and vertical speed from the previous choice")
    clearance_weight: float = option(0.5, ge=0.0, le=100.0, doc="cost weight of passing near "
                                     "observed surfaces")
    clearance_wanted: float = option(2.0, gt=0.0, le=100.0, doc="clearance beyond the robot "
                                     "radius that costs nothing, metres")
    height_gap_in_time: bool = option(True, doc="progress counts a metre of height to the "
                                      "goal as the ground covered while climbing or sinking it "
                                      "(speed / max_vertical_speed metres), so the goal's "
                                      "height is reached on the way; false: as one metre")
    landing_radius: float = option(0.5, ge=0.0, le=10.0, doc="after a mission timeout or no "
                                   "safe primitive, the vehicle glides to a site ahead seen "
                                   "free this far round its column down to the floor before "
                                   "landing (landing.py); 0: it lands where it stopped, metres")
    # The VINS's scale needs the accelerometer to see speed change: a steady cruise lets it
    # walk (docs/vins.md, "The hallway's drift is the cruise's"). Never faster than checked.
    speed_swing: float = option(0.0, ge=0.0, le=5.0, doc="the speed wave (speed_wave.py): "
                                "each arc is flown up to this much slower, m/s, and back, "
                                "along the same path; 0: at its speed throughout")
    speed_swing_period_s: float = option(3.3, gt=0.0, le=60.0, doc="the speed wave's "
                                         "period, seconds")
    height_swing: float = option(0.0, ge=0.0, le=0.5, doc="the height wave (height_wave.py): "
                                 "each arc is flown this much up and down about its path, "
                                 "metres, and checked at its crest and trough; 0: level")
    height_swing_period_s: float = option(2.0, ge=0.5, le=60.0, doc="the height wave's "
                                          "period, seconds")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.period_s >= self.duration_s:
            raise OptionError("period_s", f"must be < duration_s ({self.duration_s:g}), "
                              f"got {self.period_s:g}")
        if self.escape_radius > self.robot_radius:
            raise OptionError("escape_radius", f"must be <= robot_radius "
                              f"({self.robot_radius:g}), got {self.escape_radius:g}")
        if self.landing_radius > self.robot_radius:
            raise OptionError("landing_radius", f"must be <= robot_radius "
                              f"({self.robot_radius:g}), got {self.landing_radius:g}")
        if self.max_range <= self.robot_radius:
            raise OptionError("max_range", f"must be > robot_radius ({self.robot_radius:g}), "
                              f"got {self.max_range:g}")

    @property
    def waves(self) -> tuple[SpeedWave | None, HeightWave | None]:
        """The speed and height waves the arcs are flown on (None: off), as the planner and the
        simulator's recordings fly them."""
        return (SpeedWave.of(self.speed_swing, self.speed_swing_period_s),
                HeightWave.of(self.height_swing, self.height_swing_period_s))

    @property
    def primitives(self) -> PrimitiveOptions:
        """The library's shape alone, as :class:`PrimitiveOptions`."""
        return PrimitiveOptions(**{f.name: getattr(self, f.name)
                                   for f in fields(PrimitiveOptions)})


class Setpoint(NamedTuple):
    """A plan's command at one instant, in the planning world ``W``: ``velocity_W`` (3,) m/s,
    ``yaw_rate`` rad/s about z up, ``acceleration_W`` (3,) m/s² (feed-forward), and
    ``position_W`` (3,) metres, where the plan has the body then (None: hold no position)."""

    velocity_W: np.ndarray
    yaw_rate: float
    acceleration_W: np.ndarray
    position_W: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class PlanRequest:
    """What :meth:`Planner.plan` was asked: the body's pose and velocity, the goal, and
    whether to stop there. Kept on the plan so a replay can ask again."""

    T_W_B: np.ndarray
    velocity_W: np.ndarray
    goal_W: np.ndarray
    stop_at_goal: bool


class TierCheck(NamedTuple):
    """A tier's primitives against the depth history: ``safe`` (P,) bool; ``clearance`` (P,)
    metres, the least along a safe one (:meth:`Planner.check`); ``blocked`` (P,) bool, an
    observed surface inside the robot's sphere somewhere along the primitive (an unsafe one
    that is not blocked met only unknown space: out of view, or beyond the depth's range)."""

    safe: np.ndarray
    clearance: np.ndarray
    blocked: np.ndarray


class FasterTier(NamedTuple):
    """A tier checked before the one a round chose from, with nothing safe: its ``speed``, and
    of its primitives how many an observed surface ``blocked`` and how many met only
    ``unseen`` space (out of view, or beyond the depth's range)."""

    speed: float
    blocked: int
    unseen: int

    @classmethod
    def of(cls, speed: float, check: TierCheck) -> "FasterTier":
        blocked = int(check.blocked.sum())
        return cls(speed, blocked, int((~check.safe).sum()) - blocked)


@dataclass(frozen=True, eq=False)
class Candidates:
    """One round's choice: the tier's ``primitives`` (in ``Plan.T_W_S``'s start frame), which
    were ``safe`` and which ``blocked`` by an observed surface (:class:`TierCheck`), and the
    index of the one ``chosen``, -1 when none was safe (the slowest tier's, on a stop), and
    the ``radius`` of the sphere they were checked with (less than the robot's when hemmed
    in, swept over the height wave's crest and trough when it is flown: module docstring);
    ``faster``: why each faster tier checked had nothing safe, fastest first (the flight
    record says why the vehicle flew slower)."""

    speed: float
    primitives: Sequence[Primitive]
    safe: np.ndarray
    chosen: int
    blocked: np.ndarray
    radius: float
    faster: tuple[FasterTier, ...] = ()


@dataclass(frozen=True, eq=False)
class Plan:
    """What to fly from time ``t``: ``primitive`` in the start frame whose pose is ``T_W_S``.

    ``kind``: "arc" (a forward arc, its stopping extension after it), "glide" (a straight
    glide flown through its end, its stopping extension after it: :meth:`Planner.glide`) or
    "stop" (braking; the previous round's checked branch, whose ``t`` and ``T_W_S`` are that
    round's, or braking from the velocity at ``t``; a glide to rest). ``reason``: "" for an
    arc, else why it stops or glides. ``safe_count``: primitives found safe this round.
    ``clearance``: metres between the robot's sphere and the observed surfaces along the
    primitive (inf where none was measured, NaN for an unchecked stop or glide).
    ``stop_duration_s``: the braking time. ``candidates``: what an arc was chosen from,
    or for "no safe primitive" the slowest tier checked (None for another stop);
    ``request``: what the round asked (None for a plan not of :meth:`Planner.plan`); both for
    the flight recorder and replay.
    """

    t: float
    T_W_S: np.ndarray
    primitive: Primitive
    kind: str
    reason: str
    safe_count: int
    clearance: float
    stop_duration_s: float
    candidates: "Candidates | None" = None
    request: PlanRequest | None = None
    wave: SpeedWave | None = None
    height_wave: HeightWave | None = None

    def setpoint(self, t: float) -> "Setpoint":
        """What to command at time ``t``: the primitive's motion ``tau = t - self.t`` after its
        start (:meth:`Primitive.motion_S`: along the arc, then braking over
        ``stop_duration_s``, at rest after) turned into ``W``. The acceleration is the
        feed-forward that lets the autopilot's velocity loop follow the arc and the braking
        without the lag of its feedback alone, the position what the application's tracking
        corrects toward: the collision check assumed the primitive is flown as it is.

        With a speed ``wave`` the same motion is flown slower by the wave's ``m(t)``: at
        ``tau = W(t) - W(self.t)`` (speed_wave.py), velocity and yaw rate times ``m``, the
        acceleration ``m² a + m' v``. With a ``height_wave`` the path is offset vertically by
        the wave's ``h(t)`` (height_wave.py), its share of motion falling over the braking at
        the rate the braking is flown."""
        if not math.isfinite(t):
            raise ValueError(f"setpoint time must be finite, got {t!r}")
        if self.wave is None:
            tau, m, rate = t - self.t, 1.0, 0.0
        else:
            share = self.wave.share(self.primitive.speed)
            tau = self.wave.progress(self.t, t, share)
            m, rate = self.wave.factor(t, share), self.wave.rate(t, share)
        p_S, v_S, a_S, yaw_rate = self.primitive.motion_S(tau, self.stop_duration_s)
        if tau < 0.0:  # before the plan's start: at its start, not moving on the wave
            m, rate = 1.0, 0.0
        a_S = m * m * a_S + rate * v_S
        R = self.T_W_S[:3, :3]
        setpoint = Setpoint(R @ (m * v_S), float(m * yaw_rate), R @ a_S,
                            R @ p_S + self.T_W_S[:3, 3])
        if self.height_wave is None:
            return setpoint
        up = np.array([0.0, 0.0, 1.0])
        offset = self.height_wave.offset(t, *self._motion_share(tau, m, rate))
        return Setpoint(setpoint.velocity_W + offset.velocity * up, setpoint.yaw_rate,
                        setpoint.acceleration_W + offset.acceleration * up,
                        setpoint.position_W + offset.height * up)

    def _motion_share(self, tau: float, m: float, rate: float) -> tuple[float, float, float]:
        """The height wave's ``(f, f', f'')`` at ``tau`` into the primitive flown at ``m``
        times its pace (rate ``m'``): 1 along the arc, ``1 - s / T`` over the braking."""
        braking = tau - self.primitive.duration
        if braking < 0.0:
            return 1.0, 0.0, 0.0
        if braking >= self.stop_duration_s:
            return 0.0, 0.0, 0.0
        T = self.stop_duration_s
        return 1.0 - braking / T, -m / T, -rate / T

    @property
    def end_time(self) -> float:
        """When the plan comes to rest."""
        span = self.primitive.duration + self.stop_duration_s
        if self.wave is None:
            return self.t + span
        return self.wave.time_at(self.t, span, self.wave.share(self.primitive.speed))


class Planner:
    """Checks the library against the newest depth frames and chooses, every round."""

    def __init__(self, camera: PinholeCamera, options: PlannerOptions | None = None):
        check_camera(camera)
        o = options or PlannerOptions()
        self.camera = camera
        self.options = o
        # the height wave's arcs are checked with swept spheres (module docstring)
        self.history = DepthHistory(robot_radius=self._swept(o.robot_radius),
                                    min_confidence=o.min_confidence,
                                    max_range=o.max_range, max_frames=o.history_frames,
                                    max_age_s=o.history_s, near_tail_share=o.near_tail_share,
                                    far_tail_share=o.far_tail_share)
        self.tiers = [PrimitiveTier(speed, o) for speed in tier_speeds(o.primitives)]
        self.wave, self.height_wave = o.waves
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

    def plan(self, t: float, T_W_B, velocity_W, goal_W, stop_at_goal: bool = False) -> Plan:
        """The plan for the round at time ``t`` with the body at ``T_W_B`` moving at
        ``velocity_W`` (m/s), heading for ``goal_W`` (module docstring). ``stop_at_goal``: the
        vehicle is to stop there (the last waypoint, a sharp corner), so only tiers whose
        arc and braking end no farther than the goal are flown, the slowest always."""
        plan = self._plan(t, T_W_B, velocity_W, goal_W, stop_at_goal)
        return dataclasses.replace(plan, request=PlanRequest(
            np.array(T_W_B, dtype=float), np.array(velocity_W, dtype=float),
            np.array(goal_W, dtype=float), stop_at_goal))

    def _plan(self, t: float, T_W_B, velocity_W, goal_W, stop_at_goal: bool) -> Plan:
        t = _finite_time(t)
        T_W_S = _start_pose(T_W_B)
        velocity = _vector(velocity_W, "velocity_W")
        goal = _vector(goal_W, "goal_W")
        if not any(ft >= t - self.options.history_s for ft in self.history.times):
            return self._stop(t, T_W_S, velocity, "no depth")
        tiers = self.tiers
        if stop_at_goal:
            room = float(np.hypot(*(goal - T_W_S[:3, 3])[:2]))
            tiers = [tier for tier in tiers[:-1] if tier.reach <= room] + tiers[-1:]
        faster = []
        for tier in tiers:  # fastest first; a slower one only when nothing is safe
            check, T_W_L, height_wave, radius = self._check_tier(t, T_W_S, tier)
            safe, clearance, blocked = check
            if safe.any():
                break
            faster.append(FasterTier.of(tier.speed, check))
        else:
            faster.pop()  # the slowest tier's own candidates say why
            escape = self._escape(t, T_W_L, tier) if self._hemmed_in(t, T_W_L, tier) else None
            if escape is not None:
                radius, (safe, clearance, blocked) = escape
                radius = self._swept(radius)
            if not safe.any():  # why each primitive failed goes into the flight record
                return replace(self._stop(t, T_W_S, velocity, "no safe primitive"),
                               candidates=Candidates(tier.speed, tier.library, safe, -1,
                                                     blocked, radius, tuple(faster)))
        count = int(safe.sum())
        cost = np.where(safe, self._cost(tier, T_W_L[:3, 3], T_W_L[:3, :3], goal, clearance),
                        np.inf)
        i = int(np.argmin(cost))
        chosen = float(clearance[i])
        plan = Plan(t, T_W_L, tier.library[i], "arc", "", count, chosen,
                    self.options.stop_duration_s,
                    Candidates(tier.speed, tier.library, safe, i, blocked, radius,
                               tuple(faster)), wave=self.wave, height_wave=height_wave)
        self._previous = plan
        # on the same wave: a stop taking over from the arc goes on at the arc's speed
        self._checked_stop = Plan(t, T_W_L, tier.branches[i], "stop", "", count, chosen,
                                  self.options.stop_duration_s, wave=self.wave,
                                  height_wave=height_wave)
        return plan

    def _check_tier(self, t: float, T_W_S: np.ndarray, tier: "PrimitiveTier"
                    ) -> tuple[TierCheck, np.ndarray, HeightWave | None, float]:
        """``tier`` checked for the round at ``t`` from the body's start frame ``T_W_S``, and
        how its arcs are to be flown: ``(check, start frame, height wave, sphere's radius)``.
        On the height wave, about the line it swings about, with the swept spheres; where no
        arc clears the wave's crest and trough but one clears the level path, level from the
        body with the robot's own sphere (module docstring)."""
        T_W_L = self._wave_line(t, T_W_S)
        check = self.check(t, T_W_L, tier)
        if self.height_wave is not None and not check.safe.any():
            level = self.check(t, T_W_S, tier, level=True)
            if level.safe.any():  # too tight to swing at this speed: fly it level
                return level, T_W_S, None, self.options.robot_radius
        return check, T_W_L, self.height_wave, self._swept(self.options.robot_radius)

    def _wave_line(self, t: float, T_W_S: np.ndarray) -> np.ndarray:
        """The start frame of the line the height wave swings about at ``t``: ``T_W_S`` less
        the wave's height there (``T_W_S`` without a wave). An arc planned from it starts at
        the body, wherever on the wave the body is."""
        if self.height_wave is None:
            return T_W_S
        T_W_L = T_W_S.copy()
        T_W_L[2, 3] -= self.height_wave.offset(t, 1.0).height
        return T_W_L

    def check(self, t: float, T_W_S, tier: "PrimitiveTier | None" = None,
              radius: float | None = None, level: bool = False) -> TierCheck:
        """Every primitive of ``tier`` (default the fastest) and its branch, placed at the
        start frame ``T_W_S``, against the frames no older than ``t - history_s``, with the
        robot's sphere (or one of ``radius``, no larger); with a height wave, unless ``level``,
        at its crest and trough, the spheres swept (module docstring): ``safe``
        (P,) bool; ``clearance`` (P,) the least clearance along a safe one (metres between the
        sphere's far side and the surface behind it; inf where only rays judged it);
        ``blocked`` (P,) bool. An unsafe primitive's points are not all judged (the check
        stops at the first occupied one), so its clearance means nothing."""
        tier = self.tiers[0] if tier is None else tier
        R, start = T_W_S[:3, :3], T_W_S[:3, 3]
        points, groups = tier.points_S @ R.T + start, tier.primitive_of_point
        swing = 0.0 if level else self.options.height_swing
        radius = self.options.robot_radius if radius is None else radius
        if swing > 0.0:
            radius = self._swept(radius)
            points = np.vstack([points - [0.0, 0.0, swing], points + [0.0, 0.0, swing]])
            groups = np.concatenate([groups, groups])
        result = self.history.check(points, start_W=start, now=t, groups=groups, radius=radius)
        free, clearance, occupied = result.free, result.clearance, result.occupied
        if swing > 0.0:  # a point is free where both its crest and its trough are
            n = len(tier.points_S)
            free, occupied = free[:n] & free[n:], occupied[:n] | occupied[n:]
            clearance = np.fmin(clearance[:n], clearance[n:])
        return TierCheck(np.logical_and.reduceat(free, tier.starts),
                         np.fmin.reduceat(clearance, tier.starts),
                         np.logical_or.reduceat(occupied, tier.starts))

    def _swept(self, radius: float) -> float:
        """The radius of the spheres at the height wave's crest and trough that hold every
        sphere of ``radius`` between them: ``sqrt(radius² + A²)`` (``radius`` without a
        wave)."""
        return math.hypot(radius, self.options.height_swing)

    def _hemmed_in(self, t: float, T_W_S: np.ndarray, tier: "PrimitiveTier") -> bool:
        """Is a surface inside the robot's sphere about ``tier``'s probe (its straight arc's
        first point, a step ahead of the vehicle)?"""
        start = T_W_S[:3, 3]
        probe = T_W_S[:3, :3] @ tier.probe_S + start
        return bool(self.history.check(probe[None, :], start_W=start, now=t).occupied[0])

    def _escape(self, t: float, T_W_S: np.ndarray, tier: "PrimitiveTier"
                ) -> tuple[float, TierCheck] | None:
        """``tier`` checked with the largest sphere, in steps of :data:`ESCAPE_STEP_M` below
        ``robot_radius`` down to ``escape_radius``, with which an arc is safe (the last tried
        when none is); ``(radius, check)``, None when no step fits. Module docstring,
        "Hemmed in"."""
        o = self.options
        steps = int(math.floor((o.robot_radius - o.escape_radius) / ESCAPE_STEP_M + 1e-9))
        if steps == 0:
            return None
        for k in range(1, steps + 1):
            radius = o.robot_radius - k * ESCAPE_STEP_M
            check = self.check(t, T_W_S, tier, radius)
            if check.safe.any():
                break
        return radius, check

    def approach(self, t: float, T_W_B, goal_W) -> Plan | None:
        """:meth:`glide` to ``goal_W``, checked against the history as the arcs are (its points
        and braking); None when unsafe. For stopping at a corner or the goal precisely, where
        a narrow passage leaves no room to be off its axis, and the arcs cannot stop on a
        point."""
        plan = self.glide(t, T_W_B, goal_W, APPROACH_REASON)
        if plan is None:
            return None
        start, points = _glide_points(plan)
        result = self.history.check(points, start_W=start, now=plan.t,
                                    radius=self.options.robot_radius)
        if not result.free.all():
            return None
        plan = replace(plan, safe_count=1, clearance=float(np.min(result.clearance)))
        self._checked_stop = plan
        return plan

    def landing_glide(self, t: float, T_W_B, floor_z: float) -> Plan | None:
        """The :meth:`glide` to the nearest landing site ahead (landing.py) whose column,
        from the body's height down to the floor at height ``floor_z`` (frame W), the history
        judges free for spheres of ``landing_radius``, and whose way there
        :meth:`_glide_free_from_rest` frees; None when no site passes, or ``landing_radius``
        is 0."""
        radius = self.options.landing_radius
        if radius == 0.0:
            return None
        T_W_B = as_pose(T_W_B, "T_W_B")
        if not math.isfinite(floor_z):
            raise ValueError(f"floor_z must be finite, got {floor_z!r}")
        sites = candidate_sites(T_W_B[:3, 3], yaw_of(T_W_B[:3, :3]))
        columns = [column_points(site, floor_z, radius) for site in sites]
        if not any(len(column) for column in columns):
            return None  # the vehicle is lower than a column's lowest sphere
        groups = np.repeat(np.arange(len(sites)), [len(column) for column in columns])
        free = self.history.check(np.vstack(columns), now=t, groups=groups, radius=radius).free
        clear = np.bincount(groups, weights=~free, minlength=len(sites)) == 0
        for site in sites[clear]:
            glide = self.glide(t, T_W_B, site, LANDING_REASON)
            if self._glide_free_from_rest(glide):
                self._checked_stop = glide
                return glide
        return None

    def _glide_free_from_rest(self, glide: Plan) -> bool:
        """The points of ``glide`` (a glide begun at rest) beyond ``robot_radius`` from its
        start free, by the history's rule near the vehicle or, where that cannot tell
        (neither free nor occupied), by the ring rule (each is conservative, history.py);
        those nearer not occupied for spheres of ``landing_radius``. The vehicle stands
        there, on the stop the last round checked, so the robot's spheres there overlap its
        own, and a vehicle within ``2 robot_radius`` of a wall (any in a tunnel) finds them
        occupied; the smaller spheres keep the first metre clear of what is near the
        vehicle's body. The rule near the vehicle reads every pixel block its sphere meets,
        so a hovering vehicle's frames, all from where it stands, leave it unknown wherever a
        block holds one unknown pixel (the sky over the dome): hence the ring rule after it."""
        start, points = _glide_points(glide)
        own = np.linalg.norm(points - start, axis=1) <= self.options.robot_radius
        body = self.history.check(points[own], start_W=start, now=glide.t,
                                  radius=self.options.landing_radius)
        if body.occupied.any():
            return False
        away = points[~own]
        radius = self.options.robot_radius  # a glide flies level: the robot's own sphere
        near = self.history.check(away, start_W=start, now=glide.t, radius=radius)
        retry = ~near.free & ~near.occupied
        return not near.occupied.any() and bool(
            self.history.check(away[retry], now=glide.t, radius=radius).free.all())

    def glide(self, t: float, T_W_B, goal_W, reason: str,
              stop_at_goal: bool = True) -> Plan | None:
        """A straight glide from the body at ``T_W_B`` to come to rest at ``goal_W``, heading
        held: horizontally at no more than the slowest tier's speed ``u``, cruise then brake
        over ``stop_duration_s`` (``u T / 2``), slower when the goal is nearer than that;
        vertically at the constant rate ``c`` (then braking with the rest) that ends at the
        goal's height, at most ``max_vertical_speed``. It starts at its speed: from rest, the
        autopilot's velocity loop takes it up. With ``stop_at_goal`` False it cruises at
        ``u`` through ``goal_W`` and brakes after it (kind "glide"): a run along a path,
        replaced every round by the glide toward the next point of it, that brakes once, at
        the path's end. None when already there. Unchecked: :meth:`approach` checks it."""
        t = _finite_time(t)
        T_W_B = as_pose(T_W_B, "T_W_B")
        start = T_W_B[:3, 3]
        offset = _vector(goal_W, "goal_W") - start
        distance = float(np.hypot(offset[0], offset[1]))
        if distance < 1e-3 and abs(offset[2]) < 1e-3:
            return None
        o = self.options
        slowest = self.tiers[-1].speed
        braking = slowest * o.stop_duration_s / 2.0 if stop_at_goal else 0.0
        speed = slowest if distance >= braking else 2.0 * distance / o.stop_duration_s
        cruise_s = max(0.0, distance - braking) / max(speed, 1e-9)
        climb_s = cruise_s + (o.stop_duration_s / 2.0 if stop_at_goal else 0.0)
        climb = float(np.clip(offset[2] / max(climb_s, 1e-9),
                              -o.max_vertical_speed, o.max_vertical_speed))
        heading = math.atan2(offset[1], offset[0]) if distance >= 1e-3 else yaw_of(T_W_B[:3, :3])
        T_W_S = make_pose(rot_z(heading), start)
        primitive = (forward_arc(speed, 0.0, climb, o.primitives, cruise_s) if cruise_s > 0.0
                     else stop_primitive(np.array([speed, 0.0, climb]), o.primitives))
        return Plan(t, T_W_S, primitive, "stop" if stop_at_goal else "glide", reason, 0,
                    math.nan, o.stop_duration_s)

    def stop_plan(self, t: float, T_W_B, velocity_W, reason: str,
                  held: Plan | None = None) -> Plan:
        """The stop for the application's failsafes: the stop checked at the last round,
        continued, while it has not run out; else braking from ``velocity_W``. ``held``: the
        stop the application holds as its checked one, taken when newer than the last
        round's (a glide to rest that a behaviour flies: after a backing-off's glides, the
        last round's stop lies at the dead end it left)."""
        if not isinstance(reason, str) or not reason:
            raise ValueError(f"a stop needs a reason, got {reason!r}")
        if held is not None and (self._checked_stop is None or held.t > self._checked_stop.t):
            self._checked_stop = held
        return self._stop(_finite_time(t), _start_pose(T_W_B),
                          _vector(velocity_W, "velocity_W"), reason)

    def stop_afresh(self, t: float, T_W_B, velocity_W, reason: str) -> Plan:
        """A stop braking from ``velocity_W`` at ``t``, continued by the stops after it in
        place of the one checked before: for a vehicle about to turn in place, at rest or
        nearly. The stop checked before the turn continues the last arc for a period and brakes
        along it from the speed it had then; flown after the turn (or by a failsafe during it)
        it would carry the vehicle on toward what blocked it, ahead of where it came to rest
        (a collision in the navigation benchmark, docs/flight.md, "Blocked: turn, then back
        off")."""
        self._checked_stop = None
        return self.stop_plan(t, T_W_B, velocity_W, reason)

    def _stop(self, t: float, T_W_S: np.ndarray, velocity: np.ndarray, reason: str) -> Plan:
        stop = self._checked_stop
        if stop is not None and stop.t <= t and (t < stop.end_time or np.linalg.norm(
                stop.setpoint(t).position_W - T_W_S[:3, 3]) <= self.options.robot_radius):
            return replace(stop, reason=reason, safe_count=0)
        # Braking from the present velocity, kept and continued by the next rounds: braking
        # begun afresh every round from the velocity then would never come to rest, and a
        # stop begun afresh where the vehicle has crept to would let it creep on.
        velocity_S = T_W_S[:3, :3].T @ velocity
        self._checked_stop = Plan(t, T_W_S, stop_primitive(velocity_S, self.options.primitives),
                                  "stop", reason, 0, math.nan, self.options.stop_duration_s)
        return self._checked_stop

    def _cost(self, tier: "PrimitiveTier", start: np.ndarray, R: np.ndarray, goal: np.ndarray,
              clearance: np.ndarray) -> np.ndarray:
        """The cost ``J`` of the module docstring for every primitive of ``tier``."""
        o = self.options
        ends = tier.ends_S @ R.T + start
        stretch = np.array([1.0, 1.0, self._height_stretch(tier)])
        progress = (np.linalg.norm((start - goal) * stretch)
                    - np.linalg.norm((ends - goal) * stretch, axis=1))
        cost = -o.progress_weight * progress / (tier.speed * o.duration_s)
        if self._previous is not None:
            change = np.zeros(len(cost))
            if o.max_yaw_rate_deg > 0.0:
                w0 = self._previous.primitive.yaw_rate
                change += ((tier.yaw_rates - w0) / math.radians(o.max_yaw_rate_deg)) ** 2
            if o.max_vertical_speed > 0.0:
                c0 = self._previous.primitive.vertical_speed
                change += ((tier.vertical_speeds - c0) / o.max_vertical_speed) ** 2
            cost += o.smoothness_weight * change
        near = np.clip(1.0 - clearance / o.clearance_wanted, 0.0, 1.0)
        return cost + o.clearance_weight * near

    def _height_stretch(self, tier: "PrimitiveTier") -> float:
        """``k`` of the progress term: metres of ground per metre of height to the goal."""
        o = self.options
        if not o.height_gap_in_time:
            return 1.0
        # With no climb in the library no arc closes a height gap: it costs every arc alike.
        return tier.speed / o.max_vertical_speed if o.max_vertical_speed > 0.0 else 0.0


class PrimitiveTier:
    """The library at one speed, ready to check: ``library`` its arcs, ``branches`` each
    arc's "one period, then brake" branch, and every point checked per primitive, stacked:
    the arc (less its start, the vehicle's own sphere), its extension, then the branch's
    braking (``points_S``, primitive ``i``'s from ``starts[i]``). The branch's own short arc
    is the first piece of the arc, so it is checked as the arc is, at the arc's samples (its
    end point, a few centimetres ahead at a slow tier, would sit beside or behind the camera,
    where no frame can see it)."""

    def __init__(self, speed: float, options: PlannerOptions):
        shape = options.primitives
        self.speed = speed
        self.library = library(shape, speed)
        self.branches = [forward_arc(a.speed, a.yaw_rate, a.vertical_speed, shape,
                                     options.period_s) for a in self.library]
        groups = [np.vstack([a.points_S[1:], a.stop_points_S, b.stop_points_S])
                  for a, b in zip(self.library, self.branches)]
        self.points_S = np.vstack(groups)
        self.starts = np.cumsum([0] + [len(g) for g in groups[:-1]])
        self.primitive_of_point = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
        self.ends_S = np.array([a.points_S[-1] for a in self.library])
        straight = int(np.argmin([abs(a.yaw_rate) + abs(a.vertical_speed)
                                  for a in self.library]))
        #: Where the room about a hemmed-in vehicle is measured: the straight arc's first point.
        self.probe_S = self.points_S[self.starts[straight]]
        #: How far ahead the straight arc comes to rest: its length and braking, v (D + T / 2).
        self.reach = speed * (options.duration_s + options.stop_duration_s / 2.0)
        self.yaw_rates = np.array([a.yaw_rate for a in self.library])
        self.vertical_speeds = np.array([a.vertical_speed for a in self.library])


def _glide_points(glide: Plan) -> tuple[np.ndarray, np.ndarray]:
    """``glide``'s start and the points it is checked at (frame W): the arc less its
    start, the vehicle's own sphere, then its braking."""
    start = glide.T_W_S[:3, 3]
    points_S = np.vstack([glide.primitive.points_S[1:], glide.primitive.stop_points_S])
    return start, points_S @ glide.T_W_S[:3, :3].T + start


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
