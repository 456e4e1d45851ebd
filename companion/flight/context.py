"""What the flight process's stages share: the clock, the mission, the channels and the run's
counters. A stage gets this and the parts it owns; it never reaches into another stage."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from autonomy.messages import Frame, ImuSample, MetricDepth, Odometry
from autonomy.navigation.failsafes import BlindClock
from autonomy.navigation.mission import FlightOptions, FlightState, Mission, Transition
from autonomy.planning.planner import Plan, Setpoint
from autonomy.vins.estimator import FrameUpdate
from companion.flight.channels import Latest


@dataclass(frozen=True)
class Alignment:
    """The tie of the VINS world ``W`` to PX4's local frame ``L``, made once on the ground
    (:func:`autonomy.geometry.yaw_alignment`), and the ground's height in ``L`` then."""

    T_L_W: np.ndarray
    home_z: float


class Channels:
    """Every channel of the flight process (docs/architecture.md lists who publishes and who
    reads each). Each keeps the newest value; its taps see every one, in order."""

    def __init__(self):
        self.frames: Latest[Frame] = Latest("frames")  # perception: each camera frame
        self.imu: Latest[ImuSample] = Latest("imu")  # perception: each sample fed to the VINS
        self.vins: Latest[FrameUpdate] = Latest("vins")  # perception: the VINS on each frame
        self.depth: Latest[MetricDepth] = Latest("depth")  # perception: each frame's depth
        self.alignment: Latest[Alignment] = Latest("alignment")  # perception: once
        self.odometry: Latest[Odometry] = Latest("odometry")  # perception: on request
        self.plan: Latest[Plan] = Latest("plan")  # navigation, health: what to fly
        self.checked_stop: Latest[Plan] = Latest("checked_stop")  # the watchdog's fallback
        self.setpoints: Latest[Setpoint] = Latest("setpoints")  # command: each one sent (W)
        self.transitions: Latest[Transition] = Latest("transitions")  # the mission's


#: The reasons given when PX4 reports the motors off while the companion commands the flight:
#: in the air, or once its land detector had the vehicle on the ground (a touch-down).
DISARMED_IN_THE_AIR = "PX4 disarmed the vehicle in the air"
DISARMED_ON_THE_GROUND = "PX4 disarmed the vehicle on the ground"


@dataclass
class FlightStats:
    """What the run measured, for the summary."""

    frames: int = 0
    frames_out_of_order: int = 0  # dropped: not after the last frame taken
    frames_stale: int = 0  # dropped: the device's number of the last frame taken, again
    depth_ok: int = 0
    depth_fallbacks: int = 0  # of depth_ok: on the affine fallback (autonomy/depth/stage.py)
    depth_reasons: dict = field(default_factory=dict)
    planning_rounds: int = 0
    stop_rounds: int = 0
    backoffs: int = 0
    loop_lag_s: list = field(default_factory=list)
    frame_age_s: list = field(default_factory=list)  # each frame's, taken from the camera
    navigation_start: float | None = None
    navigation_end: float | None = None
    navigation_end_L: dict | None = None  # t and the VINS position in PX4's local frame then
    # (or at its first position after, in the hold: Steps._note_navigation_end)
    takeoff_t: float | None = None
    landed_t: float | None = None
    vins_reinitialisations_at_takeoff: int = 0
    vins_still_keyframes_at_takeoff: int | None = None  # given the zero-velocity prior
    vins_rebuilds_seen: int = 0
    vins_corrections_m: list = field(default_factory=list)  # keyframes' while navigating

    @property
    def navigating(self) -> bool:
        """Between Offboard and the end of navigation."""
        return self.navigation_start is not None and self.navigation_end is None


class FlightContext:
    """The clock, the ``[flight]`` options, the autopilot, the mission state machine, the
    channels and the counters of one flight."""

    def __init__(self, options: FlightOptions, clock, autopilot, workers: dict):
        self.options, self.clock, self.autopilot, self.workers = options, clock, autopilot, workers
        self.mission = Mission(clock.now(), on_transition=self._transition)
        self.channels = Channels()
        self.stats = FlightStats()
        # how long the VINS has been flown on blind: the health stage keeps it, the odometry
        # to PX4 reads it
        self.blind = BlindClock()

    @property
    def vins_blind(self) -> bool:
        """The VINS blind past ``blind_timeout_s``: its pose no longer fit to fly or fuse."""
        return self.blind.expired(self.options)

    def _transition(self, transition: Transition) -> None:
        self.channels.transitions.publish(transition)

    @property
    def state(self) -> FlightState:
        return self.mission.state

    @property
    def T_L_W(self) -> np.ndarray | None:
        """The tie of the VINS world to PX4's local frame; None before it is made."""
        alignment = self.channels.alignment.value
        return None if alignment is None else alignment.T_L_W

    def go(self, state: FlightState, reason: str) -> None:
        self.mission.go(self.clock.now(), state, reason)

    def abort(self, reason: str) -> None:
        self.go(FlightState.ABORTED, reason)

    def motors_stopped(self) -> None:
        """PX4 stopped the motors while the companion flew the vehicle. Nothing the companion
        sends can fly it, and it must never re-arm one on its own: the mission ends here. The
        reason tells a disarm in the air from PX4's own after the vehicle came down
        (:attr:`drivers.mavlink.autopilot.Autopilot.disarmed_on_the_ground`)."""
        if self.autopilot.disarmed_on_the_ground:
            reason, causes = DISARMED_ON_THE_GROUND, (
                "its land detector had the vehicle down before the disarm: flown or crashed "
                "onto the ground and left there (COM_DISARM_LAND's auto-disarm), a kill "
                "switch held, or COM_DISARM_PRFLT before a take-off")
        else:
            reason, causes = DISARMED_IN_THE_AIR, (
                "its land detector had the vehicle in the air: a ground station's forced "
                "disarm, a crash or failure PX4 disarmed on at once, or a reboot")
        self.mission.failsafe(self.clock.now(), reason)
        self.abort(f"{reason} ({causes}); nothing more is commanded")

    async def wait(self, condition, timeout_s: float, poll_s: float) -> bool:
        """Until ``condition()`` (True), ``timeout_s`` or the mission's end (False)."""
        deadline = self.clock.now() + timeout_s
        while not condition():
            if self.clock.now() >= deadline or self.mission.done:
                return False
            await self.clock.sleep(poll_s)
        return True
