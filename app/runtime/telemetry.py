"""The daemon's own measurements: stage durations, counters, latency percentiles and
memory, kept in bounded windows so hours of running cost no more than minutes."""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


def rss_mb() -> float | None:
    """Resident memory of this process (Linux), or None."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def nearest_rank(ordered: Sequence[float], q: float) -> float:
    """The ``q`` quantile of non-empty sorted ``ordered``: the value at the nearest rank
    (no interpolation; every figure in the reports uses this rule)."""
    return float(ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))])


def percentiles_ms(values_s: Any) -> dict[str, float | None]:
    """p50, p95 and max in milliseconds of durations in seconds, and their count."""
    data = sorted(values_s)
    if not data:
        return {"p50": None, "p95": None, "max": None, "n": 0}

    def pick(q: float) -> float:
        return round(nearest_rank(data, q) * 1000, 2)

    return {"p50": pick(0.5), "p95": pick(0.95), "max": round(data[-1] * 1000, 2), "n": len(data)}


class FloatWindow:
    """The newest ``maxlen`` samples, in a ring preallocated and written at the start: an
    hour of 30 fps samples costs no more memory than the first minute (a deque of Python
    floats grew the daemon by ~20 MB over an hour). Single precision: the samples are
    durations, and 7 digits are more than a clock's.

    Appending is O(1); iteration is oldest first; `tail` reads the newest few as one
    slice (`newest`, the stage medians and the metrics' histograms)."""

    def __init__(self, maxlen: int = 100_000) -> None:
        self.maxlen = maxlen
        # Filled, not np.zeros: zeroed pages stay unmapped until written, and the ring
        # would then grow the resident memory for as long as it fills (55 min at 30 fps).
        self._data = np.full(maxlen, 0.0, dtype=np.float32)
        self._appended = 0

    def append(self, value: float) -> None:
        self._data[self._appended % self.maxlen] = value
        self._appended += 1

    def __len__(self) -> int:
        return min(self._appended, self.maxlen)

    def values(self) -> NDArray[np.float32]:
        """A copy, oldest first."""
        return self.tail(len(self)).copy()

    def __iter__(self) -> Iterator[float]:
        return iter(self.values().tolist())

    def tail(self, n: int) -> NDArray[np.float32]:
        """The newest ``min(n, len(self))`` samples as an array, oldest first (a view of
        the ring when they do not wrap: copy it to keep it past the next `append`)."""
        count = min(n, len(self))
        end = self._appended % self.maxlen or (self.maxlen if self._appended else 0)
        if count <= end:
            return self._data[end - count : end]
        return np.concatenate((self._data[self.maxlen - (count - end) :], self._data[:end]))


def newest(values: FloatWindow, n: int) -> list[float]:
    """The last ``n`` values, newest first, without copying the whole (100k-long) window."""
    out: list[float] = values.tail(n)[::-1].tolist()
    return out


class StageClock:
    """Per-stage durations (seconds), newest last, bounded."""

    def __init__(self, maxlen: int = 100_000) -> None:
        self.maxlen = maxlen
        self.samples: dict[str, FloatWindow] = {}
        self.totals: dict[str, int] = {}
        """Samples ever added per stage (the windows drop old ones; metrics need counts)."""

    def add(self, stage: str, seconds: float) -> None:
        window = self.samples.get(stage)
        if window is None:
            window = self.samples[stage] = FloatWindow(self.maxlen)
        window.append(seconds)
        self.totals[stage] = self.totals.get(stage, 0) + 1

    def summary_ms(self) -> dict[str, dict[str, float | None]]:
        return {name: percentiles_ms(values) for name, values in self.samples.items()}

    def recent_ms(self, n: int = 30) -> dict[str, float]:
        out = {}
        for name, values in self.samples.items():
            # statistics on a short list: np.median's overhead is ~10x on 30 values.
            tail = newest(values, n)
            if tail:
                out[name] = round(statistics.median(tail) * 1000, 2)
        return out


@dataclass
class Counters:
    frames_captured: int = 0
    frames_perceived: int = 0
    learned_floor_passes: int = 0
    """Frames on which floornet ran its second pass for a learned floor colour."""
    learned_floor_passes_adding: int = 0
    """Those of them whose second pass added floor."""
    frames_mapped: int = 0
    frames_skipped: int = 0
    bad_frames: int = 0
    commands_sent: int = 0
    send_errors: int = 0
    watchdog_stops: int = 0
    clearance_stops: int = 0
    premise_stops: int = 0
    """Times the safe zone ahead stopped being floor while driving (rising edges)."""
    zone_known_floor_frames: int = 0
    """Frames whose safe zone perception doubted but the map knew was floor (no stop)."""
    faults: int = 0
    """Faults latched (they need the operator)."""
    protective_stops: int = 0
    """Protective stops that zeroed the motors (they clear by themselves)."""


class RssWatch:
    """Resident memory sampled over the run: the start, the first minute after warm-up
    (when caches and compiled kernels have settled), the steady state, the peak and the
    end, so growth after warm-up shows.

    One reading is not a level: it swings by 10-20 MB with the frames' arrays in flight
    (measured at 15 s spacing in a run whose baseline did not move: 281-300 MB within one
    minute), so a growth figure from two readings measures where each fell in that
    swing. The levels are medians over ``window_s`` of readings: the minute that starts
    at ``settle_s``, the last minute, and every reading after ``settle_s`` (kept in a ring
    of ``maxlen`` float32s; a day at 1 Hz is 346 kB).

    Parameters
    ----------
    settle_s : when warm-up is over (the first level is measured from here).
    period_s : the least time between readings (`sample` is called more often).
    window_s : the span of readings one level is the median of.
    read_mb : the reader (`rss_mb`; tests pass their own).
    """

    def __init__(
        self,
        settle_s: float = 60.0,
        period_s: float = 1.0,
        window_s: float = 60.0,
        *,
        maxlen: int = 86_400,
        read_mb: Callable[[], float | None] = rss_mb,
    ) -> None:
        self.settle_s = settle_s
        self.period_s = period_s
        self.window_s = window_s
        self._read_mb = read_mb
        self._last_s = -math.inf
        self.start_mb: float | None = None
        self.peak_mb: float | None = None
        self.last_mb: float | None = None
        self._settling: list[float] = []
        self._recent: deque[tuple[float, float]] = deque()
        self._settled = FloatWindow(maxlen)

    def sample(self, elapsed_s: float, *, force: bool = False) -> None:
        """Read the RSS if ``period_s`` passed since the last reading (or ``force``)."""
        if not force and elapsed_s - self._last_s < self.period_s:
            return
        self._last_s = elapsed_s
        mb = self._read_mb()
        if mb is None:
            return
        if self.start_mb is None:
            self.start_mb = mb
        self.peak_mb = mb if self.peak_mb is None else max(self.peak_mb, mb)
        self.last_mb = mb
        if elapsed_s < self.settle_s:
            return
        if elapsed_s < self.settle_s + self.window_s:
            self._settling.append(mb)
        self._settled.append(mb)
        self._recent.append((elapsed_s, mb))
        while self._recent[0][0] < elapsed_s - self.window_s:
            self._recent.popleft()

    def summary(self) -> dict[str, float | None]:
        """MB: ``after_first_minute`` (median of the minute after ``settle_s``), ``end``
        (median of the last minute), ``steady_median`` (of every reading after
        ``settle_s``), ``peak`` and ``last`` (single readings), and the growth of ``end``
        over ``after_first_minute`` in percent; None where there are no readings."""

        def median(values: Sequence[float]) -> float | None:
            return round(float(statistics.median(values)), 2) if len(values) else None

        settled = median(self._settling)
        end = median([mb for _, mb in self._recent])
        growth = None
        if settled and end is not None:
            growth = round((end / settled - 1.0) * 100.0, 2)
        return {
            "start": self.start_mb,
            "after_first_minute": settled,
            "steady_median": median(self._settled.values().tolist()),
            "peak": self.peak_mb,
            "end": end,
            "last": self.last_mb,
            "growth_after_first_minute_pct": growth,
        }
