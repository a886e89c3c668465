"""Differential-drive kinematics, command limits and wheel odometry."""

import math

import pytest

from app.config import DriveConfig
from app.control.kinematics import (
    MAX_EXTRAPOLATION_S,
    RateLimiter,
    WheelOdometry,
    limit_twist,
    speed_to_pwm,
    twist_to_pwm,
    wheel_speeds,
)
from app.control.mux import Twist
from app.mapping.frames import Pose2D
from app.sim.robot import RobotParams, pwm_to_speed

DRIVE = DriveConfig()


def test_wheel_speeds_of_a_turn_in_place() -> None:
    left, right = wheel_speeds(Twist(0.0, 1.0), wheel_base_m=0.2)
    assert (left, right) == pytest.approx((-0.1, 0.1))


def test_pwm_inverts_the_simulated_motor_model() -> None:
    params = RobotParams(
        deadband_pwm=DRIVE.pwm_deadband, max_wheel_speed_m_s=DRIVE.max_wheel_speed_m_s
    )
    for speed in (0.05, 0.1, 0.3, -0.2):
        assert pwm_to_speed(speed_to_pwm(speed, DRIVE), params) == pytest.approx(speed, abs=0.003)
    assert speed_to_pwm(0.0, DRIVE) == 0
    assert speed_to_pwm(10.0, DRIVE) == 255


def test_limits_keep_the_curvature() -> None:
    # Within the body limits (0.5 m/s, 5 rad/s: the most the wheels allow), but the
    # outer wheel would need 0.4 + 2.0 * 0.1 = 0.6 m/s: both are scaled down together.
    drive = DriveConfig(
        max_linear_speed_m_s=0.5, max_angular_speed_rad_s=5.0, max_wheel_speed_m_s=0.5
    )
    limited = limit_twist(Twist(0.4, 2.0), drive)
    left, right = wheel_speeds(limited, drive.wheel_base_m)
    assert max(abs(left), abs(right)) == pytest.approx(0.5)
    assert limited.omega_rad_s / limited.v_m_s == pytest.approx(5.0)


def test_body_limits_clamp() -> None:
    limited = limit_twist(Twist(5.0, -50.0), DRIVE)
    assert abs(limited.v_m_s) <= DRIVE.max_linear_speed_m_s
    assert abs(limited.omega_rad_s) <= DRIVE.max_angular_speed_rad_s


def test_forward_gives_equal_positive_pwm() -> None:
    left, right = twist_to_pwm(Twist(0.2, 0.0), DRIVE)
    assert left == right > DRIVE.pwm_deadband


def test_rate_limiter_ramps_up_and_stops_at_once() -> None:
    limiter = RateLimiter(DRIVE)
    assert limiter(Twist(0.3, 0.0), 0.0).v_m_s == 0.0  # first call: no time elapsed
    v = limiter(Twist(0.3, 0.0), 0.1).v_m_s
    assert v == pytest.approx(DRIVE.max_linear_accel_m_s2 * 0.1)
    assert limiter(Twist(0.0, 0.0), 0.11).v_m_s == 0.0  # stop is immediate
    limiter(Twist(0.3, 0.0), 0.5)
    assert limiter(Twist(-0.3, 0.0), 0.6).v_m_s == pytest.approx(-0.1)  # reverse through zero


def drive_ticks(odo: WheelOdometry, left_m: float, right_m: float, t0: float, t1: float) -> None:
    """Feed counts in ten steps (each below the jump limit), as telemetry would."""
    per_m = DRIVE.ticks_per_rev / (2 * math.pi * DRIVE.wheel_radius_m)
    base_l, base_r = odo._last_ticks or (0, 0)
    for i in range(1, 11):
        f = i / 10
        odo.update(
            base_l + round(left_m * f * per_m),
            base_r + round(right_m * f * per_m),
            t0 + (t1 - t0) * f,
        )


