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
    # The band moves down and is too thick for a seam (0.5 m); behind it only two
    # unknown cells.
    cells[11:16, :] = OCCUPIED
    cells[16:, :] = FREE
    cells[16, 5:7] = UNKNOWN
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    # The edge before the two unknown cells is only two cells long: no probe
    # (min_cluster_cells 3).
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


def seam(thickness_cells: int = 1) -> np.ndarray:
    """Free floor on both sides of an occupied band at rows 10.. (a threshold the colour
    method calls an edge, seen from both sides), unknown beyond row 20: the frontier
    there is unreachable, and nothing unknown lies right behind the band."""
    cells = np.full(GRID.shape, UNKNOWN, np.int8)
    cells[1:21, 1:29] = FREE
    cells[0, :] = OCCUPIED
    cells[:21, [0, 29]] = OCCUPIED
    cells[10 : 10 + thickness_cells, 1:29] = OCCUPIED
    return cells


def test_a_thin_seam_with_floor_behind_is_probed_from_its_near_side() -> None:
    cells = seam()
    assert find_frontiers(cells, GRID, ROBOT, PARAMS).reason == "no reachable frontier"
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool))
    goal = search.goal
    assert goal is not None and goal.probe and search.reason == ""
    # Row 9 is within the inflation radius of the band: row 8 is the last cell the
    # robot can drive to, straight below it.
    assert goal.cell == (8, 14)
    assert tuple(goal.path_cells[0]) == (4, 14) and tuple(goal.path_cells[-1]) == goal.cell
    assert abs(goal.path_length_m - 0.4) < 1e-9


def test_the_thinnest_part_of_a_seam_is_crossed() -> None:
    cells = seam(thickness_cells=3)
    cells[11:13, 20:26] = FREE  # one cell thick here, 0.3 m elsewhere
    goal = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=np.ones(GRID.shape, bool)).goal
    assert goal is not None and goal.probe
    # It heads for the thin part (columns 20-25), not straight down (column 14): it
    # leaves the drivable floor two columns before it and crosses the inflated row 9
    # diagonally.
    assert goal.cell == (8, 18)


def test_no_seam_probe_through_a_thick_band_a_standing_one_or_where_the_robot_stands() -> None:
    probe_all = np.ones(GRID.shape, bool)
    thick = seam(thickness_cells=5)  # 0.5 m: more than MAX_SEAM_M
    assert find_frontiers(thick, GRID, ROBOT, PARAMS, probe_cells=probe_all).goal is None
    standing = probe_all.copy()
    standing[10, :] = False  # parallax saw the band stand
    assert find_frontiers(seam(), GRID, ROBOT, PARAMS, probe_cells=standing).goal is None
    at_the_seam = (2.15, 0.05)  # cell (8, 14): the look was had from here
    assert find_frontiers(seam(), GRID, at_the_seam, PARAMS, probe_cells=probe_all).goal is None


def test_a_threshold_between_standing_jambs_is_crossed_where_nothing_stands() -> None:
    cells = seam()
    jambs = np.zeros(GRID.shape, bool)
    jambs[10, 1:11] = jambs[10, 19:29] = True  # the doorway is columns 11-18
    # Edge probes keep a margin (here three cells) around what stands: the whole
    # threshold lies within it.
    probe_cells = np.ones(GRID.shape, bool)
    probe_cells[7:14, :] = False
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=probe_cells)
    assert search.goal is None
    search = find_frontiers(cells, GRID, ROBOT, PARAMS, probe_cells=probe_cells, seam_cells=~jambs)
    assert search.goal is not None and search.goal.probe
    assert search.goal.cell == (8, 14)
