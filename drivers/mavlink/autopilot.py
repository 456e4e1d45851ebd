"""The companion's side of the link to PX4, for an asyncio application (docs/mavlink.md).

:class:`Autopilot` owns one :class:`~drivers.mavlink.link.MavlinkLink`. Its :meth:`Autopilot.run`
task polls the link without blocking, sleeping on the application's clock between polls (so it
runs in lockstep on a ``SimClock``), and keeps up the companion's half of the protocol:
HEARTBEAT, TIMESYNC both ways, the HIGHRES_IMU rate. What PX4 reports is kept, converted to
our conventions: frame ``L`` is PX4's local frame expressed ENU (x east, y north, z up), the
body frame is FLU, and times are on the companion clock.

- State: :attr:`~Autopilot.connected`, :attr:`~Autopilot.armed`, :attr:`~Autopilot.mode`,
  :attr:`~Autopilot.landed`, :attr:`~Autopilot.in_air`,
  :attr:`~Autopilot.disarmed_on_the_ground`, :attr:`~Autopilot.state`,
  :attr:`~Autopilot.imu_rate_hz` (measured), :attr:`~Autopilot.last_imu_t`,
  :attr:`~Autopilot.link_losses`, :attr:`~Autopilot.statustexts`, and while not connected
  :attr:`~Autopilot.link_problem`: why, for a person (a PX4 without our signing key, or with
  another, included).
- Signing (``[mavlink] signing_key_file``): everything we send is signed, nothing unsigned or
  wrongly signed is taken; :attr:`~Autopilot.signing` counts what was refused, and the log
  says so once per burst (docs/mavlink.md, Signing).
- A device that goes away (a USB adapter unplugged) is a lost link at once, reopened every
  :data:`REOPEN_INTERVAL_S` until it comes back.
- IMU: a bounded ring of :class:`~autonomy.messages.ImuSample` drained by
  :meth:`~Autopilot.take_imu` (stamping rules in :mod:`drivers.mavlink.imu_stream`).
- Verbs (coroutines, COMMAND_ACK with timeout and retries): arm, disarm, set_mode, takeoff,
  land, hold return True when PX4 accepted, else False with the reason (an
  :class:`AutopilotError`) logged and kept in :attr:`~Autopilot.last_command_error`;
  :meth:`~Autopilot.command` raises it instead.
- Setpoints and odometry (plain methods, thread-safe: a watchdog thread may call them):
  :meth:`~Autopilot.send_velocity`, :meth:`~Autopilot.send_odometry`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import threading
from collections import Counter, deque
from dataclasses import dataclass
from enum import IntEnum
from typing import Callable

import numpy as np

from autonomy.geometry import make_pose, quat_to_rot
from autonomy.messages import ImuSample
from autonomy.options import OptionError, option, validate
from drivers.clock import Clock
from drivers.mavlink import px4_protocol
from drivers.mavlink.frames import (enu_to_ned, frd_to_flu, ned_to_enu,
                                    quat_ned_frd_to_enu_flu)
from drivers.mavlink.imu_stream import ImuStamper, updated_pressure
from drivers.mavlink.link import LinkLost, MavlinkLink, mavlink, open_link, parse_url
from drivers.mavlink.odometry import odometry_fields, pose_covariance_to_mavlink
from drivers.mavlink.parameters import ParameterReader
from drivers.mavlink.signing import BAD_SIGNATURE, UNSIGNED, check_key_options, load_key
from drivers.mavlink.timesync import TimesyncFilter

log = logging.getLogger(__name__)

#: Seconds of IMU messages over which :attr:`Autopilot.imu_rate_hz` is measured.
IMU_RATE_WINDOW_S = 1.0
#: A measured IMU rate below this fraction of the requested one is "far below": re-request.
IMU_LOW_RATE_FRACTION = 0.75
#: At least this long between two HIGHRES_IMU interval requests made for a low rate.
IMU_REREQUEST_S = 3.0
#: Statustexts kept in :attr:`Autopilot.statustexts`.
STATUSTEXT_HISTORY = 50
#: TIMESYNC requests awaiting an answer, at most (older ones are forgotten).
TIMESYNC_PENDING = 16
#: A gap between two polls longer than this means our own loop was starved (a stall, a
#: blocking call): nobody read the socket, whose buffer may have overflowed and dropped PX4's
#: HEARTBEATs, so the gap does not count as PX4's silence. Far above a loaded loop's lag.
DEAF_POLL_GAP_S = 0.1
#: STATUSTEXT chunk length: a shorter chunk ends a multi-chunk text (MAVLink 2).
STATUSTEXT_CHUNK = 50
#: The most chunks one text is kept for: PX4's texts are at most 126 characters, 3 chunks
#: (msg/MavlinkLog.msg, ``char[127] text``). A longer one is cut there, marked, not held.
STATUSTEXT_MAX_CHUNKS = 3
#: Seconds between two tries to reopen a device that went away (a USB adapter unplugged: it
#: comes back under its name when plugged in again).
REOPEN_INTERVAL_S = 1.0
#: Seconds without a message refused by signing after which the next one starts a new burst
#: (and is logged).
REFUSAL_QUIET_S = 10.0
#: RC_CHANNELS' value for "this channel is unused" (UINT16_MAX, common.xml): no pulse width.
RC_UNUSED = 65535
#: A quaternion further than this from unit norm is no attitude (PX4 sends float32 unit
#: quaternions, off by about 1e-7): the estimate carrying it is refused.
QUATERNION_NORM_TOLERANCE = 1e-3


class CompanionStatus(IntEnum):
    """The companion's health as its HEARTBEAT.system_status shows it to PX4 and ground
    stations (MAV_STATE)."""

    STANDBY = mavlink.MAV_STATE_STANDBY
    ACTIVE = mavlink.MAV_STATE_ACTIVE
    CRITICAL = mavlink.MAV_STATE_CRITICAL
    EMERGENCY = mavlink.MAV_STATE_EMERGENCY


@dataclass(frozen=True)
class MavlinkOptions:
    """The link to PX4 (the ``[mavlink]`` config table)."""

    url: str = option(
        "udpout://127.0.0.1:14540",
        doc="connection string, MAVSDK's forms: udpout://HOST:PORT (default: the "
            "simulator's `companion sim serve` on loopback), udpin://0.0.0.0:14540 for PX4 "
            "SITL's onboard link, serial:///dev/ttyTHS1:921600 for a flight controller on a "
            "UART (baud one of PX4's SER_TELn_BAUD rates), tcpin://HOST:PORT to listen for "
            "a TCP client, tcpout://HOST:PORT to connect to a TCP server (tcp:// is "
            "deprecated: 0.0.0.0 or no host listens, any other host connects), pty for a new "
            "pseudo-terminal (docs/mavlink.md)")
    system_id: int = option(1, ge=1, le=255,
                            doc="our MAVLink system id (a companion shares its vehicle's)")
    component_id: int = option(191, ge=1, le=255,
                               doc="our component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)")
    target_system: int = option(1, ge=1, le=255, doc="PX4's system id [MAV_SYS_ID]")
    target_component: int = option(1, ge=1, le=255, doc="PX4's component id (1 = autopilot)")
    imu_rate_hz: float = option(200.0, gt=0.0, le=1000.0,
                                doc="HIGHRES_IMU rate requested from PX4, Hz")
    imu_queue_size: int = option(1000, ge=1, le=100000,
                                 doc="IMU samples kept until the application takes them")
    heartbeat_rate_hz: float = option(1.0, gt=0.0, le=50.0, doc="our HEARTBEAT rate, Hz")
    link_timeout_s: float = option(
        1.5, gt=0.0, le=60.0,
        doc="seconds without PX4's HEARTBEAT before the link is lost; never up since opening "
            "for this long, the log says what came instead (no bytes, bytes that are not "
            "MAVLink) and what to check")
    timesync_rate_hz: float = option(10.0, gt=0.0, le=100.0,
                                     doc="our TIMESYNC request rate, Hz")
    command_timeout_s: float = option(0.5, gt=0.0, le=30.0,
                                      doc="seconds to wait for one COMMAND_ACK")
    command_retries: int = option(3, ge=0, le=20,
                                  doc="times a command is re-sent when its ack does not come")
    poll_interval_s: float = option(0.002, gt=0.0, le=0.05,
                                    doc="seconds between two polls of the link")
    signing_key_file: str = option(
        "", doc="file holding the MAVLink 2 signing secret as 64 hex digits, readable by its "
                "owner only (`companion signing keygen FILE` makes one); a relative path is "
                "looked up in $CREDENTIALS_DIRECTORY (the unit's LoadCredential=), else the "
                "working directory. Set: every message is signed and unsigned or wrongly "
                "signed ones are ignored and counted; empty (and no signing_key): signing off")
    signing_key: str = option(
        "", doc="the signing secret itself, 64 hex digits, for tests and the simulator only "
                "(a secret does not belong in a config file); not with signing_key_file")

    def __post_init__(self) -> None:
        validate(self)
        try:
            parse_url(self.url)
        except ValueError as error:
            raise OptionError("url", str(error)) from None
        check_key_options(self)


@dataclass(frozen=True)
class VehicleState:
    """PX4's estimate at time ``t`` (companion clock): frame L (PX4 local, ENU), body FLU."""

    t: float
    position_L: np.ndarray
    velocity_L: np.ndarray
    q_L_B: np.ndarray
    angular_velocity_B: np.ndarray

    @property
    def T_L_B(self) -> np.ndarray:
        """The pose as a 4x4 matrix, ``p_L = T_L_B @ p_B``."""
        return make_pose(quat_to_rot(self.q_L_B), self.position_L)


