"""Talking to systemd from the flight application: readiness, status, the watchdog, stopping.

The unit (``systemd/companion.service``) is ``Type=notify`` with ``WatchdogSec=``: systemd
counts the service as started only once it says ``READY=1``, shows its ``STATUS=`` line in
``systemctl status``, and kills and restarts it when the ``WATCHDOG=1`` keep-alive stops coming,
which is how a wedged event loop gets noticed on a vehicle nobody is watching.

This is the sd_notify(3) protocol itself, a few lines over a socket, rather than a new
dependency: each message is one datagram of newline-separated ``KEY=VALUE`` assignments sent to
the AF_UNIX SOCK_DGRAM socket named by ``$NOTIFY_SOCKET`` (a path, or an abstract-namespace
name when it starts with ``@``). Outside systemd ``$NOTIFY_SOCKET`` is unset and every call is
a no-op, so the same code runs from a terminal, in CI and under the service manager.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Sends sd_notify messages to the service manager, or nothing when there is none.

    A notification must never take the flight application down or stall its event loop: the
    socket is non-blocking, and a send that fails (systemd restarting, a full queue) is logged
    once and reported as ``False``, never raised.
    """

    def __init__(self, environ: Mapping[str, str] | None = None):
        env = os.environ if environ is None else environ
        self._address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self._sock: socket.socket | None = None
        self._warned = False

    @property
    def enabled(self) -> bool:
        """Whether a service manager listens (``$NOTIFY_SOCKET`` was set and usable)."""
        return self._address is not None

    def ready(self, status: str = "") -> bool:
        """Start-up is complete: systemd marks the unit started and arms its watchdog."""
        return self.notify("READY=1", *_status(status))

    def status(self, text: str) -> bool:
        """A one-line state shown by ``systemctl status companion`` (newlines become spaces)."""
        return self.notify(*_status(text))

    def watchdog(self) -> bool:
        """The keep-alive; send it every :func:`watchdog_interval_s` from the event loop."""
        return self.notify("WATCHDOG=1")

    def extend_timeout(self, seconds: float) -> bool:
        """Ask for ``seconds`` more before systemd gives up on a slow start or stop (a first
        TensorRT engine build can take minutes); repeat it before that time runs out."""
        if not seconds > 0:
            raise ValueError(f"extend_timeout needs a positive number of seconds, got {seconds!r}")
        return self.notify(f"EXTEND_TIMEOUT_USEC={round(seconds * 1e6)}")

    def stopping(self, status: str = "") -> bool:
        """Shutdown has begun, so a slow landing-and-close is not mistaken for a hang."""
        return self.notify("STOPPING=1", *_status(status))

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` assignments as one datagram; True when it was sent.

        False without a service manager, or when sending failed (logged once per notifier).
        """
        if self._address is None or not assignments:
            return False
        for item in assignments:
            if "=" not in item or "\n" in item:
                raise ValueError(f"a notification is one KEY=VALUE line, got {item!r}")
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)
            self._sock.sendto("\n".join(assignments).encode(), self._address)
        except OSError as error:
            if not self._warned:
                log.warning("systemd notification to %r failed: %s", self._address, error)
                self._warned = True
            return False
        return True

    def close(self) -> None:
        """Close the socket; later notifications open a new one."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _status(text: str) -> tuple[str, ...]:
    """The STATUS assignment for ``text`` (none for empty text), flattened to one line: a
    newline in it would otherwise start a new assignment."""
    flat = " ".join(str(text).split())
    return (f"STATUS={flat}",) if flat else ()


def _socket_address(value: str) -> str | bytes | None:
    """The sendto address for ``$NOTIFY_SOCKET``: an absolute path, or ``@name`` for the
    abstract namespace (a leading NUL byte); None when unset or of a kind not supported here."""
    if value.startswith("@") and len(value) > 1:
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    if value:
        log.warning("NOTIFY_SOCKET=%r is neither a path nor @abstract; not notifying systemd",
                    value)
    return None


def watchdog_interval_s(environ: Mapping[str, str] | None = None,
                        pid: int | None = None) -> float | None:
    """Seconds between ``WATCHDOG=1`` keep-alives, or None when systemd expects none.

    As sd_watchdog_enabled(3): the watchdog is on when ``$WATCHDOG_USEC`` is set and
    ``$WATCHDOG_PID`` is unset or this process's id (``pid``, default ``os.getpid()``); the
    keep-alive should then come every half of that timeout, the interval returned, so one late
    ping does not get the service killed. A value systemd would not write raises ValueError.
    """
    env = os.environ if environ is None else environ
    usec_text = env.get("WATCHDOG_USEC")
    if not usec_text:
        return None
    pid_text = env.get("WATCHDOG_PID")
    if pid_text:
        if not pid_text.isdigit():
            raise ValueError(f"WATCHDOG_PID must be a process id, got {pid_text!r}")
        if int(pid_text) != (os.getpid() if pid is None else pid):
            return None  # the keep-alive is expected from another process
    if not usec_text.isdigit() or int(usec_text) == 0:
        raise ValueError(f"WATCHDOG_USEC must be a positive integer (microseconds), "
                         f"got {usec_text!r}")
    return int(usec_text) / 2e6
