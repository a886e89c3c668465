"""A simulated differential-drive robot: the `MotorPlant` a simulated Uno drives.

Motors: signed PWM (-255..255) per wheel maps linearly to a target wheel speed above a
deadband (``|pwm| <= deadband_pwm`` gives 0), and each wheel follows its target with a
first-order lag of time constant ``motor_tau_s``. Within a `SimRobot.step` the targets
are constant, so each wheel's travel has a closed form, and the robot moves along the
exact arc of those two travels. Encoders count ``ticks_per_rev`` per wheel revolution.

Wheel slip (off in `RobotParams`' defaults, on in the daemon's ``[sim]`` configuration):
the floor moves the robot by each wheel's *ground* travel, while the encoders count the
wheel's *rotation*. Ground travel = rotation * (1 + scale error) * (1 + slip):

- the scale error of each wheel (tyre radius, load, floor) is drawn once per robot,
  N(0, ``wheel_scale_sigma_frac``): a calibrated robot's residual, which makes odometry
  drift systematically (a straight drive curves);
- the slip is ``slip_sigma_frac * severity * u`` with ``u`` a unit Ornstein-Uhlenbeck
  process per wheel (correlation time ``slip_time_constant_s``, so its statistics do not
  depend on the step length), and ``severity`` in [0, 1] growing with how much the step
  turns (a skid-steer scrubs its wheels sideways, most in a spin turn) and with the
  wheels' acceleration, from ``slip_rolling_share`` when rolling straight and steady;
- optionally the encoders miscount: each counted tick adds N(0, ``encoder_tick_noise``)
  ticks to a count error that accumulates (a random walk, as lost or double counts do).

The draws come from one generator seeded by ``seed`` (the ``[sim] seed``), so a run is
reproducible. With all three sigmas 0 nothing is drawn and the model is exactly the
ideal one above.

The robot is a circle of ``radius_m`` in the world's plan frame. When a step would make
it touch a wall or a box, it stops at the contact (found by bisection along the arc),
both wheels stop (stalled: encoders count only the travel before contact) and
`SimRobot.collisions` counts the new contact and `SimRobot.contacts` keeps what it was
doing (`Contact`). It can always turn in place or back away.
A contact ends once the robot is `CONTACT_RELEASE_M` clear of everything: a robot that
scrubs along a box while turning on the spot (slip moves its centre by fractions of a
millimetre) is in one collision, not in one per step.

Thread-safe: ``apply_pwm``/``read_encoders`` come from the simulated Uno's thread,
``step`` from whoever owns the clock (`SimRobot.start` runs one).
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections import deque
from dataclasses import dataclass

from app.mapping.frames import Pose2D
from app.sim.world import DEFAULT_ROBOT_RADIUS_M, World

PWM_MAX = 255


CONTACT_RELEASE_M = 0.01
"""How far from everything a robot in contact must get before a new contact counts."""


CONTACTS_KEPT = 64
"""`SimRobot.contacts` keeps the newest this many."""


@dataclass(frozen=True)
class Contact:
    """One collision: where the robot was, what it hit and how it was moving."""

    number: int
    """1 for the run's first collision."""
    sim_time_s: float
    """Simulated time since the robot was made."""
    pose: Pose2D
    """T_plan_robot at the contact."""
    bearing_rad: float | None
    """Direction of the touched point in the robot frame (0 ahead, +pi/2 left; None
    without a world)."""
    forward_m_s: float
    """Forward speed just before the contact (negative: reversing)."""
    yaw_rate_rad_s: float
    """Turn rate just before the contact (positive: counter-clockwise)."""

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "number": self.number,
            "sim_time_s": round(self.sim_time_s, 3),
            "x_m": round(self.pose.x_m, 3),
            "y_m": round(self.pose.y_m, 3),
            "theta_rad": round(self.pose.theta_rad, 3),
            "bearing_deg": None
            if self.bearing_rad is None
            else round(math.degrees(self.bearing_rad), 1),
            "forward_m_s": round(self.forward_m_s, 3),
            "yaw_rate_rad_s": round(self.yaw_rate_rad_s, 3),
        }


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
    wheel_scale_sigma_frac: float = 0.0
    """Std of each wheel's ground travel per unit of rotation, drawn once per robot."""
    slip_sigma_frac: float = 0.0
    """Std of the slip fraction at full severity (a spin turn, a hard acceleration)."""
    slip_time_constant_s: float = 0.3
    """Correlation time of the slip: slip on a floor patch or through a turn persists."""
    slip_rolling_share: float = 0.2
    """Severity when rolling straight at constant speed (a spin turn's is 1)."""
    slip_full_accel_m_s2: float = 2.0
    """Wheel acceleration at which the severity reaches 1 by itself."""
    encoder_tick_noise: float = 0.0
    """Std of the count error each counted tick adds (ticks; it accumulates)."""

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
        for name in ("wheel_scale_sigma_frac", "slip_sigma_frac", "encoder_tick_noise"):
            if not 0 <= getattr(self, name) < math.inf:
                raise ValueError(f"RobotParams.{name} must be finite and >= 0")
        for name in ("slip_time_constant_s", "slip_full_accel_m_s2"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"RobotParams.{name} must be finite and > 0")
        if not 0 <= self.slip_rolling_share <= 1:
            raise ValueError("RobotParams.slip_rolling_share must be in [0, 1]")

    @property
    def slips(self) -> bool:
        """Whether the ground travel differs from the rotation at all."""
        return self.wheel_scale_sigma_frac > 0 or self.slip_sigma_frac > 0


