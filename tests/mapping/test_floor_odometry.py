"""Visual odometry on the floor (`GroundMapper._floor_odometry`): the pose follows the
floor's motion between key frames, not the wheels'."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.config import CameraConfig, load_config
from app.mapping.calibration import Intrinsics
from app.mapping.frames import Pose2D
from app.mapping.ground_map import GroundMapper
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

CONFIG = Path(__file__).resolve().parents[2] / "config.toml"


def mapper_and_renderer(**mapping: object) -> tuple[GroundMapper, object]:
    # Floor odometry alone: the building's axis (`test_manhattan.py`) corrects headings too.
    config = load_config(CONFIG, mapping={"manhattan_heading": False, **mapping})
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    return mapper, renderer_from_config(config)


def pose_error(a: Pose2D, b: Pose2D) -> tuple[float, float]:
    return math.hypot(a.x_m - b.x_m, a.y_m - b.y_m), abs(
        math.remainder(a.theta_rad - b.theta_rad, math.tau)
    )


def drive(
    mapper: GroundMapper, renderer: object, heading_rad: float, image_of: object = None
) -> tuple[Pose2D, Pose2D, Pose2D]:
    """Drive the wooden floor of the shipped flat, starting at ``heading_rad`` (0: along
    the planks): 0.5 m ahead, a 40 degree spin on the spot, 0.3 m on, at 2 cm and 1.5
    degrees a frame. The wheels over-read travel by 6 % and each turn by 8 %, and they
    pull 0.2 degrees left every step. As in the daemon, each frame is fused first and
    followed on the floor after, and each correction is left-multiplied onto odometry.
    Returns, at the last frame, the truth, the wheels' own pose and the frame's pose
    corrected by its own step (where the next frame starts from)."""
    truth = Pose2D(3.2, 3.05, heading_rad)
    wheels = truth
    correction = Pose2D(0.0, 0.0, 0.0)
    steps = [(0.02, 0.0)] * 25 + [(0.0, math.radians(1.5))] * 27 + [(0.02, 0.0)] * 15
    fused = truth
    for k, (ahead_m, turn_rad) in enumerate(steps):
        frame = renderer.render(truth)  # type: ignore[attr-defined]
        image = frame.image if image_of is None else image_of(frame)  # type: ignore[operator]
        fused = correction.compose(wheels)
        update = mapper.update(frame.floor_mask, fused, 0.05 * k, image)
        assert update.correction is None  # scan matching is off
        step = mapper.follow_floor(image, frame.floor_mask, fused, 0.05 * k)
        if step is not None:
            correction = step.compose(correction)
            fused = step.compose(fused)
        if k < len(steps) - 1:
            truth = truth.compose(Pose2D(ahead_m, 0.0, turn_rad))
            wheels = wheels.compose(
                Pose2D(1.06 * ahead_m, 0.0, 1.08 * turn_rad + math.radians(0.2))
            )
    return truth, wheels, fused


def test_the_pose_follows_the_floors_motion_where_the_wheels_slip() -> None:
    mapper, renderer = mapper_and_renderer(floor_odometry=True)
    assert mapper.floor_odometry
    truth, wheels, fused = drive(mapper, renderer, 0.5)
    wheels_off_m, wheels_off_rad = pose_error(wheels, truth)
    assert wheels_off_m > 0.08 and wheels_off_rad > math.radians(15.0)
    off_m, off_rad = pose_error(fused, truth)
    assert off_m < 0.003 and off_rad < math.radians(0.15)
    # A key frame every 5 cm or 0.1 rad (5.7 degrees), and every one lined up.
    assert 15 <= mapper.floor_odometry_steps <= 25
    assert mapper.floor_odometry_applied == mapper.floor_odometry_steps


def test_driving_along_the_planks_their_seams_leave_the_travel_to_the_wheels() -> None:
    # A shift along parallel seams changes nothing the views show (the aperture
    # problem): the wheels' over-read travel stays while the robot drives along them;
    # the heading is still the floor's (the wheels' is 16 degrees off).
    mapper, renderer = mapper_and_renderer(floor_odometry=True)
    truth, wheels, fused = drive(mapper, renderer, 0.0)
    off_m, off_rad = pose_error(fused, truth)
    assert 0.005 < off_m < 0.03 and off_rad < math.radians(0.2)
    assert off_m < 0.25 * pose_error(wheels, truth)[0]
    assert off_rad < 0.02 * pose_error(wheels, truth)[1]


def test_a_floor_without_texture_leaves_the_wheels_alone() -> None:
    mapper, renderer = mapper_and_renderer(floor_odometry=True)

    def plain(frame: object) -> np.ndarray:
        return np.full_like(frame.image, 128)  # type: ignore[attr-defined]

    _, wheels, fused = drive(mapper, renderer, 0.5, plain)
    assert mapper.floor_odometry_steps > 10 and mapper.floor_odometry_applied == 0
    assert pose_error(fused, wheels) == (0.0, 0.0)


def test_floor_odometry_is_off_when_asked_and_for_frames_with_lens_distortion() -> None:
    mapper, renderer = mapper_and_renderer(floor_odometry=False)
    assert not mapper.floor_odometry
    _, wheels, fused = drive(mapper, renderer, 0.5)
    assert mapper.floor_odometry_steps == 0 and pose_error(fused, wheels) == (0.0, 0.0)
    on, _ = mapper_and_renderer(floor_odometry=True)
    intrinsics = Intrinsics(
        np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5), (640, 480), 0.1
    )
    distorted = GroundMapper(
        replace(on.calibration, intrinsics=intrinsics), on.mapping, CameraConfig()
    )
    assert not distorted.floor_odometry
