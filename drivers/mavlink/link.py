"""A MAVLink 2 connection opened from a URL, read without blocking.

URLs follow MAVSDK's connection strings, so a person types what they already know:

==========================  =============================================================
``udpin://host:port``       listen on host:port; answer whoever sent to us (a flight
                            controller's side, or a companion waiting for PX4)
``udpout://host:port``      send to host:port (and receive the replies on the same socket)
``tcp://host:port``         connect to a TCP server (PX4 SITL's simulator port style)
``tcpin://host:port``       listen for one TCP client
``serial:///dev/ttyX[:baud]``  a serial port, 57600 baud unless given
``pty``                     a new pseudo-terminal pair: we hold the master side, and a
                            client opens :attr:`MavlinkLink.pty_path` like a serial port
==========================  =============================================================

Every link speaks MAVLink 2 with the ``common`` dialect (everything PX4 sends and accepts
here is in it). Signing follows the MAVLink 2 message signing spec: a 32-byte secret key,
outgoing messages signed, and unsigned incoming ones accepted only when a callback allows
their message id (see :func:`drivers.mavlink.px4_protocol.accept_unsigned`).
"""

from __future__ import annotations

import os
import select
import termios
import tty
from dataclasses import dataclass
from typing import Callable
from urllib.parse import urlsplit

from autonomy.options import OptionError

os.environ["MAVLINK20"] = "1"  # pymavlink picks the wire protocol when a dialect is loaded

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

mavutil.set_dialect("common")

DEFAULT_SERIAL_BAUD = 57600
SECRET_KEY_LENGTH = 32
#: Most messages taken from the link in one :meth:`MavlinkLink.receive_pending` call, so a
#: flood cannot starve the caller's loop; the rest wait for the next call.
MAX_MESSAGES_PER_RECEIVE = 2000

SCHEMES = ("udpin", "udpout", "tcp", "tcpin", "serial", "pty")


@dataclass(frozen=True)
class LinkAddress:
    """A parsed connection URL: ``scheme`` and either host/port, a serial device, or nothing."""

    scheme: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0


def signing_secret(key_hex: str) -> bytes | None:
    """The MAVLink 2 signing secret written as 64 hex digits (a 32-byte key; PX4's
    ``MAV_SIGN_CFG`` key is the same), None for "" (signing off); an
    :class:`~autonomy.options.OptionError` naming ``signing_key`` otherwise."""
    if not key_hex:
        return None
    try:
        key = bytes.fromhex(key_hex)
    except ValueError:
        key = b""
    if len(key) != 32:
        raise OptionError("signing_key", "must be 64 hex digits (a 32-byte key), "
                          f"got {len(key_hex)} characters")
    return key


def parse_url(url: str) -> LinkAddress:
    """Parse a connection URL (see the module docstring); ValueError naming the problem."""
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
    if not baud_text.isdigit() or int(baud_text) <= 0:
        raise ValueError(f"MAVLink URL {url!r}: baud rate must be a positive integer, "
                         f"got {baud_text!r}")
    return LinkAddress("serial", device=device, baud=int(baud_text))


def _parse_host_port(url: str, scheme: str) -> LinkAddress:
    parts = urlsplit(url)
    if parts.path or parts.query or parts.fragment:
        raise ValueError(f"MAVLink URL {url!r}: expected {scheme}://host:port and nothing after")
    try:
        port = parts.port
    except ValueError as error:
        raise ValueError(f"MAVLink URL {url!r}: bad port ({error})") from None
    if not parts.hostname or port is None or port == 0:
        raise ValueError(f"MAVLink URL {url!r}: expected {scheme}://host:port with a port "
                         "in 1..65535")
    return LinkAddress(scheme, host=parts.hostname, port=port)


