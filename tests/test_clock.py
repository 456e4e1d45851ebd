"""The simulated clock wakes sleepers in simulated time, in order, and never runs backwards."""

import asyncio

import pytest

from drivers.clock import MonotonicClock, Rate, SimClock


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


def _round_starts(period_s, work_s, rounds):
    """When each round of a fixed-rate loop whose rounds take ``work_s`` began, in lockstep."""
    clock, starts = SimClock(), []

    async def loop():
        rate = Rate(clock, period_s)
        for _ in range(rounds):
            starts.append(clock.now())
            await clock.sleep(work_s(len(starts)))
            await rate.sleep()

    async def scenario():
        task = asyncio.create_task(loop())
        while not task.done():
            await asyncio.sleep(0)
            if clock.next_deadline is not None:
                clock.advance_to(clock.next_deadline)
        await task

    asyncio.run(scenario())
    return starts


def test_a_rounds_work_comes_out_of_the_period_not_on_top_of_it():
    # a planning round that computes for 60 ms of an 83 ms period: rounds stay 83 ms apart
    starts = _round_starts(1 / 12, lambda k: 0.06, 6)
    assert starts == pytest.approx([k / 12 for k in range(6)])


def test_an_overrun_round_is_followed_at_once_and_never_by_a_burst():
    # the third round takes 0.3 s (3.6 periods): the fourth starts when it ends, and the
    # rounds after it keep one period apart from there instead of catching up
    starts = _round_starts(0.1, lambda k: 0.3 if k == 3 else 0.01, 6)
    assert starts == pytest.approx([0.0, 0.1, 0.2, 0.5, 0.6, 0.7])


@pytest.mark.parametrize("period", [0.0, -0.1, float("nan")])
def test_a_rate_needs_a_positive_period(period):
    with pytest.raises(ValueError, match="positive seconds"):
        Rate(SimClock(), period)
