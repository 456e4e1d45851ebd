"""The stale-setpoint watchdog: a thread that does not depend on the event loop.

The setpoint sender runs on the event loop; if the loop stalls (a runaway computation, a
blocking call), PX4 keeps flying the last velocity it was given until its own offboard-loss
timeout (``COM_OF_LOSS_T``, a second or more) — at 2 m/s that is metres towards whatever the
last plan did not foresee. The watchdog thread checks the age of the last setpoint every
``deadline / 4`` of wall time and, once it is older than ``deadline`` on the application's
clock, sends the stop behaviour itself (``stop_setpoint(now)``, the stop primitive checked at
the last planning round), at the setpoint rate, until the loop sends again.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable

log = logging.getLogger(__name__)


class SetpointWatchdog:
    """Watches ``last_setpoint_t`` (set by the loop through :meth:`fed`) against ``deadline_s``.

    ``send_stop(now)`` sends one stop setpoint; it must be thread-safe. ``now()`` is the
    application's clock. ``fired`` counts the setpoints the watchdog sent, ``episodes`` the
    times it took over.
    """

    def __init__(self, now: Callable[[], float], send_stop: Callable[[float], None],
                 deadline_s: float, period_s: float):
        if not deadline_s > 0.0 or not period_s > 0.0:
            raise ValueError("watchdog deadline and period must be positive seconds")
        self._now, self._send_stop = now, send_stop
        self.deadline_s, self.period_s = deadline_s, period_s
        self._last_setpoint_t: float | None = None
        self._armed = False
        self._in_charge = False
        self.fired = 0
        self.episodes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="setpoint-watchdog", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def fed(self, t: float) -> None:
        """The loop sent a setpoint at ``t``; it is in charge again."""
        self._last_setpoint_t = t
        self._in_charge = False

    def arm(self, armed: bool) -> None:
        """Watch (True) only while the application commands the vehicle with setpoints.

        Arming again after a pause forgets the setpoint sent before it: a pause in commanding
        (the link lost, PX4 flying a mode of its own) is not a late loop, and the deadline runs
        from the first setpoint after it. Without this the watchdog could see the old setpoint
        between the loop's ``arm(True)`` and its ``fed``, and send a stop the loop was about to
        send anyway (the fault matrix's packet loss at take-off, docs/reliability.md)."""
        if armed and not self._armed:
            self._last_setpoint_t = None  # written before _armed: _check reads in that order
        self._armed = armed

    @property
    def in_charge(self) -> bool:
        """True while the watchdog is sending the stop because the loop is late."""
        return self._in_charge

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.wait(self._wait_s()):
            self._check()

    def _wait_s(self) -> float:
        return self.period_s if self._in_charge else self.deadline_s / 4.0

    def _check(self) -> None:
        if not self._armed:
            return
        last = self._last_setpoint_t  # read after _armed: None until fed since arming
        if last is None:
            return
        now = self._now()
        if now - last <= self.deadline_s:
            return
        if not self._in_charge:
            self._in_charge = True
            self.episodes += 1
            log.warning("setpoint %.0f ms old: watchdog sends the stop", 1e3 * (now - last))
        try:
            self._send_stop(now)
            self.fired += 1
        except Exception:  # noqa: BLE001 - a watchdog must never die; the loop will see it
            log.exception("watchdog could not send the stop")
