"""A MAVLink 2 connection opened from a URL, read without blocking.

URLs follow MAVSDK's connection strings (MAVSDK v2 and later, ``cpp/src/mavsdk/core/cli_arg.cpp``
and its "Connecting to Systems" guide), so a person types what they already know:

==============================  ==============================================================
``udpin://HOST:PORT``           listen on HOST:PORT (``0.0.0.0``: every interface) and answer
                                whoever sent to us; PX4 SITL's onboard link sends to 14540
``udpout://HOST:PORT``          send to HOST:PORT and receive the replies on the same socket
                                (what ``companion sim serve`` expects on 14540)
``tcpin://HOST:PORT``           listen for a TCP client, one at a time (when it hangs up, listen
                                again); HOST empty or ``0.0.0.0``: every interface
``tcpout://HOST:PORT``          connect to a TCP server; a server that goes away is a lost link,
                                reconnected like an unplugged serial port
``tcp://HOST:PORT``             deprecated, as in MAVSDK: HOST empty or ``0.0.0.0`` listens
                                (``tcpin``), any other host is connected to (``tcpout``); opening
                                it logs the URL to write instead
``serial:///dev/ttyX[:BAUD]``   a serial port at one of PX4's baud rates (``SER_TELn_BAUD``),
                                57600 unless given, e.g. ``serial:///dev/ttyTHS1:921600``
``pty``                         a new pseudo-terminal pair: we hold the master side, and a
                                client opens :attr:`MavlinkLink.pty_path` like a serial port
==============================  ==============================================================

As MAVSDK does, ``udpout`` and ``tcpout`` refuse ``0.0.0.0`` (every interface can be listened
on, not sent to) and ``udpin`` needs a host.

Serial ports are opened through pyserial: raw 8N1, no flow control, non-blocking, at the given
rate directly (as MAVSDK does; pymavlink's detour through 1200 baud works around kernels long
gone), and exclusively, so two programs never share a port silently, each reading half of the
bytes: pyserial's ``exclusive`` (flock) stops another process that locks too (a second
companion, any pyserial program), and TIOCEXCL makes the kernel refuse every later open but
root's (mavproxy, screen). A process that had the port open before us (nvgetty's console) is
seen by neither: ``fuser -v /dev/ttyTHS1`` names it. What cannot be opened raises
:class:`LinkError`, an OSError the command line prints as one line, naming the port, the
baud rate and what to check.

A device that goes away while open (a USB adapter unplugged: EIO; a pseudo-terminal whose other
side closed: end of file; a TCP server gone) sets :attr:`MavlinkLink.lost` and is closed, so an
adapter plugged back in gets its old name again; the link then receives and sends nothing until
:meth:`MavlinkLink.reopen` finds it back. When nothing MAVLink arrives,
:meth:`MavlinkLink.describe_silence` says what came instead (no bytes at all, or bytes that do
not parse: a wrong baud rate) and what to check for that kind of link.

Every link speaks MAVLink 2 with the ``common`` dialect (everything PX4 sends and accepts
here is in it). Signing follows the MAVLink 2 message signing spec: a 32-byte secret key,
outgoing messages signed, and unsigned incoming ones accepted only when a callback allows
their message id (see :func:`drivers.mavlink.px4_protocol.accept_unsigned`).
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import socket
import termios
import threading
import tty
from dataclasses import dataclass
from typing import Callable
from urllib.parse import urlsplit

import serial

os.environ["MAVLINK20"] = "1"  # pymavlink picks the wire protocol when a dialect is loaded

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from drivers.mavlink.signing import REFUSED_REASON, SECRET_KEY_LENGTH, Refusals  # noqa: E402

mavutil.set_dialect("common")

log = logging.getLogger(__name__)
# pymavlink logs every frame whose signature fails at INFO ("sig mismatch"): 300 lines a
# second from a flight controller with another key. The link counts them by sender and warns
# once per burst (drivers/mavlink/signing.py), so pymavlink's logger keeps its warnings only.
logging.getLogger(mavlink.__name__).setLevel(logging.WARNING)

DEFAULT_SERIAL_BAUD = 57600
#: The rates PX4 can set a serial port to: the values of its ``SER_xxx_BAUD`` parameters
#: (PX4-Autopilot's generated ``serial_params.c``), 0 (auto, for a GPS) left out.
PX4_BAUD_RATES = (50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200,
                  38400, 57600, 115200, 230400, 460800, 500000, 921600, 1000000, 1500000,
                  2000000, 3000000)
#: Most reads of a message (good or bad) in one :meth:`MavlinkLink.receive_pending` call, so a
#: flood, of garbage too, cannot starve the caller's loop; the rest wait for the next call.
MAX_MESSAGES_PER_RECEIVE = 2000
#: Bytes read from a byte stream (serial port, pseudo-terminal, TCP) at once.
READ_CHUNK = 4096
#: Longest wait for a TCP server to accept us when the link is opened, and when it is
#: reopened from the poll loop (which must not stall), seconds.
TCP_CONNECT_TIMEOUT_S = 3.0
TCP_RECONNECT_TIMEOUT_S = 0.1
#: Every interface, for a listening link.
ANY_HOST = "0.0.0.0"

SCHEMES = ("udpin", "udpout", "tcpin", "tcpout", "tcp", "serial", "pty")


class LinkError(OSError):
    """A link that cannot be opened (or reopened): the message names the port or address and
    says what to check. An OSError, so whoever reports OSErrors as one line reports it too."""


class LinkLost(LinkError):
    """The device or peer went away while the link was open."""


@dataclass(frozen=True)
class LinkAddress:
    """A parsed connection URL: ``scheme`` and either host/port, a serial device, or nothing."""

    scheme: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    @property
    def where(self) -> str:
        """The link as a message names it: ``/dev/ttyTHS1 at 921600 baud``, a URL."""
        if self.scheme == "serial":
            return f"{self.device} at {self.baud} baud"
        if self.scheme == "pty":
            return "a new pseudo-terminal"
        return f"{self.scheme}://{self.host}:{self.port}"


@dataclass(frozen=True)
class Traffic:
    """What a link has received: bytes, and the MAVLink messages among them."""

    bytes: int = 0
    messages: int = 0

    def since(self, earlier: "Traffic") -> "Traffic":
        return Traffic(self.bytes - earlier.bytes, self.messages - earlier.messages)


def parse_url(url: str) -> LinkAddress:
    """Parse a connection URL (see the module docstring); ValueError naming the problem. A
    deprecated ``tcp://`` comes back as the ``tcpin`` or ``tcpout`` it means."""
    if not isinstance(url, str) or not url.strip():
        raise ValueError(f"MAVLink URL must be a non-empty string, got {url!r}")
    url = url.strip()
    if url == "pty":
        return LinkAddress("pty")
    if "://" not in url:
        raise ValueError(
            f"MAVLink URL {url!r} has no scheme; expected one of "
            + ", ".join(f"{s}://" for s in SCHEMES if s != "pty") + " or 'pty'"
        )
    scheme, rest = url.split("://", 1)
    if scheme not in SCHEMES or scheme == "pty":
        raise ValueError(f"MAVLink URL {url!r}: unknown scheme {scheme!r}; expected one of "
                         f"{', '.join(SCHEMES)}")
    if scheme == "serial":
        return _parse_serial(url, rest)
    return _parse_host_port(url, scheme)


