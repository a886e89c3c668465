"""Wheel-stall detection from telemetry (PWM applied, encoder counts)."""

from __future__ import annotations

import math

import pytest

from app.config import DriveConfig
from app.control.kinematics import speed_to_pwm
from app.control.stall import StallDetector, StallParams, pwm_to_speed_m_s
from app.sim.robot import RobotParams, SimRobot
from app.sim.world import parse_world

DRIVE = DriveConfig()
TICKS_PER_M = DRIVE.ticks_per_rev / (2 * math.pi * DRIVE.wheel_radius_m)
PERIOD_S = 0.05  # the Uno's telemetry period


def feed(
    detector: StallDetector,
    pwm: tuple[int, int],
    speeds_m_s: tuple[float, float],
    seconds: float,
    start: tuple[float, tuple[float, float]] = (0.0, (0.0, 0.0)),
) -> tuple[list[object], tuple[float, tuple[float, float]]]:
    """Telemetry every 50 ms while the wheels turn at ``speeds_m_s`` under ``pwm``."""
    t, (left_m, right_m) = start
    seen = []
    for _ in range(round(seconds / PERIOD_S)):
        t += PERIOD_S
        left_m += speeds_m_s[0] * PERIOD_S
        right_m += speeds_m_s[1] * PERIOD_S
        ticks = (math.floor(left_m * TICKS_PER_M), math.floor(right_m * TICKS_PER_M))
        seen.append(detector.observe(t, ticks, pwm))
    return seen, (t, (left_m, right_m))


def test_pwm_to_speed_inverts_speed_to_pwm() -> None:
    for speed in (0.05, 0.2, -0.35, 0.5):
        assert pwm_to_speed_m_s(speed_to_pwm(speed, DRIVE), DRIVE) == pytest.approx(
            speed, abs=0.002
        )
    assert pwm_to_speed_m_s(DRIVE.pwm_deadband, DRIVE) == 0.0
    assert pwm_to_speed_m_s(0, DRIVE) == 0.0


def test_wheels_that_turn_as_commanded_are_not_stalled() -> None:
    detector = StallDetector(DRIVE)
    pwm = speed_to_pwm(0.3, DRIVE)
    seen, _ = feed(detector, (pwm, pwm), (0.3, 0.3), 3.0)
    assert seen == [None] * len(seen)


def test_held_wheels_stall_after_the_window() -> None:
    detector = StallDetector(DRIVE)
    pwm = speed_to_pwm(0.3, DRIVE)
    seen, state = feed(detector, (pwm, pwm), (0.3, 0.3), 1.0)
    assert seen == [None] * len(seen)
    seen, _ = feed(detector, (pwm, pwm), (0.0, 0.0), 0.7, start=state)
    held_s = PERIOD_S * (1 + next(i for i, s in enumerate(seen) if s is not None))
    # The wheel turned for the part of the 0.5 s window before it was held; at <= 20 %
    # of the commanded travel (held >= 0.4 s) it is a stall (ticks round down; the
    # window holds the sample at or before its start).
    assert 0.4 - 1e-9 <= held_s <= 0.5 + 1e-9
    stall = seen[-1]
    assert stall is not None and stall.forward
    assert stall.moved_m == pytest.approx(0.0, abs=0.002)
    assert stall.commanded_m == pytest.approx(0.15, abs=0.01)
    assert "stalled: commanded 15 cm, turned 0.0 cm in 0.5 s" in stall.describe()


def test_a_start_from_rest_with_motor_lag_is_not_a_stall() -> None:
    detector = StallDetector(DRIVE)
    pwm = speed_to_pwm(0.35, DRIVE)
    t, left_m, tau_s = 0.0, 0.0, 0.15  # slower motors than the simulator's
    for _ in range(40):
        t += PERIOD_S
        left_m = 0.35 * (t - tau_s * (1 - math.exp(-t / tau_s)))
        ticks = math.floor(left_m * TICKS_PER_M)
        assert detector.observe(t, (ticks, ticks), (pwm, pwm)) is None


def test_creeping_and_standing_prove_nothing() -> None:
    detector = StallDetector(DRIVE)
    creep = DRIVE.pwm_deadband + 3  # asks for a few mm per second
    seen, state = feed(detector, (creep, creep), (0.0, 0.0), 2.0)
    assert seen == [None] * len(seen)
    seen, _ = feed(detector, (0, 0), (0.0, 0.0), 2.0, start=state)
    assert seen == [None] * len(seen)


def test_one_held_wheel_while_turning_and_reversing() -> None:
    detector = StallDetector(DRIVE)
    left, right = speed_to_pwm(-0.2, DRIVE), speed_to_pwm(0.3, DRIVE)
    seen, _ = feed(detector, (left, right), (0.0, 0.3), 1.0)
    stall = seen[-1]
    assert stall is not None
    assert stall.wheel == "left" and not stall.forward


def test_counter_wrap_is_not_a_jump() -> None:
    detector = StallDetector(DRIVE)
    pwm = speed_to_pwm(0.3, DRIVE)
    ticks = 2**31 - 40
    for k in range(20):
        wrapped = (ticks + k * 17 + 2**31) % 2**32 - 2**31  # crosses int32's end
        assert detector.observe(k * PERIOD_S, (wrapped, wrapped), (pwm, pwm)) is None


def test_params_are_checked() -> None:
    with pytest.raises(ValueError, match="max_moved_fraction"):
        StallParams(max_moved_fraction=1.0)
    with pytest.raises(ValueError, match="window_s"):
        StallParams(window_s=0.0)


MINIMAL_ROOM = """
name = "box"
[start]
x_m = 1.0
y_m = 1.0
[[rooms]]
rect_m = [0.0, 0.0, 3.0, 2.0]
"""


def test_the_simulated_robot_driving_into_a_wall_stalls_and_nothing_else_does() -> None:
    """End to end with the simulator's motor model (lag, slip): free driving and
    turning never stall; pushing against the wall does, within 0.5 s of the contact."""
    world = parse_world(MINIMAL_ROOM)
    params = RobotParams(slip_sigma_frac=0.03, wheel_scale_sigma_frac=0.005)
    robot = SimRobot(world, params, seed=3)
    detector = StallDetector(DRIVE)
    t = 0.0
    contact_s: float | None = None
    stalled_s: float | None = None
    plan = [((-90, 90), 1.5), ((90, -90), 1.5), ((140, 140), 12.0)]  # turn, turn back, go
    for pwm, seconds in plan:
        robot.apply_pwm(*pwm)
        for _ in range(round(seconds / 0.01)):
            robot.step(0.01)
            t += 0.01
            if contact_s is None and robot.collisions:
                contact_s = t
            if round(t / 0.01) % 5 == 0:  # telemetry every 50 ms
                stall = detector.observe(t, robot.read_encoders(), pwm)
                if stall is not None and stalled_s is None:
                    stalled_s = t
                    assert stall.forward
    assert contact_s is not None, "the robot never reached the wall"
    assert stalled_s is not None and contact_s < stalled_s <= contact_s + 0.5
