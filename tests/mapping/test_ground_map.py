"""Floor mask -> bird's-eye patch -> occupancy grid -> frontiers, end to end with a
synthetic calibrated camera."""

from __future__ import annotations

import numpy as np

from app.config import CameraConfig, MappingConfig
from app.mapping.calibration import apply_homography, homography_from_point_pairs
from app.mapping.frames import FLOOR, NOT_FLOOR, Pose2D
from app.mapping.ground_map import GroundMapper
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN

from .test_calibration import HEIGHT, WIDTH, camera_homography


def make_mapper() -> GroundMapper:
    H_true = camera_homography()
    ground = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])
    calibration = homography_from_point_pairs(
        apply_homography(H_true, ground), ground, (WIDTH, HEIGHT)
    )
    return GroundMapper(calibration, MappingConfig(max_range_m=2.5), CameraConfig(x_m=0.0))


def wall_mask(mapper: GroundMapper, wall_x_m: float) -> np.ndarray:
    """Floor up to a wall ``wall_x_m`` ahead (a straight line across the image)."""
    row = mapper.calibration.ground_to_image(np.array([[wall_x_m, 0.0]]))[0, 1]
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[int(np.ceil(row)) :] = True
    return mask


def test_wall_ahead_becomes_free_floor_then_an_occupied_band() -> None:
    mapper = make_mapper()
    pose = Pose2D(0.0, 0.0, 0.0)
    for t in range(3):
        update = mapper.update(wall_mask(mapper, 1.2), pose, now_s=0.1 * t)
    patch = update.patch
    assert (patch == FLOOR).any() and (patch == NOT_FLOOR).any()
    cells = mapper.grid.classify()
    grid = mapper.grid.world_grid
    row_col = grid.cell_of(np.array([[0.8, 0.0], [1.22, 0.0], [1.6, 0.0], [-0.5, 0.0]]))
    states = [int(cells[r, c]) for r, c in row_col]
    assert states == [FREE, OCCUPIED, UNKNOWN, UNKNOWN]  # behind the wall: not updated


def test_turned_robot_maps_into_the_world_frame() -> None:
    mapper = make_mapper()
    pose = Pose2D(1.0, 2.0, np.pi / 2)  # facing world +y
    for t in range(3):
        mapper.update(wall_mask(mapper, 1.2), pose, now_s=0.1 * t)
    cells = mapper.grid.classify()
    r, c = mapper.grid.world_grid.cell_of(np.array([[1.0, 2.8]]))[0]
    assert cells[r, c] == FREE
    r, c = mapper.grid.world_grid.cell_of(np.array([[1.0, 3.22]]))[0]
    assert cells[r, c] == OCCUPIED


def test_frontier_goal_lies_at_the_edge_of_what_was_seen() -> None:
    mapper = make_mapper()
    pose = Pose2D(0.0, 0.0, 0.0)
    open_floor = np.ones((HEIGHT, WIDTH), bool)
    for t in range(3):
        mapper.update(open_floor, pose, now_s=0.1 * t)
    search = mapper.frontiers(pose)
    assert search.goal is not None, search.reason
    assert search.clusters
    x, _ = search.goal.xy
    assert 0.0 < x <= 2.6  # at the far edge or the sides of the seen wedge