class MavlinkLink:
    """One MAVLink 2 connection: send messages, take every pending one without blocking.

    ``mav`` is pymavlink's encoder bound to this link (``link.mav.heartbeat_send(...)``).
    Bytes that do not parse (noise, bad CRC, rejected unsigned messages) are counted in
    :attr:`bad_data_count` and never returned.
    """

    def __init__(self, connection: mavutil.mavfile, address: LinkAddress,
                 pty_path: str | None = None):
        self._connection = connection
        self.address = address
        self.pty_path = pty_path
        self.bad_data_count = 0

    @property
    def mav(self) -> mavlink.MAVLink:
        return self._connection.mav

    @property
    def signing_enabled(self) -> bool:
        return self.mav.signing.secret_key is not None

    def send(self, message: mavlink.MAVLink_message) -> None:
        """Encode (and sign, when signing is on) one message and write it."""
        self.mav.send(message)

    def receive_pending(self) -> list[mavlink.MAVLink_message]:
        """Every message that has arrived, in order, without waiting for more."""
        messages = []
        while len(messages) < MAX_MESSAGES_PER_RECEIVE:
            message = self._receive_one()
            if message is None:
                if not self._readable():
                    break
                continue
            if message.get_type() == "BAD_DATA":
                self.bad_data_count += 1
                continue
            messages.append(message)
        return messages

    def _receive_one(self):
        try:
            return self._connection.recv_msg()
        except (mavlink.MAVError, ValueError, IndexError, TypeError, UnicodeDecodeError):
            # pymavlink's robust parser reports most corruption as BAD_DATA, but a few
            # malformed payloads still raise while unpacking; treat them alike.
            self.bad_data_count += 1
            return None

    def _readable(self) -> bool:
        fd = self._connection.fd
        if fd is None:
            return False
        return bool(select.select([fd], [], [], 0)[0])

    def setup_signing(self, secret_key: bytes, *,
                      accept_unsigned: Callable[[int], bool] | None = None,
                      link_id: int = 0, initial_timestamp: int | None = None) -> None:
        """Sign every outgoing message and reject unsigned incoming ones.

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
        self._connection.setup_signing(bytes(secret_key), sign_outgoing=True,
                                       allow_unsigned_callback=callback,
                                       initial_timestamp=initial_timestamp, link_id=link_id)

    def close(self) -> None:
        self._connection.close()

    def __enter__(self) -> "MavlinkLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _PtyConnection(mavutil.mavfile):
    """The master side of a pseudo-terminal pair as a pymavlink connection.

    The slave is put in raw mode (no echo, no line discipline) and kept open by us, so the
    master neither sees EIO when no client has it open nor loses the terminal settings.
    Writes that find the terminal buffer full (nobody reading) are dropped, like bytes on a
    serial wire nobody listens to.
    """

    def __init__(self, source_system: int, source_component: int):
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd, termios.TCSANOW)
        os.set_blocking(self.master_fd, False)
        self.slave_path = os.ttyname(self.slave_fd)
        super().__init__(self.master_fd, self.slave_path, source_system=source_system,
                         source_component=source_component)

    def recv(self, n=None):
        try:
            return os.read(self.master_fd, 4096)
        except (BlockingIOError, OSError):
            return b""

    def write(self, buf):
        try:
            os.write(self.master_fd, buf)
        except (BlockingIOError, OSError):
            pass

    def close(self):
        for fd in (self.master_fd, self.slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass


def open_link(url: str, *, source_system: int = 1, source_component: int = 1) -> MavlinkLink:
    """Open the connection a URL names (see the module docstring), speaking as the given ids."""
    address = parse_url(url)
    ids = {"source_system": source_system, "source_component": source_component}
    if address.scheme == "pty":
        connection = _PtyConnection(**ids)
        return MavlinkLink(connection, address, pty_path=connection.slave_path)
    if address.scheme == "serial":
        device = address.device
        connection = mavutil.mavlink_connection(device, baud=address.baud, **ids)
    else:
        pymavlink_scheme = {"udpin": "udpin", "udpout": "udpout", "tcp": "tcp",
                            "tcpin": "tcpin"}[address.scheme]
        connection = mavutil.mavlink_connection(
            f"{pymavlink_scheme}:{address.host}:{address.port}", **ids)
    return MavlinkLink(connection, address)
