"""Frontier clusters, reachability and the exploration goal on hand-made grids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid
from app.mapping.frontiers import (
    REASON_NO_FRONTIER,
    REASON_NO_REACHABLE,
    REASON_OUTSIDE_MAP,
    FrontierParams,
    clearance_weights,
    find_frontiers,
    frontier_mask,
    inflate_obstacles,
    path_distances,
)
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN

CELL = 0.5
SYMBOLS = {"?": UNKNOWN, ".": FREE, "#": OCCUPIED}

# Frontier clusters (4-adjacency): A = row 1, cols 0..3 (4 cells, reachable);
# B = row 1, cols 5..9 (5 cells, walled off by column 4 and row 3);
# C = (4, 9), (5, 8), (6, 9) around the unknown cell (5, 9) (3 cells).
ROOM = """
????#?????
....#.....
....#.....
....######
..........
.........?
..........
..........
"""


def parse(text: str) -> tuple[NDArray[np.int8], GroundGrid]:
    rows = text.strip().splitlines()
    cells = np.array([[SYMBOLS[ch] for ch in row] for row in rows], dtype=np.int8)
    rows_n, cols_n = cells.shape
    grid = GroundGrid(rows_n * CELL, cols_n * CELL, CELL, rows_n, cols_n)
    return cells, grid


def centre(grid: GroundGrid, row: float, col: float) -> tuple[float, float]:
    return (grid.x_max_m - (row + 0.5) * grid.cell_m, grid.y_max_m - (col + 0.5) * grid.cell_m)


# Bare geometry: no inflation, the footprint is the robot's own cell.
BARE = FrontierParams(min_cluster_cells=4, inflation_radius_m=0.0, robot_radius_m=0.0)


def test_clusters_sizes_and_goal_are_exact() -> None:
    cells, grid = parse(ROOM)
    result = find_frontiers(cells, grid, centre(grid, 7, 1), BARE)
    assert [c.size_cells for c in result.clusters] == [4, 5]
    assert result.dropped_clusters == 1  # C
    a, b = result.clusters
    assert a.cells.tolist() == [[1, 0], [1, 1], [1, 2], [1, 3]]
    assert a.centroid_xy == pytest.approx(centre(grid, 1, 1.5))
    assert a.representative_cell == (1, 1) and a.path_length_m == pytest.approx(6 * CELL)
    assert a.representative_xy == pytest.approx(centre(grid, 1, 1))
    assert not b.reachable and b.representative_cell is None and math.isinf(b.path_length_m)
    goal = result.goal
    assert goal is not None and result.reason == ""
    assert goal.cluster_index == 0 and goal.cell == (1, 1)
    assert goal.path_length_m == pytest.approx(3.0) and goal.score == pytest.approx(3.0)
    path = goal.path_cells
    assert path[0].tolist() == [7, 1] and path[-1].tolist() == [1, 1] and len(path) == 7
    assert (np.abs(np.diff(path, axis=0)).max(axis=1) == 1).all()


def test_smaller_clusters_kept_and_nearest_chosen() -> None:
    cells, grid = parse(ROOM)
    params = FrontierParams(min_cluster_cells=3, inflation_radius_m=0.0, robot_radius_m=0.0)
    result = find_frontiers(cells, grid, centre(grid, 6, 7), params)
    assert [c.size_cells for c in result.clusters] == [4, 5, 3]
    goal = result.goal
    assert goal is not None and goal.cluster_index == 2
    assert goal.cell == (5, 8) and goal.path_length_m == pytest.approx(math.sqrt(2) * CELL)
    # A size penalty prefers the bigger (and here farther) opening A.
    penalised = FrontierParams(
        min_cluster_cells=3, inflation_radius_m=0.0, robot_radius_m=0.0, size_penalty_m=100.0
    )
    goal = find_frontiers(cells, grid, centre(grid, 6, 7), penalised).goal
    assert goal is not None and goal.cluster_index == 0


def test_unreachable_frontier_behind_a_wall_is_not_chosen() -> None:
    cells, grid = parse(ROOM)
    # From (4, 7), B is 3 rows away through the wall; A is far round the corner.
    result = find_frontiers(cells, grid, centre(grid, 4, 7), BARE)
    goal = result.goal
    assert goal is not None and goal.cluster_index == 0
    assert goal.path_length_m > 3 * CELL
    assert not result.clusters[1].reachable


def test_no_reachable_frontier() -> None:
    cells, grid = parse(
        """
        ?????
        #####
        .....
        .....
        """.replace(" ", "")
    )
    cells[0, 2:] = FREE  # floor seen beyond the wall: (0, 2) is a frontier cell
    params = FrontierParams(min_cluster_cells=1, inflation_radius_m=0.0, robot_radius_m=0.0)
    result = find_frontiers(cells, grid, centre(grid, 3, 2), params)
    assert result.goal is None and result.reason == REASON_NO_REACHABLE
    assert len(result.clusters) == 1 and not result.clusters[0].reachable


def test_no_frontier_gives_none_with_reason() -> None:
    cells, grid = parse(
        """
        #####
        #...#
        #...#
        #####
        """.replace(" ", "")
    )
    result = find_frontiers(cells, grid, centre(grid, 2, 2), BARE)
    assert result.goal is None and result.reason == REASON_NO_FRONTIER
    assert result.clusters == () and result.dropped_clusters == 0
    cells[0, 2] = UNKNOWN  # one frontier cell: a cluster too small to keep
    result = find_frontiers(cells, grid, centre(grid, 2, 2), BARE)
    assert result.goal is None and result.reason == REASON_NO_FRONTIER
    assert result.dropped_clusters == 1
    result = find_frontiers(cells, grid, (100.0, 0.0), BARE)
    assert result.goal is None and result.reason == REASON_OUTSIDE_MAP


def test_inflation_closes_a_narrow_door_and_footprint_lets_the_robot_start() -> None:
    cells, grid = parse(
        """
        ?????????
        .........
        ####.####
        .........
        .........
        """.replace(" ", "")
    )
    robot = centre(grid, 4, 4)
    open_door = find_frontiers(cells, grid, robot, BARE)
    assert open_door.goal is not None and open_door.goal.cell[0] == 1
    closed = FrontierParams(min_cluster_cells=4, inflation_radius_m=CELL, robot_radius_m=0.0)
    result = find_frontiers(cells, grid, robot, closed)
    assert result.goal is None and result.reason == REASON_NO_REACHABLE
    inflated = inflate_obstacles(cells == OCCUPIED, 1.0)
    assert inflated[1:4, 3].all() and inflated[2, 4] and not inflated[0, 4]

    # The robot on an unknown cell (never seen: the camera does not see under it) with free
    # floor around it: the footprint is traversable and not a frontier.
    cells[4, 4] = UNKNOWN
    bare = find_frontiers(cells, grid, robot, BARE)
    assert bare.goal is not None and bare.goal.cell[0] == 1


def test_the_robots_track_keeps_a_door_it_came_through_open() -> None:
    cells, grid = parse(
        """
        ?????????
        .........
        ####.####
        .........
        .........
        """.replace(" ", "")
    )
    robot = centre(grid, 4, 4)
    params = FrontierParams(min_cluster_cells=4, inflation_radius_m=CELL, robot_radius_m=0.0)
    assert find_frontiers(cells, grid, robot, params).goal is None  # the door is inflated shut
    # The robot's centre came down column 4 through the door: it fitted there.
    track = np.zeros(cells.shape, bool)
    track[1:5, 4] = True
    through = find_frontiers(cells, grid, robot, params, track=track)
    assert through.goal is not None and through.goal.cell[0] == 1
    assert [tuple(p) for p in through.goal.path_cells[:4]] == [(4, 4), (3, 4), (2, 4), (1, 4)]
    # A track cell the map calls occupied now (something put down since) is not crossed.
    blocked = cells.copy()
    blocked[2, 4] = OCCUPIED
    assert find_frontiers(blocked, grid, robot, params, track=track).goal is None
    # The track keeps the body's clearance: a robot a cell in radius does not fit the door.
    wide = FrontierParams(min_cluster_cells=4, inflation_radius_m=CELL, robot_radius_m=CELL)
    assert find_frontiers(cells, grid, robot, wide, track=track).goal is None
    with pytest.raises(ValueError, match="track: expected shape"):
        find_frontiers(cells, grid, robot, params, track=track[1:])


def test_frontier_mask_adjacency() -> None:
    cells = np.array([[UNKNOWN, FREE, FREE], [FREE, FREE, FREE]], np.int8)
    assert frontier_mask(cells).astype(int).tolist() == [[0, 1, 0], [1, 0, 0]]
    assert frontier_mask(cells, adjacency=8).astype(int).tolist() == [[0, 1, 0], [1, 1, 0]]


def test_path_distances_do_not_cut_corners() -> None:
    traversable = np.array([[True, False], [False, True]])
    distance, _ = path_distances(traversable, (0, 0), 1.0)
    assert math.isinf(distance[1, 1])
    distance, _ = path_distances(np.ones((2, 2), bool), (0, 0), 1.0)
    assert distance[1, 1] == pytest.approx(math.sqrt(2))


def _path_clearance_m(cells: NDArray[np.int8], grid: GroundGrid, params: FrontierParams) -> float:
    """The least distance from the goal path's cells to the box's cells (centres)."""
    search = find_frontiers(cells, grid, centre(grid, 10, 1), params)
    assert search.goal is not None
    occupied = np.argwhere(cells[1:] == OCCUPIED) + np.array([1, 0])
    path = search.goal.path_cells
    gaps = np.hypot(*(path[:, None, :] - occupied[None, :, :]).transpose(2, 0, 1))
    return float(gaps.min()) * grid.cell_m


def test_paths_pass_obstacles_wide_where_there_is_room_and_still_take_a_narrow_door() -> None:
    """A box stands between the robot (bottom left) and the only frontier (top right
    corner). Shortest paths graze it at the inflation radius; with the clearance cost the
    path keeps the preferred distance, and a door just wide enough stays open."""
    room = """
        ?????????????
        .............
        .............
        .............
        .............
        .............
        .....###.....
        .....###.....
        .............
        .............
        .............
        .............
        .............
        """.replace(" ", "")
    cells, grid = parse(room)
    cells[0, :-1] = OCCUPIED  # only the top right corner is a frontier: the path goes
    plain = FrontierParams(min_cluster_cells=1, inflation_radius_m=CELL, robot_radius_m=0.0)
    wide = FrontierParams(
        min_cluster_cells=1,
        inflation_radius_m=CELL,
        robot_radius_m=0.0,
        clearance_preferred_m=3 * CELL,
        clearance_cost=4.0,
    )
    # The inflated band covers one cell round the box: the shortest path runs just past it.
    assert _path_clearance_m(cells, grid, plain) == pytest.approx(2 * CELL)
    # Near the preferred three cells (a corner cut diagonally costs a tenth of a cell).
    assert _path_clearance_m(cells, grid, wide) >= 2 * math.sqrt(2) * CELL

    door = parse(
        """
        ?????
        .....
        ##.##
        .....
        .....
        """.replace(" ", "")
    )
    narrow = FrontierParams(
        min_cluster_cells=1, robot_radius_m=0.0, clearance_preferred_m=4 * CELL, clearance_cost=20.0
    )
    through = find_frontiers(*door, centre(door[1], 4, 2), narrow)
    assert through.goal is not None and through.goal.cell[0] == 1


def test_clearance_weights_are_one_far_away_and_grow_to_one_plus_the_cost() -> None:
    occupied = np.zeros((1, 7), bool)
    occupied[0, 0] = True
    weights = clearance_weights(occupied, 0.5, 0.5, 2.0, 3.0)
    # distances 0, 0.5, 1.0, 1.5, 2.0 ...: shortfall 1, 1, 2/3, 1/3, 0
    assert weights[0].tolist() == pytest.approx([4.0, 4.0, 1 + 3 * 4 / 9, 1 + 3 / 9, 1, 1, 1])
    assert np.all(clearance_weights(occupied, 0.5, 0.5, 0.5, 3.0) == 1.0)  # no span
    assert np.all(clearance_weights(np.zeros((2, 2), bool), 0.5, 0.1, 2.0, 3.0) == 1.0)
    with pytest.raises(ValueError, match="step_weight"):
        path_distances(np.ones((2, 2), bool), (0, 0), 1.0, np.full((2, 2), 0.5))


def test_bad_inputs_raise_clear_value_errors() -> None:
    cells, grid = parse(ROOM)
    robot = centre(grid, 7, 1)
    with pytest.raises(ValueError, match="int8"):
        find_frontiers(cells.astype(np.int64), grid, robot)
    with pytest.raises(ValueError, match="shape"):
        find_frontiers(cells[:, :-1], grid, robot)
    bad = cells.copy()
    bad[0, 0] = 5
    with pytest.raises(ValueError, match="values"):
        find_frontiers(bad, grid, robot)
    with pytest.raises(ValueError, match="robot_xy_world"):
        find_frontiers(cells, grid, (float("nan"), 0.0))
    negative = GroundGrid(grid.x_max_m, grid.y_max_m, -CELL, grid.rows, grid.cols)
    with pytest.raises(ValueError, match="cell size"):
        find_frontiers(cells, negative, robot)
    with pytest.raises(ValueError, match="min_cluster_cells"):
        FrontierParams(min_cluster_cells=0)
    with pytest.raises(ValueError, match="inflation_radius_m"):
        FrontierParams(inflation_radius_m=-0.1)
    with pytest.raises(ValueError, match="clearance_cost"):
        FrontierParams(clearance_cost=-1.0)
    with pytest.raises(ValueError, match="frontier_adjacency"):
        FrontierParams(frontier_adjacency=6)
    with pytest.raises(ValueError, match="start_cell"):
        path_distances(np.ones((2, 2), bool), (2, 0), 1.0)
