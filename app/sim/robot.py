"""A simulated differential-drive robot: the `MotorPlant` a simulated Uno drives.

Motors: signed PWM (-255..255) per wheel maps linearly to a target wheel speed above a
deadband (``|pwm| <= deadband_pwm`` gives 0), and each wheel follows its target with a
first-order lag of time constant ``motor_tau_s``. Within a `SimRobot.step` the targets
are constant, so each wheel's travel has a closed form, and the robot moves along the
exact arc of those two travels. Encoders count ``ticks_per_rev`` per wheel revolution.

The robot is a circle of ``radius_m`` in the world's plan frame. When a step would make
it touch a wall or a box, it stops at the contact (found by bisection along the arc),
both wheels stop (stalled: encoders count only the travel before contact) and
`SimRobot.collisions` counts the new contact. It can always turn in place or back away.

Thread-safe: ``apply_pwm``/``read_encoders`` come from the simulated Uno's thread,
``step`` from whoever owns the clock (`SimRobot.start` runs one).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from app.mapping.frames import Pose2D
from app.sim.world import DEFAULT_ROBOT_RADIUS_M, World

PWM_MAX = 255


@dataclass(frozen=True)
class RobotParams:
    """Geometry and motor model of the simulated robot."""

    wheel_base_m: float = 0.20
    wheel_radius_m: float = 0.033
    max_wheel_speed_m_s: float = 0.5
    """Wheel surface speed at PWM 255."""
    deadband_pwm: int = 30
    """Below this the motor does not overcome friction (a real gear motor's stall)."""
    motor_tau_s: float = 0.08
    ticks_per_rev: int = 360
    radius_m: float = DEFAULT_ROBOT_RADIUS_M
    """The circle the robot occupies, for collisions."""

    def __post_init__(self) -> None:
        for name in ("wheel_base_m", "wheel_radius_m", "max_wheel_speed_m_s", "radius_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RobotParams.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.deadband_pwm < PWM_MAX:
            raise ValueError(f"RobotParams.deadband_pwm must be 0..254, got {self.deadband_pwm}")
        if self.motor_tau_s < 0:
            raise ValueError(f"RobotParams.motor_tau_s must be >= 0, got {self.motor_tau_s}")
        if self.ticks_per_rev < 1:
            raise ValueError(f"RobotParams.ticks_per_rev must be >= 1, got {self.ticks_per_rev}")


def pwm_to_speed(pwm: int, params: RobotParams) -> float:
    """Steady-state wheel speed (m/s) of a signed PWM: linear above the deadband."""
    pwm = max(-PWM_MAX, min(PWM_MAX, int(pwm)))
    if abs(pwm) <= params.deadband_pwm:
        return 0.0
    frac = (abs(pwm) - params.deadband_pwm) / (PWM_MAX - params.deadband_pwm)
    return math.copysign(frac * params.max_wheel_speed_m_s, pwm)


def lagged_wheel(speed: float, target: float, tau_s: float, dt_s: float) -> tuple[float, float]:
    """(travel_m, end_speed) of a wheel following ``target`` with a first-order lag
    from ``speed`` for ``dt_s``: exact for a constant target."""
    if tau_s <= 0.0:
        return target * dt_s, target
    decay = math.exp(-dt_s / tau_s)
    travel = target * dt_s + (speed - target) * tau_s * (1.0 - decay)
    return travel, target + (speed - target) * decay


def arc_pose(pose: Pose2D, left_m: float, right_m: float, wheel_base_m: float) -> Pose2D:
    """The pose after the left and right wheels travel ``left_m``/``right_m`` along a
    constant-curvature arc (exact; straight when they are equal)."""
    ds = (left_m + right_m) / 2
    dtheta = (right_m - left_m) / wheel_base_m
    if abs(dtheta) < 1e-9:
        dx_r, dy_r = ds, ds * dtheta / 2  # second-order term keeps it smooth at 0
    else:
        radius = ds / dtheta
        dx_r = radius * math.sin(dtheta)
        dy_r = radius * (1.0 - math.cos(dtheta))
    c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
    theta = math.atan2(math.sin(pose.theta_rad + dtheta), math.cos(pose.theta_rad + dtheta))
    return Pose2D(pose.x_m + c * dx_r - s * dy_r, pose.y_m + s * dx_r + c * dy_r, theta)


class SimRobot:
    """A differential-drive robot in a `World` (pose in the plan frame).

    Parameters
    ----------
    world : the floor plan it collides with (None: an empty plane)
    params : geometry and motors
    pose : the start pose (default: the world's start pose, else the origin)
    """

    _MAX_SUBSTEP_M = 0.02
    """Longest distance any point of the robot moves between collision checks."""

    def __init__(
        self,
        world: World | None = None,
        params: RobotParams | None = None,
        *,
        pose: Pose2D | None = None,
    ) -> None:
        self.world = world
        self.params = params if params is not None else RobotParams()
        if pose is None:
            pose = world.start_pose if world is not None else Pose2D()
        self._lock = threading.Lock()
        self._pose = pose
        self._pwm = (0, 0)
        self._speed = [0.0, 0.0]
        self._travel_m = [0.0, 0.0]
        self._collisions = 0
        self._in_contact = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # -- MotorPlant --------------------------------------------------------------------

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
        with self._lock:
            self._pwm = (int(left_pwm), int(right_pwm))

    def read_encoders(self) -> tuple[int, int]:
        with self._lock:
            per_m = self.params.ticks_per_rev / (2 * math.pi * self.params.wheel_radius_m)
            return (
                math.floor(self._travel_m[0] * per_m),
                math.floor(self._travel_m[1] * per_m),
            )

    # -- state -------------------------------------------------------------------------

    @property
    def pose(self) -> Pose2D:
        """T_plan_robot."""
        with self._lock:
            return self._pose

    @property
    def collisions(self) -> int:
        with self._lock:
            return self._collisions

    @property
    def wheel_speeds_m_s(self) -> tuple[float, float]:
        with self._lock:
            return self._speed[0], self._speed[1]

    def teleport(self, pose: Pose2D) -> None:
        """Put the robot at ``pose`` at rest (tests, resets)."""
        with self._lock:
            self._pose = pose
            self._speed = [0.0, 0.0]
            self._in_contact = False

    # -- simulation --------------------------------------------------------------------

    def step(self, dt_s: float) -> None:
        """Advance the simulation by ``dt_s`` seconds."""
        if dt_s < 0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        if dt_s == 0:
            return
        p = self.params
        with self._lock:
            travels: list[float] = []
            for i in range(2):
                target = pwm_to_speed(self._pwm[i], p)
                travel, self._speed[i] = lagged_wheel(self._speed[i], target, p.motor_tau_s, dt_s)
                travels.append(travel)
            start = self._pose
            fraction = self._free_fraction(start, travels[0], travels[1])
            if fraction < 1.0:
                self._speed = [0.0, 0.0]
                if not self._in_contact:
                    self._collisions += 1
                self._in_contact = True
            else:
                self._in_contact = False
            left, right = travels[0] * fraction, travels[1] * fraction
            self._pose = arc_pose(start, left, right, p.wheel_base_m)
            self._travel_m[0] += left
            self._travel_m[1] += right

    def _clear(self, pose: Pose2D, from_clearance: float) -> bool:
        """Is ``pose`` collision-free? Moving away from contact is always allowed."""
        assert self.world is not None
        clearance = self.world.clearance_m(pose.x_m, pose.y_m)
        return clearance >= self.params.radius_m or clearance > from_clearance

    def _free_fraction(self, start: Pose2D, left_m: float, right_m: float) -> float:
        """Largest fraction in [0, 1] of the step's arc the robot can travel."""
        if self.world is None:
            return 1.0
        p = self.params
        reach = max(abs(left_m), abs(right_m)) + p.radius_m * abs(right_m - left_m) / p.wheel_base_m
        n = max(1, math.ceil(reach / self._MAX_SUBSTEP_M))
        clearance = self.world.clearance_m(start.x_m, start.y_m)
        lo = 0.0
        for k in range(1, n + 1):
            hi = k / n
            pose = arc_pose(start, left_m * hi, right_m * hi, p.wheel_base_m)
            if not self._clear(pose, clearance):
                for _ in range(30):
                    mid = (lo + hi) / 2
                    mid_pose = arc_pose(start, left_m * mid, right_m * mid, p.wheel_base_m)
                    if self._clear(mid_pose, clearance):
                        lo = mid
                    else:
                        hi = mid
                return lo
            clearance = self.world.clearance_m(pose.x_m, pose.y_m)
            lo = hi
        return 1.0

    def start(self, period_s: float = 0.01) -> None:
        """Step in real time (``time.monotonic``) on a daemon thread until `close`."""
        if self._thread is not None:
            return
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        self._stop.clear()

        def run() -> None:
            last = time.monotonic()
            while not self._stop.wait(period_s):
                now = time.monotonic()
                self.step(now - last)
                last = now

        self._thread = threading.Thread(target=run, name="sim-robot", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the `start` thread (if any)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
