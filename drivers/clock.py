"""The clock every component is handed (DESIGN.md: a ``Clock`` is passed in, never read globally).

Time is float seconds on one monotonic timeline. :class:`MonotonicClock` is the real one;
:class:`SimClock` is advanced by the simulator, so a whole stack can run in lockstep, faster
than real time and deterministically, with the same code that flies in real time.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import time
from typing import Protocol


class Clock(Protocol):
    """What a component may ask of time."""

    def now(self) -> float:
        """Seconds on this clock's monotonic timeline."""

    async def sleep(self, seconds: float) -> None:
        """Return once ``seconds`` have passed on this clock."""


class MonotonicClock:
    """Real time: ``time.monotonic`` and ``asyncio.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


class SimClock:
    """Simulated time, moved forward only by :meth:`advance_to`.

    Sleepers are woken in time order when the simulator passes their deadline, so in lockstep
    a task that sleeps 50 ms sleeps 50 ms of simulated time however fast the CPU is.
    """

    def __init__(self, start: float = 0.0):
        self._now = float(start)
        self._sleepers: list[tuple[float, int, asyncio.Future]] = []
        self._order = itertools.count()

    def now(self) -> float:
        return self._now

    async def sleep(self, seconds: float) -> None:
        future = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (self._now + max(0.0, seconds), next(self._order), future))
        await future

    def advance_to(self, t: float) -> None:
        """Move time to ``t`` (never backwards) and wake every sleeper whose deadline passed."""
        if t < self._now:
            raise ValueError(f"simulated time cannot go back from {self._now} to {t}")
        self._now = float(t)
        while self._sleepers and self._sleepers[0][0] <= self._now:
            _, _, future = heapq.heappop(self._sleepers)
            if not future.done():
                future.set_result(None)

    @property
    def next_deadline(self) -> float | None:
        """The earliest time a sleeper waits for, or None when nobody sleeps."""
        return self._sleepers[0][0] if self._sleepers else None


class Rate:
    """A loop's fixed rate on ``clock``: :meth:`sleep` returns ``period_s`` after the previous
    round began, so the work a round does (a planning round's compute, charged to simulated
    time in lockstep) comes out of the period instead of being added to it. A round that
    overruns its period is followed by the next at once, and the schedule starts again from
    there: no burst of rounds to catch up."""

    def __init__(self, clock: Clock, period_s: float):
        if not period_s > 0.0:
            raise ValueError(f"a rate's period must be positive seconds, got {period_s!r}")
        self._clock, self.period_s = clock, float(period_s)
        self._due = clock.now()  # the first round begins as the rate is made

    async def sleep(self) -> None:
        """Wait until the next round is due: one period after the last one was due, or now
        when that has passed."""
        now = self._clock.now()
        self._due = max(self._due + self.period_s, now)
        await self._clock.sleep(self._due - now)
