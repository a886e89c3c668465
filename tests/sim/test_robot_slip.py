"""Wheel slip, tyre scale errors and encoder noise of the simulated robot: off, it is the
ideal robot exactly; on, odometry from its encoders drifts, reproducibly per seed."""

from __future__ import annotations

import math
import random
from dataclasses import replace

import pytest

from app.config import DriveConfig, FloornavConfig
from app.control.kinematics import RateLimiter, WheelOdometry, twist_to_pwm
from app.control.mux import Twist
from app.devices import robot_params
from app.mapping.frames import Pose2D
from app.sim.robot import RobotParams, SimRobot, slip_severity
from app.sim.world import parse_world

BOX_ROOM = """
name = "box room"
[start]
x_m = 1.0
y_m = 1.0
[[rooms]]
rect_m = [0.0, 0.0, 4.0, 2.0]
[[boxes]]
center_m = [2.5, 1.4]
size_m = [0.3, 0.3]
"""
SCRIPT = [
    (200, 200, 3.0),
    (-150, 150, 1.1),
    (255, 255, 6.0),
    (120, 240, 2.0),
    (-200, -200, 0.7),
    (255, 90, 2.5),
    (255, 255, 8.0),
]
"""(left PWM, right PWM, seconds): drives, turns, two collisions."""
STEPS_S = (0.01, 0.013, 0.007, 0.02)


def run_script(robot: SimRobot) -> None:
    k = 0
    for left, right, seconds in SCRIPT:
        robot.apply_pwm(left, right)
        t = 0.0
        while t < seconds:
            dt = STEPS_S[k % len(STEPS_S)]
            k += 1
            robot.step(dt)
            t += dt


def test_zero_settings_are_the_ideal_robot_exactly() -> None:
    """The pose, counts and collisions this script gave before slip existed (any
    change of the float operations on the ideal path shows in the last digits)."""
    for seed in (0, 7):
        robot = SimRobot(parse_world(BOX_ROOM), RobotParams(), seed=seed)
        run_script(robot)
        assert robot.pose == Pose2D(
            x_m=0.458857517843015, y_m=0.15000000000008193, theta_rad=-1.6866666666662957
        )
        assert robot.read_encoders() == (9114, 8528)
        assert robot.collisions == 2
        assert robot.wheel_scale == (1.0, 1.0)


def test_the_daemon_config_slips_by_default_and_zero_turns_it_off() -> None:
    params = robot_params(FloornavConfig())
    assert params.slips and params.wheel_scale_sigma_frac > 0 and params.slip_sigma_frac > 0
    off = FloornavConfig(
        sim={"wheel_scale_sigma_frac": 0.0, "slip_sigma_frac": 0.0, "encoder_tick_noise": 0.0}
    )
    assert robot_params(off) == replace(
        params, wheel_scale_sigma_frac=0.0, slip_sigma_frac=0.0, encoder_tick_noise=0.0
    )
    assert not robot_params(off).slips


def test_severity_is_highest_spinning_and_accelerating() -> None:
    params = RobotParams(slip_rolling_share=0.2, slip_full_accel_m_s2=2.0)
    assert slip_severity((0.01, 0.01), 0.0, params) == pytest.approx(0.2)
    assert slip_severity((0.0, 0.01), 0.0, params) == pytest.approx(0.7)
    assert slip_severity((-0.01, 0.01), 0.0, params) == pytest.approx(1.0)
    assert slip_severity((0.01, 0.01), 1.0, params) == pytest.approx(0.7)
    assert slip_severity((0.0, 0.0), 0.0, params) == pytest.approx(0.2)