def slip_severity(rotation_m: tuple[float, float], accel_m_s2: float, params: RobotParams) -> float:
    """How hard a step slips, in [0, 1]: the share of the wheels' travel that turns the
    robot rather than moving it (1 in a spin turn), plus the acceleration's share of
    ``slip_full_accel_m_s2``, on top of ``slip_rolling_share``."""
    left, right = rotation_m
    peak = max(abs(left), abs(right))
    # |r - l| / (|r + l| + |r - l|): 0 rolling straight, 1/2 about one wheel, 1 spinning.
    turning = abs(right - left) / (2 * peak) if peak > 0 else 0.0
    accel = abs(accel_m_s2) / params.slip_full_accel_m_s2
    return min(1.0, params.slip_rolling_share + turning + accel)


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
    params : geometry, motors and slip
    pose : the start pose (default: the world's start pose, else the origin)
    seed : of the slip's and the encoders' random draws
    """

    _MAX_SUBSTEP_M = 0.02
    """Longest distance any point of the robot moves between collision checks."""

    def __init__(
        self,
        world: World | None = None,
        params: RobotParams | None = None,
        *,
        pose: Pose2D | None = None,
        seed: int = 0,
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
        """Each wheel's rotation (surface metres): what the encoders count."""
        # A string seed: a stream of its own, apart from the camera's noise (same seed).
        self._rng = random.Random(f"floornav.sim.robot:{seed}")
        sigma = self.params.wheel_scale_sigma_frac
        self.wheel_scale = (
            (1.0 + self._rng.gauss(0.0, sigma), 1.0 + self._rng.gauss(0.0, sigma))
            if sigma > 0
            else (1.0, 1.0)
        )
        """Ground travel per unit of rotation of each wheel (drawn once)."""
        self._slip_state = [0.0, 0.0]
        self._count_error = [0.0, 0.0]
        self._collisions = 0
        self._contacts: deque[Contact] = deque(maxlen=CONTACTS_KEPT)
        self._sim_time_s = 0.0
        self._in_contact = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # -- MotorPlant --------------------------------------------------------------------

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
        with self._lock:
            self._pwm = (int(left_pwm), int(right_pwm))

    def read_encoders(self) -> tuple[int, int]:
        with self._lock:
            per_m = self._ticks_per_m()
            return (
                math.floor(self._travel_m[0] * per_m + self._count_error[0]),
                math.floor(self._travel_m[1] * per_m + self._count_error[1]),
            )

    def _ticks_per_m(self) -> float:
        return self.params.ticks_per_rev / (2 * math.pi * self.params.wheel_radius_m)

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
    def contacts(self) -> tuple[Contact, ...]:
        """The newest `CONTACTS_KEPT` collisions, oldest first."""
        with self._lock:
            return tuple(self._contacts)

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
            rotations: list[float] = []
            accel = 0.0
            for i in range(2):
                target = pwm_to_speed(self._pwm[i], p)
                before = self._speed[i]
                rotation, self._speed[i] = lagged_wheel(before, target, p.motor_tau_s, dt_s)
                rotations.append(rotation)
                accel = max(accel, abs(self._speed[i] - before) / dt_s)
            travels = self._ground_travels(rotations, accel, dt_s) if p.slips else rotations
            start = self._pose
            fraction = self._free_fraction(start, travels[0], travels[1])
            self._sim_time_s += dt_s
            if fraction < 1.0:
                if not self._in_contact:
                    self._collisions += 1
                    self._contacts.append(self._contact(start, travels, fraction))
                self._speed = [0.0, 0.0]
                self._in_contact = True
            self._pose = arc_pose(
                start, travels[0] * fraction, travels[1] * fraction, p.wheel_base_m
            )
            if fraction == 1.0 and self._in_contact and self.world is not None:
                clearance = self.world.clearance_m(self._pose.x_m, self._pose.y_m)
                self._in_contact = clearance < p.radius_m + CONTACT_RELEASE_M
            for i in range(2):
                turned = rotations[i] * fraction
                self._travel_m[i] += turned
                if p.encoder_tick_noise > 0:
                    ticks = abs(turned) * self._ticks_per_m()
                    self._count_error[i] += self._rng.gauss(
                        0.0, p.encoder_tick_noise * math.sqrt(ticks)
                    )

    def _contact(self, start: Pose2D, travels: list[float], fraction: float) -> Contact:
        p = self.params
        pose = arc_pose(start, travels[0] * fraction, travels[1] * fraction, p.wheel_base_m)
        bearing = None
        touched = self.world.nearest_obstacle_xy(pose.x_m, pose.y_m) if self.world else None
        if touched is not None:
            world_angle = math.atan2(touched[1] - pose.y_m, touched[0] - pose.x_m)
            bearing = math.atan2(
                math.sin(world_angle - pose.theta_rad), math.cos(world_angle - pose.theta_rad)
            )
        left, right = self._speed
        return Contact(
            number=self._collisions,
            sim_time_s=self._sim_time_s,
            pose=pose,
            bearing_rad=bearing,
            forward_m_s=(left + right) / 2,
            yaw_rate_rad_s=(right - left) / p.wheel_base_m,
        )

    def _ground_travels(
        self, rotations: list[float], accel_m_s2: float, dt_s: float
    ) -> list[float]:
        """The wheels' travel over the floor for their ``rotations`` in a step of
        ``dt_s`` (see the module docstring); advances the slip processes."""
        p = self.params
        severity = slip_severity((rotations[0], rotations[1]), accel_m_s2, p)
        keep = math.exp(-dt_s / p.slip_time_constant_s)
        fresh = math.sqrt(1.0 - keep * keep)
        travels = []
        for i in range(2):
            if p.slip_sigma_frac > 0:
                self._slip_state[i] = keep * self._slip_state[i] + fresh * self._rng.gauss(0.0, 1.0)
            slip = p.slip_sigma_frac * severity * self._slip_state[i]
            travels.append(rotations[i] * self.wheel_scale[i] * (1.0 + slip))
        return travels

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
