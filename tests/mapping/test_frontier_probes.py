"""Edge probes (`app.mapping.frontiers`): with no reachable frontier, the search sends
the robot to look at an edge of the floor that geometry has not seen standing."""

from __future__ import annotations

import numpy as np

from app.mapping.floor_memory import FloorMemory
from app.mapping.frames import GroundGrid
from app.mapping.frontiers import (
    REASON_NO_FRONTIER,
    REASON_NO_REACHABLE,
    FrontierParams,
    find_frontiers,
)
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


def test_the_probe_goes_to_the_reachable_cell_nearest_where_its_way_meets_the_edge() -> None:
    search = find_frontiers(boxed_in(), GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    goal = search.goal
    assert goal is not None and goal.probe and search.reason == ""
    # Straight below the robot, where its way to the unknown meets row 10: the nearest
    # reachable cell to that point (row 9 lies inside the inflation).
    assert goal.cell == (8, 14)
    assert tuple(goal.path_cells[0]) == (4, 14) and tuple(goal.path_cells[-1]) == goal.cell
    assert abs(goal.path_length_m - 0.4) < 1e-9


def test_edges_seen_standing_or_already_probed_are_left_alone() -> None:
    probe_cells = np.ones(GRID.shape, bool)
    probe_cells[10, :] = False  # the band is known to stand
    search = find_frontiers(boxed_in(), GRID, ROBOT, PARAMS, probe_cells=probe_cells)
    assert search.goal is None and search.reason == REASON_NO_FRONTIER


def test_a_small_frontier_behind_an_edge_is_not_worth_a_probe() -> None:
    cells = boxed_in()
    cells[10, :] = FREE
    cells[11, :] = OCCUPIED  # the band moves down; behind it seen floor, one cell unknown
    cells[12:, :] = FREE
    cells[12, 5] = UNKNOWN
    params = FrontierParams(
        robot_radius_m=0.1, inflation_radius_m=0.1, exclude_radius_m=0.3, min_cluster_cells=5
    )
    search = find_frontiers(cells, GRID, ROBOT, params, probe_cells=np.ones(GRID.shape, bool))
    # Even with the band taken for floor, the frontier round the one unknown cell is four
    # cells: fewer than min_cluster_cells, no probe.
    assert search.goal is None
    cells[12, 5:8] = UNKNOWN  # three unknown cells: a frontier worth the look
    search = find_frontiers(cells, GRID, ROBOT, params, probe_cells=np.ones(GRID.shape, bool))
    assert search.goal is not None and search.goal.probe


def seam_across_the_floor() -> np.ndarray:
    """Seen floor rows 1..19 cut by a one-cell occupied line at row 10 (a plank seam the
    colour method took for a wall), unexplored floor past row 19, walls at the sides."""
    cells = np.full(GRID.shape, UNKNOWN, np.int8)
    cells[1:20, 1:29] = FREE
    cells[0, :] = OCCUPIED
    cells[:21, [0, 29]] = OCCUPIED
    cells[10, 1:29] = OCCUPIED
    return cells


def test_a_false_wall_across_seen_floor_is_probed_where_the_way_crosses_it() -> None:
    cells = seam_across_the_floor()
    # Nothing unknown touches the seam, yet it is all that keeps the robot from row 19.
    search = find_frontiers(cells, GRID, ROBOT, PARAMS)
    assert search.goal is None and search.reason == REASON_NO_REACHABLE
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    goal = search.goal
    assert goal is not None and goal.probe
    assert goal.cell == (8, 14)  # straight before the seam, on the way to row 19
    assert tuple(goal.path_cells[0]) == (4, 14) and tuple(goal.path_cells[-1]) == goal.cell
    # It looks at the seam's cells within 0.3 m of where the way meets it.
    assert goal.edge_cells is not None
    assert sorted(map(tuple, goal.edge_cells.tolist())) == [(10, c) for c in range(11, 18)]


def test_the_probe_crosses_the_seam_where_nothing_was_seen_standing() -> None:
    probe_cells = np.ones(GRID.shape, bool)
    probe_cells[10, :21] = False  # this part of the line was seen standing: a real wall
    search = find_frontiers(seam_across_the_floor(), GRID, ROBOT, PARAMS, probe_cells=probe_cells)
    goal = search.goal
    assert goal is not None and goal.probe
    # Before the unproven part (columns 21..28), not before the wall in front.
    assert goal.cell[0] == 8 and goal.cell[1] >= 19


def test_floor_memory_remembers_what_stood_until_it_is_floor_again() -> None:
    memory = FloorMemory(GRID)  # a cell stands from 2 net marks; marks saturate at 3
    cells = np.array([5, 6, 7], dtype=np.int64)

    def layer() -> list[int]:
        return [int(v) for v in memory.standing.reshape(-1)[cells]]

    memory.mark_standing(cells)
    assert layer() == [0, 0, 0]  # one test's foot is not enough
    memory.mark_standing(cells)
    assert layer() == [1, 1, 1]
    memory.confirm_cells(np.array([6], dtype=np.int64))
    assert layer() == [1, 0, 1]
    memory.mark_standing(np.array([5], dtype=np.int64))  # 5 at 3 marks, 7 at 2
    memory.see_floor(np.array([5, 7, 7, 40], dtype=np.int64))  # one test, each cell once
    assert layer() == [1, 0, 0]
    assert memory.standing_marks.reshape(-1)[cells].tolist() == [2, 0, 1]
    memory.see_floor(np.array([5, -1], dtype=np.int64))
    assert layer() == [0, 0, 0] and memory.standing_marks.reshape(-1)[40] == 0
    memory.mark_standing(cells)
    memory.mark_standing(cells)
    memory.reset()
    assert not memory.standing.any() and not memory.standing_marks.any()


def test_only_feet_seen_where_they_stand_keep_their_edge_from_probes() -> None:
    """A foot placed where a frame's floor ended (below a gap the tests could not
    judge: a threshold, tiles past it) stands, but only feet seen at the standing
    thing's own base make a real edge (`FloorMemory.standing_seen`)."""
    memory = FloorMemory(GRID)  # 2 net marks to stand; marks saturate at 3
    seen_cells = np.array([5, 6], dtype=np.int64)
    placed = np.array([7, 8], dtype=np.int64)
    cells = np.concatenate((seen_cells, placed))

    def layers() -> tuple[list[int], list[bool]]:
        standing = memory.standing.reshape(-1)[cells]
        seen = memory.standing_seen().reshape(-1)[cells]
        return [int(v) for v in standing], [bool(v) for v in seen]

    memory.mark_standing(cells, seen_cells=seen_cells)
    assert layers() == ([0, 0, 0, 0], [False] * 4)
    # A seen cell that is no foot of this test is not counted.
    memory.mark_standing(cells, seen_cells=np.array([5, 6, 40], dtype=np.int64))
    assert layers() == ([1, 1, 1, 1], [True, True, False, False])
    assert memory.seen_foot_marks.reshape(-1)[40] == 0
    # Floor seen takes a seen mark with the mark; confirmed floor takes them all.
    memory.see_floor(np.array([5], dtype=np.int64))
    assert layers() == ([0, 1, 1, 1], [False, True, False, False])
    memory.confirm_cells(np.array([6], dtype=np.int64))
    assert layers() == ([0, 0, 1, 1], [False] * 4)
    # Without ``seen_cells`` every foot was seen where it stands.
    memory.mark_standing(np.array([7], dtype=np.int64))
    memory.mark_standing(np.array([7], dtype=np.int64))
    assert layers() == ([0, 0, 1, 1], [False, False, True, False])
    memory.reset()
    assert not memory.seen_foot_marks.any()
