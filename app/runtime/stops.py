"""Why the robot stops, and when it may go again.

Two kinds of stop, as robot safety standards name them:

- **protective stop**: a transient cause (the Uno link dropped, the camera skipped, the
  perception fell behind) holds the robot: the motors go to zero at once, and once the
  cause has been clear for ``safety.resume_after_clear_s`` autonomy resumes by itself.
- **latched fault**: a cause that keeps coming back (``safety.fault_latch_repeats``
  times within ``safety.fault_latch_window_s``) or a device gone for longer than
  ``safety.device_lost_latch_s`` means something is broken: autonomy stops and stays
  stopped until a person resets the fault. Coming back counts after the robot went on:
  a cause that returns while its stop still holds (clear for less than
  ``resume_after_clear_s``) continues that stop (a map that arrives just late three
  times in half a second is one stall, not three), and a device's time gone counts
  from the stop's start.

The forward-only layers (too little clearance, a safe zone that is not floor) are
recorded here too, so the last stop is always explained, but they neither hold nor latch:
they only take forward motion away and clear as soon as the way is free. So is a failed
calibration, which left autonomy off (`StopPolicy.record`: an event, not a state). The
e-stop is latched by the command mux, above all of this.

What a cause does is data (`STOP_RULES`), in the spirit of twist_mux's priority table.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from app.config import SafetyConfig


@dataclass(frozen=True)
class StopRule:
    """What one stop cause does."""

    zeroes_motors: bool
    """Holds autonomy at zero (else it only takes forward motion away)."""
    latches: bool
    """Repeats latch a fault."""
    device: bool
    """A device that is gone: latches when it stays gone for ``device_lost_latch_s``."""


STOP_RULES: dict[str, StopRule] = {
    "link": StopRule(zeroes_motors=True, latches=True, device=True),
    "camera": StopRule(zeroes_motors=True, latches=True, device=True),
    "stale": StopRule(zeroes_motors=True, latches=True, device=False),
    "clearance": StopRule(zeroes_motors=False, latches=False, device=False),
    "not_floor": StopRule(zeroes_motors=False, latches=False, device=False),
    "calibration": StopRule(zeroes_motors=False, latches=False, device=False),
}
"""``link``: the Uno is not connected; ``camera``: no recent frame; ``stale``: no recent
perception or map while exploring; ``clearance``: too little free floor ahead;
``not_floor``: the safe zone ahead is not floor; ``calibration``: a calibration failed
after it had stopped autonomy, which stays off until started (recorded, never held)."""


@dataclass(frozen=True)
class StopEvent:
    """A stop as people see it: what, why, when, and whether it latched."""

    cause: str
    reason: str
    monotonic_s: float
    wall_time: float
    latched: bool = False

    def as_dict(self, now_s: float) -> dict[str, Any]:
        return {
            "cause": self.cause,
            "reason": self.reason,
            "t": round(self.wall_time, 3),
            "age_s": round(max(0.0, now_s - self.monotonic_s), 2),
            "latched": self.latched,
        }


@dataclass(frozen=True)
class ProtectiveStop:
    """The stop layer holding the robot back now. ``cause`` is a `STOP_RULES` key or
    ``"fault"`` (a latched fault); ``reason`` says it in a sentence for people."""

    cause: str
    reason: str


@dataclass
class _Episode:
    reason: str
    since_s: float


class StopPolicy:
    """Tracks every stop cause, decides protective stop vs latched fault, and remembers
    the last stop. Meant for one thread (the event loop's)."""

    def __init__(
        self,
        safety: SafetyConfig,
        *,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.safety = safety
        self.wall_clock = wall_clock
        self.last_stop: StopEvent | None = None
        self.latched: StopEvent | None = None
        self.stops_by_cause: dict[str, int] = dict.fromkeys(STOP_RULES, 0)
        self.faults_latched = 0
        self._active: dict[str, _Episode] = {}
        self._cleared_s: dict[str, float] = {}
        self._cleared_since_s: dict[str, float] = {}
        """When the stop a cleared cause ended began (a return within the resume time
        continues it)."""
        self._recent: dict[str, deque[float]] = {cause: deque() for cause in STOP_RULES}

    def observe(self, cause: str, problem: str | None, now_s: float) -> StopEvent | None:
        """Report one cause's state: ``problem`` in a sentence, or None when clear.
        Returns the stop this observation started or latched (None otherwise)."""
        rule = STOP_RULES[cause]
        episode = self._active.get(cause)
        if not problem:
            if episode is not None:
                del self._active[cause]
                self._cleared_s[cause] = now_s
                self._cleared_since_s[cause] = episode.since_s
            return None
        if episode is None:
            cleared_s = self._cleared_s.pop(cause, None)
            since_s = self._cleared_since_s.pop(cause, now_s)
            if (
                rule.zeroes_motors
                and cleared_s is not None
                and now_s - cleared_s < self.safety.resume_after_clear_s
            ):
                # Back before the robot went on: the same stop, still holding.
                episode = self._active[cause] = _Episode(problem, since_s)
        if episode is not None:
            episode.reason = problem
            lost_s = now_s - episode.since_s
            if rule.device and self.latched is None and lost_s > self.safety.device_lost_latch_s:
                return self._latch(
                    cause, f"{problem} (for more than {self.safety.device_lost_latch_s:g} s)", now_s
                )
            return None
        self._active[cause] = _Episode(problem, now_s)
        self.stops_by_cause[cause] += 1
        event = StopEvent(cause, problem, now_s, self.wall_clock())
        self.last_stop = event
        if rule.latches and self.latched is None:
            recent = self._recent[cause]
            recent.append(now_s)
            while recent and now_s - recent[0] > self.safety.fault_latch_window_s:
                recent.popleft()
            if len(recent) >= self.safety.fault_latch_repeats:
                return self._latch(
                    cause,
                    f"{problem} ({len(recent)} times within "
                    f"{self.safety.fault_latch_window_s:g} s)",
                    now_s,
                )
        return event

    def record(self, cause: str, reason: str, now_s: float) -> StopEvent:
        """A one-off stop that is over as it happens (nothing to clear later): counted
        and remembered as the last stop, never held or latched."""
        rule = STOP_RULES[cause]
        if rule.zeroes_motors or rule.latches or rule.device:
            raise ValueError(f"{cause} stops are observed, not recorded")
        self.stops_by_cause[cause] += 1
        event = StopEvent(cause, reason, now_s, self.wall_clock())
        self.last_stop = event
        return event

    def _latch(self, cause: str, reason: str, now_s: float) -> StopEvent:
        event = StopEvent(cause, reason, now_s, self.wall_clock(), latched=True)
        self.latched = event
        self.last_stop = event
        self.faults_latched += 1
        return event

    def active(self, cause: str) -> str | None:
        """The problem of ``cause`` if it holds now."""
        episode = self._active.get(cause)
        return episode.reason if episode is not None else None

    def holding(self, now_s: float) -> ProtectiveStop | None:
        """What holds autonomy at zero now: a latched fault, a motor-zeroing cause that is
        active, or one that cleared less than ``resume_after_clear_s`` ago."""
        if self.latched is not None:
            return ProtectiveStop(
                "fault", f"fault latched: {self.latched.reason}; reset it to go on"
            )
        for cause, episode in self._active.items():
            if STOP_RULES[cause].zeroes_motors:
                return ProtectiveStop(cause, f"{episode.reason}: motors zero")
        resume_s = self.safety.resume_after_clear_s
        for cause, cleared_s in self._cleared_s.items():
            waited = now_s - cleared_s
            if STOP_RULES[cause].zeroes_motors and waited < resume_s:
                return ProtectiveStop(
                    cause,
                    f"{cause} clear for {waited:.1f} s: resuming after {resume_s:g} s",
                )
        return None

    def reset(self) -> StopEvent | None:
        """Clear a latched fault (the operator's call); returns it, or None. The repeat
        history goes too, so the next blip starts counting afresh."""
        latched, self.latched = self.latched, None
        for recent in self._recent.values():
            recent.clear()
        return latched

    def as_dict(self, now_s: float) -> dict[str, Any]:
        return {
            "last_stop": self.last_stop.as_dict(now_s) if self.last_stop else None,
            "fault_latched": self.latched.as_dict(now_s) if self.latched else None,
            "stops_by_cause": dict(self.stops_by_cause),
            "faults_latched": self.faults_latched,
        }
