"""`StallClock` (exact answers on a fake clock) and `TtyDeliveryProbe` on a real pty."""

from __future__ import annotations

import asyncio
import time

import pytest

from app.hardware.stall_clock import HORIZON_S, StallClock, TtyDeliveryProbe


class FakeTime:
    def __init__(self, now_s: float = 0.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


def test_overlapping_stalls_count_once() -> None:
    clock = StallClock(clock=FakeTime(5.0))
    clock.add(1.0, 2.0)
    clock.add(1.5, 3.0)  # the reader and the probe saw the same stall
    assert clock.stalled_s() == pytest.approx(2.0)
    clock.add(4.0, 4.5)
    clock.add(0.5, 0.5)  # empty: nothing
    assert clock.stalled_s() == pytest.approx(2.5)
    assert clock.awake_s() == pytest.approx(2.5)
    assert clock.stalled_s(now_s=4.25) == pytest.approx(2.25)  # up to now only


def test_an_ongoing_stall_counts_up_to_its_cap_and_the_awake_clock_never_runs_back() -> None:
    now = FakeTime(10.0)
    clock = StallClock(max_excused_s=2.0, clock=now)
    clock.add(9.8, 10.3)  # overlaps the ongoing one below
    clock.begin_stall(10.0)
    awake = []
    for t in (10.0, 10.2, 10.5, 11.0, 12.0, 13.0):
        now.now_s = t
        awake.append(clock.awake_s())
    assert clock.stalled_s(now_s=10.5) == pytest.approx(0.7)  # 9.8..10.5, once
    # Capped: a kernel that never delivers again does not keep a silent link alive.
    assert clock.stalled_s(now_s=13.0) == pytest.approx(2.2)  # 9.8..12.0
    clock.end_stall(13.0)
    now.now_s = 14.0
    awake.append(clock.awake_s())
    assert clock.stalled_s() == pytest.approx(2.2)
    assert awake == sorted(awake)
    assert awake[-1] - awake[-2] == pytest.approx(1.0)  # awake again after the cap


def test_a_stall_that_ends_before_its_tolerance_counts_nothing() -> None:
    clock = StallClock(clock=FakeTime(1.0))
    clock.begin_stall(1.02)  # a probe byte sent at 1.0, tolerance 20 ms
    assert clock.stalled_s(now_s=1.01) == 0.0
    clock.end_stall(1.01)
    assert clock.stalled_s(now_s=2.0) == 0.0


def test_old_stalls_are_folded_into_the_total() -> None:
    now = FakeTime(0.0)
    clock = StallClock(clock=now)
    for k in range(200):
        clock.add(k * 1.0, k * 1.0 + 0.25)
    now.now_s = 300.0
    assert clock.stalled_s() == pytest.approx(50.0)
    assert len(clock._intervals) <= HORIZON_S + 2


def test_max_excused_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_excused_s"):
        StallClock(max_excused_s=0.0)


async def test_probe_times_bytes_through_a_pty_and_reports_a_late_one() -> None:
    clock = StallClock()
    probe = TtyDeliveryProbe(clock, period_s=0.005)
    task = asyncio.create_task(probe.run())
    try:
        deadline = time.monotonic() + 2.0
        while len(probe.latencies_s) < 5:
            assert time.monotonic() < deadline, "no probe byte came back"
            await asyncio.sleep(0.01)
        assert min(probe.latencies_s) < 0.05
        # A byte on its way while nothing reads it (here the loop is blocked): it comes
        # back late, and that time is a stall on the clock.
        while not probe.in_flight:
            await asyncio.sleep(0)
        before_s = clock.stalled_s()
        count = len(probe.latencies_s)
        time.sleep(0.3)
        while len(probe.latencies_s) == count:
            await asyncio.sleep(0.001)
        assert probe.latencies_s[-1] >= 0.3
        assert clock.stalled_s() - before_s >= 0.3 - probe.tolerance_s - 1e-6
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
