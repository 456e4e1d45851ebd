"""The flight state machine and its failsafe rules (DESIGN.md, "Flight behaviour").

Pure bookkeeping, no I/O and no clock of its own: the application passes the time in. A flight
goes

    PREFLIGHT -> INITIALISING -> TAKING_OFF -> ENTERING_OFFBOARD [-> CALIBRATING]
              -> NAVIGATING -> STOPPING (goal reached) -> LANDING -> LANDED

(CALIBRATING: the yaw swing in place that shows the camera's time offset, while it is
estimated and not yet known: :class:`autonomy.navigation.behaviours.OffsetSwing`.)

and whatever goes wrong in the air takes the safe way down:

    any airborne state --failsafe--> FAILSAFE_STOP (follow the stop primitive checked at the
    last planning round) [-> TO_LANDING_SITE] -> HOLDING (PX4 Hold)
    -> LANDING -> LANDED

A failsafe is terminal for the mission: the vehicle stops, holds for ``hold_before_land_s``
and lands. After a failsafe that leaves the vehicle and its sensing sound
(:data:`SITE_SEEKING_FAILSAFES`) it first glides to a landing site ahead seen clear to the
floor, when there is one (:mod:`autonomy.planning.landing`); else it lands where it is. On
the ground, a failed step ends in ABORTED. Every transition is kept with its time and reason,
and logged.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

from autonomy.options import OptionError, option, validate

log = logging.getLogger(__name__)


#: Fastest yaw rate an offset swing may command, degrees per second: three times the 30 deg/s
#: of a turn in place, which a 10 degree swing of 2 s (the one measured) matches at its peak.
MAX_SWING_RATE_DEG = 90.0


@dataclass(frozen=True)
class FlightOptions:
    """The mission and its failsafe thresholds (the ``[flight]`` table)."""

    waypoints: tuple[str, ...] = option(
        (), doc="the mission of `companion fly`: points 'x,y,z' in metres in PX4's local frame "
                "(x east, y north, z up from its origin), flown in order; the last is the goal")
    takeoff_altitude: float = option(1.5, gt=0.2, le=50.0,
                                     doc="take-off height above the ground, metres")
    goal_tolerance: float = option(1.5, gt=0.0, le=10.0,
                                   doc="horizontal distance to the goal that counts as "
                                       "reached, metres")
    waypoint_tolerance: float = option(2.0, gt=0.0, le=20.0,
                                       doc="horizontal distance at which a waypoint counts as "
                                           "passed, metres")
    height_tolerance: float = option(1.0, gt=0.0, le=10.0,
                                     doc="height difference a reached goal may have (the "
                                         "tolerances above are horizontal), metres")
    corner_turn_deg: float = option(
        60.0, gt=0.0, le=180.0,
        doc="a waypoint where the route turns by more than this is a corner: approached "
            "slowly, stopped at, and the next leg faced in place, degrees")
    corner_tolerance: float = option(0.5, gt=0.0, le=5.0,
                                     doc="horizontal distance at which a corner counts as "
                                         "reached, metres")
    approach_distance: float = option(
        4.0, ge=0.0, le=20.0,
        doc="within this distance of a corner or the goal the vehicle glides straight to it "
            "at the slowest tier's speed when that is safe, metres (0: never)")
    backoff_distance: float = option(
        2.0, ge=0.0, le=5.0,
        doc="blocked at rest facing the next waypoint: glide back this far along the flown "
            "trail and try again from there, metres (0: never)")
    max_backoffs: int = option(2, ge=0, le=10,
                               doc="backings-off per waypoint before the no-path failsafe")
    align_threshold_deg: float = option(
        90.0, gt=0.0, le=180.0,
        doc="heading error to the next waypoint that makes the vehicle turn in place first, "
            "degrees")
    align_done_deg: float = option(15.0, gt=0.0, le=90.0,
                                   doc="heading error at which turning in place ends, degrees")
    align_yaw_rate_deg: float = option(30.0, gt=0.0, le=180.0,
                                       doc="yaw rate of a turn in place, degrees per second")
    offset_swing_deg: float = option(
        0.0, ge=0.0, le=45.0,
        doc="before navigating, while the camera's time offset is estimated and not yet known, "
            "yaw in place this far to each side and back until it is, degrees (0: never, the "
            "default; 10 measured, docs/vins.md)")
    offset_swing_period_s: float = option(2.0, ge=0.5, le=20.0,
                                          doc="period of the offset swing, seconds")
    offset_swing_timeout_s: float = option(
        10.0, gt=0.0, le=120.0,
        doc="longest offset swing: navigation starts after it, the offset known or not, s")
    setpoint_rate_hz: float = option(30.0, ge=20.0, le=50.0,
                                     doc="offboard velocity setpoints per second (PX4: > 2)")
    tracking_gain: float = option(
        1.0, ge=0.0, le=5.0,
        doc="velocity added per metre between the plan's position and the VINS position, 1/s "
            "(0: velocity and acceleration feed-forward alone)")
    max_tracking_speed: float = option(0.5, ge=0.0, le=2.0,
                                       doc="largest tracking correction, m/s")
    odometry_rate_hz: float = option(30.0, ge=1.0, le=50.0,
                                     doc="ODOMETRY messages to PX4 per second")
    monitor_rate_hz: float = option(20.0, gt=0.0, le=200.0,
                                    doc="failsafe checks (and loop-lag probes) per second")
    setpoint_deadline_s: float = option(
        0.25, gt=0.0, le=2.0,
        doc="a setpoint older than this is replaced by the stop, by the watchdog thread")
    camera_timeout_s: float = option(0.5, gt=0.0, le=10.0,
                                     doc="no camera frame for this long is a failsafe, seconds")
    imu_timeout_s: float = option(0.25, gt=0.0, le=10.0,
                                  doc="no IMU sample for this long is a failsafe, seconds")
    depth_timeout_s: float = option(1.0, gt=0.0, le=10.0,
                                    doc="no metric depth for this long is a failsafe, seconds")
    no_path_timeout_s: float = option(
        3.0, gt=0.0, le=30.0,
        doc="the planner finding no safe primitive for this long is a failsafe, seconds")
    blind_landmarks: int = option(
        5, ge=0, le=1000,
        doc="with fewer VINS landmarks than this the vehicle flies blind: its pose is IMU "
            "propagation alone")
    blind_timeout_s: float = option(
        3.0, gt=0.0, le=30.0,
        doc="flying blind for this long (turns in place not counted) is a failsafe, seconds")
    max_loop_lag_s: float = option(0.3, gt=0.0, le=10.0,
                                   doc="event-loop lag above this is a failsafe, seconds")
    stopped_speed: float = option(0.2, gt=0.0, le=2.0,
                                  doc="speed under which a stopping vehicle counts as stopped")
    stop_timeout_s: float = option(3.0, gt=0.0, le=30.0,
                                   doc="longest a stop may take before PX4 Hold, seconds")
    hold_before_land_s: float = option(2.0, ge=0.0, le=120.0,
                                       doc="time in Hold after a failsafe before landing, s")
    preflight_timeout_s: float = option(15.0, gt=0.0, le=300.0,
                                        doc="longest wait for link, IMU and camera, seconds")
    init_timeout_s: float = option(20.0, gt=0.0, le=300.0,
                                   doc="longest wait for the VINS static initialisation, s")
    takeoff_timeout_s: float = option(20.0, gt=0.0, le=300.0,
                                      doc="longest a take-off may take, seconds")
    land_timeout_s: float = option(30.0, gt=0.0, le=600.0,
                                   doc="longest wait for landing and disarm, seconds")
    mission_timeout_s: float = option(300.0, gt=0.0, le=36000.0,
                                      doc="longest navigation before a failsafe, seconds")

    def __post_init__(self) -> None:
        validate(self)
        for text in self.waypoints:
            parse_point(text, "waypoints")
        peak = self.offset_swing_deg * 2.0 * math.pi / self.offset_swing_period_s
        if peak > MAX_SWING_RATE_DEG:
            raise OptionError("offset_swing_deg", f"with offset_swing_period_s = "
                              f"{self.offset_swing_period_s} the swing peaks at {peak:.0f} "
                              f"deg/s, above {MAX_SWING_RATE_DEG:.0f} (2 pi A / T)")
        if self.offset_swing_timeout_s < self.offset_swing_period_s / 2.0:
            raise OptionError("offset_swing_timeout_s", "must be at least half of "
                              f"offset_swing_period_s ({self.offset_swing_period_s / 2.0} s), "
                              f"got {self.offset_swing_timeout_s}")

    def waypoint_points(self) -> list[tuple[float, float, float]]:
        """The waypoints as (x, y, z) tuples, metres."""
        return [parse_point(text, "waypoints") for text in self.waypoints]


def parse_point(text: str, key: str = "point") -> tuple[float, float, float]:
    """``"x,y,z"`` -> three finite floats; OptionError naming ``key`` otherwise."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise OptionError(key, f"expected 'x,y,z' in metres, got {text!r}")
    return values


