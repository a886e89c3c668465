"""How far the daemon's pose estimate is from the simulator's truth: odometry drifts with
wheel slip, and scan matching should hold it near the truth. The run report's
``pose_error_m`` (null on hardware, where no truth exists)."""

from __future__ import annotations

import math
from collections import deque

from app.devices import SimHandles
from app.mapping.frames import Pose2D

SAMPLE_PERIOD_S = 0.1
"""Samples at most this often (10 Hz): the error changes over seconds, and an hour
of samples stays small."""
MAX_SAMPLES = 100_000
"""Nearly three hours at 10 Hz; older samples are dropped."""


class PoseErrorTracker:
    """Distance between the true position and the estimated one, both in the plan frame
    (the estimate is ``T_plan_odom * T_odom_robot``). Sample it right after odometry
    updates, so both poses are of the same instant (the truth is read when sampled)."""

    def __init__(self, sim: SimHandles, *, period_s: float = SAMPLE_PERIOD_S) -> None:
        self.sim = sim
        self.period_s = period_s
        self.errors_m: deque[float] = deque(maxlen=MAX_SAMPLES)
        self._due_s = -math.inf

    def sample(self, T_odom_robot: Pose2D, now_s: float) -> float | None:
        """Record the error of ``T_odom_robot`` against the robot's true pose now (at
        most once per ``period_s`` of ``now_s``); returns it, None when not due."""
        if now_s < self._due_s:
            return None
        self._due_s = now_s + self.period_s
        true = self.sim.robot.pose
        estimate = self.sim.T_plan_odom.compose(T_odom_robot)
        error = math.hypot(true.x_m - estimate.x_m, true.y_m - estimate.y_m)
        self.errors_m.append(error)
        return error

    def summary(self) -> dict[str, float] | None:
        """``{"p50": m, "p95": m, "final": m}`` to the millimetre; None before a sample."""
        if not self.errors_m:
            return None
        ordered = sorted(self.errors_m)

        def pick(q: float) -> float:
            return round(ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))], 3)

        return {"p50": pick(0.5), "p95": pick(0.95), "final": round(self.errors_m[-1], 3)}
