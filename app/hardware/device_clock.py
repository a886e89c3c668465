"""When a device's reading was taken, in host time.

Telemetry is stamped by the host when it arrives, late by the serial transfer and by
however long the event loop took to read it: in a daemon run that lateness varied by
tens of milliseconds, which at 1.5 rad/s is degrees of heading for whatever is timed
by it (a camera frame's pose, `WheelOdometry.pose_at`). The Uno also sends its own
clock (``uptime_ms``, read with the encoders). Its offset to the host clock,
``received_s - device_s``, is the true offset plus the delay, so the smallest offset
over the last few seconds is the least delayed reading, the one closest to the truth
(NTP's minimum-delay filter). The window stays short because an Uno's ceramic
resonator may run 0.5 % fast or slow: 10 ms over 2 s.
"""

from __future__ import annotations

from collections import deque

WINDOW_S = 2.0
"""Offsets are compared over this much host time."""
_WRAP_MS = 1 << 32


class DeviceClock:
    """Maps a device's millisecond clock onto the host's clock (seconds)."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        self._offsets: deque[tuple[float, float]] = deque()  # (received_s, offset_s)
        self._last_ms: int | None = None
        self._wraps = 0

    def host_time_s(self, device_ms: int, received_s: float) -> float:
        """The host time at which the device read ``device_ms`` (its uint32 clock) for
        a message that arrived at ``received_s``; never later than ``received_s``."""
        device_ms &= _WRAP_MS - 1
        if self._last_ms is not None and device_ms < self._last_ms:
            if self._last_ms - device_ms > _WRAP_MS // 2:
                self._wraps += 1  # the uint32 wrapped (after 49.7 days)
            else:
                # The clock went back: the board restarted, the old offsets are void.
                self._offsets.clear()
                self._wraps = 0
        self._last_ms = device_ms
        device_s = (device_ms + self._wraps * _WRAP_MS) / 1000.0
        self._offsets.append((received_s, received_s - device_s))
        while self._offsets[0][0] < received_s - self.window_s:
            self._offsets.popleft()
        return device_s + min(offset for _, offset in self._offsets)
