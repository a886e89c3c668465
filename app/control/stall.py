"""Wheel-stall detection: the bumper a robot without one has.

A robot that drives into something its camera missed (a floor-coloured box, a chair leg
in the blind strip right in front of its wheels) stops moving while its motors still
push. The Uno's telemetry carries both sides of that: the PWM it applies and the encoder
counts. Over a sliding window, the travel the PWM asks for (the inverse of
`app.control.kinematics.speed_to_pwm`) is compared with the travel the encoders counted;
a wheel that was asked for at least ``min_commanded_m`` and turned less than
``max_moved_fraction`` of it is stalled.

It only sees a wheel that is held. A wheel that spins in place on a slippery floor
counts ticks as if it drove, and a push so gentle that it stays under
``min_commanded_m`` in the window goes unnoticed.

Pure: `StallDetector.observe` takes each telemetry sample and returns the stall it sees,
or None.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

from app.config import DriveConfig
from app.control.kinematics import PWM_MAX


@dataclass(frozen=True)
class StallParams:
    """How a stall is told from a robot that is just slow to start.

    window_s : the span compared (longer than the motors' lag, so that a start from rest
        still turns the wheels most of the commanded way)
    min_commanded_m : the commanded travel of one wheel in the window below which nothing
        is judged (a wheel asked to creep proves nothing)
    max_moved_fraction : a wheel that turned less than this share of its commanded travel
        is stalled
    """

    window_s: float = 0.5
    min_commanded_m: float = 0.05
    max_moved_fraction: float = 0.2

    def __post_init__(self) -> None:
        if self.window_s <= 0:
            raise ValueError(f"window_s must be > 0, got {self.window_s}")
        if self.min_commanded_m <= 0:
            raise ValueError(f"min_commanded_m must be > 0, got {self.min_commanded_m}")
        if not 0 < self.max_moved_fraction < 1:
            raise ValueError(f"max_moved_fraction must be in (0, 1), got {self.max_moved_fraction}")


@dataclass(frozen=True)
class Stall:
    """One stalled wheel (the worse of the two), over ``span_s``."""

    wheel: str
    commanded_m: float
    moved_m: float
    span_s: float
    forward: bool
    """The held wheel was driven forwards (so what holds it is ahead)."""

    def describe(self) -> str:
        return (
            f"{self.wheel} wheel stalled: commanded {self.commanded_m * 100:.0f} cm, "
            f"turned {self.moved_m * 100:.1f} cm in {self.span_s:.1f} s"
        )


def pwm_to_speed_m_s(pwm: int, drive: DriveConfig) -> float:
    """The wheel speed a PWM asks for: the inverse of `speed_to_pwm` (0 in the
    deadband)."""
    magnitude = abs(pwm)
    if magnitude <= drive.pwm_deadband:
        return 0.0
    frac = (min(magnitude, PWM_MAX) - drive.pwm_deadband - 1) / (PWM_MAX - drive.pwm_deadband - 1)
    speed = max(0.0, frac) * drive.max_wheel_speed_m_s
    return speed if pwm > 0 else -speed


@dataclass(frozen=True)
class _Sample:
    time_s: float
    ticks: tuple[int, int]
    pwm: tuple[int, int]


class StallDetector:
    """Feed it every telemetry sample (`observe`); it says when a wheel is held."""

    def __init__(self, drive: DriveConfig, params: StallParams | None = None) -> None:
        self.drive = drive
        self.params = params or StallParams()
        self.meters_per_tick = 2 * math.pi * drive.wheel_radius_m / drive.ticks_per_rev
        self._samples: deque[_Sample] = deque()

    def reset(self) -> None:
        """Forget the history (after a reconnect the counters may restart)."""
        self._samples.clear()

    def observe(self, time_s: float, ticks: tuple[int, int], pwm: tuple[int, int]) -> Stall | None:
        """One telemetry sample: encoder counts and the PWM the Uno applies now. Returns
        the stall over the last ``window_s``, or None."""
        samples = self._samples
        if samples and time_s <= samples[-1].time_s:
            samples.clear()  # time went back: a new clock, a new history
        samples.append(_Sample(time_s, ticks, pwm))
        # Keep the newest sample at or before the window's start, so the window is full.
        start = time_s - self.params.window_s
        while len(samples) >= 2 and samples[1].time_s <= start:
            samples.popleft()
        first = samples[0]
        span_s = time_s - first.time_s
        if span_s < self.params.window_s * 0.9:
            return None
        worst: Stall | None = None
        for i, name in enumerate(("left", "right")):
            steps = [
                # The PWM reported with a sample is what drives the wheel until the next.
                pwm_to_speed_m_s(a.pwm[i], self.drive) * (b.time_s - a.time_s)
                for a, b in itertools.pairwise(samples)
            ]
            if any(x > 0 for x in steps) and any(x < 0 for x in steps):
                continue  # reversed within the window: the motor's lag proves nothing
            commanded = abs(sum(steps))
            if commanded < self.params.min_commanded_m:
                continue
            direction = 1 if sum(steps) > 0 else -1
            # Progress in the commanded direction (a wheel pushed back counts as none).
            moved = max(0, direction * _tick_delta(ticks[i], first.ticks[i])) * self.meters_per_tick
            if moved > self.params.max_moved_fraction * commanded:
                continue
            stall = Stall(name, commanded, moved, span_s, forward=direction > 0)
            if worst is None or stall.moved_m / stall.commanded_m < (
                worst.moved_m / worst.commanded_m
            ):
                worst = stall
        return worst


def _tick_delta(now: int, before: int) -> int:
    """Counter difference modulo 2**32 (the Uno's counters are int32)."""
    return (now - before + 2**31) % 2**32 - 2**31
