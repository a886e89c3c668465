"""The daemon's bounded measurement windows."""

from __future__ import annotations

import numpy as np

from app.runtime.telemetry import FloatWindow, RssWatch, StageClock, newest, percentiles_ms


def test_float_window_keeps_the_newest_in_order_and_never_grows() -> None:
    window = FloatWindow(maxlen=4)
    assert len(window) == 0 and list(window) == [] and newest(window, 3) == []
    for value in range(1, 7):
        window.append(float(value))
    assert len(window) == 4
    assert list(window) == [3.0, 4.0, 5.0, 6.0]
    assert newest(window, 2) == [6.0, 5.0]
    assert newest(window, 10) == [6.0, 5.0, 4.0, 3.0]
    assert window.values().nbytes == 4 * 4


def test_float_window_tail_is_the_newest_oldest_first_across_the_wrap() -> None:
    window = FloatWindow(maxlen=5)
    assert window.tail(3).tolist() == []
    for value in range(1, 13):
        window.append(float(value))
        for n in range(0, 8):
            expected = [float(v) for v in range(max(1, value - 4), value + 1)][-n or len(window) :]
            assert window.tail(n).tolist() == (expected if n else []), (value, n)


def test_stage_clock_recent_medians() -> None:
    clock = StageClock(maxlen=4)
    for ms in (100, 1, 2, 3, 4, 50):
        clock.add("mapping", ms / 1000)
    assert clock.recent_ms(3) == {"mapping": 4.0}  # median of 3, 4, 50
    assert clock.recent_ms(4) == {"mapping": 3.5}  # the window holds 4: 2, 3, 4, 50


def test_stage_clock_percentiles_over_the_window() -> None:
    clock = StageClock(maxlen=1000)
    for ms in range(1, 1001):
        clock.add("perception", ms / 1000)
    summary = clock.summary_ms()["perception"]
    assert summary["p50"] == 500.0 or summary["p50"] == 501.0
    assert summary["max"] == 1000.0 and summary["n"] == 1000
    assert clock.totals["perception"] == 1000
    assert percentiles_ms(np.array([])) == {"p50": None, "p95": None, "max": None, "n": 0}


def _watch_over(readings_mb: list[float], **kwargs: float) -> RssWatch:
    """A watch fed one reading per second, from t = 0."""
    feed = iter(readings_mb)
    watch = RssWatch(read_mb=lambda: next(feed), **kwargs)
    for t in range(len(readings_mb)):
        watch.sample(float(t))
    return watch


def test_rss_growth_compares_minute_medians_not_two_readings() -> None:
    # A flat 280 MB baseline with a frame's arrays in flight every third reading (+18
    # MB), sampled so that the first minute's reading at 60 s falls on the baseline and
    # the last on a spike: two readings would call that +6.4 % growth.
    readings = [250.0] * 60 + [298.0 if t % 3 == 2 else 280.0 for t in range(60, 240)]
    summary = _watch_over(readings, settle_s=60.0, window_s=60.0).summary()
    assert summary["start"] == 250.0
    assert summary["after_first_minute"] == 280.0
    assert summary["end"] == 280.0
    assert summary["steady_median"] == 280.0
    assert summary["peak"] == 298.0
    assert summary["last"] == 298.0
    assert summary["growth_after_first_minute_pct"] == 0.0


def test_rss_growth_shows_a_baseline_that_rises() -> None:
    # 300 MB through the first minute after warm-up, then +0.1 MB a second: the last
    # minute (t = 179..239 s) has its median at t = 209 s, 300 + 0.1 * 90 MB.
    readings = [300.0] * 120 + [300.0 + 0.1 * (t - 119) for t in range(120, 240)]
    summary = _watch_over(readings, settle_s=60.0, window_s=60.0).summary()
    assert summary["after_first_minute"] == 300.0
    assert summary["end"] == 309.0
    assert summary["growth_after_first_minute_pct"] == 3.0


def test_rss_watch_before_warm_up_ends_has_no_levels() -> None:
    summary = _watch_over([300.0] * 30, settle_s=60.0).summary()
    assert summary["start"] == 300.0 and summary["peak"] == 300.0
    assert summary["after_first_minute"] is None and summary["end"] is None
    assert summary["growth_after_first_minute_pct"] is None


def test_rss_watch_reads_at_most_once_a_period_unless_forced() -> None:
    reads: list[float] = []

    def read() -> float:
        reads.append(1.0)
        return 300.0

    watch = RssWatch(period_s=1.0, read_mb=read)
    for t in (0.0, 0.2, 0.9, 1.0, 1.5):
        watch.sample(t)
    watch.sample(1.6, force=True)
    assert len(reads) == 3
