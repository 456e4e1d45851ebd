"""What the vehicle does beside following the planner's arcs (docs/flight.md):

- **Offset swing.** Before navigating, while the camera's time offset is not yet known, the
  vehicle yaws to and fro in place: the offset shows only in a change of the angular
  velocity, and with none before the cruise it was first estimated as the vehicle pitched
  into it, too late for the scale the VINS sets there (:class:`OffsetSwing`).
- **Turn at a corner.** At a stop waypoint just passed, or with the next waypoint far off the
  heading, the vehicle comes to rest and turns in place to face it: the arcs would sweep wide.
- **Parallax glide.** After the turn the view is new, and a monocular VINS has no landmarks in
  it until the camera moves sideways: no anchors, no metric depth, no arc checked, and a pose
  that is the IMU's alone. The vehicle glides back to the trail point half a metre behind and
  returns to the corner, the camera moving across its view. A long turn is paused for the
  glide when the landmarks run low, and goes on after it.
- **Regaining depth.** With no fresh fit for half the staleness timeout on the arcs, the
  vehicle brakes on the stop checked at the last round and glides for parallax, once per
  lapse, the staleness failsafe waiting meanwhile.
- **Approach.** Near a stop waypoint and slow, it glides straight to the point when that is
  checked safe (the arcs cannot stop on a point, and a narrow passage leaves no room off its
  axis).
- **Blocked.** With no safe primitive, at rest: first one turn in place toward the waypoint (the
  arcs only turn while moving on), then, blocked for half the no-path time, backing off along
  the flown trail to see the place from farther back; at most ``max_backoffs`` times a
  waypoint. With no way back left (none flown yet, as just after take-off, or the backings-off
  spent), it looks aside: a turn in place to :data:`LOOK_ASIDE` off the waypoint's bearing,
  the less blocked side first, then the other, for a view the arcs can turn into. Then the
  no-path failsafe.

Each is a small rule or state machine here; :mod:`companion.flight.navigation` runs them with
the planner on its worker.
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple

import numpy as np

from autonomy.navigation.trail import GLIDE_STEP_M, Trail
from autonomy.planning.planner import APPROACH_REASON

#: Blocked with no way back: the angle off the waypoint's bearing looked at on each side. A
#: pole dead ahead of the take-off (the dome's pair 4, seed 3) left every arc of a view aimed
#: at the waypoint blocked or unseen; looking 45 degrees left, both depth sources' flights
#: reached the goal (docs/flight.md).
LOOK_ASIDE = math.radians(45.0)
#: After a turn: how long without a fresh fit before the parallax glide starts, seconds.
PARALLAX_WAIT_S = 0.3
#: After a turn: with fewer VINS landmarks in front of the camera than this, the parallax glide
#: starts even with a fresh fit (true depth needs no anchors, so its fit never lapses). A
#: quarter of the window's 80-landmark budget, of which cruise keeps 40 in view; a realistic
#: mine flight on true depth turned 126 degrees in place, flew on with 0-8 landmarks, and
#: dead-reckoned 4.6 m off before "VINS blind" (docs/results.md).
PARALLAX_LANDMARKS = 20
#: A corner's turn in place is paused for the parallax glide once it has turned this far and
#: the VINS's landmarks are starved (:func:`pause_turn`), radians.
TURN_STEP = math.radians(30.0)
#: The reasons the glides' plans carry (what the failsafe checks and the logs read).
PARALLAX_REASON = "gliding for parallax"
BACKOFF_REASON = "backing off along the trail"
#: The reason of the stop a corner's turn begins with. It brakes on the stop the last
#: planning round checked (or from the present velocity where none is left), so it needs no
#: new depth: while it lasts (:func:`on_glide`) the staleness failsafe waits, as it does
#: through the turn and the glides after it (a turn in the dome's open space can leave the view
#: without landmarks before the vehicle is at rest); once it has run out, it no longer waits
#: for a vehicle that does not come to rest.
TURN_STOP_REASON = "stopping to turn to the next waypoint"
#: The reason of the stop in force through a turn in place and after it until the next plan:
#: braking afresh from the velocity where the turn begins (at rest, or nearly), in place of
#: the stop checked before (:meth:`~autonomy.planning.planner.Planner.stop_afresh`).
TURN_HOLD_REASON = "holding where it turns"
#: The reason of the stop begun when the depth fit lapses on the arcs (:func:`depth_lapsed`):
#: like the corner's, it brakes on the stop the last round checked, and the staleness failsafe
#: waits while it lasts and through the parallax glide after it.
DEPTH_STOP_REASON = "stopping to regain metric depth"
#: The reason of the stop at the goal (and of the transition to STOPPING). It brakes on the
#: stop the last round checked, so it needs no new depth either: a realistic mine flight (pair
#: 3, seed 0, estimated depth) reached its goal with the view starved and got "no metric depth"
#: 0.02 s into this stop, a failsafe's hold before the landing instead of the landing.
GOAL_STOP_REASON = "goal reached"
#: The glides and stops over ground flown or checked, on which depth may lapse
#: (:meth:`companion.flight.navigation.Navigation.on_flown_ground`).
FLOWN_GROUND_REASONS = (PARALLAX_REASON, BACKOFF_REASON, TURN_STOP_REASON, TURN_HOLD_REASON,
                        DEPTH_STOP_REASON, GOAL_STOP_REASON)


def on_glide(plan, reason: str, now: float) -> bool:
    """Is ``plan`` a glide (or the turn's stop) for ``reason`` that has not come to rest by
    ``now``?"""
    return plan is not None and plan.reason == reason and now < plan.end_time


def must_turn(corner_pending: bool, heading_error: float, plan, options) -> bool:
    """Turn in place before planning on: a corner was just passed, or the next waypoint is
    more than ``align_threshold_deg`` off the heading while not on an approach glide (near the
    point, the bearing to it swings wildly)."""
    approaching = plan is not None and plan.reason == APPROACH_REASON
    return corner_pending or (abs(heading_error) > math.radians(options.align_threshold_deg)
                              and not approaching)


def still_turning(heading_error: float, options) -> bool:
    """Is the heading error beyond ``align_done_deg`` (a turn in place is due)?"""
    return abs(heading_error) > math.radians(options.align_done_deg)


def facing(heading_error: float, options) -> bool:
    """Is the heading error within ``align_done_deg`` (a turn in place is done)?"""
    return abs(heading_error) < math.radians(options.align_done_deg)


def turn_rate(heading_error: float, options) -> float:
    """Yaw rate of a turn in place toward a heading ``heading_error`` away, rad/s."""
    return math.copysign(math.radians(options.align_yaw_rate_deg), heading_error)


def approach_targets(goal_W: np.ndarray, position_W: np.ndarray, speed: float, *,
                     stop_here: bool, is_goal: bool, slowest_speed: float,
                     options) -> list[np.ndarray]:
    """Where to try gliding, in order, near a stop waypoint ``goal_W``: none unless it is one,
    within ``approach_distance`` horizontally, and the vehicle no faster than the slowest
    tier plus ``stopped_speed``. A corner exactly; the goal half ``goal_tolerance`` short of
    it, then 0.9 of it (horizontally, at its height), since a goal near a wall may leave no
    room for the robot's sphere on the point."""
    offset = goal_W - position_W
    distance = float(np.hypot(offset[0], offset[1]))
    if not stop_here or distance > options.approach_distance \
            or speed > slowest_speed + options.stopped_speed:
        return []
    targets = []
    for short in ((0.5, 0.9) if is_goal else (0.0,)):
        target = goal_W.copy()
        if short > 0.0 and distance > 0.0:
            target[:2] -= offset[:2] * (min(distance, short * options.goal_tolerance)
                                        / distance)
        targets.append(target)
    return targets


def offset_unknown(offset, max_sigma_s: float) -> bool:
    """Is the VINS's camera-IMU time offset (a :class:`~autonomy.vins.time_offset.TimeOffset`)
    estimated online and not yet shown by the motion, its sigma None or above
    ``max_sigma_s`` (``[vins] time_offset_max_sigma_s``)?"""
    return offset.estimating and (offset.sigma is None or offset.sigma > max_sigma_s)


class OffsetSwing:
    """The yaw swing in place that shows the camera's time offset before navigating.

    The heading follows ``psi(t) = A sin(2 pi t / T)`` (``A`` ``offset_swing_deg``, ``T``
    ``offset_swing_period_s``, ``t`` from the swing's start): the yaw rate
    ``A (2 pi / T) cos(2 pi t / T)`` changes all the time, which is what shows the offset
    (:mod:`autonomy.vins.time_offset`: a frame pair informs it by the change of the angular
    velocity between its ends; hovering or a steady turn, not at all). Once the offset is
    known the swing goes on to the next time the heading is back where it began (a multiple
    of ``T / 2``), so navigation starts facing as it was; it ends unknown after
    ``offset_swing_timeout_s``. Why (docs/vins.md, "The error at the end of navigation,
    split"): without it the offset's first estimate came as the vehicle pitched into its
    cruise, and the scale the VINS set over that first second and a half, from frames fitted
    15 ms off, stayed 1-17 % short for the flight."""

    def __init__(self, options):
        self.options = options
        self.end_s: float | None = None  # when the swing ends, once the offset is known

    def rate(self, elapsed_s: float) -> float:
        """The yaw rate ``elapsed_s`` into the swing, rad/s."""
        o = self.options
        omega = 2.0 * math.pi / o.offset_swing_period_s
        return math.radians(o.offset_swing_deg) * omega * math.cos(omega * elapsed_s)

    def over(self, elapsed_s: float, known: bool) -> bool:
        """Is the swing over, ``elapsed_s`` into it, the offset ``known`` (class docstring)?"""
        o = self.options
        if known and self.end_s is None:
            half = o.offset_swing_period_s / 2.0
            self.end_s = half * math.ceil(elapsed_s / half)
        if self.end_s is not None:
            return elapsed_s >= self.end_s
        return elapsed_s >= o.offset_swing_timeout_s


class Step(enum.Enum):
    """What a glide behaviour wants this round."""

    IDLE = "idle"  # not active: decide otherwise
    KEEP = "keep"  # on its present glide: plan nothing


def depth_lapsed(fit_age_s: float, options) -> bool:
    """No fresh fit for half ``depth_timeout_s`` on the arcs: a corner flown on an arc swung
    the view to one with too few anchors, and flying on, the staleness failsafe would come
    (four realistic estimated-depth flights ended so, docs/results.md). Time to stop and glide
    for parallax, as after a turn in place."""
    return fit_age_s > 0.5 * options.depth_timeout_s


def view_starved(fit_age_s: float, landmarks: int | None) -> bool:
    """Does the view after a turn want the parallax glide: no fresh fit for
    :data:`PARALLAX_WAIT_S` (a held fit does not count), or fewer than
    :data:`PARALLAX_LANDMARKS` VINS landmarks (None: no VINS update yet, not counted)?"""
    return fit_age_s > PARALLAX_WAIT_S or (landmarks is not None
                                           and landmarks < PARALLAX_LANDMARKS)


def pause_turn(turned: float, landmarks: int | None) -> bool:
    """Pause a corner's turn in place, ``turned`` radians into it, for the parallax glide:
    at least :data:`TURN_STEP` turned and fewer than :data:`PARALLAX_LANDMARKS` VINS
    landmarks. A turn in place gives new tracks no parallax, so a long one leaves the VINS no
    landmark: a 126-degree turn in a realistic mine flight did, and once the VINS had
    dead-reckoned for a second its drifting poses triangulated none, glide or not
    (docs/results.md). Paused while it still holds some, the glide rebuilds them; the step
    keeps the turn going when it began starved."""
    return turned >= TURN_STEP and landmarks is not None and landmarks < PARALLAX_LANDMARKS


class ParallaxGlide:
    """Back to the trail point :data:`~autonomy.navigation.trail.GLIDE_STEP_M` behind the
    turning point, then to the turning point again, each a straight glide to rest; given up
    before it starts when the view is not :func:`view_starved` (the anchors and landmarks
    came back by themselves)."""

    def __init__(self):
        self.reason = PARALLAX_REASON
        self.targets: list[np.ndarray] = []

    @property
    def active(self) -> bool:
        return bool(self.targets)

    def start(self, trail: Trail, position_W: np.ndarray) -> None:
        """Arm the glides from ``position_W`` at rest after a turn (none without a trail
        point far enough behind)."""
        back = trail.point_behind(position_W)
        if back is not None:
            self.targets = [back, position_W.copy()]

    def step(self, plan, now: float, starved: bool) -> Step | np.ndarray:
        """The next target, :attr:`Step.KEEP` while gliding, :attr:`Step.IDLE` when done;
        ``starved``: :func:`view_starved` now."""
        if not self.targets:
            return Step.IDLE
        started = len(self.targets) < 2
        if not started and not starved:
            self.targets.clear()
            return Step.IDLE
        if started and on_glide(plan, self.reason, now):
            return Step.KEEP
        return self.targets.pop(0)


class BackoffMove(NamedTuple):
    """A backing-off round's glide: toward ``target``, through it (``stop`` False) or to rest
    on it (True, the way back's end)."""

    target: np.ndarray
    stop: bool


class Backoff:
    """Backing off along the flown trail from a dead end, ``backoff_distance`` at a time, at
    most ``max_backoffs`` times per waypoint (``count`` is reset when one is passed).

    The way back is one run that brakes once, at its end. Every round glides on, without
    braking, toward the first point of the way at least :data:`PURSUIT_M` from the vehicle
    (pure pursuit, from the point of the way nearest it); with no more than
    the glides' braking distance of the way left, it glides to the end and comes to rest
    there. Every stop costs ``stop_duration_s`` whatever the distance before
    it: the half-metre glides from rest to rest this replaced took 8 s for 2 m, one run takes
    5 s (docs/results.md, "Where mine pair 2's time goes"). Unchecked: the ground is the
    vehicle's own trail, behind the camera."""

    #: How far ahead the glides aim, metres: a sharp corner of the trail (a turn in place) is
    #: cut by about half of it (0.12 m at 90 degrees), a smooth one by millimetres.
    PURSUIT_M = 0.25
    #: How many points of the way past the nearest one the next nearest is searched among: a
    #: metre of trail, far more than a round's flight.
    SEARCH_POINTS = 10

    def __init__(self):
        self.reason = BACKOFF_REASON
        self.count = 0
        self.way: np.ndarray | None = None
        self.run = np.zeros(0)
        self.nearest = 0
        self.braking = False
        self.deadline: float | None = None

    @property
    def active(self) -> bool:
        return self.way is not None

    def start(self, trail: Trail, position_W: np.ndarray, options) -> bool:
        """Arm a backing-off from ``position_W``; False when none is left for this waypoint
        or the trail has no way back."""
        if self.count >= options.max_backoffs:
            return False
        way = trail.way_back(position_W, options.backoff_distance)
        if way is None:
            return False
        self.count += 1
        self.way, self.nearest, self.braking, self.deadline = way, 0, False, None
        self.run = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(way, axis=0),
                                                                   axis=1))])
        return True

    def step(self, plan, now: float, position_W: np.ndarray, speed: float,
             braking_m: float) -> Step | BackoffMove:
        """This round's glide from ``position_W``, :attr:`Step.KEEP` while braking to the
        way's end, :attr:`Step.IDLE` when not backing off (any more). ``speed``: the glides'
        (the slowest tier's); ``braking_m``: their braking distance (``speed T / 2``). A run that has taken twice as long as the way at ``speed``
        (the vehicle held back, or its estimate drifting) comes to rest on the nearest point
        of the way instead: the staleness failsafe waits while it lasts."""
        if self.way is None:
            return Step.IDLE
        if self.braking:
            if on_glide(plan, self.reason, now):
                return Step.KEEP
            self.way = None
            return Step.IDLE
        if self.deadline is None:
            self.deadline = now + 2.0 * self.run[-1] / speed
        way = self.way
        window = way[self.nearest:self.nearest + self.SEARCH_POINTS + 1]
        self.nearest += int(np.argmin(np.linalg.norm(window - position_W, axis=1)))
        if now > self.deadline:
            self.braking = True
            return BackoffMove(way[self.nearest].copy(), stop=True)
        distances = np.linalg.norm(way[self.nearest:] - position_W, axis=1)
        left = distances[0] + self.run[-1] - self.run[self.nearest]
        ahead = np.flatnonzero(distances >= self.PURSUIT_M)
        if left <= braking_m or not len(ahead):
            self.braking = True
            return BackoffMove(way[-1].copy(), stop=True)
        return BackoffMove(way[self.nearest + ahead[0]].copy(), stop=False)


