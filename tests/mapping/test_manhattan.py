"""The heading held by the building's straight lines (`app.mapping.manhattan`)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.config import load_config
from app.mapping.calibration import FloorCalibration
from app.mapping.frames import Pose2D
from app.mapping.ground_map import GroundMapper
from app.mapping.ipm import build_ground_lookup
from app.mapping.manhattan import (
    HeadingAxis,
    ManhattanParams,
    floor_edge_segments,
    quarter_turn_offset,
)
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

CONFIG = Path(__file__).resolve().parents[2] / "config.toml"


def sim_calibration() -> FloorCalibration:
    return sim_floor_calibration(camera_model(load_config(CONFIG)))


def edges_of(gray: np.ndarray, floor: np.ndarray) -> np.ndarray:
    calibration = sim_calibration()
    near = build_ground_lookup(calibration, max_range_m=ManhattanParams().max_range_m).valid
    return floor_edge_segments(gray, floor, calibration, near)


def wall_foot_image(direction_rad: float, through_m: tuple[float, float]) -> tuple:
    """A grey image of floor (light) meeting a wall (dark) along a straight line on the
    floor through ``through_m`` (robot frame) in ``direction_rad``; the floor is on the
    robot's side. Returns (gray, floor_mask)."""
    # Every pixel below the horizon, however far.
    ground = build_ground_lookup(sim_calibration(), max_range_m=1e6)
    below_horizon = ground.valid
    x = np.where(below_horizon, ground.x_m, 0.0)
    y = np.where(below_horizon, ground.y_m, 0.0)
    # Which side of the line: the robot (the origin) is on the floor's side.
    c, s = math.cos(direction_rad), math.sin(direction_rad)
    side = (x - through_m[0]) * s - (y - through_m[1]) * c
    robot_side = (0.0 - through_m[0]) * s - (0.0 - through_m[1]) * c
    floor = below_horizon & (np.sign(side) == np.sign(robot_side))
    gray = np.where(floor, 170, 60).astype(np.uint8)
    return gray, floor


@pytest.mark.parametrize("direction_deg", [0.0, 12.0, -30.0, 90.0])
def test_the_floors_straight_edge_is_found_on_the_floor_in_its_direction(
    direction_deg: float,
) -> None:
    direction = math.radians(direction_deg)
    gray, floor = wall_foot_image(direction, (1.6, 0.2))
    # Anti-aliased, as a camera (and the renderer) sees an edge.
    gray = cv2.GaussianBlur(gray, (0, 0), 1.0)
    segments = edges_of(gray, floor)
    assert len(segments) >= 1
    longest = segments[np.argmax(segments[:, 1])]
    # A line has no sense: the direction is modulo a half turn.
    assert abs(math.remainder(longest[0] - direction, math.pi)) < math.radians(0.7)
    assert longest[1] >= 0.5


@pytest.mark.parametrize("through_m", [(1.6, 0.6), (1.6, -0.6), (1.0, 0.9), (2.2, -0.3)])
@pytest.mark.parametrize("direction_deg", [0.0, 3.0, -5.0, 12.0])
def test_a_hard_edges_direction_is_exact_to_a_twentieth_of_a_degree(
    direction_deg: float, through_m: tuple[float, float]
) -> None:
    # A wall's foot along the robot's way, on either side, unblurred (the renderer's
    # edges are hard). Canny keeps the pixel on one side of such an edge or the other;
    # Hough's ends lie on its lattice: fitted as found, these lines were 0.05-0.3
    # degrees off, always the same way for a wall on the same side.
    direction = math.radians(direction_deg)
    gray, floor = wall_foot_image(direction, through_m)
    segments = edges_of(gray, floor)
    longest = segments[np.argmax(segments[:, 1])]
    assert abs(math.remainder(longest[0] - direction, math.pi)) < math.radians(0.05)
    assert longest[1] >= 0.8


