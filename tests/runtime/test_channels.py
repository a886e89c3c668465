"""Latest-value slots: newest wins, skipped values are counted, producers never block."""

import asyncio

from app.channels import LatestSlot, SlotReader


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
