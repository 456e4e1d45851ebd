"""Where heavy numeric work runs: off the event loop in real time, inline in lockstep.

In real time the depth network, the VINS and the planner run in worker threads (onnxruntime,
OpenCV and numpy release the GIL), so the loop stays free for the setpoint sender; each stage
gets its own single thread, so a stage's calls stay in order and two stages overlap. In
lockstep the same calls run inline: simulated time stands still while they compute, which makes
a simulated flight deterministic and independent of the machine's speed (the loop's lag is then
measured in simulated time, where it is what the vehicle feels).
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

T = TypeVar("T")


class InlineWorker:
    """Runs each call at once, on the loop (lockstep); :meth:`compute` then holds the worker
    for ``latency`` seconds of ``clock`` before handing the result back."""

    def __init__(self, clock=None, latency: float = 0.0):
        if latency and clock is None:
            raise ValueError("a worker with a latency needs the clock it passes on")
        self._clock, self._latency = clock, latency
        self._busy = asyncio.Lock()

    async def run(self, function: Callable[..., T], *args) -> T:
        async with self._busy:
            return function(*args)

    async def compute(self, function: Callable[..., T], *args) -> T:
        async with self._busy:
            result = function(*args)
            if self._latency:
                await self._clock.sleep(self._latency)
            return result

    def close(self) -> None:
        pass


class ThreadWorker:
    """Runs each call on one dedicated thread, in order (real time)."""

    def __init__(self, name: str):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)

    async def run(self, function: Callable[..., T], *args) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, function, *args)

    compute = run  # real time: the computation takes what it takes

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_workers(lockstep: bool, names: tuple[str, ...], clock=None,
                 latency: dict[str, float] | None = None) -> dict:
    """One worker per stage name: inline ones in lockstep, each charging its stage's
    ``latency`` (seconds by name; none: instant) to ``clock``; threads otherwise."""
    latency = latency or {}
    unknown = set(latency) - set(names)
    if unknown:
        raise ValueError(f"latency for unknown stages {sorted(unknown)}; stages: {names}")
    if not lockstep:
        return {name: ThreadWorker(name) for name in names}
    return {name: InlineWorker(clock, latency.get(name, 0.0)) for name in names}
