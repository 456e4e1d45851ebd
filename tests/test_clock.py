"""The simulated clock wakes sleepers in simulated time, in order, and never runs backwards."""

import asyncio

import pytest

from drivers.clock import MonotonicClock, SimClock


def test_sleepers_wake_in_simulated_time_order():
    clock = SimClock()
    woke = []

    async def sleeper(name, seconds):
        await clock.sleep(seconds)
        woke.append((name, clock.now()))

    async def scenario():
        tasks = [asyncio.create_task(sleeper(n, s)) for n, s in (("b", 0.2), ("a", 0.1), ("c", 0.3))]
        await asyncio.sleep(0)  # let every sleeper register
        assert clock.next_deadline == pytest.approx(0.1)
        for t in (0.05, 0.15, 0.25, 0.35):
            clock.advance_to(t)
            await asyncio.sleep(0)
        await asyncio.gather(*tasks)

    asyncio.run(scenario())
    assert woke == [("a", 0.15), ("b", 0.25), ("c", 0.35)]


def test_simulated_time_cannot_go_back():
    clock = SimClock(start=2.0)
    with pytest.raises(ValueError, match="cannot go back"):
        clock.advance_to(1.0)


def test_monotonic_clock_moves_forward():
    clock = MonotonicClock()
    first = clock.now()
    asyncio.run(clock.sleep(0.001))
    assert clock.now() > first
