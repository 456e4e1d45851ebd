"""The failsafe rules (DESIGN.md, "Flight behaviour"): which failure, if any, stops the
flight now. The health monitor measures; this decides, in a fixed order of precedence, so the
reason a flight stopped is the most basic one that held (an operator's stop before a stalled
loop, before a silent sensor, before what follows from it)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from autonomy.navigation.mission import NO_SAFE_PRIMITIVE
from autonomy.vins.health import HealthState


@dataclass(frozen=True)
class Vitals:
    """What the monitor measured at one check. Ages are seconds since the newest camera frame,
    IMU sample and metric depth (inf: none yet)."""

    stop_requested: str  # an operator's stop, with its reason ("" if none)
    loop_lag_s: float
    watchdog_in_charge: bool  # the setpoint watchdog has sent the stop
    camera_age_s: float
    imu_age_s: float
    vins_problem: str  # see vins_problem ("" if none)
    depth_age_s: float
    depth_reason: str  # why the newest frame had no metric depth
    blind_s: float  # how long the VINS has been flown on blind (BlindClock)
    blind_expired: bool  # for longer than blind_timeout_s
    on_flown_ground: bool  # braking to a turn, turning in place, gliding over the trail
    no_path_expired: bool  # no safe primitive for longer than no_path_timeout_s


def age(t: float | None, now: float) -> float:
    """Seconds from ``t`` to ``now`` (inf when there was no ``t``)."""
    return math.inf if t is None else now - t


def vins_problem(health_state: HealthState | None, health_reason: str,
                 reinitialisations: int, reinitialisations_at_takeoff: int) -> str:
    """Why the VINS cannot be flown on ("" when it can): lost, or reinitialised since the
    take-off (its world frame, and so the route's tie to PX4's frame, has moved)."""
    if health_state is None:
        return ""
    if health_state == HealthState.LOST:
        return f"VINS lost ({health_reason})"
    if reinitialisations > reinitialisations_at_takeoff:
        return "VINS reset in flight"
    return ""


class BlindClock:
    """How long the vehicle has flown on a blind VINS: fewer than ``blind_landmarks``
    landmarks in its window, in front of the camera. Its pose is then IMU propagation alone,
    whose error grows without bound (as t^2 from an accelerometer bias error, t^3 from a gyro
    bias error) while tracked features, a healthy-looking DEGRADED, hide it.

    A turn in place does not count: it is short (at most 180 degrees at
    ``align_yaw_rate_deg``) and the view it turns to has no landmark until the parallax glide
    after it. Flying back over the flown trail does count: the trail is in the VINS's frame,
    and a drifted VINS glides along it into a wall (docs/results.md: a realistic mine flight
    backed off blind for 8 s into one). Held, not reset, while not counting."""

    def __init__(self):
        self.blind_s = 0.0
        self._last_t: float | None = None

    def update(self, now: float, landmarks: int | None, counting: bool, options) -> None:
        """One check at ``now``: ``landmarks`` at the newest VINS update (None: none yet, not
        blind), ``counting`` in the air on the application's setpoints, not turning in place;
        ``options`` the :class:`~autonomy.navigation.mission.FlightOptions`."""
        elapsed = 0.0 if self._last_t is None else max(0.0, now - self._last_t)
        self._last_t = now
        if landmarks is None or landmarks >= options.blind_landmarks:
            self.blind_s = 0.0
        elif counting:
            self.blind_s += elapsed

    def expired(self, options) -> bool:
        """Blind for longer than ``blind_timeout_s``: the failsafe."""
        return self.blind_s > options.blind_timeout_s


def vins_failed(vitals: Vitals) -> bool:
    """Has the VINS failed (lost, reset in flight, or blind past the timeout)? Its pose and
    velocity are then no longer the vehicle's, so the stop must not be flown on them: a stop
    tracked on a dead-reckoning VINS follows its drift (docs/results.md: a realistic mine
    flight flew its stop after "VINS blind" into a wall, 12 m off by the VINS)."""
    return vitals.vins_problem != "" or vitals.blind_expired


def failsafe_reason(vitals: Vitals, options) -> str:
    """The first failed check's reason ("" when all pass); ``options`` the
    :class:`~autonomy.navigation.mission.FlightOptions`. Depth may lapse over flown ground
    (the turn and the glides are there to get new depth)."""
    o = options
    checks = (
        (bool(vitals.stop_requested), vitals.stop_requested),
        (vitals.loop_lag_s > o.max_loop_lag_s,
         f"event loop stalled ({1e3 * vitals.loop_lag_s:.0f} ms late)"),
        (vitals.watchdog_in_charge, "setpoint deadline missed (watchdog sent the stop)"),
        (vitals.camera_age_s > o.camera_timeout_s, "camera silent"),
        (vitals.imu_age_s > o.imu_timeout_s, "IMU silent"),
        (vitals.vins_problem != "", vitals.vins_problem),
        (vitals.blind_expired,
         f"VINS blind (< {o.blind_landmarks} landmarks for {vitals.blind_s:.1f} s)"),
        (vitals.depth_age_s > o.depth_timeout_s and not vitals.on_flown_ground,
         f"no metric depth ({vitals.depth_reason or 'none yet'})"),
        (vitals.no_path_expired, NO_SAFE_PRIMITIVE),
    )
    return next((reason for failed, reason in checks if failed), "")
