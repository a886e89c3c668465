"""World loader, robot kinematics and collisions."""

from __future__ import annotations

import math

import pytest

from app.mapping.frames import Pose2D
from app.sim.robot import CONTACT_RELEASE_M, RobotParams, SimRobot, pwm_to_speed
from app.sim.world import WorldError, load_world, parse_world

MINIMAL = """
name = "box room"
[start]
x_m = 1.0
y_m = 1.0
[[rooms]]
rect_m = [0.0, 0.0, 4.0, 2.0]
"""


def test_default_world_loads() -> None:
    world = load_world()
    assert 6 <= len(world.spec.boxes) <= 10
    assert any(w.finish == "floor" for w in world.spec.walls)
    start = world.start_pose
    assert world.clearance_m(start.x_m, start.y_m) > 0.5
    grid, occ = world.occupancy()
    assert occ.shape == grid.shape and occ.max() == 1
    row, col = grid.cell_of(__import__("numpy").array([[start.x_m, start.y_m]]))[0]
    assert occ[row, col] == 0


def test_minimal_world() -> None:
    world = parse_world(MINIMAL)
    assert world.name == "box room"
    assert len(world.wall_segments) == 4


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[start\nx_m = 1", "<file>"),
        (MINIMAL + "colour = 'red'\n", "rooms[0].colour"),
        (MINIMAL + "[[boxes]]\ncenter_m = [3.0, 1.0]\nsize_m = [-0.2, 0.3]\n", "boxes[0].size_m"),
        (MINIMAL + "[[boxes]]\ncenter_m = [1.0, 1.0]\nsize_m = [0.4, 0.4]\n", "start"),
        (MINIMAL + "[[walls]]\npoints_m = [[2.0, 0.5], [2.0, 0.5]]\n", "walls[0].points_m[1]"),
        ("[start]\nx_m = 0.05\ny_m = 1.0\n[[rooms]]\nrect_m = [0.0, 0.0, 4.0, 2.0]\n", "start"),
        ("[[rooms]]\nrect_m = [0.0, 0.0, 4.0, 2.0]\n", "start"),
    ],
)
def test_bad_worlds_name_the_key(text: str, key: str) -> None:
    with pytest.raises(WorldError) as info:
        parse_world(text)
    keys = [issue.key for issue in info.value.issues]
    assert any(k.startswith(key) for k in keys), keys
    assert key in str(info.value)


def test_unknown_key_has_line() -> None:
    with pytest.raises(WorldError) as info:
        parse_world(MINIMAL + "[[boxes]]\ncenter_m = [3.0, 1.0]\nsize_m = [0.2, 0.3]\nhue = 3\n")
    issue = info.value.issues[0]
    assert issue.key == "boxes[0].hue" and issue.message == "unknown key"
    assert issue.line == MINIMAL.count("\n") + 4


PARAMS = RobotParams(
    wheel_base_m=0.2, max_wheel_speed_m_s=0.5, deadband_pwm=30, motor_tau_s=0.0, ticks_per_rev=360
)


def _drive(robot: SimRobot, left: int, right: int, seconds: float, dt: float = 0.01) -> None:
    robot.apply_pwm(left, right)
    for _ in range(round(seconds / dt)):
        robot.step(dt)