@dataclass(frozen=True)
class StatusText:
    """A STATUSTEXT from PX4: arrival time (companion clock), MAV_SEVERITY, text."""

    t: float
    severity: int
    text: str


class AutopilotError(Exception):
    """A verb PX4 did not carry out."""


class NotConnected(AutopilotError):
    """No HEARTBEAT from PX4 within the link timeout."""


class CommandTimeout(AutopilotError):
    """No COMMAND_ACK after every retry."""


class CommandDenied(AutopilotError):
    """PX4 acknowledged the command with a result other than ACCEPTED."""

    def __init__(self, message: str, result: int):
        super().__init__(message)
        self.result = result


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else f"{enum} {value}"


def _log_level(severity: int) -> int:
    """MAV_SEVERITY as a logging level."""
    if severity <= mavlink.MAV_SEVERITY_CRITICAL:
        return logging.CRITICAL
    return {mavlink.MAV_SEVERITY_ERROR: logging.ERROR,
            mavlink.MAV_SEVERITY_WARNING: logging.WARNING,
            mavlink.MAV_SEVERITY_DEBUG: logging.DEBUG}.get(severity, logging.INFO)


class Autopilot:
    """PX4 seen from the companion: state, IMU, verbs, setpoints (module docstring)."""

    def __init__(self, link: MavlinkLink, clock: Clock, options: MavlinkOptions | None = None):
        self.link = link
        self.clock = clock
        self.options = options or MavlinkOptions()
        secret = load_key(self.options)
        if secret is not None:
            # nothing unsigned: PX4 signs all it sends once it has the key, and an unsigned
            # HEARTBEAT (which PX4 itself accepts) is what a rogue would forge to pass as PX4
            link.setup_signing(secret)
        self.timesync = TimesyncFilter()
        #: Called as ``on_timesync(now, used)`` after each TIMESYNC round trip (the flight
        #: recorder's tap); ``used``: whether it updated ``timesync.offset``.
        self.on_timesync: Callable[[float, bool], None] | None = None
        self.counts: Counter = Counter()
        self.statustexts: deque[StatusText] = deque(maxlen=STATUSTEXT_HISTORY)
        self.connected = False
        self.link_losses = 0
        self.armed = False
        self.mode: px4_protocol.Px4Mode | None = None
        self.state: VehicleState | None = None
        self.home_altitude_amsl: float | None = None
        self.home_position_L: np.ndarray | None = None
        self.imu_rate_hz = 0.0
        self.last_imu_t: float | None = None
        #: The latest RC_CHANNELS pulse widths (channel 1 first, microseconds; None for a
        #: channel the receiver reports unused), None before one.
        self.rc_channels_us: tuple[int | None, ...] | None = None
        #: ``on_go(source) -> bool``: a ground station's MAV_CMD_MISSION_START to us; True
        #: when taken (acknowledged ACCEPTED), False when not now (TEMPORARILY_REJECTED).
        self.on_go = None
        self._status = CompanionStatus.STANDBY
        self.last_command_error: AutopilotError | None = None
        self._send_lock = threading.Lock()
        self._command_lock = asyncio.Lock()
        self._imu = ImuStamper(self.options.imu_rate_hz)
        self._imu_queue: deque[ImuSample] = deque(maxlen=self.options.imu_queue_size)
        self._imu_request: asyncio.Task | None = None
        self._imu_requested_at = -math.inf
        self._rate_window = (-math.inf, 0)  # (start, messages since)
        self._landed_state = mavlink.MAV_LANDED_STATE_UNDEFINED
        # since when PX4 has said on the ground while armed (None: not now); the last HEARTBEAT
        # that said armed
        self._armed_on_the_ground_since: float | None = None
        self._last_armed_heartbeat = -math.inf
        #: PX4's last disarm came once its land detector had the vehicle down (on the ground
        #: while armed before PX4's last armed HEARTBEAT:
        #: :meth:`_came_down_before_last_armed_heartbeat`), not in the air; False before any
        #: disarm and from the next arm on.
        self.disarmed_on_the_ground = False
        self._attitude: tuple[np.ndarray, np.ndarray] | None = None
        self._last_odometry = -math.inf
        self._last_heartbeat = -math.inf
        self._last_poll: float | None = None
        self._reopen_at: float | None = None  # the next try while the device is gone
        self._refusals_seen, self._last_refusal_t = 0, -math.inf
        self._listen(clock.now())
        self._deaf_s = 0.0  # time since the last HEARTBEAT we were not reading the link
        self._next_heartbeat = -math.inf
        self._next_timesync = -math.inf
        self._timesync_sent: dict[int, float] = {}
        self._pending_ack: tuple[int, asyncio.Future] | None = None
        self._statustext_total = 0
        self._chunks: dict[int, list[str]] = {}
        self._handlers = {
            "HEARTBEAT": self._on_heartbeat, "TIMESYNC": self._on_timesync,
            "HIGHRES_IMU": self._on_highres_imu, "COMMAND_ACK": self._on_command_ack,
            "EXTENDED_SYS_STATE": self._on_extended_sys_state, "ODOMETRY": self._on_odometry,
            "LOCAL_POSITION_NED": self._on_local_position, "STATUSTEXT": self._on_statustext,
            "ATTITUDE_QUATERNION": self._on_attitude, "HOME_POSITION": self._on_home_position,
            "RC_CHANNELS": self._on_rc_channels,
        }
        self.parameters = ParameterReader(self._send, clock, self.options.target_system,
                                          self.options.target_component)
        self._handlers["PARAM_VALUE"] = self.parameters.on_param_value

    @classmethod
    def open(cls, options: MavlinkOptions, clock: Clock) -> "Autopilot":
        """Open ``options.url`` speaking as ``system_id``/``component_id``."""
        link = open_link(options.url, source_system=options.system_id,
                         source_component=options.component_id)
        try:
            return cls(link, clock, options)
        except BaseException:
            link.close()
            raise

    def close(self) -> None:
        """Close the link (after :meth:`run` has been cancelled)."""
        self.link.close()

    # ---------------------------------------------------------------- state

    @property
    def landed(self) -> bool:
        """PX4's land detector says on the ground (EXTENDED_SYS_STATE)."""
        return self._landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND

    @property
    def in_air(self) -> bool:
        """In the air, taking off or landing (EXTENDED_SYS_STATE)."""
        return self._landed_state in (mavlink.MAV_LANDED_STATE_IN_AIR,
                                      mavlink.MAV_LANDED_STATE_TAKEOFF,
                                      mavlink.MAV_LANDED_STATE_LANDING)

    @property
    def time_synced(self) -> bool:
        """Whether TIMESYNC has an offset, so PX4 times can be mapped (and odometry sent)."""
        return self.timesync.offset is not None

    @property
    def status(self) -> CompanionStatus:
        return self._status

    def set_status(self, status: CompanionStatus | int) -> None:
        """The application's health for our HEARTBEAT (a CompanionStatus or its MAV_STATE
        number); a change is sent at the next poll."""
        status = CompanionStatus(status)
        if status != self._status:
            self._status = status
            self._next_heartbeat = -math.inf

    @property
    def link_problem(self) -> str:
        """Why PX4 is not connected, for a person ("" while it is): the device gone, or what
        arrived instead of PX4's HEARTBEAT since the link was opened (or lost, or reopened)
        and what to check."""
        if self.connected:
            return ""
        if self.link.lost is not None:
            return _reopening(self.link.lost)
        since, before, refused_before = self._listening
        seconds = self.clock.now() - since
        heard = self.link.traffic.since(before)
        refused = self._px4_refusals() - refused_before
        if refused:
            return self._px4_key_problem(refused, seconds)
        if heard.messages:
            return (f"MAVLink arrives from {self.link.address.where} but no HEARTBEAT from "
                    f"system {self.options.target_system} component "
                    f"{self.options.target_component} in {seconds:.1f} s: check [mavlink] "
                    "target_system and target_component (PX4's MAV_SYS_ID)")
        return self.link.describe_silence(seconds, heard)

    def _px4_refusals(self) -> Counter:
        """Messages from PX4's ids that signing refused, by kind, since the link opened."""
        px4 = (self.options.target_system, self.options.target_component)
        return Counter({kind: self.link.refused.total(kind, px4)
                        for kind in (UNSIGNED, BAD_SIGNATURE)})

    def _px4_key_problem(self, refused: Counter, seconds: float) -> str:
        """What PX4's refused messages say about its key, and the fix."""
        px4 = (f"PX4 (system {self.options.target_system} component "
               f"{self.options.target_component}) on {self.link.address.where}")
        if refused[BAD_SIGNATURE]:
            return (f"{px4} signs with another key: {refused[BAD_SIGNATURE]} of its messages "
                    f"failed our signature check in {seconds:.1f} s; give it this key "
                    "(`companion signing provision --current-key-file PX4S_KEY`) or use its "
                    "key here ([mavlink] signing_key_file)")
        return (f"{px4} does not sign: {refused[UNSIGNED]} unsigned messages ignored in "
                f"{seconds:.1f} s; it has no signing key: give it this one with `companion "
                "signing provision` (MAVLink signing needs PX4 v1.18 or later)")

    @property
    def signing(self) -> dict:
        """MAVLink signing on this link: ``on``, and the messages it refused since it opened,
        from any sender: ``unsigned`` and ``bad_signature`` (a wrong key, or a replay)."""
        return {"on": self.link.signing_enabled, **self.link.refused.summary()}

    def take_imu(self) -> list[ImuSample]:
        """Every IMU sample since the last call, oldest first (the ring keeps the newest
        ``imu_queue_size``; overflow is counted in ``counts['imu_overflow']``)."""
        samples = []
        while self._imu_queue:
            samples.append(self._imu_queue.popleft())
        return samples

    def stats(self) -> dict[str, int]:
        """Every counter: messages ignored, IMU samples dropped (``imu_*``), TIMESYNC samples
        rejected, undecodable bytes (``bad_data``), odometry not sent, ..."""
        stats = dict(self.counts)
        stats.update({f"imu_{key}": value for key, value in self._imu.counts.items()})
        stats.update(timesync_outliers=self.timesync.outliers,
                     timesync_rejected_rtt=self.timesync.rejected_rtt,
                     timesync_resets=self.timesync.resets,
                     bad_data=self.link.bad_data_count)
        return stats

    # ---------------------------------------------------------------- the task

    async def run(self) -> None:
        """Poll the link and keep up the protocol until cancelled; never raises otherwise."""
        try:
            while True:
                self._poll(self.clock.now())
                await self.clock.sleep(self.options.poll_interval_s)
        finally:
            if self._imu_request is not None:
                self._imu_request.cancel()

    def _poll(self, now: float) -> None:
        self._count_deaf_time(now)
        if self.link.lost is None:
            for message in self._receive():
                self._dispatch(message, now)
        self._watch_device(now)
        self._watch_link(now)
        self._watch_refusals(now)
        self._send_due(now)
        self._check_imu_rate(now)

    def _receive(self) -> list:
        try:
            return self.link.receive_pending()
        except OSError as error:
            self.counts["receive_errors"] += 1
            log.debug("MAVLink receive failed: %s", error)
            return []

    def _dispatch(self, message, now: float) -> None:
        source = (message.get_srcSystem(), message.get_srcComponent())
        if message.get_type() in ("COMMAND_LONG", "COMMAND_INT") and self._for_us(message):
            self._on_command_to_us(message, source)
            return
        if source != (self.options.target_system, self.options.target_component):
            self.counts["foreign"] += 1
            return
        handler = self._handlers.get(message.get_type())
        if handler is None:
            self.counts["unhandled"] += 1
            return
        try:
            handler(message, now)
        except Exception as error:  # noqa: BLE001 - a bad message must never stop the link
            self.counts["handler_errors"] += 1
            log.warning("ignored %s: %s: %s", message.get_type(), type(error).__name__, error)

    def _count_deaf_time(self, now: float) -> None:
        if self._last_poll is not None and now - self._last_poll > DEAF_POLL_GAP_S:
            self._deaf_s += now - self._last_poll
        self._last_poll = now

    def _watch_link(self, now: float) -> None:
        """The link is lost after ``link_timeout_s`` of PX4's silence while we listened; one
        that is down says why (:attr:`link_problem`) once it has been silent as long."""
        if not self.connected:
            self._log_silence(now)
            return
        silent_s = now - self._last_heartbeat - self._deaf_s
        if silent_s > self.options.link_timeout_s:
            self._lose_link(now, f"no HEARTBEAT for {now - self._last_heartbeat:.1f} s "
                                 f"({self._deaf_s:.1f} s of it not listening)")

    def _watch_refusals(self, now: float) -> None:
        """One warning per burst of messages signing refused (the first after
        :data:`REFUSAL_QUIET_S` without any), naming the newest: a ground station without the
        key sends a stream of them, and a line for each would bury the log."""
        refused = self.link.refused
        total = refused.total()
        if total == self._refusals_seen:
            return
        if now - self._last_refusal_t >= REFUSAL_QUIET_S:
            counts = refused.summary()
            log.warning("MAVLink signing: ignored %s (%d unsigned and %d badly signed messages "
                        "so far); a sender without this vehicle's key", refused.last.describe(),
                        counts[UNSIGNED], counts[BAD_SIGNATURE])
        self._refusals_seen, self._last_refusal_t = total, now

    def _log_silence(self, now: float) -> None:
        since, _, _ = self._listening
        if (self._silence_logged or self.link.lost is not None
                or now - since <= self.options.link_timeout_s):
            return
        self._silence_logged = True
        log.warning("%s", self.link_problem)

    def _listen(self, now: float) -> None:
        """From ``now`` on, :attr:`link_problem` tells what arrives instead of PX4."""
        self._listening = (now, self.link.traffic, self._px4_refusals())
        self._silence_logged = False

    def _watch_device(self, now: float) -> None:
        """A device gone away (:attr:`MavlinkLink.lost`) is a lost link at once, and is
        reopened every :data:`REOPEN_INTERVAL_S` until it comes back."""
        lost = self.link.lost
        if lost is None:
            return
        if self._reopen_at is None:
            self.counts["device_lost"] += 1
            self._reopen_at = now + REOPEN_INTERVAL_S
            if self.connected:
                self._lose_link(now, _reopening(lost))
            else:
                log.warning("%s", _reopening(lost))
        elif now >= self._reopen_at:
            self._reopen(now)

    def _reopen(self, now: float) -> None:
        self._reopen_at = now + REOPEN_INTERVAL_S
        try:
            self.link.reopen()
        except OSError as error:
            self.counts["reopen_failures"] += 1
            log.debug("not back: %s", error)
            return
        log.info("%s is back", self.link.address.where)
        self._reopen_at = None
        self._listen(now)

    def _lose_link(self, now: float, reason: str) -> None:
        """Connected no more: counted, and the IMU chain and the TIMESYNC estimate dropped
        (PX4 may come back rebooted, its boot time restarted)."""
        self.connected = False
        self.link_losses += 1
        log.warning("PX4 link lost: %s", reason)
        self._listen(now)
        self._imu.restart()
        self.timesync.reset()
        self._timesync_sent.clear()
        self.imu_rate_hz = 0.0
        # what PX4 said before the loss says nothing of a disarm heard after it (a reboot)
        self._armed_on_the_ground_since = None
        if self._imu_request is not None:
            self._imu_request.cancel()

    def _on_connect(self, now: float) -> None:
        self.connected = True
        log.info("PX4 link up (system %d component %d)", self.options.target_system,
                 self.options.target_component)
        self._next_timesync = now
        self._rate_window = (now, 0)
        self._request_imu(now)

    # ---------------------------------------------------------------- periodic sends

    def _send_due(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0 / self.options.heartbeat_rate_hz
            self._send(self.link.mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                int(self._status)))
        if now >= self._next_timesync:
            self._next_timesync = now + 1.0 / self.options.timesync_rate_hz
            self._send_timesync_request(now)

    def _send_timesync_request(self, now: float) -> None:
        ts1 = _ns(now)
        self._timesync_sent[ts1] = now
        while len(self._timesync_sent) > TIMESYNC_PENDING:
            del self._timesync_sent[next(iter(self._timesync_sent))]
        self._send(self.link.mav.timesync_encode(0, ts1))

    def _check_imu_rate(self, now: float) -> None:
        start, count = self._rate_window
        if now - start < IMU_RATE_WINDOW_S:
            return
        self._rate_window = (now, 0)
        if not math.isfinite(start):
            return
        self.imu_rate_hz = count / (now - start)
        wanted = self.options.imu_rate_hz
        if (self.connected and self.imu_rate_hz < IMU_LOW_RATE_FRACTION * wanted
                and now - self._imu_requested_at >= IMU_REREQUEST_S
                and (self._imu_request is None or self._imu_request.done())):
            log.warning("HIGHRES_IMU arrives at %.0f Hz, %.0f Hz asked: asking again",
                        self.imu_rate_hz, wanted)
            self._request_imu(now)

    def _request_imu(self, now: float) -> None:
        self._imu_requested_at = now
        self.counts["imu_interval_requests"] += 1
        if self._imu_request is not None:
            self._imu_request.cancel()
        self._imu_request = asyncio.get_running_loop().create_task(self._set_imu_interval())

    async def _set_imu_interval(self) -> None:
        rate = self.options.imu_rate_hz
        try:
            await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                               mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, round(1e6 / rate))
        except AutopilotError as error:
            log.warning("HIGHRES_IMU at %g Hz not set: %s", rate, error)
        else:
            log.info("HIGHRES_IMU requested at %g Hz", rate)

    # ---------------------------------------------------------------- incoming

    def _on_heartbeat(self, message, now: float) -> None:
        self._last_heartbeat, self._deaf_s = now, 0.0
        armed = bool(message.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if armed and not self.armed:
            self._armed_on_the_ground_since, self.disarmed_on_the_ground = None, False
        elif self.armed and not armed:
            self.disarmed_on_the_ground = self._came_down_before_last_armed_heartbeat()
        if armed:
            self._last_armed_heartbeat = now
        self.armed = armed
        try:
            self.mode = px4_protocol.Px4Mode.from_custom_mode(message.custom_mode)
        except ValueError:
            self.mode = None
            self.counts["unknown_mode"] += 1
        if not self.connected:
            self._on_connect(now)

    def _on_timesync(self, message, now: float) -> None:
        if message.tc1 == 0:  # PX4's request: answer with our time
            self._send(self.link.mav.timesync_encode(_ns(now), message.ts1))
            self.counts["timesync_answered"] += 1
            return
        sent = self._timesync_sent.pop(message.ts1, None)
        if sent is None:
            self.counts["timesync_unmatched"] += 1
            return
        used = self.timesync.add(sent, message.tc1 * 1e-9, now)
        if self.on_timesync is not None:
            self.on_timesync(now, used)

    def _on_highres_imu(self, message, now: float) -> None:
        start, count = self._rate_window
        self._rate_window = (start, count + 1)
        sample = self._imu.push(message.time_usec * 1e-6,
                                (message.xgyro, message.ygyro, message.zgyro),
                                (message.xacc, message.yacc, message.zacc), self.timesync.offset,
                                updated_pressure(message.fields_updated, message.abs_pressure))
        if sample is None:
            return
        if len(self._imu_queue) == self._imu_queue.maxlen:
            self.counts["imu_overflow"] += 1
        self._imu_queue.append(sample)
        self.last_imu_t = sample.t

    def _on_command_ack(self, message, now: float) -> None:
        pending = self._pending_ack
        ours = (message.target_system in (0, self.options.system_id)
                and message.target_component in (0, self.options.component_id))
        if pending is None or pending[0] != message.command or pending[1].done() or not ours:
            self.counts["unexpected_ack"] += 1
            return
        pending[1].set_result(message.result)

    def _came_down_before_last_armed_heartbeat(self) -> bool:
        """Did PX4 say on the ground, armed, before the last HEARTBEAT that said armed? Then
        the disarm that followed was of a vehicle that had come down.
        PX4's land detector says landed within its hysteresis of any disarm, in the air too
        (MulticopterLandDetector.cpp, ``_get_landed_state``: ``!_armed || ...``, through
        ``_landed_hysteresis``, ``LNDMC_TRIG_TIME / 3``), so after a disarm in the air the
        word comes after PX4's last armed HEARTBEAT, however many are lost; its auto-disarm
        waits ``COM_DISARM_LAND`` (2 s by default) on the ground, over a HEARTBEAT period."""
        since = self._armed_on_the_ground_since
        return since is not None and since < self._last_armed_heartbeat

    def _on_extended_sys_state(self, message, now: float) -> None:
        self._landed_state = message.landed_state
        if message.landed_state != mavlink.MAV_LANDED_STATE_ON_GROUND:
            self._armed_on_the_ground_since = None
        elif self.armed and self._armed_on_the_ground_since is None:
            self._armed_on_the_ground_since = now

    def _on_home_position(self, message, now: float) -> None:
        self.home_altitude_amsl = message.altitude * 1e-3
        position = ned_to_enu((message.x, message.y, message.z))
        self.home_position_L = position if np.isfinite(position).all() else None
        if self.home_position_L is None:
            self.counts["home_position_unknown"] += 1

    def _on_odometry(self, message, now: float) -> None:
        t = self.timesync.to_local(message.time_usec * 1e-6)
        if message.frame_id != mavlink.MAV_FRAME_LOCAL_NED or t is None:
            self.counts["odometry_ignored"] += 1
            return
        q_L_B = quat_ned_frd_to_enu_flu(message.q)
        velocity = (message.vx, message.vy, message.vz)
        if message.child_frame_id == mavlink.MAV_FRAME_BODY_FRD:
            velocity_L = quat_to_rot(q_L_B) @ frd_to_flu(velocity)
        elif message.child_frame_id == mavlink.MAV_FRAME_LOCAL_NED:
            velocity_L = ned_to_enu(velocity)
        else:
            self.counts["odometry_ignored"] += 1
            return
        rates = frd_to_flu((message.rollspeed, message.pitchspeed, message.yawspeed))
        self._set_state(VehicleState(t, ned_to_enu((message.x, message.y, message.z)),
                                     velocity_L, q_L_B, rates))
        self._last_odometry = now

    def _on_attitude(self, message, now: float) -> None:
        q = quat_ned_frd_to_enu_flu((message.q1, message.q2, message.q3, message.q4))
        rates = frd_to_flu((message.rollspeed, message.pitchspeed, message.yawspeed))
        self._attitude = (q, rates)

    def _on_local_position(self, message, now: float) -> None:
        """The estimate from LOCAL_POSITION_NED + ATTITUDE_QUATERNION, used only while no
        ODOMETRY has come for a link timeout."""
        if now - self._last_odometry <= self.options.link_timeout_s or self._attitude is None:
            return
        t = self.timesync.to_local(message.time_boot_ms * 1e-3)
        if t is None:
            return
        self._set_state(VehicleState(t, ned_to_enu((message.x, message.y, message.z)),
                                     ned_to_enu((message.vx, message.vy, message.vz)),
                                     *self._attitude))

    def _set_state(self, state: VehicleState) -> None:
        """Keep ``state`` when its position is finite and its quaternion a unit one (within
        :data:`QUATERNION_NORM_TOLERANCE`, then normalised); else count ``state_invalid``."""
        norm = float(np.linalg.norm(state.q_L_B))
        if not (np.isfinite(state.position_L).all()
                and abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE):
            self.counts["state_invalid"] += 1
            return
        self.state = dataclasses.replace(state, q_L_B=state.q_L_B / norm)

    def _on_rc_channels(self, message, now: float) -> None:
        count = min(int(message.chancount), 18)
        raw = (int(getattr(message, f"chan{i}_raw")) for i in range(1, count + 1))
        self.rc_channels_us = tuple(None if pulse == RC_UNUSED else pulse for pulse in raw)

    def _for_us(self, message) -> bool:
        return (message.target_system == self.options.system_id
                and message.target_component == self.options.component_id)

    def _on_command_to_us(self, message, source: tuple[int, int]) -> None:
        """A command a ground station addressed to the companion (PX4 forwards it): the
        operator's go (MAV_CMD_MISSION_START) is handed to :attr:`on_go`; anything else is
        UNSUPPORTED. Every one is acknowledged to its sender."""
        if message.command != mavlink.MAV_CMD_MISSION_START:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        elif self.on_go is not None and self.on_go(f"MAV_CMD_MISSION_START from "
                                                   f"{source[0]}/{source[1]}"):
            result = mavlink.MAV_RESULT_ACCEPTED
        else:
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self.counts["commands_to_us"] += 1
        self._send(self.link.mav.command_ack_encode(message.command, result, 0, 0,
                                                    source[0], source[1]))

    def _on_statustext(self, message, now: float) -> None:
        text = self._assemble(message)
        if text is None:
            return
        self.statustexts.append(StatusText(now, message.severity, text))
        self._statustext_total += 1
        log.log(_log_level(message.severity), "PX4: %s", text)

    def _assemble(self, message) -> str | None:
        """The whole text once its last chunk arrived (MAVLink 2 ``id``/``chunk_seq``)."""
        text, chunk_id = message.text, getattr(message, "id", 0)
        if not chunk_id:
            return text
        chunks = self._chunks.setdefault(chunk_id, [])
        chunks.append(text)
        if len(chunks) >= STATUSTEXT_MAX_CHUNKS and len(text) >= STATUSTEXT_CHUNK:
            return "".join(self._chunks.pop(chunk_id)) + " [cut]"
        if len(text) >= STATUSTEXT_CHUNK:
            if len(self._chunks) > 4:  # abandoned texts: keep the newest only
                self._chunks = {chunk_id: chunks}
            return None
        return "".join(self._chunks.pop(chunk_id))

    # ---------------------------------------------------------------- commands

    async def command(self, command: int, *params: float) -> None:
        """COMMAND_LONG to PX4 (unused params 0), re-sent ``command_retries`` times without
        an ack; returns on MAV_RESULT_ACCEPTED. Raises :class:`NotConnected`,
        :class:`CommandDenied` (with PX4's statustexts of the moment) or
        :class:`CommandTimeout`."""
        name = _enum_name("MAV_CMD", command)
        if len(params) > 7:
            raise ValueError(f"{name}: at most 7 params, got {len(params)}")
        if not self.connected:
            raise NotConnected(f"{name}: no HEARTBEAT from PX4 (system "
                               f"{self.options.target_system}) within "
                               f"{self.options.link_timeout_s:g} s")
        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        async with self._command_lock:
            texts_before = self._statustext_total
            for attempt in range(1 + self.options.command_retries):
                self._send(self.link.mav.command_long_encode(
                    self.options.target_system, self.options.target_component, command,
                    attempt, *values))
                result = await self._await_ack(command)
                if result == mavlink.MAV_RESULT_ACCEPTED:
                    return
                if result is not None:
                    raise CommandDenied(self._denial(name, result, texts_before), result)
        raise CommandTimeout(f"{name}: no COMMAND_ACK from PX4 after "
                             f"{1 + self.options.command_retries} tries of "
                             f"{self.options.command_timeout_s:g} s")

    def _denial(self, name: str, result: int, texts_before: int) -> str:
        new = min(self._statustext_total - texts_before, len(self.statustexts))
        texts = [entry.text for entry in list(self.statustexts)[len(self.statustexts) - new:]]
        said = f" (PX4: {'; '.join(texts)})" if texts else ""
        return f"{name} refused by PX4: {_enum_name('MAV_RESULT', result)}{said}"

    async def _await_ack(self, command: int) -> int | None:
        """The result of the next COMMAND_ACK for ``command``, None after the timeout;
        IN_PROGRESS acks extend the wait."""
        loop = asyncio.get_running_loop()
        try:
            while True:
                future = loop.create_future()
                self._pending_ack = (command, future)
                result = await self._wait(future, self.options.command_timeout_s)
                if result != mavlink.MAV_RESULT_IN_PROGRESS:
                    return result
        finally:
            self._pending_ack = None

    async def _wait(self, future: asyncio.Future, timeout: float):
        """``future``'s result, or None once ``timeout`` has passed on our clock."""
        sleeper = asyncio.ensure_future(self.clock.sleep(timeout))
        try:
            await asyncio.wait({future, sleeper}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            sleeper.cancel()
        return future.result() if future.done() else None

    async def _verb(self, command: int, *params: float) -> bool:
        """:meth:`command` as a verb: True when accepted; False when not, the reason logged
        and kept in :attr:`last_command_error`."""
        try:
            await self.command(command, *params)
        except AutopilotError as error:
            self.last_command_error = error
            log.warning("%s", error)
            return False
        self.last_command_error = None
        return True

    async def arm(self) -> bool:
        """Arm (PX4 runs its preflight checks)."""
        return await self._verb(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0)

    async def disarm(self, force: bool = False) -> bool:
        """Disarm; ``force`` also in the air (PX4's 21196 magic: the motors stop)."""
        return await self._verb(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                px4_protocol.FORCE_ARM_DISARM_MAGIC if force else 0)

    async def set_mode(self, mode: px4_protocol.Px4Mode) -> bool:
        """Switch PX4's flight mode (MAV_CMD_DO_SET_MODE with the custom main/sub mode).
        OFFBOARD needs setpoints streamed at more than 2 Hz for over a second first."""
        return await self._verb(mavlink.MAV_CMD_DO_SET_MODE,
                                mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(mode.main),
                                int(mode.sub))

    async def takeoff(self, altitude_m: float | None = None) -> bool:
        """Take off to ``altitude_m`` above home, or PX4's MIS_TAKEOFF_ALT when None.

        MAV_CMD_NAV_TAKEOFF's param7 is AMSL: home's altitude (HOME_POSITION, requested when
        not yet known) plus ``altitude_m``; NaN asks for PX4's default. ValueError for an
        altitude that is not a positive number."""
        amsl = math.nan
        if altitude_m is not None:
            if not (math.isfinite(altitude_m) and altitude_m > 0.0):
                raise ValueError(f"takeoff altitude must be a positive number of metres, got "
                                 f"{altitude_m!r}")
            home = await self._home_altitude()
            if home is None:
                return False
            amsl = home + altitude_m
        nan = math.nan
        return await self._verb(mavlink.MAV_CMD_NAV_TAKEOFF, nan, 0, 0, nan, nan, nan, amsl)

    async def _home_altitude(self) -> float | None:
        """Home's AMSL altitude, asked for when not yet known; None (reason kept) if PX4
        does not send it."""
        if self.home_altitude_amsl is None and await self._verb(
                mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION):
            deadline = self.clock.now() + self.options.command_timeout_s
            while self.home_altitude_amsl is None and self.clock.now() < deadline:
                await self.clock.sleep(self.options.poll_interval_s)
            if self.home_altitude_amsl is None:
                self.last_command_error = AutopilotError(
                    "takeoff: PX4 sent no HOME_POSITION, so no take-off altitude can be "
                    "given (pass None for PX4's default)")
                log.warning("%s", self.last_command_error)
        return self.home_altitude_amsl

    async def land(self) -> bool:
        """Land where the vehicle is (AUTO.LAND)."""
        nan = math.nan
        return await self._verb(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, nan, nan, nan, nan)

    async def hold(self) -> bool:
        """Hold position (AUTO.LOITER, "Hold" in QGroundControl)."""
        return await self.set_mode(px4_protocol.AUTO_LOITER)

    async def read_parameters(self, names, timeout_s: float) -> dict[str, int | float]:
        """PX4's values of the named parameters, decoded (drivers/mavlink/parameters.py); a
        name PX4 does not answer within ``timeout_s`` is absent."""
        return await self.parameters.read(names, timeout_s)

    # ---------------------------------------------------------------- thread-safe sends

    def _send(self, message) -> None:
        """Send under the lock: pymavlink's sequence numbers and signing are not thread-safe."""
        with self._send_lock:
            try:
                self.link.send(message)
            except OSError as error:
                self.counts["send_errors"] += 1
                log.debug("MAVLink send failed: %s", error)

    def _boot_ms(self) -> int:
        remote = self.timesync.to_remote(self.clock.now())
        return 0 if remote is None else int(min(max(remote * 1e3, 0.0), 2**32 - 1))

    def send_velocity(self, velocity_L, yaw_rate: float = 0.0, acceleration_L=None) -> None:
        """Offboard velocity setpoint: ``velocity_L`` (3,) m/s in frame L (ENU), a yaw rate in
        rad/s about z up and, optionally, ``acceleration_L`` (3,) m/s² as feed-forward; sent as
        SET_POSITION_TARGET_LOCAL_NED (local NED). ValueError for non-finite input: nothing is
        sent."""
        velocity = _finite_vector(velocity_L, "velocity_L", "m/s")
        if not math.isfinite(yaw_rate):
            raise ValueError(f"yaw_rate must be a finite number (rad/s), got {yaw_rate!r}")
        if acceleration_L is None:
            mask, acceleration = px4_protocol.TYPE_MASK_VELOCITY_YAW_RATE, np.zeros(3)
        else:
            mask = px4_protocol.TYPE_MASK_VELOCITY_ACCELERATION_YAW_RATE
            acceleration = _finite_vector(acceleration_L, "acceleration_L", "m/s²")
        self._send(self.link.mav.set_position_target_local_ned_encode(
            self._boot_ms(), self.options.target_system, self.options.target_component,
            mavlink.MAV_FRAME_LOCAL_NED, mask, 0.0, 0.0, 0.0,
            *enu_to_ned(velocity), *enu_to_ned(acceleration), 0.0, -float(yaw_rate)))

    def send_odometry(self, t: float, position_L, q_L_B, velocity_L=None,
                      angular_velocity_B=None, pose_covariance=None, reset_counter: int = 0,
                      quality: int = 100) -> bool:
        """External-vision ODOMETRY for PX4's estimator; False (counted as
        ``odometry_no_time``) while TIMESYNC has no offset to stamp it in PX4 boot time.

        ``t`` companion time, ``position_L``/``velocity_L`` frame L (ENU), ``q_L_B`` (w, x, y,
        z), ``angular_velocity_B`` FLU, ``pose_covariance`` 6x6 rotation then position in the
        body frame (conversion in :mod:`drivers.mavlink.odometry`); None or NaN: unknown.
        ``reset_counter`` goes out modulo 256; ``quality`` as MAVLink defines it: -1 the
        odometry has failed, 0 unknown, 1 (worst) to 100 (best)."""
        if isinstance(quality, bool) or not isinstance(quality, int) \
                or not -1 <= quality <= 100:
            raise ValueError(f"quality must be an integer -1..100, got {quality!r}")
        if not math.isfinite(t):
            raise ValueError(f"odometry time must be finite, got {t!r}")
        fields = odometry_fields(position_L, q_L_B, velocity_L, angular_velocity_B)
        covariance = pose_covariance_to_mavlink(pose_covariance, fields["q_L_B"])
        remote = self.timesync.to_remote(t)
        if remote is None or remote < 0.0:
            self.counts["odometry_no_time"] += 1
            return False
        self._send(self.link.mav.odometry_encode(
            round(remote * 1e6), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD,
            *fields["position"], fields["q"], *fields["velocity"], *fields["rates"],
            covariance, [math.nan] + [0.0] * 20, int(reset_counter) % 256,
            mavlink.MAV_ESTIMATOR_TYPE_VIO, quality))
        self.counts["odometry_sent"] += 1
        return True


def _reopening(lost: LinkLost) -> str:
    return f"{lost}; reopening it every {REOPEN_INTERVAL_S:g} s"


def _ns(t: float) -> int:
    """Companion seconds as TIMESYNC nanoseconds, never 0 (tc1 = 0 marks a request)."""
    return max(1, int(round(t * 1e9)))


def _finite_vector(value, name: str, unit: str) -> np.ndarray:
    vector = np.asarray(value, dtype=float)
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise ValueError(f"{name} must be 3 finite numbers ({unit}), got {value!r}")
    return vector