def _parse_serial(url: str, rest: str) -> LinkAddress:
    device, _, baud_text = rest.partition(":")
    if not device.startswith("/"):
        raise ValueError(f"MAVLink URL {url!r}: serial device must be an absolute path "
                         "like serial:///dev/ttyTHS1:921600")
    if not baud_text:
        return LinkAddress("serial", device=device, baud=DEFAULT_SERIAL_BAUD)
    if not baud_text.isdigit():
        raise ValueError(f"MAVLink URL {url!r}: baud rate must be a positive integer, "
                         f"got {baud_text!r}")
    if int(baud_text) not in PX4_BAUD_RATES:
        raise ValueError(f"MAVLink URL {url!r}: {int(baud_text)} baud is not a rate PX4 can "
                         "set its port to (SER_TELn_BAUD); one of "
                         + ", ".join(map(str, PX4_BAUD_RATES)))
    return LinkAddress("serial", device=device, baud=int(baud_text))


def _parse_host_port(url: str, scheme: str) -> LinkAddress:
    """host:port with MAVSDK's rules (module docstring)."""
    parts = urlsplit(url)
    if parts.path or parts.query or parts.fragment:
        raise ValueError(f"MAVLink URL {url!r}: expected {scheme}://host:port and nothing after")
    try:
        port = parts.port
    except ValueError as error:
        raise ValueError(f"MAVLink URL {url!r}: bad port ({error})") from None
    if port is None or port == 0:
        raise ValueError(f"MAVLink URL {url!r}: expected {scheme}://host:port with a port "
                         "in 1..65535")
    host = parts.hostname or ""
    if scheme == "tcp":
        scheme = "tcpin" if host in ("", ANY_HOST) else "tcpout"
    if scheme == "tcpin":
        return LinkAddress(scheme, host=host or ANY_HOST, port=port)
    if not host:
        raise ValueError(f"MAVLink URL {url!r}: expected {scheme}://host:port"
                         + (f" ({ANY_HOST} listens on every interface)"
                            if scheme == "udpin" else ""))
    if host == ANY_HOST and scheme != "udpin":
        raise ValueError(f"MAVLink URL {url!r}: {ANY_HOST} can be listened on, not sent to: "
                         f"{scheme.replace('out', 'in')}://{ANY_HOST}:{port} listens on every "
                         "interface")
    return LinkAddress(scheme, host=host, port=port)


