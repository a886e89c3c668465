"""How far the daemon's pose estimate is from the simulator's truth: odometry drifts with
wheel slip, and scan matching should hold it near the truth. The run report's
``pose_error_m`` (null on hardware, where no truth exists)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

from app.devices import SimHandles
from app.mapping.frames import Pose2D
from app.runtime.telemetry import nearest_rank

SAMPLE_PERIOD_S = 0.1
"""Samples at most this often (10 Hz): the error changes over seconds, and an hour
of samples stays small."""
MAX_SAMPLES = 100_000
"""Nearly three hours at 10 Hz; older samples are dropped."""
TRACK_PERIOD_S = 5.0
"""The report's ``pose_error_track`` keeps one sample per this many seconds..."""
TRACK_KEPT = 2000
"""...the latest this many (nearly three hours): when and where the error grew."""


class PoseErrorTracker:
    """Distance between the true position and the estimated one, both in the plan frame
    (the estimate is ``T_plan_odom * T_odom_robot``). Sample it right after odometry
    updates, so both poses are of the same instant (the truth is read when sampled)."""

    def __init__(self, sim: SimHandles, *, period_s: float = SAMPLE_PERIOD_S) -> None:
        self.sim = sim
        self.period_s = period_s
        self.errors_m: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.heading_errors_rad: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.track: deque[tuple[float, float, float, float, float]] = deque(maxlen=TRACK_KEPT)
        """(seconds since the first sample, true x and y in the plan frame (m), position
        error (m), heading error (degrees, estimate minus truth)), every
        `TRACK_PERIOD_S`."""
        self._due_s = -math.inf
        self._first_s: float | None = None
        self._track_due_s = -math.inf

    def sample(self, T_odom_robot: Pose2D, now_s: float) -> float | None:
        """Record the error of ``T_odom_robot`` against the robot's true pose now (at
        most once per ``period_s`` of ``now_s``); returns it, None when not due."""
        if now_s < self._due_s:
            return None
        self._due_s = now_s + self.period_s
        true = self.sim.robot.pose
        estimate = self.sim.T_plan_odom.compose(T_odom_robot)
        error = math.hypot(true.x_m - estimate.x_m, true.y_m - estimate.y_m)
        heading = math.remainder(estimate.theta_rad - true.theta_rad, math.tau)
        self.errors_m.append(error)
        self.heading_errors_rad.append(heading)
        if self._first_s is None:
            self._first_s = now_s
        if now_s >= self._track_due_s:
            self._track_due_s = now_s + TRACK_PERIOD_S
            self.track.append(
                (
                    round(now_s - self._first_s, 1),
                    round(true.x_m, 2),
                    round(true.y_m, 2),
                    round(error, 3),
                    round(math.degrees(heading), 2),
                )
            )
        return error

    def summary(self) -> dict[str, float] | None:
        """``{"p50": m, "p95": m, "final": m}`` to the millimetre; None before a sample."""
        return _summary(self.errors_m, 3)

    def heading_summary_deg(self) -> dict[str, float] | None:
        """The heading error's size in degrees: ``{"p50", "p95", "final"}``; None before a
        sample. Heading is the costliest error: one degree moves a wall 3 m away by 5 cm."""
        return _summary([abs(math.degrees(h)) for h in self.heading_errors_rad], 2)


def _summary(values: Sequence[float], digits: int) -> dict[str, float] | None:
    """``{"p50", "p95", "final"}`` of ``values`` (oldest first), rounded; None if empty."""
    if not values:
        return None
    ordered = sorted(values)

    def pick(q: float) -> float:
        return round(nearest_rank(ordered, q), digits)

    return {"p50": pick(0.5), "p95": pick(0.95), "final": round(values[-1], digits)}
