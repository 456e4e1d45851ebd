"""The operator's go: the vehicle stays disarmed until a person says to fly.

A service started at boot must not take off because link, IMU, camera and VINS became ready:
a drone on a bench would. So after the VINS has initialised the mission waits, disarmed, in
``awaiting_go`` for one of (``[go]``):

- a MAVLink ``COMMAND_LONG``/``COMMAND_INT`` ``MAV_CMD_MISSION_START`` (300) addressed to the
  companion (its system id and component id, 191 by default) from a ground station; it is
  acknowledged ACCEPTED, or TEMPORARILY_REJECTED while the mission is not waiting;
- an RC switch: ``rc_channel`` moved from below to above ``rc_high_us`` while waiting (an edge,
  so a switch left high at power-up gives no go; PX4 forwards ``RC_CHANNELS`` to the companion);
- ``companion go`` on the vehicle, a datagram on the Unix socket ``socket`` (the unit's
  ``RuntimeDirectory``, writable by the service's group only).

What it waits for is in the log, the HEARTBEAT (STANDBY) and systemd's status line. A go that
came before the waiting began is discarded: consent is given to a vehicle that is ready.
"""

from __future__ import annotations

import logging
import os
import socket
from dataclasses import dataclass

from autonomy.options import option, validate

log = logging.getLogger(__name__)

#: The datagram ``companion go`` sends.
GO_MESSAGE = b"go"


class GoError(RuntimeError):
    """The go socket cannot be set up; the message names the path and the fix."""


@dataclass(frozen=True)
class GoOptions:
    """The ``[go]`` table: how the operator says to fly."""

    required: bool = option(True, doc="wait, disarmed, for an operator's go before arming "
                                      "(`sim fly` gives the go itself)")
    rc_channel: int = option(0, ge=0, le=18, doc="RC channel whose switch, moved high while "
                                                 "waiting, gives the go; 0: none")
    rc_high_us: int = option(1800, ge=1000, le=2200, doc="pulse width above which that "
                                                         "switch is high, microseconds")
    socket: str = option("/run/companion/go.sock", doc="Unix socket `companion go` writes to; "
                                                       "empty: none")

    def __post_init__(self) -> None:
        validate(self)


class OperatorGate:
    """Collects the go from the sources of the module docstring.

    ``autopilot`` provides ``rc_channels_us`` (the latest RC_CHANNELS, None before one came)
    and hands ground stations' go commands to its ``on_go``, which the gate takes over.
    ``given_by`` non-empty makes a gate that is already open (``sim fly``: the command line is
    the operator's go).
    """

    def __init__(self, options: GoOptions, autopilot, given_by: str = ""):
        self.options, self.autopilot = options, autopilot
        autopilot.on_go = self.command
        self.given_by = given_by
        self.waiting = False
        self._socket: socket.socket | None = None
        self._rc_was_low = False

    def open(self) -> None:
        """Bind the go socket (when configured); :class:`GoError` when it cannot be."""
        path = self.options.socket
        if not path or self.given_by or not self.options.required:
            return
        if os.path.exists(path):
            os.unlink(path)  # a socket left by a previous run
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        try:
            sock.bind(path)
            os.chmod(path, 0o660)  # the service's user and group may give the go
        except OSError as error:
            sock.close()
            raise GoError(f"[go] socket {path}: cannot create it ({error.strerror}); the "
                          "service unit's RuntimeDirectory=companion makes /run/companion, "
                          "or set [go] socket to a writable path, or to '' to use only "
                          "MAVLink and RC") from None
        sock.setblocking(False)
        self._socket = sock

    def close(self) -> None:
        if self._socket is not None:
            path = self._socket.getsockname()
            self._socket.close()
            self._socket = None
            try:
                os.unlink(path)
            except OSError:
                pass

    def describe(self) -> str:
        """What the mission waits for, for the log and systemd's status line."""
        ways = ["MAV_CMD_MISSION_START from the ground station"]
        if self.options.rc_channel:
            ways.insert(0, f"RC channel {self.options.rc_channel} switched above "
                           f"{self.options.rc_high_us} us")
        if self._socket is not None:
            ways.append(f"`companion go` ({self.options.socket})")
        return "operator's go: " + ", or ".join(ways)

    def start_waiting(self) -> None:
        """From now on a go counts; anything sent earlier is discarded."""
        self._drain_socket()
        self._rc_was_low = False
        self.waiting = True

    def command(self, source: str) -> bool:
        """A go command from ``source`` (MAVLink); True when it was taken (the mission is
        waiting), False when it came too early or too late."""
        if not self.waiting or self.given_by:
            return False
        self._give(source)
        return True

    def poll(self) -> str:
        """Who gave the go, or "" while none has; checks the RC switch and the socket."""
        if self.waiting and not self.given_by:
            if self._rc_switched_high():
                self._give(f"RC channel {self.options.rc_channel}")
            elif self._drain_socket():
                self._give("companion go")
        return self.given_by

    def _give(self, source: str) -> None:
        self.given_by = source
        self.waiting = False
        log.info("operator's go from %s", source)

    def _rc_switched_high(self) -> bool:
        channel = self.options.rc_channel
        values = getattr(self.autopilot, "rc_channels_us", None)
        if not channel or values is None or len(values) < channel:
            return False
        pulse = values[channel - 1]
        if pulse is None:  # the receiver reports the channel unused: a fresh low is needed
            self._rc_was_low = False
            return False
        high = pulse >= self.options.rc_high_us
        if not high:
            self._rc_was_low = True
        return high and self._rc_was_low

    def _drain_socket(self) -> bool:
        """Whether a go datagram was waiting (all pending ones are read)."""
        got = False
        while self._socket is not None:
            try:
                data = self._socket.recv(64)
            except (BlockingIOError, InterruptedError):
                break
            got = got or data.strip() == GO_MESSAGE
        return got


def send_go(path: str) -> None:
    """``companion go``: tell the running application at ``path`` to fly; OSError with the
    reason when nobody listens there."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.sendto(GO_MESSAGE, path)