def test_odometry_straight_and_turning() -> None:
    odo = WheelOdometry(DRIVE)
    odo.update(0, 0, 0.0)
    drive_ticks(odo, 1.0, 1.0, 0.0, 1.0)
    assert odo.pose.x_m == pytest.approx(1.0, abs=0.002) and odo.pose.y_m == pytest.approx(0.0)
    # Turn in place by pi/2: each wheel travels a quarter of the wheel-base circle.
    arc = math.pi / 2 * DRIVE.wheel_base_m / 2
    drive_ticks(odo, -arc, arc, 1.0, 2.0)
    assert odo.pose.theta_rad == pytest.approx(math.pi / 2, abs=0.01)
    assert odo.pose.x_m == pytest.approx(1.0, abs=0.003)
    assert odo.distance_m == pytest.approx(1.0, abs=0.002)


def test_odometry_interpolates_by_time() -> None:
    odo = WheelOdometry(DRIVE)
    odo.update(0, 0, 0.0)
    drive_ticks(odo, 0.2, 0.2, 0.0, 1.0)
    assert odo.pose_at(0.55).x_m == pytest.approx(0.11, abs=0.002)
    assert odo.pose_at(-5.0).x_m == 0.0  # before the history: its first pose
    # Past the last sample the last interval's motion (0.2 m/s) goes on, for at most
    # MAX_EXTRAPOLATION_S.
    assert odo.pose_at(1.05).x_m == pytest.approx(0.21, abs=0.002)
    assert odo.pose_at(9.0).x_m == pytest.approx(0.2 + 0.2 * MAX_EXTRAPOLATION_S, abs=0.002)


def test_odometry_past_its_last_sample_carries_a_turn_on() -> None:
    odo = WheelOdometry(DRIVE)
    odo.update(0, 0, 0.0)
    # A spin turn at 1 rad/s, sampled every 50 ms as the Uno's telemetry comes.
    arc = 0.5 * DRIVE.wheel_base_m / 2
    drive_ticks(odo, -arc, arc, 0.0, 0.5)
    assert odo.pose.theta_rad == pytest.approx(0.5, abs=0.01)
    assert odo.pose_at(0.53).theta_rad == pytest.approx(0.53, abs=0.01)


def test_odometry_survives_counter_wrap_and_rejects_jumps() -> None:
    odo = WheelOdometry(DRIVE)
    odo.update(2**31 - 5, 2**31 - 5, 0.0)
    odo.update(-(2**31) + 5, -(2**31) + 5, 0.1)  # int32 wrap: +10 ticks
    assert odo.pose.x_m == pytest.approx(10 * odo.meters_per_tick)
    odo.update(1000000, 1000000, 0.2)  # a reset / garbage: dropped
    assert odo.rejected_steps == 1
    assert odo.pose.x_m == pytest.approx(10 * odo.meters_per_tick)


def test_odometry_correction_moves_the_pose_and_its_history_not_the_distance() -> None:
    odo = WheelOdometry(DRIVE)
    odo.update(0, 0, 0.0)
    drive_ticks(odo, 0.2, 0.2, 0.0, 1.0)
    before_mid, distance = odo.pose_at(0.5), odo.distance_m
    # A scan match: the robot is 1 cm further left and 0.01 rad more to the left.
    T_corrected_odom = Pose2D(0.0, 0.01, 0.01)
    odo.correct(T_corrected_odom)
    expected = T_corrected_odom.compose(Pose2D(odo.pose.x_m, 0.0, 0.0))
    assert (odo.pose.x_m, odo.pose.y_m) == pytest.approx((expected.x_m, expected.y_m), abs=0.003)
    assert odo.pose.theta_rad == pytest.approx(0.01)
    mid = odo.pose_at(0.5)
    moved = T_corrected_odom.compose(before_mid)
    assert (mid.x_m, mid.y_m, mid.theta_rad) == pytest.approx((moved.x_m, moved.y_m, 0.01))
    assert odo.distance_m == distance
    # Travel continues from the corrected pose, along the corrected heading.
    drive_ticks(odo, 0.1, 0.1, 1.0, 2.0)
    end = T_corrected_odom.compose(Pose2D(0.3, 0.0, 0.0))
    assert (odo.pose.x_m, odo.pose.y_m) == pytest.approx((end.x_m, end.y_m), abs=0.003)
