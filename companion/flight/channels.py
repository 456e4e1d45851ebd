"""Channels between the flight process's stages (DESIGN.md, "The process").

A stage publishes a typed message (:mod:`autonomy.messages`, a :class:`~autonomy.planning.
planner.Plan`, ...) on a channel; another stage reads the newest one when it needs it; a tap
(the flight recorder, a live view, a test) subscribes a callback that sees every message as
it is published. A channel keeps only the newest value (:class:`Latest`), so nothing queues
up: where every message matters (IMU samples, state transitions), the consumer is a tap, or
the driver's own bounded ring (:meth:`drivers.mavlink.autopilot.Autopilot.take_imu`).

Publishing and reading never await, so adding a tap changes neither the order of the stages'
work nor a lockstep flight. A tap runs on the publisher's thread and must return at once (put
the message in its own bounded buffer); one that raises is logged and dropped, never lets the
error into the stage.
"""

from __future__ import annotations

import logging
from typing import Callable, Generic, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


class _Taps(Generic[T]):
    """Callbacks that see every published message."""

    def __init__(self, name: str):
        self.name = name
        self._taps: list[Callable[[T], None]] = []
        self.published = 0

    def subscribe(self, tap: Callable[[T], None]) -> Callable[[], None]:
        """Call ``tap(message)`` on every publish from now on; returns the unsubscriber (safe
        to call again, or after a failing tap was dropped)."""
        self._taps.append(tap)
        return lambda: self._drop(tap)

    def _drop(self, tap: Callable[[T], None]) -> None:
        if tap in self._taps:
            self._taps.remove(tap)

    def _notify(self, message: T) -> None:
        self.published += 1
        for tap in tuple(self._taps):
            try:
                tap(message)
            except Exception:  # noqa: BLE001 - a tap's fault never reaches the stage
                log.exception("tap on channel %r failed; unsubscribed", self.name)
                self._drop(tap)


class Latest(_Taps[T]):
    """The newest value published (None before the first)."""

    def __init__(self, name: str, value: T | None = None):
        super().__init__(name)
        self.value: T | None = value

    def publish(self, value: T) -> None:
        self.value = value
        self._notify(value)

