"""`LoopLagMonitor`: lags recorded as actual minus scheduled wake-up, in a window, a
running count / sum / max and cumulative histogram buckets."""

from __future__ import annotations

import asyncio
import math
import time

import pytest

from app.loop_lag import LAG_BUCKETS_S, LoopLagMonitor


class ScriptedLoop:
    """A clock and a sleep that oversleeps by the scripted lags, then stops the run."""

    def __init__(self, lags_s: list[float]) -> None:
        self.now = 100.0
        self.lags_s = list(lags_s)
        self.asked: list[float] = []

    def clock(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        if not self.lags_s:
            raise asyncio.CancelledError
        self.asked.append(seconds)
        self.now += seconds + self.lags_s.pop(0)


async def test_records_how_late_each_wake_up_was() -> None:
    # -1e-6: asyncio fires timers up to its clock resolution early; that is no lag.
    loop = ScriptedLoop([0.0, 0.003, -1e-6, 0.015, 0.4])
    monitor = LoopLagMonitor(0.02, clock=loop.clock, sleep=loop.sleep)
    with pytest.raises(asyncio.CancelledError):
        await monitor.run()
    assert loop.asked == [0.02] * 5
    assert list(monitor.lags_s) == pytest.approx([0.0, 0.003, 0.0, 0.015, 0.4])
    assert monitor.count == 5
    assert monitor.max_s == pytest.approx(0.4)
    assert monitor.sum_s == pytest.approx(0.418)
    buckets = dict(monitor.cumulative_buckets())
    assert list(buckets) == [*LAG_BUCKETS_S, math.inf]
    assert buckets[0.001] == 2
    assert buckets[0.005] == 3
    assert buckets[0.02] == 4
    assert buckets[0.25] == 4
    assert buckets[0.5] == buckets[math.inf] == 5
    summary = monitor.summary_ms()
    assert summary == {"p50": 3.0, "p99": 400.0, "max": 400.0, "samples": 5}


def test_a_lag_equal_to_a_bound_is_in_that_bucket() -> None:
    monitor = LoopLagMonitor()
    monitor.record(0.02)
    buckets = dict(monitor.cumulative_buckets())
    assert (buckets[0.01], buckets[0.02]) == (0, 1)  # Prometheus' le: less or equal


def test_window_bounds_the_percentiles_not_the_totals() -> None:
    monitor = LoopLagMonitor(window=3)
    for lag_s in (0.9, 0.001, 0.001, 0.001):
        monitor.record(lag_s)
    assert len(monitor.lags_s) == 3
    summary = monitor.summary_ms()
    assert summary["p99"] == 1.0  # the 0.9 s lag left the window...
    assert summary["max"] == 900.0  # ...but not the run's maximum
    assert summary["samples"] == 4
    assert monitor.cumulative_buckets()[-1] == (math.inf, 4)


def test_a_reused_summary_is_refreshed_after_so_many_new_lags() -> None:
    monitor = LoopLagMonitor()
    monitor.record(0.001)
    first = monitor.summary_ms(reuse_within=3)
    assert first == {"p50": 1.0, "p99": 1.0, "max": 1.0, "samples": 1}
    monitor.record(0.5)
    monitor.record(0.5)
    assert monitor.summary_ms(reuse_within=3) == first  # 2 new lags: the same summary
    monitor.record(0.5)
    assert monitor.summary_ms(reuse_within=3) == {
        "p50": 500.0,
        "p99": 500.0,
        "max": 500.0,
        "samples": 4,
    }
    monitor.record(0.001)
    assert monitor.summary_ms()["samples"] == 5  # the default is always fresh


def test_summary_before_any_sample() -> None:
    assert LoopLagMonitor().summary_ms() == {"p50": None, "p99": None, "max": None, "samples": 0}


@pytest.mark.parametrize("period_s", [0.0, -1.0, math.nan, math.inf])
def test_rejects_a_bad_period(period_s: float) -> None:
    with pytest.raises(ValueError, match="period_s"):
        LoopLagMonitor(period_s)


async def test_a_blocking_call_on_the_loop_shows_as_lag() -> None:
    """The real thing: a coroutine that blocks the loop for 60 ms delays the monitor's
    wake-up by about that much."""
    monitor = LoopLagMonitor(0.01)
    task = asyncio.create_task(monitor.run())
    await asyncio.sleep(0.05)
    time.sleep(0.06)  # blocks the event loop, as a slow handler would
    await asyncio.sleep(0.05)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    summary = monitor.summary_ms()
    assert summary["samples"] >= 3
    assert summary["max"] is not None and summary["max"] >= 50.0