def test_the_images_border_and_a_floor_without_edges_give_no_segments() -> None:
    width, height = sim_calibration().image_size
    gray = np.full((height, width), 150, np.uint8)
    # Floor everywhere below the horizon: its only boundaries are the horizon (no image
    # edge there) and the image's border.
    _, floor = wall_foot_image(0.0, (50.0, 0.0))
    assert len(edges_of(gray, floor)) == 0
    # A strong image edge far from the floor's boundary is not the floor's edge.
    edged = gray.copy()
    edged[: height // 4, width // 2 :] = 20
    assert len(edges_of(edged, np.ones_like(floor))) == 0
    with pytest.raises(ValueError, match="differ"):
        edges_of(gray, floor[:-1])


def test_quarter_turn_offsets_fold_square_directions_together() -> None:
    axis = math.radians(10.0)
    angles = np.radians([10.0, 100.0, -80.0, 190.0, 12.0, 53.0])
    expected = np.radians([0.0, 0.0, 0.0, 0.0, 2.0, -47.0 + 90.0])
    np.testing.assert_allclose(quarter_turn_offset(angles, axis), expected, atol=1e-12)


def segments(*pairs: tuple[float, float]) -> np.ndarray:
    return np.array([(math.radians(d), length) for d, length in pairs], np.float64)


def test_the_axis_is_learned_from_square_lines_despite_stray_ones() -> None:
    axis = HeadingAxis(ManhattanParams(learn_length_m=10.0))
    # Robot-frame lines seen at heading 30 degrees: world 40 and 130 (square), one stray.
    frame = segments((10.0, 1.0), (100.0, 1.0), (-5.0, 0.6))
    for _ in range(3):
        assert axis.observe(frame, math.radians(30.0)) is None
        assert axis.axis_rad is None  # 7.8 m so far
    assert axis.observe(frame, math.radians(30.0)) is None  # the frame that fixes it
    # Modulo a quarter turn, in [-45, 45) degrees; the stray line is out of the window.
    assert axis.axis_rad == pytest.approx(math.radians(40.0), abs=1e-9)
    assert axis.summary()["axis_deg"] == 40.0


def test_lines_in_every_direction_fix_no_axis() -> None:
    axis = HeadingAxis(ManhattanParams(learn_length_m=5.0))
    rng = np.random.default_rng(0)
    for _ in range(40):
        frame = np.stack([rng.uniform(-math.pi / 2, math.pi / 2, 4), np.full(4, 0.8)], axis=1)
        axis.observe(frame, 0.0)
    assert axis.axis_rad is None


def test_a_heading_off_the_axis_is_turned_back_by_how_sure_each_is() -> None:
    params = ManhattanParams(
        line_sigma_rad=math.radians(1.0),
        start_sigma_rad=math.radians(1.0),
        drift_rad2_per_m=math.radians(1.0) ** 2,
        drift_rad2_per_rad=0.0,
        floor_drift_share=0.01,
    )
    axis = HeadingAxis(params)
    axis.restore(0.0)
    # The walls run along x and y; the estimate says 32 degrees where the robot is at 30:
    # lines 30 degrees off its nose along the walls appear at 32 - 30 = 2 degrees off.
    frame = segments((-30.0, 1.2), (60.0, 0.8))
    # Heading and line equally sure: half the way back, and the heading surer after.
    turn = axis.observe(frame, math.radians(32.0))
    assert turn == pytest.approx(-0.5 * math.radians(2.0), abs=1e-9)
    assert axis.variance_rad2 == pytest.approx(0.5 * math.radians(1.0) ** 2)
    assert axis.frames_used == 1
    # 2.5 m of wheels: variance 3 (degrees squared), the line's 1: three quarters back.
    axis.moved(2.5, 0.0)
    turn = axis.observe(frame, math.radians(32.0))
    assert turn == pytest.approx(-0.75 * math.radians(2.0), abs=1e-9)
    # Where floor odometry held the motion, a hundredth of the drift is added.
    before = axis.variance_rad2
    axis.moved(2.5, 0.0, floor_held=True)
    assert axis.variance_rad2 == pytest.approx(before + 0.025 * math.radians(1.0) ** 2)
    # ...and a frame that may not correct only teaches (here nothing: the axis is known).
    assert axis.observe(frame, math.radians(32.0), may_correct=False) is None
    assert axis.frames_used == 2


def test_lines_beyond_the_gate_or_too_short_or_none_correct_nothing() -> None:
    axis = HeadingAxis(ManhattanParams(gate_rad=math.radians(6.0)))
    axis.restore(0.0)
    # Sure heading: the gate is narrow (2.5 x the spread of 1 and 1.5 degrees: 4.5).
    assert axis.observe(segments((-30.0, 1.2)), math.radians(35.0)) is None
    # Unsure after 100 m of wheels: never beyond gate_rad.
    axis.moved(100.0, 0.0)
    assert axis.observe(segments((-30.0, 1.2)), math.radians(37.0)) is None
    assert axis.observe(segments((-30.0, 0.3)), math.radians(32.0)) is None
    assert axis.observe(np.zeros((0, 2)), 0.0) is None
    assert axis.frames_used == 0
    # The weighted median: a short stray inside the gate does not pull the turn.
    one = axis.observe(segments((-30.0, 1.2)), math.radians(32.0))
    axis.restore(0.0)
    axis.moved(100.0, 0.0)
    two = axis.observe(segments((-30.0, 1.2), (-26.0, 0.4)), math.radians(32.0))
    assert one is not None and one == pytest.approx(two)


def test_a_heading_turned_beyond_the_gate_comes_back_once_views_apart_agree() -> None:
    params = ManhattanParams(gate_rad=math.radians(6.0), recover_limit_rad=math.radians(25.0))
    axis = HeadingAxis(params)
    axis.restore(0.0)
    # A spin turn's slip left the estimate 12 degrees off: the walls' lines, 30 degrees
    # off the true nose, appear at 42 - 30 = 12 degrees off the axis, beyond the gate.
    wall = segments((-30.0, 1.2))
    heading = math.radians(42.0)
    for _ in range(5):
        axis.moved(0.2, 0.0)
        assert axis.observe(wall, heading) is None
    axis.moved(0.2, 0.0)
    turn = axis.observe(wall, heading)
    assert turn == pytest.approx(-math.radians(12.0), abs=1e-9)
    assert axis.recoveries == 1 and axis.frames_used == 0
    assert axis.variance_rad2 == pytest.approx(params.start_sigma_rad**2)


def test_no_turn_back_from_one_place_a_stray_frame_a_line_in_the_gate_or_past_the_limit() -> None:
    axis = HeadingAxis(ManhattanParams(gate_rad=math.radians(6.0)))
    axis.restore(0.0)
    wall, heading = segments((-30.0, 1.2)), math.radians(42.0)
    # Seen from one place (0.05 m and no turn between frames): one object, seen again.
    for _ in range(8):
        axis.moved(0.05, 0.0)
        assert axis.observe(wall, heading) is None
    # A frame whose lines say 16 degrees keeps the row from agreeing while it is in it
    # (the row holds the latest six)...
    axis.restore(0.0)
    axis.moved(0.3, 0.0)
    assert axis.observe(wall, math.radians(46.0)) is None
    for _ in range(5):
        axis.moved(0.3, 0.0)
        assert axis.observe(wall, heading) is None
    axis.moved(0.3, 0.0)
    assert axis.observe(wall, heading) == pytest.approx(-math.radians(12.0), abs=1e-9)
    # ...a frame with a line inside the gate starts the row again (and corrects)...
    axis.restore(0.0)
    for k in range(10):
        axis.moved(0.3, 0.0)
        frame = segments((-30.0, 1.2), (60.0 - 10.0, 0.8)) if k == 4 else wall
        turn = axis.observe(frame, heading)
        assert (turn is not None) == (k == 4)
    assert axis.recoveries == 1 and axis.frames_used == 1
    # ...and lines further off than recover_limit_rad are no evidence.
    axis.restore(0.0)
    for _ in range(10):
        axis.moved(0.3, 0.0)
        assert axis.observe(wall, math.radians(60.0)) is None
    assert axis.recoveries == 1


@pytest.mark.parametrize("floor_odometry", [False, True])
def test_the_mapper_turns_a_drifted_heading_back_about_the_robot(floor_odometry: bool) -> None:
    config = load_config(CONFIG, mapping={"floor_odometry": floor_odometry})
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    renderer = renderer_from_config(config)
    assert mapper.heading_axis is not None
    # The flat's walls run along the plan's axes; the daemon's odometry frame starts at
    # the start pose, here the plan frame itself. Facing the living room's north wall.
    mapper.heading_axis.restore(0.0)
    truth = Pose2D(1.2, 3.0, math.radians(90.0))
    drifted = Pose2D(truth.x_m, truth.y_m, truth.theta_rad + math.radians(3.0))
    frame = renderer.render(truth)
    if floor_odometry:
        # The first frame is floor odometry's key; while its floors line up, floor
        # odometry holds the heading and the axis only learns...
        assert mapper.follow_floor(frame.image, frame.floor_mask, drifted, 0.0) is None
        assert mapper.heading_axis.frames_used == 0
        # ...once they did not (a floor without texture), the axis corrects, and the key
        # frame turns with the pose (or the next floor step would turn it back).
        mapper._key_misses = 1
    turns = []
    for k in range(6):
        step = mapper.follow_floor(frame.image, frame.floor_mask, drifted, 0.1 * (k + 1))
        if step is not None:
            drifted = step.compose(drifted)
            turns.append(step)
    assert len(turns) == 6, "the flat's north wall gives straight floor edges"
    off = math.degrees(math.remainder(drifted.theta_rad - truth.theta_rad, math.tau))
    assert abs(off) < 1.0  # from 3 degrees
    # Turned about the robot: the place is kept.
    assert math.hypot(drifted.x_m - truth.x_m, drifted.y_m - truth.y_m) < 1e-9
    assert mapper.heading_axis.frames_used == len(turns)
    if floor_odometry:
        key = mapper._keyframe
        assert key is not None
        assert key.pose[2] == pytest.approx(drifted.theta_rad)


def test_off_there_is_no_axis() -> None:
    config = load_config(CONFIG, mapping={"manhattan_heading": False, "floor_odometry": False})
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    assert mapper.heading_axis is None
    frame = renderer_from_config(config).render(Pose2D(1.5, 3.0, 0.3))
    assert mapper.follow_floor(frame.image, frame.floor_mask, Pose2D(1.5, 3.0, 0.4), 0.0) is None
