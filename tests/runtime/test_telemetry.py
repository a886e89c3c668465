"""The daemon's bounded measurement windows."""

from __future__ import annotations

import numpy as np

from app.runtime.telemetry import FloatWindow, StageClock, newest, percentiles_ms


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