#: What to check when a link heard nothing at all, by scheme (formatted with the address
#: and the pseudo-terminal's path).
_SILENT_HINTS = {
    "serial": "check the TELEM port and its wiring (PX4 runs MAVLink on the port MAV_n_CONFIG "
              "names; its TX goes to our RX) and the baud rate (PX4 SER_TELn_BAUD)",
    "udpin": "check that PX4 sends to this computer's port {a.port} (PX4 SITL's onboard link "
             "sends to 14540; on a vehicle, `mavlink start -o {a.port}` or mavlink-router) and "
             "that no firewall drops it",
    "udpout": "check that PX4 or `companion sim serve` listens on {a.host}:{a.port} (UDP "
              "cannot tell whether anyone receives what we send)",
    "tcpin": "check that PX4 or mavlink-router connects to port {a.port} here",
    "tcpout": "check that {a.host}:{a.port} is a MAVLink endpoint (PX4, mavlink-router, "
              "`companion sim serve --mavlink tcpin://...`)",
    "pty": "check that a client opened {pty_path}",
}
#: What to check when bytes arrived but none parse as MAVLink, by scheme.
_GARBLED_HINTS = {
    "serial": "check the baud rate (PX4 SER_TELn_BAUD must be {a.baud}) and the TELEM port "
              "(MAV_n_CONFIG: a port running something else, a GPS or a console, sends bytes "
              "too)",
}
_GARBLED_ELSEWHERE = "something that is not MAVLink sends to it"


