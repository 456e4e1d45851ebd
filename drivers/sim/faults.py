"""Faults the simulator can inject, to test the application's failsafes end to end.

Each fault is something that goes wrong on a real vehicle, injected where it would happen:

==================  ==========================================================================
``camera_freeze``   the camera stops delivering frames (a USB camera or driver that hangs)
``camera_blackout`` the camera delivers black frames (lens covered, lights out): the VINS
                    front-end starves, the estimate is lost and re-initialised (a VINS reset)
``camera_stale``    the camera delivers its last image again with fresh stamps (a driver whose
                    buffer stopped updating): the features stay tracked but stand still, so
                    the landmarks leave the VINS and its pose is the IMU's alone
``imu_gap``         PX4 stops streaming HIGHRES_IMU
``link_cut``        the MAVLink link drops every byte both ways (a cable or radio lost)
``network_nan``     the depth network outputs NaN (a broken engine, an overflow in fp16)
``disarm``          PX4 stops the motors in the air, as on a ground station's forced disarm
                    (MAV_CMD_COMPONENT_ARM_DISARM with 21196, which PX4's Commander accepts in
                    flight) or a crash: the vehicle falls
``loop_stall``      the application's event loop is blocked (a runaway computation); the
                    application injects this one itself, as only it owns its loop
==================  ==========================================================================

A fault starts ``after_s`` seconds of simulated time after the vehicle is first *in cruise*
(horizontal speed above :data:`CRUISE_SPEED`), so a test hits the flight it means to, however
long take-off and initialisation took, and lasts ``duration_s`` seconds (``inf``: for good).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

FAULT_KINDS = ("camera_freeze", "camera_blackout", "camera_stale", "imu_gap", "link_cut",
               "network_nan", "disarm", "loop_stall")

CRUISE_SPEED = 1.0
"""Horizontal speed, m/s, from which the vehicle counts as in cruise (the fault clock starts)."""


@dataclass(frozen=True)
class Fault:
    """One fault: what, when (seconds after cruise begins) and for how long."""

    kind: str
    after_s: float = 1.0
    duration_s: float = math.inf

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {self.kind!r}; choose one of {', '.join(FAULT_KINDS)}")
        if not (math.isfinite(self.after_s) and self.after_s >= 0.0):
            raise ValueError(f"fault {self.kind}: after_s must be a finite number >= 0, "
                             f"got {self.after_s}")
        if not self.duration_s > 0.0:
            raise ValueError(f"fault {self.kind}: duration_s must be > 0, got {self.duration_s}")

    @classmethod
    def parse(cls, text: str) -> "Fault":
        """``kind``, ``kind@after`` or ``kind@after+duration`` (seconds), as the CLI takes it."""
        kind, _, timing = text.strip().partition("@")
        after, _, duration = timing.partition("+")
        try:
            return cls(kind, float(after) if after else 1.0,
                       float(duration) if duration else math.inf)
        except ValueError as error:
            if "could not convert" in str(error):
                raise ValueError(f"fault {text!r}: expected kind[@after_s[+duration_s]]") from None
            raise


class FaultSchedule:
    """Which faults are active, judged on the simulated vehicle's true motion.

    :meth:`update` is called every physics tick with the time and true velocity; ``active``
    then answers for any kind.
    """

    def __init__(self, faults: tuple[Fault, ...] = ()):
        self.faults = tuple(faults)
        self.cruise_since: float | None = None

    def update(self, t: float, velocity) -> None:
        if self.cruise_since is None and math.hypot(velocity[0], velocity[1]) > CRUISE_SPEED:
            self.cruise_since = float(t)

    def active(self, kind: str, t: float) -> bool:
        if self.cruise_since is None:
            return False
        elapsed = t - self.cruise_since
        return any(f.kind == kind and f.after_s <= elapsed < f.after_s + f.duration_s
                   for f in self.faults)

    def has(self, kind: str) -> bool:
        return any(f.kind == kind for f in self.faults)


class CuttableLink:
    """A MAVLink link that can be cut: while ``cut`` is True nothing is sent and everything
    received is read and thrown away, as bytes on a severed wire."""

    def __init__(self, link):
        self._link = link
        self.cut = False

    def __getattr__(self, name):
        return getattr(self._link, name)

    def send(self, message) -> None:
        if not self.cut:
            self._link.send(message)

    def receive_pending(self):
        messages = self._link.receive_pending()
        return [] if self.cut else messages

