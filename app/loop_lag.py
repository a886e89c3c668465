"""How late the event loop runs its callbacks, measured all the time.

Everything the daemon does between two frames runs on one event loop: the drive stage's
20 ms commands, the Uno link's ACK deadlines, the API. Anything that holds the loop (a
blocking call in a coroutine, a thread holding the GIL, a garbage collection) delays all
of them at once. `LoopLagMonitor` sleeps for ``period_s`` over and over and records how
much later than asked it woke: that lag is the delay every other callback suffered too.
"""

from __future__ import annotations

import asyncio
import bisect
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable

LAG_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0)
"""Upper bounds of the lag histogram's buckets (Prometheus ``le``), plus +Inf."""
DEFAULT_PERIOD_S = 0.02
"""One wake-up per drive command period: a lag shorter than that would not delay one."""
DEFAULT_WINDOW = 30_000
"""Lags kept for the percentiles: the last 10 minutes at the default period."""


class LoopLagMonitor:
    """Run ``await monitor.run()`` as a task on the loop to watch; read the numbers from
    the same thread (``summary_ms`` for the run report, the rest for ``/metrics``).

    Parameters
    ----------
    period_s : how long each sleep asks for.
    window : how many of the newest lags the percentiles are taken over.
    clock, sleep : the loop's clock and sleep (tests pass fakes).
    """

    def __init__(
        self,
        period_s: float = DEFAULT_PERIOD_S,
        *,
        window: int = DEFAULT_WINDOW,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
        buckets_s: tuple[float, ...] = LAG_BUCKETS_S,
    ) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"period_s must be finite and > 0, got {period_s}")
        if list(buckets_s) != sorted(set(buckets_s)):
            raise ValueError(f"buckets_s must increase strictly, got {buckets_s}")
        self.period_s = period_s
        self.clock = clock
        self.sleep = sleep
        self.buckets_s = buckets_s
        self.lags_s: deque[float] = deque(maxlen=window)
        """The newest lags in seconds, newest last."""
        self.count = 0
        """Lags ever recorded."""
        self.sum_s = 0.0
        """Their sum, in seconds."""
        self.max_s = 0.0
        """The largest lag ever recorded, in seconds."""
        self._bucket_counts = [0] * (len(buckets_s) + 1)  # the last one is +Inf
        self._summary: dict[str, float | int | None] | None = None
        self._summary_count = 0

    async def run(self) -> None:
        """Measure until cancelled."""
        while True:
            due = self.clock() + self.period_s
            await self.sleep(self.period_s)
            # asyncio may fire a timer up to its clock resolution early: never negative.
            self.record(max(0.0, self.clock() - due))

    def record(self, lag_s: float) -> None:
        self.lags_s.append(lag_s)
        self.count += 1
        self.sum_s += lag_s
        self.max_s = max(self.max_s, lag_s)
        # bisect_left: a lag equal to a bound belongs to that bucket (``le``).
        self._bucket_counts[bisect.bisect_left(self.buckets_s, lag_s)] += 1

    def cumulative_buckets(self) -> list[tuple[float, int]]:
        """``(upper bound in seconds, lags <= it)`` per bucket, +Inf last (= ``count``)."""
        bounds = [*self.buckets_s, math.inf]
        out: list[tuple[float, int]] = []
        running = 0
        for bound, count in zip(bounds, self._bucket_counts, strict=True):
            running += count
            out.append((bound, running))
        return out

    def summary_ms(self, *, reuse_within: int = 0) -> dict[str, float | int | None]:
        """``p50`` and ``p99`` of the window, ``max`` of the run (milliseconds, None
        before the first sample) and ``samples`` ever recorded.

        ``reuse_within``: return the last summary while fewer than this many lags were
        recorded since it. Sorting the 30 000-lag window holds the GIL for milliseconds;
        the status endpoint, polled up to 100 times a second, must not do it each time.
        """
        if not self.lags_s:
            return {"p50": None, "p99": None, "max": None, "samples": 0}
        if self._summary is not None and self.count - self._summary_count < reuse_within:
            return dict(self._summary)
        ordered = sorted(self.lags_s)

        def pick(q: float) -> float:
            return round(ordered[round(q * (len(ordered) - 1))] * 1e3, 2)

        self._summary = {
            "p50": pick(0.50),
            "p99": pick(0.99),
            "max": round(self.max_s * 1e3, 2),
            "samples": self.count,
        }
        self._summary_count = self.count
        return dict(self._summary)