class MavlinkLink:
    """One MAVLink 2 connection: send messages, take every pending one without blocking.

    ``mav`` is pymavlink's encoder bound to this link (``link.mav.heartbeat_send(...)``).
    Bytes that do not parse (noise, bad CRC, messages signing refused) are counted in
    :attr:`bad_data_count` and never returned; those signing refused are also sorted by kind
    and sender in :attr:`refused`. Sending may happen from another thread than receiving; a
    loss is handled on the receiving side.
    """

    def __init__(self, connection: mavutil.mavfile, address: LinkAddress,
                 pty_path: str | None = None):
        self._connection = connection
        self.address = address
        self.pty_path = pty_path
        self.bad_data_count = 0
        self.refused = Refusals()
        self.messages_received = 0
        #: Why the device went away (a :class:`LinkLost`); None while it is there.
        self.lost: LinkLost | None = None
        self._lock = threading.Lock()  # a send never writes to a device being closed

    @property
    def mav(self) -> mavlink.MAVLink:
        return self._connection.mav

    @property
    def signing_enabled(self) -> bool:
        return self.mav.signing.secret_key is not None

    @property
    def traffic(self) -> Traffic:
        """Everything received since the link was opened."""
        return Traffic(self.mav.total_bytes_received, self.messages_received)

    def send(self, message: mavlink.MAVLink_message) -> None:
        """Encode (and sign, when signing is on) one message and write it; nothing while
        :attr:`lost`."""
        with self._lock:
            if self.lost is None:
                self.mav.send(message)

    def receive_pending(self) -> list[mavlink.MAVLink_message]:
        """Every message that has arrived, in order, without waiting for more. When the
        device goes away, those before are returned and :attr:`lost` is set; while lost,
        nothing."""
        messages = []
        for _ in range(MAX_MESSAGES_PER_RECEIVE):
            if self.lost is not None:
                break
            before = self.mav.total_bytes_received
            message = self._receive_one()
            if message is None:
                if self.mav.total_bytes_received == before:
                    break  # nothing more has arrived
                continue
            if message.get_type() == "BAD_DATA":
                self._count_bad(message)
                continue
            messages.append(message)
        self.messages_received += len(messages)
        return messages

    def _count_bad(self, message) -> None:
        self.bad_data_count += 1
        if message.reason == REFUSED_REASON:
            self.refused.add(message.data)

    def _receive_one(self):
        try:
            return self._connection.recv_msg()
        except LinkLost as error:
            self._lose(error)
        except (mavlink.MAVError, ValueError, IndexError, TypeError, UnicodeDecodeError):
            # pymavlink's robust parser reports most corruption as BAD_DATA, but a few
            # malformed payloads still raise while unpacking; treat them alike.
            self.bad_data_count += 1
        return None

    def _lose(self, error: LinkLost) -> None:
        """Close the device at once: a USB adapter plugged back in while we still hold its
        node would come back under another name (ttyACM1)."""
        with self._lock:
            self.lost = error
            self._connection.close()

    def reopen(self) -> None:
        """Open the lost device again (a USB adapter back under its name), keeping the MAVLink
        state (sequence numbers, signing); :class:`LinkError` while it is not back."""
        with self._lock:
            self._connection.reopen()
            self.lost = None

    def describe_silence(self, seconds: float, heard: Traffic) -> str:
        """Why no MAVLink message came in ``seconds`` during which ``heard`` arrived (no bytes
        at all, or bytes none of which parse) and what to check on this kind of link."""
        lead = f"no MAVLink from {self.address.where} in {seconds:.1f} s"
        scheme = self.address.scheme
        if heard.bytes == 0:
            hint = _SILENT_HINTS[scheme].format(a=self.address, pty_path=self.pty_path)
            return f"{lead}: no bytes at all: {hint}"
        hint = _GARBLED_HINTS.get(scheme, _GARBLED_ELSEWHERE).format(a=self.address)
        if self.signing_enabled:
            hint += "; or the signing keys differ"
        return f"{lead}: {heard.bytes} bytes arrived but none parse as MAVLink: {hint}"

    def setup_signing(self, secret_key: bytes, *,
                      accept_unsigned: Callable[[int], bool] | None = None,
                      link_id: int = 0, initial_timestamp: int | None = None) -> None:
        """Sign every outgoing message and reject unsigned incoming ones (a new key replaces
        the old one at once; the lock keeps a send from another thread off a half-changed key).

        ``accept_unsigned(message_id)`` may let chosen unsigned messages through (PX4 keeps a
        short allowlist). ``initial_timestamp`` is in the spec's 10 µs units since
        2015-01-01; by default pymavlink takes it from the wall clock, as the spec asks.
        """
        if not isinstance(secret_key, (bytes, bytearray)):
            raise ValueError(f"MAVLink signing key must be {SECRET_KEY_LENGTH} bytes, got a "
                             f"{type(secret_key).__name__}")
        if len(secret_key) != SECRET_KEY_LENGTH:
            raise ValueError(f"MAVLink signing key must be {SECRET_KEY_LENGTH} bytes, got "
                             f"{len(secret_key)}")
        callback = None
        if accept_unsigned is not None:
            callback = lambda _mav, message_id: bool(accept_unsigned(message_id))  # noqa: E731
        with self._lock:
            self._connection.setup_signing(bytes(secret_key), sign_outgoing=True,
                                           allow_unsigned_callback=callback,
                                           initial_timestamp=initial_timestamp,
                                           link_id=link_id)

    def stop_signing(self) -> None:
        """Sign nothing and accept every message again (a flight controller whose key was
        cleared)."""
        with self._lock:
            self._connection.disable_signing()

    def close(self) -> None:
        self._connection.close()

    def __enter__(self) -> "MavlinkLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _StreamConnection(mavutil.mavfile):
    """A byte stream (serial port, pseudo-terminal, TCP socket) as a pymavlink connection,
    read and written without blocking on ``fd``.

    What the stream cannot take now (its buffer full: nobody reads) is dropped, as bytes on a
    wire nobody listens to. A failed read (EIO from an unplugged USB adapter, a reset TCP
    connection) or the end of the stream means the device or peer went away:
    :class:`LinkLost`, naming it by ``where``. A failed write is dropped too: the read that
    follows says the same, on the reading thread. Closing sets ``fd`` to -1, so a late write
    never reaches a file that took the closed descriptor's number.
    """

    where = "the link"

    def recv(self, n=None):
        # A raw terminal (VMIN = VTIME = 0) reads b"" when it has nothing, as at its end: only
        # a read that finds nothing after select() said readable is the end (pyserial's rule).
        if not select.select([self.fd], [], [], 0)[0]:
            return b""
        try:
            data = os.read(self.fd, READ_CHUNK)
        except BlockingIOError:
            return b""
        except OSError as error:
            raise LinkLost(f"{self.where} lost: {error.strerror or error}") from None
        if not data:
            raise LinkLost(f"{self.where} lost: end of file (its other side closed)")
        return data

    def write(self, buf):
        try:
            os.write(self.fd, buf)
        except OSError:
            pass


