"""Where a stall marks the map (`app.mapping.bumps`) and what the mapper does with it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.mapping.bumps import BUMP_DEPTH_M, BUMP_HALF_ANGLE_RAD, bump_cells
from app.mapping.frames import NOT_FLOOR, GroundGrid, Pose2D
from app.mapping.occupancy import OCCUPIED

from .test_ground_map import make_mapper, wall_mask

GRID = GroundGrid.covering(x_min_m=-1.0, x_max_m=1.0, y_min_m=-1.0, y_max_m=1.0, cell_m=0.02)


def centres(cells: np.ndarray) -> np.ndarray:
    rows, cols = np.divmod(cells, GRID.cols)
    x = GRID.x_max_m - (rows + 0.5) * GRID.cell_m
    y = GRID.y_max_m - (cols + 0.5) * GRID.cell_m
    return np.stack([x, y], axis=1)


@pytest.mark.parametrize("theta", [0.0, 2.0, -3.0])
@pytest.mark.parametrize("forward", [True, False])
def test_the_band_lies_just_outside_the_robot_in_the_push_direction(
    theta: float, forward: bool
) -> None:
    pose = Pose2D(0.1, -0.2, theta)
    cells = bump_cells(GRID, pose, 0.12, forward=forward)
    xy = centres(cells) - [pose.x_m, pose.y_m]
    distance = np.hypot(xy[:, 0], xy[:, 1])
    assert distance.min() > 0.12 and distance.max() <= 0.12 + BUMP_DEPTH_M
    push = theta if forward else theta + math.pi
    off = np.abs(np.remainder(np.arctan2(xy[:, 1], xy[:, 0]) - push + math.pi, math.tau) - math.pi)
    assert off.max() <= BUMP_HALF_ANGLE_RAD
    # The whole band: its area is a quarter of the ring's (a 90-degree sector).
    ring_m2 = math.pi * ((0.12 + BUMP_DEPTH_M) ** 2 - 0.12**2) / 4
    assert cells.size * GRID.cell_m**2 == pytest.approx(ring_m2, rel=0.1)
    assert np.all(np.diff(cells) > 0)


def test_a_band_off_the_grid_is_empty_and_a_bad_radius_is_refused() -> None:
    assert bump_cells(GRID, Pose2D(5.0, 5.0, 0.0), 0.12, forward=True).size == 0
    with pytest.raises(ValueError, match="radius_m"):
        bump_cells(GRID, Pose2D(), -0.1, forward=True)


def test_a_bump_is_occupied_whatever_the_camera_says_until_the_robot_stands_there() -> None:
    mapper = make_mapper()
    pose = Pose2D(0.0, 0.0, 0.0)
    everything_floor = np.ones_like(wall_mask(mapper, 1.2))
    marked = mapper.mark_bump(pose, forward=True)
    assert marked > 0
    for t in range(4):
        update = mapper.update(everything_floor, pose, now_s=0.1 * t)
    radius = mapper.mapping.robot_radius_m
    ahead = mapper.grid.world_grid.cell_of(np.array([[radius + 0.04, 0.0]]))[0]
    cells = mapper.grid.classify()
    assert cells[ahead[0], ahead[1]] == OCCUPIED
    assert np.all(cells[mapper.bumped] == OCCUPIED)
    # What the clearance stop reads: the patch's cells there are not floor.
    x, y = mapper.birdseye.grid.cell_centers()
    strip = (x > radius + 0.01) & (x < radius + 0.03) & (np.abs(y) < 0.04)
    assert strip.any() and np.all(update.patch[strip] == NOT_FLOOR)
    # The robot drives onto the marked cells: whatever held it has gone.
    mapper.update(everything_floor, Pose2D(radius + 0.04, 0.0, 0.0), now_s=1.0)
    assert not mapper.bumped[ahead[0], ahead[1]]
