"""Differential-drive kinematics: body twist <-> wheel speeds <-> PWM, command limits,
and wheel odometry from encoder counts. Pure functions and small value classes.

Frames: the robot frame has x forward, y left, origin midway between the wheels; poses
are ``T_odom_robot`` (the odometry frame is the robot's pose at start-up).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

from app.config import DriveConfig
from app.control.mux import Twist
from app.mapping.frames import Pose2D

PWM_MAX = 255


def clamp(value: float, low: float, high: float) -> float:
    return min(high, max(low, value))


def limit_twist(twist: Twist, drive: DriveConfig) -> Twist:
    """Clamp to the configured body speeds, then scale both components down together
    until each wheel is within ``max_wheel_speed_m_s`` (keeping the curvature)."""
    v = clamp(twist.v_m_s, -drive.max_linear_speed_m_s, drive.max_linear_speed_m_s)
    omega = clamp(twist.omega_rad_s, -drive.max_angular_speed_rad_s, drive.max_angular_speed_rad_s)
    left, right = wheel_speeds(Twist(v, omega), drive.wheel_base_m)
    peak = max(abs(left), abs(right))
    if peak > drive.max_wheel_speed_m_s:
        scale = drive.max_wheel_speed_m_s / peak
        v, omega = v * scale, omega * scale
    return Twist(v, omega)


def wheel_speeds(twist: Twist, wheel_base_m: float) -> tuple[float, float]:
    """(left, right) wheel surface speeds in m/s."""
    half = twist.omega_rad_s * wheel_base_m / 2
    return twist.v_m_s - half, twist.v_m_s + half


def speed_to_pwm(speed_m_s: float, drive: DriveConfig) -> int:
    """Signed PWM for a wheel speed: linear from just above the deadband (0 stays 0),
    saturating at 255. Inverse of the motor model the simulator uses."""
    if speed_m_s == 0.0:
        return 0
    frac = min(1.0, abs(speed_m_s) / drive.max_wheel_speed_m_s)
    pwm = drive.pwm_deadband + 1 + frac * (PWM_MAX - drive.pwm_deadband - 1)
    return int(math.copysign(min(PWM_MAX, round(pwm)), speed_m_s))


def twist_to_pwm(twist: Twist, drive: DriveConfig) -> tuple[int, int]:
    """(left, right) PWM for a twist (after `limit_twist`)."""
    left, right = wheel_speeds(limit_twist(twist, drive), drive.wheel_base_m)
    return speed_to_pwm(left, drive), speed_to_pwm(right, drive)


class RateLimiter:
    """Limits how fast commands grow: speeding up (in either direction) is bounded by the
    configured accelerations; slowing down and stopping are immediate, because a stop
    that ramps is a stop that comes late."""

    def __init__(self, drive: DriveConfig) -> None:
        self.drive = drive
        self._last = Twist()
        self._last_s: float | None = None

    def reset(self) -> None:
        self._last = Twist()
        self._last_s = None

    def __call__(self, target: Twist, now_s: float) -> Twist:
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s
        v = _ramp(self._last.v_m_s, target.v_m_s, self.drive.max_linear_accel_m_s2 * dt)
        omega = _ramp(
            self._last.omega_rad_s, target.omega_rad_s, self.drive.max_angular_accel_rad_s2 * dt
        )
        self._last = Twist(v, omega)
        return self._last


def _ramp(current: float, target: float, max_step: float) -> float:
    if target == 0.0 or (current * target > 0 and abs(target) <= abs(current)):
        return target  # stopping or slowing: at once
    if current * target < 0:
        current = 0.0  # reversing: through zero at once, then ramp up
    step = clamp(target - current, -max_step, max_step)
    return current + step


MAX_EXTRAPOLATION_S = 0.1
"""`WheelOdometry.pose_at` carries the last motion on at most this far past the last
sample: two telemetry periods (a longer gap is a stall, and the robot may have stopped)."""


@dataclass(frozen=True)
class OdometrySample:
    time_s: float
    pose: Pose2D
    distance_m: float


class WheelOdometry:
    """Integrates encoder counts into ``T_odom_robot`` and keeps a short history so the
    pose at a camera frame's capture time can be interpolated.

    Encoder counters are int32 on the Uno; differences are taken modulo 2**32 so a wrap
    (or a counter reset, which shows as a large jump) does not teleport the robot: jumps
    longer than ``max_step_m`` are dropped and counted in ``rejected_steps``.
    """

    def __init__(self, drive: DriveConfig, *, history_s: float = 2.0, max_step_m: float = 0.5):
        self.meters_per_tick = 2 * math.pi * drive.wheel_radius_m / drive.ticks_per_rev
        self.wheel_base_m = drive.wheel_base_m
        self.history_s = history_s
        self.max_step_m = max_step_m
        self.pose = Pose2D()
        self.distance_m = 0.0
        self.rejected_steps = 0
        self._last_ticks: tuple[int, int] | None = None
        self._history: deque[OdometrySample] = deque()
        self._times: deque[float] = deque()

    def reset_reference(self) -> None:
        """Forget the last counts (after a reconnect the device's counters may restart)."""
        self._last_ticks = None

    def start_at(self, pose: Pose2D, distance_m: float = 0.0) -> None:
        """Continue from ``pose`` (a saved map's last pose: the robot has not moved while
        the daemon was off), before the first telemetry arrives."""
        self.pose = pose
        self.distance_m = distance_m
        self._last_ticks = None
        self._history.clear()
        self._times.clear()

    def correct(self, T_corrected_odom: Pose2D) -> None:
        """Left-multiply a localization correction (`app.mapping.scan_match`) onto the
        pose and its history. The odometry frame stays the map's frame, and the poses
        of frames captured before the correction (`pose_at`) move with the pose, so
        the map, steering and paths stay in one frame. Distance is not changed."""
        self.pose = T_corrected_odom.compose(self.pose)
        self._history = deque(
            OdometrySample(sample.time_s, T_corrected_odom.compose(sample.pose), sample.distance_m)
            for sample in self._history
        )

    def update(self, left_ticks: int, right_ticks: int, time_s: float) -> Pose2D:
        if self._last_ticks is not None:
            dl = _tick_delta(left_ticks, self._last_ticks[0]) * self.meters_per_tick
            dr = _tick_delta(right_ticks, self._last_ticks[1]) * self.meters_per_tick
            if max(abs(dl), abs(dr)) > self.max_step_m:
                self.rejected_steps += 1
            else:
                self.pose = _arc(self.pose, dl, dr, self.wheel_base_m)
                self.distance_m += abs(dl + dr) / 2
        self._last_ticks = (left_ticks, right_ticks)
        self._history.append(OdometrySample(time_s, self.pose, self.distance_m))
        self._times.append(time_s)
        while self._times and self._times[0] < time_s - self.history_s:
            self._history.popleft()
            self._times.popleft()
        return self.pose

    def pose_at(self, time_s: float) -> Pose2D:
        """The pose at ``time_s``, interpolated between samples; before the history its
        first pose; after it, the last interval's motion carried on for at most
        `MAX_EXTRAPOLATION_S` (a frame is usually newer than the last telemetry: held
        at that sample, a robot turning at 1.5 rad/s would be placed up to 4 degrees
        behind where the frame was taken)."""
        if not self._history:
            return self.pose
        i = bisect.bisect_left(self._times, time_s)
        if i <= 0:
            return self._history[0].pose
        if i >= len(self._history):
            if len(self._history) < 2:
                return self._history[-1].pose
            time_s = min(time_s, self._history[-1].time_s + MAX_EXTRAPOLATION_S)
            i = len(self._history) - 1
        a, b = self._history[i - 1], self._history[i]
        span = b.time_s - a.time_s
        t = 0.0 if span <= 0 else (time_s - a.time_s) / span
        dtheta = math.remainder(b.pose.theta_rad - a.pose.theta_rad, math.tau)
        return Pose2D(
            a.pose.x_m + t * (b.pose.x_m - a.pose.x_m),
            a.pose.y_m + t * (b.pose.y_m - a.pose.y_m),
            a.pose.theta_rad + t * dtheta,
        )


def _tick_delta(now: int, before: int) -> int:
    delta = (now - before) & 0xFFFFFFFF
    return delta - (1 << 32) if delta >= 1 << 31 else delta


def _arc(pose: Pose2D, left_m: float, right_m: float, wheel_base_m: float) -> Pose2D:
    ds = (left_m + right_m) / 2
    dtheta = (right_m - left_m) / wheel_base_m
    # Midpoint heading integrates a constant-curvature arc to second order.
    mid = pose.theta_rad + dtheta / 2
    return Pose2D(
        pose.x_m + ds * math.cos(mid),
        pose.y_m + ds * math.sin(mid),
        math.remainder(pose.theta_rad + dtheta, math.tau),
    )