class _PtyConnection(_StreamConnection):
    """The master side of a pseudo-terminal pair as a pymavlink connection.

    The slave is put in raw mode (no echo, no line discipline) and kept open by us, so the
    master neither sees EIO when no client has it open nor loses the terminal settings.
    """

    def __init__(self, source_system: int, source_component: int):
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd, termios.TCSANOW)
        os.set_blocking(self.master_fd, False)
        self.slave_path = os.ttyname(self.slave_fd)
        self.where = f"pseudo-terminal {self.slave_path}"
        super().__init__(self.master_fd, self.slave_path, source_system=source_system,
                         source_component=source_component)

    def reopen(self):
        raise LinkError(f"{self.where} is closed: a pseudo-terminal cannot come back")

    def close(self):
        for fd in (self.master_fd, self.slave_fd):
            if fd >= 0:
                os.close(fd)
        self.master_fd = self.slave_fd = self.fd = -1


#: Why a serial port did not open, by errno, and what to do (formatted with the device).
_SERIAL_OPEN_HINTS = {
    errno.ENOENT: "no such port; list them with `ls /dev/ttyTHS* /dev/ttyACM* /dev/ttyUSB*` "
                  "or `companion devices`",
    errno.ENXIO: "no device behind the node (unplugged?); list the ports with "
                 "`ls /dev/ttyTHS* /dev/ttyACM* /dev/ttyUSB*` or `companion devices`",
    errno.EACCES: "permission denied: add the user to the dialout group (`sudo usermod -aG "
                  "dialout $USER`, then log in again)",
    errno.EBUSY: "busy: another process holds it (nvgetty's console on a Jetson UART: `sudo "
                 "systemctl disable --now nvgetty`; a mavproxy, mavlink-router or another "
                 "companion); `fuser -v {device}` names it",
}
_SERIAL_OPEN_HINTS[errno.ENODEV] = _SERIAL_OPEN_HINTS[errno.ENXIO]
_SERIAL_OPEN_HINTS[errno.EPERM] = _SERIAL_OPEN_HINTS[errno.EACCES]
_SERIAL_OPEN_HINTS[errno.EAGAIN] = _SERIAL_OPEN_HINTS[errno.EBUSY]  # the exclusive lock


def _open_serial(port: serial.Serial, address: LinkAddress) -> None:
    """Open (or reopen) ``port`` as the module docstring says; :class:`LinkError` saying why
    not."""
    try:
        port.open()
    except serial.SerialException as error:
        hint = _SERIAL_OPEN_HINTS.get(error.errno)
        detail = hint.format(device=address.device) if hint else f"cannot open it: {error}"
        raise LinkError(f"serial port {address.where}: {detail}") from None
    except (ValueError, termios.error) as error:  # the driver refused the rate
        raise LinkError(f"serial port {address.where}: the port does not take this baud "
                        f"rate ({error})") from None
    fcntl.ioctl(port.fd, termios.TIOCEXCL)


