"""Faults the simulator can inject, to test the application's failsafes end to end.

Each fault is something that goes wrong on a real vehicle, injected where it would happen:

==================  ==========================================================================
``camera_freeze``   the camera stops delivering frames (a USB camera or driver that hangs)
``camera_blackout`` the camera delivers black frames (lens covered, lights out): the VINS
                    front-end starves, the estimate is lost and re-initialised (a VINS reset)
``camera_stale``    the camera delivers its last frame again with fresh stamps (a driver whose
                    buffer stopped updating), its device number too: the application refuses
                    it and the camera falls silent. Without numbers (``[sim] camera_counter =
                    false``) the features stay tracked but stand still, so the landmarks
                    leave the VINS and its pose is the IMU's alone
``imu_gap``         PX4 stops streaming HIGHRES_IMU
``link_cut``        the MAVLink link drops every byte both ways (a cable or radio lost)
``network_nan``     the depth network outputs NaN (a broken engine, an overflow in fp16)
``disarm``          PX4 stops the motors in the air, as on a ground station's forced disarm
                    (MAV_CMD_COMPONENT_ARM_DISARM with 21196, which PX4's Commander accepts in
                    flight) or a crash: the vehicle falls
``loop_stall``      the application's event loop is blocked (a runaway computation); the
                    application injects this one itself, as only it owns its loop
``imu_repeat``      PX4's HIGHRES_IMU arrive twice each (a link or router duplicating
                    datagrams)
``imu_reorder``     PX4's HIGHRES_IMU arrive in swapped pairs, so every other stamp goes
                    backwards (datagrams reordered on the way)
``frame_repeat``    the camera delivers each frame twice, same stamp (a driver re-queueing a
                    buffer)
``frame_reorder``   the camera delivers frames in swapped pairs, out of stamp order
``timesync_stop``   PX4 stops answering TIMESYNC (and sends no requests of its own)
``packet_loss``     half the MAVLink packets are lost, each way, at random (a failing radio
                    or a noisy cable)
``network_const``   the depth network outputs one constant disparity (a broken engine that
                    returns its bias)
``px4_reboot``      the flight controller reboots (a brown-out, a watchdog reset): the motors
                    stop, the link is silent while it boots, then its boot time starts again
                    from zero
``disk_full``       the recording's disk takes no more bytes: the kernel refuses every write
                    past the file's size then (``RLIMIT_FSIZE``, EFBIG where a full disk
                    gives ENOSPC: the same failed ``write``); the application injects this one
                    itself, on a recorded flight
==================  ==========================================================================

A fault starts ``after_s`` seconds of simulated time after its *moment* (:data:`MOMENTS`), so
a test hits the flight it means to, however long take-off and initialisation took, and lasts
``duration_s`` seconds (``inf``: for good). The moments are judged on the vehicle's truth:

============  ===================================================================================
``takeoff``   the vehicle first climbs :data:`TAKEOFF_HEIGHT` above where it stood
``cruise``    the vehicle first flies faster than :data:`CRUISE_SPEED` horizontally (the default)
``obstacle``  in cruise, the vehicle first comes within :data:`NEAR_OBSTACLE` of an obstacle
``landing``   in cruise or after, PX4 first switches to its land mode
============  ===================================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FAULT_KINDS = ("camera_freeze", "camera_blackout", "camera_stale", "imu_gap", "link_cut",
               "network_nan", "disarm", "loop_stall", "imu_repeat", "imu_reorder",
               "frame_repeat", "frame_reorder", "timesync_stop", "packet_loss", "network_const",
               "px4_reboot", "disk_full")

MOMENTS = ("takeoff", "cruise", "obstacle", "landing")

TAKEOFF_HEIGHT = 0.3
"""Height, m, above the start from which the vehicle counts as taking off."""
CRUISE_SPEED = 1.0
"""Horizontal speed, m/s, from which the vehicle counts as in cruise."""
NEAR_OBSTACLE = 2.0
"""True clearance, m, under which a vehicle in cruise counts as near an obstacle."""
OBSTACLE_CHECK_PERIOD = 0.05
"""Simulated seconds between clearance checks for the ``obstacle`` moment (a query of the
world's distance field costs more than a physics tick)."""
PACKET_LOSS = 0.5
"""Probability that a ``packet_loss`` fault loses one MAVLink packet, each way."""


@dataclass(frozen=True)
class Fault:
    """One fault: what, when (seconds after its ``moment``) and for how long."""

    kind: str
    after_s: float = 1.0
    duration_s: float = math.inf
    moment: str = "cruise"

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {self.kind!r}; choose one of {', '.join(FAULT_KINDS)}")
        if self.moment not in MOMENTS:
            raise ValueError(f"fault {self.kind}: unknown moment {self.moment!r}; choose one of "
                             f"{', '.join(MOMENTS)}")
        if not (math.isfinite(self.after_s) and self.after_s >= 0.0):
            raise ValueError(f"fault {self.kind}: after_s must be a finite number >= 0, "
                             f"got {self.after_s}")
        if not self.duration_s > 0.0:
            raise ValueError(f"fault {self.kind}: duration_s must be > 0, got {self.duration_s}")

    @classmethod
    def parse(cls, text: str) -> "Fault":
        """``kind[@[moment:]after[+duration]]`` (seconds), as the CLI takes it: e.g.
        ``imu_gap``, ``link_cut@2.5``, ``camera_freeze@1+0.5``, ``px4_reboot@landing:0.5``."""
        kind, _, timing = text.strip().partition("@")
        moment, _, timing = timing.rpartition(":")
        after, _, duration = timing.partition("+")
        try:
            return cls(kind, float(after) if after else 1.0,
                       float(duration) if duration else math.inf, moment or "cruise")
        except ValueError as error:
            if "could not convert" in str(error):
                raise ValueError(f"fault {text!r}: expected "
                                 "kind[@[moment:]after_s[+duration_s]]") from None
            raise

    def __str__(self) -> str:
        """The text :meth:`parse` reads back."""
        duration = "" if math.isinf(self.duration_s) else f"+{self.duration_s!r}"
        return f"{self.kind}@{self.moment}:{self.after_s!r}{duration}"


class FaultSchedule:
    """Which faults are active, judged on the simulated vehicle's truth.

    :meth:`update` is called every physics tick with the time, the true position and velocity
    and whether PX4 is landing; ``active`` then answers for any kind. ``clearance`` is the
    world's distance to its obstacles for an (N, 3) array of points (the ``obstacle`` moment;
    without it that moment never comes). Without faults nothing is tracked, and the world is
    queried only while a fault waits for the ``obstacle`` moment.
    """

    def __init__(self, faults: tuple[Fault, ...] = (), clearance=None):
        self.faults = tuple(faults)
        self._clearance = clearance if any(f.moment == "obstacle" for f in self.faults) \
            else None
        self._ground_z: float | None = None
        self._next_clearance_check = -math.inf
        #: When each moment came (simulated seconds), once it has.
        self.moment_since: dict[str, float] = {}

    def update(self, t: float, position, velocity, landing: bool = False) -> None:
        if not self.faults:
            return
        if self._ground_z is None:
            self._ground_z = float(position[2])
        reached = self.moment_since.setdefault
        if position[2] > self._ground_z + TAKEOFF_HEIGHT:
            reached("takeoff", float(t))
        if math.hypot(velocity[0], velocity[1]) > CRUISE_SPEED:
            reached("cruise", float(t))
        if "cruise" not in self.moment_since:
            return
        if landing:
            reached("landing", float(t))
        if "obstacle" not in self.moment_since and self._near_obstacle(t, position):
            reached("obstacle", float(t))

    def _near_obstacle(self, t: float, position) -> bool:
        if self._clearance is None or t < self._next_clearance_check:
            return False
        self._next_clearance_check = t + OBSTACLE_CHECK_PERIOD
        return float(self._clearance(np.asarray(position, dtype=float)[None, :])[0]) \
            < NEAR_OBSTACLE

    def active(self, kind: str, t: float) -> bool:
        return any(f.kind == kind and self._within(f, t) for f in self.faults)

    def _within(self, fault: Fault, t: float) -> bool:
        since = self.moment_since.get(fault.moment)
        return since is not None and fault.after_s <= t - since < fault.after_s + fault.duration_s

    def has(self, kind: str) -> bool:
        return any(f.kind == kind for f in self.faults)


class FaultyLink:
    """A MAVLink link that can be cut or lossy. While ``cut`` is True nothing is sent and
    everything received is read and thrown away, as bytes on a severed wire; with ``loss`` > 0
    each message sent or received is lost with that probability (drawn from ``rng``)."""

    def __init__(self, link, rng: np.random.Generator | None = None):
        self._link = link
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.cut = False
        self.loss = 0.0

    def __getattr__(self, name):
        return getattr(self._link, name)

    def _lost(self) -> bool:
        return self.cut or (self.loss > 0.0 and self._rng.random() < self.loss)

    def send(self, message) -> None:
        if not self._lost():
            self._link.send(message)

    def receive_pending(self):
        return [message for message in self._link.receive_pending() if not self._lost()]

