"""Workers (companion/flight/workers.py): in lockstep a stage's compute is charged its latency
in simulated time, and the stage's later calls wait behind it, as behind a busy thread. And
the slot that hands the newest frame from the VINS loop to the slower depth loop."""

import asyncio

import pytest

from drivers.clock import SimClock
from companion.flight.perception import NewestSlot
from companion.flight.workers import InlineWorker, ThreadWorker, make_workers


async def _advance(clock: SimClock, until: float, step: float = 0.001) -> None:
    while clock.now() < until:
        await asyncio.sleep(0)
        clock.advance_to(round(clock.now() + step, 9))


def test_a_compute_returns_after_its_latency_in_simulated_time_and_blocks_the_worker():
    clock = SimClock(0.0)
    worker = InlineWorker(clock, latency=0.08)
    seen = []

    async def main():
        async def planning():
            seen.append(("round done", await worker.compute(lambda: "plan"), clock.now()))

        async def bookkeeping():
            await asyncio.sleep(0)  # starts while the round is computing
            seen.append(("add_depth", await worker.run(lambda: "ok"), clock.now()))
        await asyncio.gather(planning(), bookkeeping(), _advance(clock, 0.2))
    asyncio.run(main())
    assert seen[0][:2] == ("round done", "plan") and seen[0][2] == pytest.approx(0.08, abs=2e-3)
    # the bookkeeping call waited for the round, as on the round's thread
    assert seen[1][:2] == ("add_depth", "ok") and seen[1][2] >= seen[0][2]


def test_without_latency_calls_return_at_once():
    clock = SimClock(5.0)

    async def main():
        worker = InlineWorker()
        return await worker.compute(lambda x: x + 1, 1), await worker.run(lambda: 3), clock.now()
    assert asyncio.run(main()) == (2, 3, 5.0)


def test_lockstep_workers_take_each_stages_latency_and_refuse_unknown_stages():
    clock = SimClock(0.0)
    workers = make_workers(True, ("vins", "network"), clock, {"network": 0.05})
    assert workers["network"]._latency == 0.05 and workers["vins"]._latency == 0.0
    with pytest.raises(ValueError, match="unknown stages"):
        make_workers(True, ("vins",), clock, {"planer": 0.1})
    with pytest.raises(ValueError, match="needs the clock"):
        InlineWorker(latency=0.1)


def test_real_time_workers_are_threads_whose_compute_is_a_plain_call():
    workers = make_workers(False, ("vins",), None, {"vins": 0.5})
    try:
        assert isinstance(workers["vins"], ThreadWorker)
        assert asyncio.run(workers["vins"].compute(lambda: 7)) == 7
    finally:
        workers["vins"].close()


def test_the_slow_consumer_gets_the_newest_item_and_waits_for_the_next():
    """A network busy while frames 1 and 2 arrive takes frame 2 next; then it waits."""
    async def scenario():
        slot = NewestSlot()
        slot.put(1)
        slot.put(2)
        assert await slot.take() == 2
        waiting = asyncio.ensure_future(slot.take())
        await asyncio.sleep(0)
        assert not waiting.done()
        slot.put(3)
        assert await waiting == 3
    asyncio.run(scenario())