class Blocked(enum.Enum):
    """What a round with no safe primitive leads to."""

    WAIT = "wait"  # braking, or the no-path clock still running
    TURN = "turn"  # at rest, not facing the waypoint: turn in place once
    BACK_OFF = "back_off"  # at rest, facing it, blocked for half the no-path time


class NoPathClock:
    """How long the planner has found no safe primitive, whether the one turn in place toward
    the waypoint it allows has been made, and the looks aside made (``aim``: the heading
    aimed at, radians off the waypoint's bearing); all reset by a safe plan."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.since: float | None = None
        self.turned = False
        self.looks: list[float] = []

    def restart(self) -> None:
        """A stop by choice (a corner's turn, the parallax glide): the clock does not run
        through it and starts again at the next blocked round, the turn and the looks made
        kept. A glide for parallax right after a corner's turn, beside a pillar that blocked
        every arc, ran the clock out before the back-off's half of it could come (realistic
        sewer pair 1, seed 2, estimated depth: docs/results.md)."""
        self.since = None

    @property
    def aim(self) -> float:
        """The heading aimed at, radians off the waypoint's bearing: the last look's, else 0."""
        return self.looks[-1] if self.looks else 0.0

    def blocked(self, now: float, stopped: bool, heading_error: float, options) -> Blocked:
        """A stop round at ``now``: start the clock, and say what to do. ``heading_error``:
        from the heading to the one aimed at."""
        self.since = self.since if self.since is not None else now
        if not stopped:
            return Blocked.WAIT
        if not self.turned and still_turning(heading_error, options):
            self.since, self.turned = None, True
            return Blocked.TURN
        if now - self.since >= options.no_path_timeout_s / 2.0:
            return Blocked.BACK_OFF
        return Blocked.WAIT

    def look_aside(self, candidates) -> float | None:
        """With no way back: the next heading to look from (radians off the waypoint's
        bearing, now :attr:`aim`; the clock starts again), or None when both sides have been
        looked at. First the side whose arcs the last round found less blocked by observed
        surfaces (``candidates``: its :class:`~autonomy.planning.planner.Candidates`, None:
        left first), then the other."""
        if len(self.looks) == 2:
            return None
        if not self.looks:
            left = self._left_is_freer(candidates)
            self.looks.append(LOOK_ASIDE if left else -LOOK_ASIDE)
        else:
            self.looks.append(-self.looks[0])
        self.since = None
        return self.aim

    @staticmethod
    def _left_is_freer(candidates) -> bool:
        if candidates is None:
            return True
        yaw_rates = np.array([p.yaw_rate for p in candidates.primitives])
        blocked = np.asarray(candidates.blocked, dtype=bool)
        return int(blocked[yaw_rates > 0.0].sum()) <= int(blocked[yaw_rates < 0.0].sum())

    def expired(self, now: float, options) -> bool:
        """Blocked for longer than ``no_path_timeout_s``: the failsafe."""
        return self.since is not None and now - self.since > options.no_path_timeout_s