class FlightState(enum.Enum):
    PREFLIGHT = "preflight"
    INITIALISING = "initialising"
    AWAITING_GO = "awaiting_go"
    TAKING_OFF = "taking_off"
    ENTERING_OFFBOARD = "entering_offboard"
    CALIBRATING = "calibrating"
    ALIGNING = "aligning"
    NAVIGATING = "navigating"
    STOPPING = "stopping"
    FAILSAFE_STOP = "failsafe_stop"
    TO_LANDING_SITE = "to_landing_site"
    HOLDING = "holding"
    LINK_LOST = "link_lost"
    LANDING = "landing"
    LANDED = "landed"
    ABORTED = "aborted"


#: States before arming: an operator's stop ends the mission here.
GROUND_STATES = frozenset({FlightState.PREFLIGHT, FlightState.INITIALISING,
                           FlightState.AWAITING_GO})
#: States on the ground, disarmed: before arming, and after the landing.
DISARMED_STATES = GROUND_STATES | {FlightState.LANDED}
#: States in which the application commands the vehicle with offboard setpoints.
OFFBOARD_STATES = frozenset({FlightState.ENTERING_OFFBOARD, FlightState.CALIBRATING,
                             FlightState.ALIGNING, FlightState.NAVIGATING, FlightState.STOPPING,
                             FlightState.FAILSAFE_STOP, FlightState.TO_LANDING_SITE})