def drift_after(params: RobotParams, seed: int, seconds: float) -> tuple[float, float]:
    """(position error m, heading error rad) of wheel odometry after ``seconds`` of
    exploration-like driving on an open plane (straights, arcs, spin turns; encoder
    telemetry at 20 Hz)."""
    drive = DriveConfig()
    robot = SimRobot(None, params, seed=seed)
    odometry = WheelOdometry(drive)
    limiter = RateLimiter(drive)
    plan = random.Random(1000 + seed)
    t, dt, k, segment_end, target = 0.0, 0.01, 0, 0.0, Twist()
    while t < seconds:
        if t >= segment_end:
            kind = plan.random()
            if kind < 0.5:
                target, length = Twist(0.35, plan.uniform(-0.3, 0.3)), plan.uniform(1.0, 4.0)
            elif kind < 0.8:
                target, length = Twist(0.0, plan.choice([-1.5, 1.5])), plan.uniform(0.3, 2.0)
            else:
                target, length = Twist(0.2, plan.uniform(-1.2, 1.2)), plan.uniform(0.5, 2.0)
            segment_end = t + length
        if k % 2 == 0:
            robot.apply_pwm(*twist_to_pwm(limiter(target, t), drive))
        robot.step(dt)
        t += dt
        k += 1
        if k % 5 == 0:
            odometry.update(*robot.read_encoders(), t)
    true, estimate = robot.pose, odometry.pose
    return (
        math.hypot(true.x_m - estimate.x_m, true.y_m - estimate.y_m),
        abs(math.remainder(true.theta_rad - estimate.theta_rad, math.tau)),
    )


def test_odometry_drifts_with_slip_reproducibly_per_seed() -> None:
    config = FloornavConfig()
    slipping = robot_params(config)
    ideal = replace(slipping, wheel_scale_sigma_frac=0.0, slip_sigma_frac=0.0)
    seconds = 60.0
    ideal_errors = [drift_after(ideal, seed, seconds) for seed in range(3)]
    slip_errors = [drift_after(slipping, seed, seconds) for seed in range(3)]
    # Ideal wheels: only the 20 Hz integration and tick rounding (mm, a fraction of a
    # degree); slipping ones: centimetres to decimetres and degrees.
    assert max(e for e, _ in ideal_errors) < 0.05
    assert max(h for _, h in ideal_errors) < math.radians(1.0)
    assert sum(e for e, _ in slip_errors) > 3 * sum(e for e, _ in ideal_errors)
    assert max(h for _, h in slip_errors) > math.radians(2.0)
    assert drift_after(slipping, 1, seconds) == slip_errors[1]
    assert drift_after(slipping, 2, seconds) != slip_errors[1]


def test_scale_is_drawn_once_per_seed() -> None:
    params = RobotParams(wheel_scale_sigma_frac=0.01)
    a, b = SimRobot(None, params, seed=3), SimRobot(None, params, seed=3)
    assert a.wheel_scale == b.wheel_scale != (1.0, 1.0)
    assert SimRobot(None, params, seed=4).wheel_scale != a.wheel_scale


def test_the_floor_moves_the_robot_by_ground_travel_the_encoders_count_rotation() -> None:
    """A wheel 2 % large on the ground: the robot goes 2 % further than its encoders
    say, and turns towards the other wheel."""
    robot = SimRobot(None, RobotParams(deadband_pwm=0, motor_tau_s=0.0))
    robot.wheel_scale = (1.02, 1.0)
    robot.params = replace(robot.params, wheel_scale_sigma_frac=1e-9)  # slip path on
    robot.apply_pwm(255, 255)
    for _ in range(100):
        robot.step(0.01)
    per_m = robot.params.ticks_per_rev / (2 * math.pi * robot.params.wheel_radius_m)
    assert robot.read_encoders() == (math.floor(0.5 * per_m), math.floor(0.5 * per_m))
    ground_left, ground_right = 0.51, 0.5
    assert robot.pose.theta_rad == pytest.approx((ground_right - ground_left) / 0.2)
    assert robot.pose.x_m == pytest.approx(0.505, abs=1e-3)


def test_encoder_noise_accumulates_as_a_random_walk() -> None:
    params = RobotParams(deadband_pwm=0, motor_tau_s=0.0, encoder_tick_noise=0.5)
    exact = RobotParams(deadband_pwm=0, motor_tau_s=0.0)
    noisy, ideal = SimRobot(None, params, seed=1), SimRobot(None, exact)
    for robot in (noisy, ideal):
        robot.apply_pwm(255, 255)
        for _ in range(200):
            robot.step(0.01)
    assert noisy.pose == ideal.pose  # the counts are off, not the motion
    counted = ideal.read_encoders()
    off = [abs(a - b) for a, b in zip(noisy.read_encoders(), counted, strict=True)]
    # ~1740 ticks each: sqrt(1740) * 0.5 ~ 21 ticks of error expected.
    assert 0 < max(off) < 100
