"""Latest-value slots: how the daemon's stages hand data on.

A stage publishes; consumers wait for anything newer than what they last took and get
the newest value only. A slow consumer therefore skips values instead of queueing behind
them (the frames it missed are counted), and a fast producer is never blocked.
"""

from __future__ import annotations

import asyncio
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Holds the newest value with a version number (1 for the first value)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._value: T | None = None
        self._version = 0
        self._changed = asyncio.Event()

    @property
    def version(self) -> int:
        return self._version

    def publish(self, value: T) -> int:
        """Replace the value; wakes every waiting consumer. Returns the new version."""
        self._value = value
        self._version += 1
        self._changed.set()
        self._changed = asyncio.Event()
        return self._version

    def peek(self) -> T | None:
        """The newest value (None before the first), without waiting."""
        return self._value

    async def next(self, after_version: int) -> tuple[int, T]:
        """Wait for a value newer than ``after_version``; return (version, value).

        ``version - after_version - 1`` values were skipped."""
        while self._version <= after_version or self._value is None:
            await self._changed.wait()
        return self._version, self._value


class SlotReader(Generic[T]):
    """One consumer's position in a slot, counting what it skipped."""

    def __init__(self, slot: LatestSlot[T]) -> None:
        self.slot = slot
        self.version = slot.version
        self.taken = 0
        self.skipped = 0

    @property
    def pending(self) -> bool:
        """A value newer than the last one taken is waiting."""
        return self.slot.version > self.version and self.slot.peek() is not None

    async def next(self) -> T:
        version, value = await self.slot.next(self.version)
        self.skipped += version - self.version - 1
        self.version = version
        self.taken += 1
        return value


async def wait_event(event: asyncio.Event, timeout_s: float | None) -> bool:
    """Wait until ``event`` is set or ``timeout_s`` passed; True if it is set.

    Use this, not ``asyncio.wait_for(event.wait(), ...)``: on Python 3.11, wait_for
    returns normally when its task is cancelled in the same loop iteration as the event
    fires, losing the cancellation. A stage looping on it then survives its task
    group's cancel and the group never finishes (the daemon hung at shutdown that way).
    ``asyncio.timeout`` keeps the cancellation.
    """
    try:
        async with asyncio.timeout(timeout_s):
            await event.wait()
    except TimeoutError:
        return event.is_set()
    return True
