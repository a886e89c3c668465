"""Edge probes (`app.mapping.frontiers`): with no reachable frontier, the search sends
the robot to look at an edge of the floor that geometry has not seen standing."""

from __future__ import annotations

import numpy as np

from app.mapping.floor_memory import FloorMemory
from app.mapping.frames import GroundGrid
from app.mapping.frontiers import REASON_NO_FRONTIER, FrontierParams, find_frontiers
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN

GRID = GroundGrid(3.0, 1.5, 0.1, 30, 30)  # x 0..3, y -1.5..1.5
PARAMS = FrontierParams(
    robot_radius_m=0.1, inflation_radius_m=0.1, exclude_radius_m=0.3, min_cluster_cells=3
)
ROBOT = (2.55, 0.05)  # cell (4, 14)


def boxed_in() -> np.ndarray:
    """Free floor rows 1..9 closed by an occupied band at row 10 (a rug's edge, say)
    with nothing known beyond, and walls on the other three sides."""
    cells = np.full(GRID.shape, UNKNOWN, np.int8)
    cells[1:10, 1:29] = FREE
    cells[0, :] = OCCUPIED
    cells[:11, [0, 29]] = OCCUPIED
    cells[10, :] = OCCUPIED
    return cells


def test_without_probe_cells_nothing_is_left() -> None:
    search = find_frontiers(boxed_in(), GRID, ROBOT, PARAMS)
    assert search.goal is None and search.reason == REASON_NO_FRONTIER


def test_the_probe_goes_to_the_nearest_cell_before_the_unproven_edge() -> None:
    search = find_frontiers(boxed_in(), GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    goal = search.goal
    assert goal is not None and goal.probe and search.reason == ""
    # Within the inflation radius plus two cells of row 10, straight below the robot
    # (the nearest such cell by path), and traversable (outside the inflation).
    assert goal.cell == (7, 14)
    assert tuple(goal.path_cells[0]) == (4, 14) and tuple(goal.path_cells[-1]) == goal.cell
    assert abs(goal.path_length_m - 0.3) < 1e-9


def test_edges_seen_standing_or_already_probed_are_left_alone() -> None:
    probe_cells = np.ones(GRID.shape, bool)
    probe_cells[10, :] = False  # the band is known to stand
    search = find_frontiers(boxed_in(), GRID, ROBOT, PARAMS, probe_cells=probe_cells)
    assert search.goal is None and search.reason == REASON_NO_FRONTIER


def test_a_short_edge_is_not_worth_a_probe() -> None:
    cells = boxed_in()
    cells[10, :] = FREE
    cells[11, :] = OCCUPIED  # the band moves down; behind it only two unknown cells
    cells[12:, :] = FREE
    cells[12, 5:7] = UNKNOWN
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    # The two unknown cells are a frontier too small to keep, and the edge before them
    # only two cells long: no probe (min_cluster_cells 3).
    assert search.goal is None


def test_floor_memory_remembers_what_stood_until_it_is_floor_again() -> None:
    memory = FloorMemory(GRID)
    cells = np.array([5, 6, 7], dtype=np.int64)
    memory.mark_standing(cells)
    assert memory.standing.reshape(-1)[cells].tolist() == [1, 1, 1]
    memory.confirm_cells(np.array([6], dtype=np.int64))
    assert memory.standing.reshape(-1)[cells].tolist() == [1, 0, 1]
    memory.reset()
    assert not memory.standing.any()