def test_pwm_map_and_deadband() -> None:
    assert pwm_to_speed(30, PARAMS) == 0.0
    assert pwm_to_speed(-255, PARAMS) == -0.5
    assert pwm_to_speed(400, PARAMS) == 0.5
    assert pwm_to_speed(-(30 + 225 // 2), PARAMS) == pytest.approx(-0.5 * 112 / 225)


def test_straight_exact_and_encoders() -> None:
    robot = SimRobot(None, PARAMS, pose=Pose2D(0.0, 0.0, math.pi / 2))
    _drive(robot, 255, 255, 1.0)
    pose = robot.pose
    assert pose.x_m == pytest.approx(0.0, abs=1e-12)
    assert pose.y_m == pytest.approx(0.5, abs=1e-9)
    per_m = 360 / (2 * math.pi * PARAMS.wheel_radius_m)
    left, right = robot.read_encoders()
    assert left == right == math.floor(0.5 * per_m + 1e-9)


def test_spin_in_place() -> None:
    robot = SimRobot(None, PARAMS)
    # 0.5 m/s per wheel, opposite: omega = 1 / 0.2 * 1.0 = 5 rad/s
    _drive(robot, -255, 255, math.pi / 5, dt=math.pi / 1000)
    pose = robot.pose
    assert (pose.x_m, pose.y_m) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert abs(pose.theta_rad) == pytest.approx(math.pi, abs=1e-9)


def test_arc_is_exact_whatever_the_step() -> None:
    speed_left = pwm_to_speed(100, PARAMS)
    speed_right = pwm_to_speed(200, PARAMS)
    v = (speed_left + speed_right) / 2
    omega = (speed_right - speed_left) / PARAMS.wheel_base_m
    t = 2.0
    expected = (v / omega * math.sin(omega * t), v / omega * (1 - math.cos(omega * t)))
    for dt in (0.5, 0.01):
        robot = SimRobot(None, PARAMS)
        _drive(robot, 100, 200, t, dt=dt)
        assert (robot.pose.x_m, robot.pose.y_m) == pytest.approx(expected, abs=1e-9)
        assert robot.pose.theta_rad == pytest.approx(omega * t, abs=1e-9)


def test_motor_lag_is_first_order() -> None:
    params = RobotParams(deadband_pwm=0, motor_tau_s=0.1, max_wheel_speed_m_s=0.5)
    robot = SimRobot(None, params)
    _drive(robot, 255, 255, 0.1, dt=0.1)
    assert robot.wheel_speeds_m_s[0] == pytest.approx(0.5 * (1 - math.exp(-1)))
    assert robot.pose.x_m == pytest.approx(0.5 * (0.1 - 0.1 * (1 - math.exp(-1))))


def test_collision_stops_at_contact_and_counts() -> None:
    world = parse_world(MINIMAL)
    robot = SimRobot(world, PARAMS)  # radius 0.15, wall at x = 4
    _drive(robot, 255, 255, 10.0, dt=0.05)
    assert robot.pose.x_m == pytest.approx(4.0 - PARAMS.radius_m, abs=1e-4)
    assert robot.collisions == 1
    assert robot.wheel_speeds_m_s == (0.0, 0.0)
    # Backing away is free, driving in again is a second collision.
    _drive(robot, -255, -255, 0.5)
    assert robot.pose.x_m < 3.7
    _drive(robot, 255, 255, 2.0)
    assert robot.collisions == 2


def test_each_collision_is_recorded_with_what_was_hit_and_how() -> None:
    world = parse_world(MINIMAL)
    robot = SimRobot(world, PARAMS)  # wall at x = 4, straight ahead
    _drive(robot, 255, 255, 10.0, dt=0.05)
    (first,) = robot.contacts
    assert first.number == 1
    assert first.bearing_rad == pytest.approx(0.0, abs=1e-6)
    assert first.forward_m_s == pytest.approx(0.5, abs=1e-3)
    assert first.yaw_rate_rad_s == pytest.approx(0.0, abs=1e-9)
    assert first.pose.x_m == pytest.approx(4.0 - PARAMS.radius_m, abs=1e-4)
    # Back off, turn to face away, and reverse into the wall: behind the robot.
    _drive(robot, -255, -255, 0.5)
    _drive(robot, -255, 255, math.pi / 5, dt=math.pi / 1000)
    _drive(robot, -255, -255, 2.0)
    second = robot.contacts[-1]
    assert (second.number, robot.collisions) == (2, 2)
    assert abs(second.bearing_rad) == pytest.approx(math.pi, abs=1e-3)
    assert second.forward_m_s < 0
    assert second.as_dict()["bearing_deg"] in (180.0, -180.0)
    assert first.sim_time_s < second.sim_time_s


def test_scrubbing_along_a_wall_is_one_collision() -> None:
    """Slip while turning on the spot against a wall moves the centre off and onto the
    wall by fractions of a millimetre (seen in an hour-long run: 26 "collisions" at one
    box): one contact until the robot is CONTACT_RELEASE_M clear."""
    world = parse_world(MINIMAL)
    robot = SimRobot(world, PARAMS)  # radius 0.15, wall at x = 4
    _drive(robot, 255, 255, 10.0, dt=0.05)
    assert robot.collisions == 1
    for _ in range(5):
        _drive(robot, -255, -255, 0.01)  # 5 mm off the wall
        assert 4.0 - robot.pose.x_m < PARAMS.radius_m + CONTACT_RELEASE_M
        _drive(robot, 255, 255, 0.1)  # and onto it again
    assert robot.collisions == 1
    _drive(robot, -255, -255, 0.1)  # 5 cm off: clear
    _drive(robot, 255, 255, 1.0)
    assert robot.collisions == 2


def test_collision_with_box_no_tunnelling() -> None:
    world = parse_world(MINIMAL + "[[boxes]]\ncenter_m = [2.0, 1.0]\nsize_m = [0.02, 0.5]\n")
    robot = SimRobot(world, PARAMS)
    _drive(robot, 255, 255, 3.0, dt=0.5)  # 0.25 m per step, past a 2 cm box
    assert robot.pose.x_m == pytest.approx(2.0 - 0.01 - PARAMS.radius_m, abs=1e-4)
    assert robot.collisions == 1