#: States after a failsafe in which the application still commands the vehicle.
FAILSAFE_OFFBOARD_STATES = frozenset({FlightState.FAILSAFE_STOP, FlightState.TO_LANDING_SITE})
#: Failsafes after which only the mission has failed, not the vehicle or its sensing: the
#: stop is followed by a glide to a landing site seen clear (module docstring). Not after an
#: operator's stop (which may be for something ahead), nor a stalled loop or failed sensor.
MISSION_TIMEOUT = "mission timeout"
NO_SAFE_PRIMITIVE = "no safe primitive"
SITE_SEEKING_FAILSAFES = frozenset({MISSION_TIMEOUT, NO_SAFE_PRIMITIVE})
#: States in which a failsafe check applies (in the air, on our setpoints).
GUARDED_STATES = frozenset({FlightState.CALIBRATING, FlightState.ALIGNING,
                            FlightState.NAVIGATING, FlightState.STOPPING})
#: Guarded states in which the vehicle turns in place over ground it has flown (the offset
#: swing on top of its take-off, a turn at a corner): depth may lapse there. The blind clock
#: holds only in a turn (ALIGNING), whose new view has no landmarks yet; the swing's 10
#: degrees keep its view, and a VINS blind through it is a failsafe as in flight.
IN_PLACE_STATES = frozenset({FlightState.CALIBRATING, FlightState.ALIGNING})
FINAL_STATES = frozenset({FlightState.LANDED, FlightState.ABORTED})
#: States in which nothing reads metric depth: PX4 flies the vehicle on its own (Hold after a
#: failsafe or while the link is lost, then the landing), or has landed it or stopped its
#: motors. None of them leads back to the application's commands.
DEPTH_UNUSED_STATES = FINAL_STATES | {FlightState.HOLDING, FlightState.LINK_LOST,
                                      FlightState.LANDING}


@dataclass(frozen=True)
class Transition:
    t: float
    source: FlightState
    target: FlightState
    reason: str


class Mission:
    """The present state, every transition so far, and the failsafes that fired."""

    def __init__(self, t: float = 0.0, on_transition=None):
        self.state = FlightState.PREFLIGHT
        self._on_transition = on_transition  # called with each Transition (a channel)
        self.since = t
        self.transitions: list[Transition] = []
        self.failsafes: list[str] = []
        self.stopped_by = ""  # the failsafe that stopped the flight ("" while none has)
        self.stopped_from: FlightState | None = None  # the state it stopped the flight in

    def go(self, t: float, target: FlightState, reason: str) -> None:
        """Enter ``target`` at ``t`` for ``reason`` (logged; a no-op when already there)."""
        if target == self.state:
            return
        transition = Transition(t, self.state, target, reason)
        self.transitions.append(transition)
        log.info("t=%.2f %s -> %s: %s", t, self.state.value, target.value, reason)
        self.state, self.since = target, t
        if self._on_transition is not None:
            self._on_transition(transition)

    def failsafe(self, t: float, reason: str) -> bool:
        """A failsafe for ``reason``: stop if navigating. Returns True when it changed the
        state (the first failsafe of a flight; later ones are recorded but change nothing)."""
        if reason not in self.failsafes:
            self.failsafes.append(reason)
        if self.state in GUARDED_STATES:
            log.warning("t=%.2f failsafe: %s", t, reason)
            self.stopped_by, self.stopped_from = reason, self.state
            self.go(t, FlightState.FAILSAFE_STOP, f"failsafe: {reason}")
            return True
        return False

    @property
    def done(self) -> bool:
        return self.state in FINAL_STATES

    def elapsed(self, t: float) -> float:
        """Seconds in the present state."""
        return t - self.since
