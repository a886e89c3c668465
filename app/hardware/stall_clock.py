"""The time the host could not have heard the device, so that it is not called silence.

A serial byte reaches the daemon through two things that stall on a loaded machine:

- the daemon's own event loop (the GIL held by a compile, a long collection, a paused
  VM, a starved CPU), measured by the reader when a wait returns later than scheduled;
- the kernel's tty layer. A serial driver (``cdc_acm`` for an Uno, the pty of the
  simulated Uno) hands received bytes to a kernel worker thread (the tty buffer's
  work), and read() and poll() see them only once that worker has run. The worker
  runs at normal priority, so a machine whose cores are saturated leaves it waiting: in
  the browser tests on a 2-core machine (the daemon, chromium and the simulated Uno
  together) the simulated Uno's process sat in that wait (``__flush_work``) for
  50-430 ms at a time, and the host's link timed out 200 ms of "silence" two to six
  times a minute, although the device had been talking all along.

`StallClock` holds the union of both kinds of interval. Its `StallClock.awake_s` is
``time.monotonic()`` less that union: silence and ACK timeouts are judged on it, so a
link fails for a device that is silent, not for a host that could not listen.
`TtyDeliveryProbe` measures the kernel's part with a private pty pair: it writes one
byte at a time and times its way through the same tty layer. A byte still on its way
is a stall going on now (counted up to `StallClock.max_excused_s`, so that a kernel
that stops delivering for good still lets a silent link fail).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
import tty
from collections import deque
from collections.abc import Callable

log = logging.getLogger(__name__)

HORIZON_S = 30.0
"""Intervals that ended this long before the newest one are folded into a total (a new
interval never starts that far back)."""


class StallClock:
    """Monotonic time less the stalls reported to it (their union: overlapping reports
    of one stall by the reader and by the probe count once).

    Parameters
    ----------
    max_excused_s : an ongoing stall (`begin_stall`) counts for at most this long.
    clock : the time source (``time.monotonic``; tests pass their own).
    """

    def __init__(
        self, *, max_excused_s: float = 2.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if max_excused_s <= 0:
            raise ValueError(f"max_excused_s must be > 0, got {max_excused_s}")
        self.max_excused_s = max_excused_s
        self._clock = clock
        self._intervals: list[tuple[float, float]] = []  # disjoint, sorted by start
        self._folded_s = 0.0
        self._ongoing_since_s: float | None = None

    def now(self) -> float:
        return self._clock()

    def add(self, start_s: float, end_s: float) -> None:
        """A stall from ``start_s`` to ``end_s`` (on the clock's time)."""
        if end_s <= start_s:
            return
        merged: list[tuple[float, float]] = []
        for a, b in self._intervals:
            if b < start_s or a > end_s:
                merged.append((a, b))
            else:
                start_s, end_s = min(a, start_s), max(b, end_s)
        merged.append((start_s, end_s))
        merged.sort()
        newest_end_s = max(b for _, b in merged)
        keep = [(a, b) for a, b in merged if b >= newest_end_s - HORIZON_S]
        self._folded_s += sum(b - a for a, b in merged if b < newest_end_s - HORIZON_S)
        self._intervals = keep

    def begin_stall(self, since_s: float) -> None:
        """A stall going on since ``since_s`` (until `end_stall`)."""
        self._ongoing_since_s = since_s

    def end_stall(self, at_s: float) -> None:
        """The ongoing stall ended at ``at_s``; it stays counted (up to the cap)."""
        since_s, self._ongoing_since_s = self._ongoing_since_s, None
        if since_s is not None:
            self.add(since_s, min(at_s, since_s + self.max_excused_s))

    def stalled_s(self, now_s: float | None = None) -> float:
        """The stalls up to ``now_s`` (default now), the ongoing one included."""
        now_s = self._clock() if now_s is None else now_s
        intervals = list(self._intervals)
        since_s = self._ongoing_since_s
        if since_s is not None and now_s > since_s:
            intervals.append((since_s, min(now_s, since_s + self.max_excused_s)))
            intervals.sort()
        total = self._folded_s
        covered_to_s = -float("inf")
        for a, b in intervals:
            a, b = max(a, covered_to_s), min(b, now_s)
            if b > a:
                total += b - a
            covered_to_s = max(covered_to_s, b)
        return total

    def awake_s(self, now_s: float | None = None) -> float:
        """``now`` less every stall up to it: the time the host could listen."""
        now_s = self._clock() if now_s is None else now_s
        return now_s - self.stalled_s(now_s)


class TtyDeliveryProbe:
    """Times the kernel's tty layer with a private pty pair and reports its stalls to a
    `StallClock`. Run `run` as a task; cancel it to stop (it closes the pty).

    Parameters
    ----------
    clock : where stalls go.
    period_s : the pause between one byte's arrival and the next byte.
    tolerance_s : a delivery this slow is ordinary; beyond it, the excess was a stall.
    """

    def __init__(
        self, clock: StallClock, *, period_s: float = 0.02, tolerance_s: float = 0.02
    ) -> None:
        self.clock = clock
        self.period_s = period_s
        self.tolerance_s = tolerance_s
        self.latencies_s: deque[float] = deque(maxlen=2000)
        """Write-to-read times of the probe's bytes, newest last."""
        self._sent_s: float | None = None
        self._arrived = asyncio.Event()

    def latency_ms(self, percent: float) -> float | None:
        """A percentile of the probe's recent write-to-read times (None before any)."""
        if not self.latencies_s:
            return None
        ordered = sorted(self.latencies_s)
        index = min(len(ordered) - 1, round(percent / 100 * (len(ordered) - 1)))
        return ordered[index] * 1000

    @property
    def in_flight(self) -> bool:
        """A byte is on its way through the kernel (or waiting for the loop to read it)."""
        return self._sent_s is not None

    async def run(self) -> None:
        try:
            master, slave = os.openpty()
        except OSError as exc:
            log.info("no pty for timing the kernel's tty layer (%s): not measured", exc)
            return
        loop = asyncio.get_running_loop()
        try:
            for fd in (master, slave):
                tty.setraw(fd)  # no echo back to the master, no line buffering
                os.set_blocking(fd, False)
            loop.add_reader(slave, self._on_readable, slave)
            while True:
                self._arrived.clear()
                self._sent_s = self.clock.now()
                os.write(master, b"\0")
                self.clock.begin_stall(self._sent_s + self.tolerance_s)
                await self._arrived.wait()
                await asyncio.sleep(self.period_s)
        finally:
            with contextlib.suppress(ValueError, OSError):
                loop.remove_reader(slave)
            self.clock.end_stall(self.clock.now())
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)

    def _on_readable(self, fd: int) -> None:
        try:
            if not os.read(fd, 64):
                return
        except BlockingIOError:
            return
        now_s = self.clock.now()
        sent_s, self._sent_s = self._sent_s, None
        if sent_s is None:
            return
        self.latencies_s.append(now_s - sent_s)
        # Ends the stall that `run` began (nothing is counted if the byte was on time).
        self.clock.end_stall(now_s)
        self._arrived.set()
