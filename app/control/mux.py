"""Command priority: e-stop > teleop > autonomy, each input with a timeout.

Pure logic with the clock passed in, so every rule is tested exactly:

- An input older than its timeout is ignored. When the input that was driving times out,
  the output is an explicit zero (``Twist()`` with source ``"timeout"``), never the last
  command held; twist_mux's habit of going silent instead is what users trip over.
- E-stop latches: from `estop` until `reset_estop` the output is zero whatever else comes.
- One teleop driver at a time. A different driver is refused while the current one is
  live unless it asks to take over; anyone may send a stop (zero) as teleop, and
  `release` hands back to autonomy at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Twist:
    """A body velocity command: forward speed and turn rate (counter-clockwise +)."""

    v_m_s: float = 0.0
    omega_rad_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.v_m_s) and math.isfinite(self.omega_rad_s)):
            raise ValueError(f"twist must be finite, got ({self.v_m_s}, {self.omega_rad_s})")

    @property
    def is_zero(self) -> bool:
        return self.v_m_s == 0.0 and self.omega_rad_s == 0.0


ZERO = Twist()


@dataclass(frozen=True)
class MuxOutput:
    """What to drive now and why.

    Attributes
    ----------
    twist : the command (zero unless an input is live)
    source : "estop", "teleop", "autonomy", "timeout" (the driving input just timed
        out: zero) or "idle" (no input)
    stamp_s : when the chosen input was made (for latency), or the query time for zeros
    origin_s : the capture time of the data the command came from (autonomy), else
        ``stamp_s``
    arrived_s : when the host had that data (autonomy: the frame's arrival, after
        the camera's transfer or the simulator's render), else ``origin_s``
    """

    twist: Twist
    source: str
    stamp_s: float
    origin_s: float
    arrived_s: float | None = None

    @property
    def arrival_s(self) -> float:
        return self.origin_s if self.arrived_s is None else self.arrived_s


class TeleopRefusedError(Exception):
    """Another driver holds teleop; take over explicitly to replace them."""


@dataclass(frozen=True)
class _Input:
    twist: Twist
    stamp_s: float
    origin_s: float
    driver: str = ""
    arrived_s: float | None = None


class CommandMux:
    """See the module docstring. Not thread-safe: one event loop owns it."""

    def __init__(self, *, teleop_timeout_s: float = 0.5, autonomy_timeout_s: float = 0.5) -> None:
        if teleop_timeout_s <= 0 or autonomy_timeout_s <= 0:
            raise ValueError("timeouts must be > 0")
        self.teleop_timeout_s = teleop_timeout_s
        self.autonomy_timeout_s = autonomy_timeout_s
        self._teleop: _Input | None = None
        self._autonomy: _Input | None = None
        self._estop_reason: str | None = None
        self.estops = 0

    # -- inputs -------------------------------------------------------------------------

    def estop(self, reason: str = "e-stop") -> None:
        """Latch the e-stop (counted once per latch)."""
        if self._estop_reason is None:
            self.estops += 1
            self._estop_reason = reason
        self._teleop = None
        self._autonomy = None

    def reset_estop(self) -> bool:
        """Release the latch; True if it was latched. Inputs must be sent anew."""
        was = self._estop_reason is not None
        self._estop_reason = None
        return was

    @property
    def estopped(self) -> bool:
        return self._estop_reason is not None

    @property
    def estop_reason(self) -> str | None:
        return self._estop_reason

    def teleop(self, driver: str, twist: Twist, now_s: float, *, take_over: bool = False) -> None:
        """A teleop command from ``driver``.

        Raises
        ------
        TeleopRefusedError : another driver is live and this one neither takes over nor stops.
        """
        current = self._live_teleop(now_s)
        # Anyone may stop the robot: a zero from another driver takes over as a stop.
        held_by_other = current is not None and current.driver != driver
        if held_by_other and not take_over and not twist.is_zero:
            assert current is not None
            raise TeleopRefusedError(
                f"teleop is held by {current.driver!r}; take over explicitly to drive"
            )
        self._teleop = _Input(twist, now_s, now_s, driver)

    def release(self, driver: str | None = None) -> None:
        """End teleop (of ``driver`` only, if given); autonomy resumes on its next input."""
        if self._teleop is not None and (driver is None or self._teleop.driver == driver):
            self._teleop = None

    def teleop_driver(self, now_s: float) -> str | None:
        current = self._live_teleop(now_s)
        return None if current is None else current.driver

    def autonomy(
        self,
        twist: Twist,
        now_s: float,
        *,
        origin_s: float | None = None,
        arrived_s: float | None = None,
    ) -> None:
        """A command from the autonomous steering; ``origin_s`` is when its camera frame
        was captured, ``arrived_s`` when the host had it."""
        origin_s = now_s if origin_s is None else origin_s
        self._autonomy = _Input(twist, now_s, origin_s, arrived_s=arrived_s)

    def clear_autonomy(self) -> None:
        self._autonomy = None

    # -- output -------------------------------------------------------------------------

    def output(self, now_s: float) -> MuxOutput:
        if self._estop_reason is not None:
            return MuxOutput(ZERO, "estop", now_s, now_s)
        teleop = self._live_teleop(now_s)
        if teleop is not None:
            return MuxOutput(teleop.twist, "teleop", teleop.stamp_s, teleop.origin_s)
        autonomy = self._autonomy
        if autonomy is not None and now_s - autonomy.stamp_s <= self.autonomy_timeout_s:
            return MuxOutput(
                autonomy.twist,
                "autonomy",
                autonomy.stamp_s,
                autonomy.origin_s,
                autonomy.arrived_s,
            )
        if self._teleop is not None or self._autonomy is not None:
            # An input was given and went quiet: say so with an explicit zero.
            return MuxOutput(ZERO, "timeout", now_s, now_s)
        return MuxOutput(ZERO, "idle", now_s, now_s)

    def _live_teleop(self, now_s: float) -> _Input | None:
        teleop = self._teleop
        if teleop is None or now_s - teleop.stamp_s > self.teleop_timeout_s:
            return None
        return teleop
