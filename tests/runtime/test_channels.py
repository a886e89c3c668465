"""Latest-value slots: newest wins, skipped values are counted, producers never block."""

import asyncio
import contextlib
import sys
from collections.abc import Awaitable, Callable

import pytest

from app.channels import LatestSlot, SlotReader, wait_event


async def test_slow_consumer_gets_the_newest_and_counts_skips() -> None:
    slot: LatestSlot[int] = LatestSlot("numbers")
    reader = SlotReader(slot)
    for i in range(10):
        slot.publish(i)  # never blocks, however slow the reader
    assert await reader.next() == 9
    assert reader.skipped == 9
    slot.publish(10)
    assert await reader.next() == 10
    assert reader.skipped == 9


async def test_a_reader_sees_whether_something_newer_waits() -> None:
    slot: LatestSlot[int] = LatestSlot("numbers")
    reader = SlotReader(slot)
    assert not reader.pending  # nothing published yet
    slot.publish(1)
    assert reader.pending
    assert await reader.next() == 1
    assert not reader.pending
    slot.publish(2)
    slot.publish(3)
    assert reader.pending
    assert await reader.next() == 3 and not reader.pending


async def test_consumer_waits_for_something_newer() -> None:
    slot: LatestSlot[str] = LatestSlot("s")
    reader = SlotReader(slot)
    slot.publish("a")
    assert await reader.next() == "a"
    waiting = asyncio.create_task(reader.next())
    await asyncio.sleep(0.01)
    assert not waiting.done()  # "a" was taken already
    slot.publish("b")
    assert await asyncio.wait_for(waiting, 1.0) == "b"


async def test_each_reader_keeps_its_own_place() -> None:
    slot: LatestSlot[int] = LatestSlot("n")
    fast, slow = SlotReader(slot), SlotReader(slot)
    for i in range(3):
        slot.publish(i)
        assert await fast.next() == i
    assert await slow.next() == 2
    assert (fast.skipped, slow.skipped) == (0, 2)
    assert slot.peek() == 2


async def _loop_on(wait: Callable[[asyncio.Event], Awaitable[object]]) -> None:
    event = asyncio.Event()

    async def stage() -> None:
        while True:
            with contextlib.suppress(TimeoutError):  # a timed-out wait: loop again
                await wait(event)
            event.clear()

    task = asyncio.create_task(stage())
    await asyncio.sleep(0.01)  # the stage waits on the event
    event.set()  # its wait completes in the next loop iteration...
    task.cancel()  # ...the same one in which the cancellation arrives
    await asyncio.wait({task}, timeout=0.5)
    try:
        assert task.done(), "the cancellation was lost: the stage kept looping"
    finally:
        if not task.done():
            task.cancel()  # a second cancel does land: clean up the demonstration
            await asyncio.wait({task}, timeout=0.5)


async def test_wait_event_never_loses_a_cancellation() -> None:
    await _loop_on(lambda event: wait_event(event, 0.05))


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="wait_for was fixed in Python 3.12")
async def test_wait_for_on_3_11_loses_it_which_is_why_wait_event_exists() -> None:
    with pytest.raises(AssertionError, match="cancellation was lost"):
        await _loop_on(lambda event: asyncio.wait_for(event.wait(), 0.05))


async def test_wait_event_times_out_or_reports_the_event() -> None:
    event = asyncio.Event()
    assert await wait_event(event, 0.01) is False
    event.set()
    assert await wait_event(event, 0.01) is True
    assert await wait_event(event, None) is True
