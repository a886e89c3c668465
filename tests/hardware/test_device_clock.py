"""`DeviceClock`: a device's readings timed in host time by the least delayed message."""

from __future__ import annotations

import random

import pytest

from app.hardware.device_clock import WINDOW_S, DeviceClock


def test_the_least_delayed_message_times_the_others() -> None:
    clock = DeviceClock()
    rng = random.Random(1)
    offset_s = 1000.0  # host time when the device booted
    worst = 0.0
    for k in range(200):
        device_ms = 50 * k
        delay_s = 0.002 + rng.uniform(0.0, 0.04)  # transfer, then a busy event loop
        read_s = offset_s + device_ms / 1000
        timed = clock.host_time_s(device_ms, read_s + delay_s)
        assert timed <= read_s + delay_s
        if k >= 40:  # a full window seen: some message in it came within ~2.5 ms
            worst = max(worst, abs(timed - read_s))
    assert worst < 0.005


def test_a_restarted_board_and_a_wrapped_clock() -> None:
    clock = DeviceClock()
    assert clock.host_time_s(10_000, 110.0) == pytest.approx(110.0)
    assert clock.host_time_s(10_050, 110.08) == pytest.approx(110.05)  # 30 ms late
    # The board resets: its clock starts again near 0; the old offsets are void.
    assert clock.host_time_s(200, 111.0) == pytest.approx(111.0)
    assert clock.host_time_s(250, 111.06) == pytest.approx(111.05)
    # The uint32 clock wraps after 49.7 days: time goes on.
    clock = DeviceClock()
    assert clock.host_time_s(2**32 - 20, 500.0) == pytest.approx(500.0)
    assert clock.host_time_s(30, 500.05) == pytest.approx(500.05)


def test_old_offsets_leave_the_window() -> None:
    # A clock that runs slow (0.5 %, an Uno's ceramic resonator) is followed: what
    # times a message is at most a window old.
    clock = DeviceClock()
    for k in range(400):
        device_ms = 50 * k
        host_s = device_ms / 1000 * 1.005
        timed = clock.host_time_s(device_ms, host_s)
        assert abs(timed - host_s) <= 0.005 * WINDOW_S + 1e-9