class _SerialConnection(_StreamConnection):
    """A serial port (module docstring), reopened in place after a loss."""

    def __init__(self, address: LinkAddress, **ids):
        self.spec, self.where = address, f"serial port {address.where}"
        self.port = serial.Serial(None, address.baud, timeout=0, write_timeout=0,
                                  exclusive=True)
        self.port.port = address.device
        _open_serial(self.port, address)
        super().__init__(self.port.fd, address.device, **ids)

    def reopen(self):
        _open_serial(self.port, self.spec)
        self.fd = self.port.fd

    def close(self):
        self.port.close()
        self.fd = -1


class _TcpClientConnection(_StreamConnection):
    """A TCP connection to a server (``tcpout``). Not pymavlink's: its client retries for
    seconds printing to stdout, and after a hang-up prints and reads the closed socket for
    ever."""

    def __init__(self, address: LinkAddress, **ids):
        self.spec, self.where = address, address.where
        self.sock = self._connect(TCP_CONNECT_TIMEOUT_S)
        super().__init__(self.sock.fileno(), address.where, **ids)

    def _connect(self, timeout_s: float) -> socket.socket:
        try:
            sock = socket.create_connection((self.spec.host, self.spec.port), timeout=timeout_s)
        except OSError as error:
            raise LinkError(f"{self.where}: cannot connect ({error.strerror or error}): "
                            "check that a MAVLink TCP server listens there (PX4, "
                            "mavlink-router, `companion sim serve --mavlink tcpin://...`)"
                            ) from None
        _stream_socket(sock)
        return sock

    def reopen(self):
        self.sock = self._connect(TCP_RECONNECT_TIMEOUT_S)
        self.fd = self.sock.fileno()

    def close(self):
        self.sock.close()
        self.fd = -1


class _TcpServerConnection(_StreamConnection):
    """A TCP server (``tcpin``) talking to one client at a time; when the client hangs up it
    listens again (pymavlink's server would read the closed socket for ever)."""

    def __init__(self, address: LinkAddress, **ids):
        self.where = address.where
        try:
            self.listener = socket.create_server((address.host, address.port))
        except OSError as error:
            raise LinkError(f"{self.where}: cannot listen ({error.strerror or error})") from None
        self.listener.setblocking(False)
        self.client: socket.socket | None = None
        super().__init__(self.listener.fileno(), address.where, **ids)

    def recv(self, n=None):
        if self.client is None and not self._accept():
            return b""
        try:
            return super().recv(n)
        except LinkLost as error:
            log.info("%s; listening again", error)
            self.client.close()
            self.client, self.fd = None, self.listener.fileno()
            return b""

    def write(self, buf):
        if self.client is not None:
            super().write(buf)

    def _accept(self) -> bool:
        try:
            self.client, peer = self.listener.accept()
        except (BlockingIOError, ConnectionAbortedError):
            return False
        _stream_socket(self.client)
        self.fd = self.client.fileno()
        log.info("%s: client %s:%d connected", self.where, peer[0], peer[1])
        return True

    def close(self):
        if self.client is not None:
            self.client.close()
        self.listener.close()
        self.fd = -1


def _stream_socket(sock: socket.socket) -> None:
    """Non-blocking, and each message sent at once rather than held to fill a segment."""
    sock.setblocking(False)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


_STREAMS = {"serial": _SerialConnection, "tcpin": _TcpServerConnection,
            "tcpout": _TcpClientConnection}


def open_link(url: str, *, source_system: int = 1, source_component: int = 1) -> MavlinkLink:
    """Open the connection a URL names (see the module docstring), speaking as the given ids;
    ValueError for a malformed URL, :class:`LinkError` for one that cannot be opened."""
    address = parse_url(url)
    if url.strip().startswith("tcp://"):
        log.warning("%s: tcp:// is deprecated (as in MAVSDK); it means %s://%s:%d, write that",
                    url.strip(), address.scheme, address.host, address.port)
    ids = {"source_system": source_system, "source_component": source_component}
    if address.scheme == "pty":
        connection = _PtyConnection(**ids)
        return MavlinkLink(connection, address, pty_path=connection.slave_path)
    if address.scheme in _STREAMS:
        return MavlinkLink(_STREAMS[address.scheme](address, **ids), address)
    try:
        connection = mavutil.mavlink_connection(
            f"{address.scheme}:{address.host}:{address.port}", **ids)
    except OSError as error:
        raise LinkError(f"{address.where}: {error.strerror or error}") from None
    return MavlinkLink(connection, address)
