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
    """Runs each call at once, on the loop (lockstep)."""

    async def run(self, function: Callable[..., T], *args) -> T:
        return function(*args)

    def close(self) -> None:
        pass


class ThreadWorker:
    """Runs each call on one dedicated thread, in order (real time)."""

    def __init__(self, name: str):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)

    async def run(self, function: Callable[..., T], *args) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, function, *args)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_workers(lockstep: bool, names: tuple[str, ...]) -> dict:
    """One worker per stage name: inline ones in lockstep, threads otherwise."""
    return {name: InlineWorker() if lockstep else ThreadWorker(name) for name in names}
