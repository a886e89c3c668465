"""The pose error against the simulator's truth: position and heading, and the coarse
track that says when and where it grew."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest

from app.mapping.frames import Pose2D
from app.runtime.pose_error import TRACK_PERIOD_S, PoseErrorTracker


def tracker(true_pose: Pose2D, T_plan_odom: Pose2D) -> tuple[PoseErrorTracker, Any]:
    sim: Any = SimpleNamespace(robot=SimpleNamespace(pose=true_pose), T_plan_odom=T_plan_odom)
    return PoseErrorTracker(sim), sim


def test_position_and_heading_errors_are_measured_in_the_plan_frame() -> None:
    # The odometry frame is the start pose (1, 2, 90 degrees) in the plan.
    start = Pose2D(1.0, 2.0, math.pi / 2)
    errors, sim = tracker(Pose2D(1.0, 3.0, math.pi / 2), start)
    # One metre ahead in odometry is (1, 3) in the plan; a heading 2 degrees too far left.
    assert errors.sample(Pose2D(1.0, 0.0, math.radians(2.0)), 0.0) == pytest.approx(0.0)
    sim.robot.pose = Pose2D(1.0, 3.3, math.pi / 2)
    assert errors.sample(Pose2D(1.0, 0.0, math.radians(-1.0)), 1.0) == pytest.approx(0.3)
    assert errors.summary() == {"p50": 0.0, "p95": 0.3, "final": 0.3}
    assert errors.heading_summary_deg() == {"p50": 1.0, "p95": 2.0, "final": 1.0}


def test_the_track_keeps_one_sample_per_period_with_where_the_robot_was() -> None:
    errors, sim = tracker(Pose2D(), Pose2D())
    assert errors.heading_summary_deg() is None and not errors.track
    # Samples 0.125 s apart (exact in binary, and more than the 0.1 s sampling period).
    steps = int(3 * TRACK_PERIOD_S / 0.125) + 1
    for step in range(steps):
        now = 100.0 + 0.125 * step
        sim.robot.pose = Pose2D(0.01 * step, 0.0, 0.0)
        errors.sample(Pose2D(0.0, 0.0, math.radians(0.5)), now)
    times = [row[0] for row in errors.track]
    assert times == pytest.approx([0.0, TRACK_PERIOD_S, 2 * TRACK_PERIOD_S, 3 * TRACK_PERIOD_S])
    _, x, y, error, heading = errors.track[1]
    # The estimate stood at the origin while the robot drove 1 cm per sample.
    moved = 0.01 * TRACK_PERIOD_S / 0.125
    assert (x, y, error, heading) == pytest.approx((moved, 0.0, moved, 0.5))
    # Between the track's samples, every sample still counts in the summary.
    assert len(errors.errors_m) == steps
