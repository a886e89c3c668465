"""Given-up frontier goals (`app.mapping.ground_map.GivenUpGoals`): stamped once into
world-grid masks, with the same meaning as a disk around each goal."""

from __future__ import annotations

import numpy as np

from app.mapping.frames import GroundGrid
from app.mapping.frontiers import FrontierParams, find_frontiers, footprint_mask, stamp_disk
from app.mapping.ground_map import (
    GIVEN_UP_RADIUS_M,
    PROBE_GIVEN_UP_RADIUS_M,
    GivenUpGoals,
)
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN

GRID = GroundGrid(3.0, 1.5, 0.1, 30, 30)  # x 0..3, y -1.5..1.5


def test_a_stamped_disk_is_the_footprint_of_the_same_point() -> None:
    for xy, radius in [((1.5, 0.0), 0.4), ((2.95, -1.45), 0.8), ((0.05, 1.0), 0.25)]:
        mask = np.zeros(GRID.shape, bool)
        stamp_disk(mask, GRID, xy, radius)
        assert np.array_equal(mask, footprint_mask(GRID, xy, radius))


def test_a_point_off_the_grid_stamps_only_what_its_disk_reaches() -> None:
    mask = np.zeros(GRID.shape, bool)
    stamp_disk(mask, GRID, (10.0, 10.0), 0.4)
    assert not mask.any()
    stamp_disk(mask, GRID, (3.2, 0.0), 0.4)  # 0.2 m beyond the x = 3 edge
    # Row 0 (centres at x 2.95, 0.25 m away) reaches |y| <= 0.31: six centres at
    # +-0.05, 0.15, 0.25; row 1 (x 2.85, 0.35 m away) reaches |y| <= 0.19: four.
    rows = np.nonzero(mask)[0]
    assert np.count_nonzero(rows == 0) == 6 and np.count_nonzero(rows == 1) == 4
    assert mask.sum() == 10


def test_given_up_goals_mark_the_union_of_their_disks() -> None:
    points = [(1.0, 0.5), (1.2, 0.5), (2.5, -1.0)]
    given_up = GivenUpGoals(GRID)
    for xy in points:
        given_up.add(xy)
    seen = np.zeros(GRID.shape, bool)
    no_probe = np.zeros(GRID.shape, bool)
    for xy in points:
        seen |= footprint_mask(GRID, xy, GIVEN_UP_RADIUS_M)
        no_probe |= footprint_mask(GRID, xy, PROBE_GIVEN_UP_RADIUS_M)
    assert np.array_equal(given_up.no_frontier, seen)
    assert np.array_equal(given_up.no_probe, no_probe)
    assert len(given_up) == 3 and given_up.points == points


def centre(row: int, col: int) -> tuple[float, float]:
    return (GRID.x_max_m - (row + 0.5) * GRID.cell_m, GRID.y_max_m - (col + 0.5) * GRID.cell_m)


def cluster_along_row(row: int, cols: range) -> np.ndarray:
    return np.array([(row, c) for c in cols], dtype=np.int64)


def test_a_second_failure_on_one_frontier_gives_up_the_whole_frontier() -> None:
    given_up = GivenUpGoals(GRID)
    frontier = cluster_along_row(10, range(2, 28))  # x 1.95, y 1.25 .. -1.25
    first, second = centre(10, 5), centre(10, 12)
    # The first failure stamps its disks only.
    assert given_up.add(first, frontier) is False
    assert np.array_equal(given_up.no_frontier, footprint_mask(GRID, first, GIVEN_UP_RADIUS_M))
    assert given_up.clusters == 0
    # The second, 0.7 m away on the same frontier (within the 0.8 m of the first):
    # the whole frontier and what lies within the radii of its cells.
    assert given_up.add(second, frontier) is True
    assert given_up.clusters == 1
    # Exactly the cells within 4 cells (0.4 m) of the frontier's cells; the goals' own
    # disks lie inside.
    rows, cols = np.indices(GRID.shape)
    distance2 = np.min([(rows - 10) ** 2 + (cols - c) ** 2 for c in range(2, 28)], axis=0)
    assert np.array_equal(given_up.no_frontier, distance2 <= 16)
    # Frontier goals keep no edge from a probe: the look at it is what comes next.
    assert not given_up.no_probe.any()
    assert len(given_up) == 2


def test_a_frontier_goal_given_up_at_a_doorway_leaves_its_edge_to_a_probe() -> None:
    """The home's runs: the frontier past a doorway (seen through it, never from it) ran
    out of patience, its 0.8 m disk kept the threshold's edge from every probe, and the
    run ended `explored` in the first room. Only a probe given up keeps edges from one."""
    given_up = GivenUpGoals(GRID)
    doorway = cluster_along_row(12, range(12, 18))
    given_up.add(centre(12, 15), doorway)
    assert not given_up.no_probe.any() and given_up.no_frontier[12, 15]
    given_up.add(centre(12, 15))  # then the probe there: its edge stays
    assert np.array_equal(
        given_up.no_probe, footprint_mask(GRID, centre(12, 15), PROBE_GIVEN_UP_RADIUS_M)
    )


def test_failures_on_frontiers_apart_and_finished_probes_give_up_only_their_disks() -> None:
    given_up = GivenUpGoals(GRID)
    near_frontier = cluster_along_row(3, range(0, 10))  # x 2.65, y 1.45 .. 0.55
    far_frontier = cluster_along_row(25, range(20, 30))  # x 0.45, y -0.55 .. -1.45
    # A finished edge probe right on the first frontier is no failure.
    given_up.add(centre(3, 4))
    assert given_up.add(centre(3, 2), near_frontier) is False
    # A failure on a frontier 2 m from the first failure.
    assert given_up.add(centre(25, 25), far_frontier) is False
    assert given_up.clusters == 0
    points = [centre(3, 4), centre(3, 2), centre(25, 25)]
    seen = np.zeros(GRID.shape, bool)
    for xy in points:
        seen |= footprint_mask(GRID, xy, GIVEN_UP_RADIUS_M)
    assert np.array_equal(given_up.no_frontier, seen)


def test_a_given_up_goal_makes_no_frontier_nearby_and_none_on_its_rim() -> None:
    """Floor up to x = 1.5 m, unknown beyond; the goal given up on the frontier's middle:
    the frontier loses the cells within 0.4 m of it and gains none inside the unknown
    (counting the disk as floor put a frontier on its rim, 0.4 m further in)."""
    cells = np.full(GRID.shape, UNKNOWN, np.int8)
    cells[15:] = FREE  # rows 15-29: x < 1.5 m
    given_up = GivenUpGoals(GRID)
    x, y = centre(15, 15)
    given_up.add((x, y + 0.02))  # off the cells' centres: no distance is exactly 0.4 m
    # As shipped: no frontier within 0.5 m of the robot either (it is 1 m from this one).
    params = FrontierParams(exclude_radius_m=0.5)
    found = find_frontiers(cells, GRID, (0.5, 0.0), params, no_frontier=given_up.no_frontier)
    frontier = np.zeros(GRID.shape, bool)
    for cluster in found.clusters:
        frontier[cluster.cells[:, 0], cluster.cells[:, 1]] = True
    expected = np.zeros(GRID.shape, bool)
    expected[15] = True
    expected[15, 11:19] = False  # cells 0.38 m (col 11) to 0.32 m (col 18) away
    assert np.array_equal(frontier, expected)
    assert found.goal is not None and expected[found.goal.cell]


def test_a_probe_that_opened_its_edge_gives_up_that_edge_alone() -> None:
    given_up = GivenUpGoals(GRID)
    edge = cluster_along_row(10, range(12, 17))
    given_up.looked_at(edge)
    rows, cols = np.indices(GRID.shape)
    # The edge and the cells beside it (diagonals too), nothing farther: the next edge
    # two cells on is probed in its turn.
    beside = (np.abs(rows - 10) <= 1) & (cols >= 11) & (cols <= 17)
    assert np.array_equal(given_up.no_probe, beside)
    assert not given_up.no_frontier.any() and len(given_up) == 0


def test_probe_opened_reads_the_edge_on_the_map_the_search_plans_on() -> None:
    from app.config import load_config
    from app.mapping.ground_map import PROBE_OPENED_SHARE, GroundMapper
    from app.sim.setup import camera_model, sim_floor_calibration

    config = load_config(None)
    calibration = sim_floor_calibration(camera_model(config))
    mapper = GroundMapper(calibration, config.mapping, config.camera)
    grid = mapper.grid
    edge = np.array([(200, c) for c in range(190, 200)], dtype=np.int64)
    rows, cols = edge.T
    occupied = np.float32(2 * grid.params.occupied_threshold)
    free = np.float32(2 * grid.params.free_threshold)
    grid.log_odds[rows, cols] = occupied
    assert not mapper.probe_opened(edge)
    assert not mapper.probe_opened(edge[:0])
    opened = int(np.ceil(PROBE_OPENED_SHARE * len(edge)))
    grid.log_odds[rows[:opened], cols[:opened]] = free
    assert mapper.probe_opened(edge)
    grid.log_odds[rows[opened - 1], cols[opened - 1]] = occupied
    assert not mapper.probe_opened(edge)
    # Faded to unknown, a cell counts as what it was last (the remembered map).
    grid.log_odds[rows[:opened], cols[:opened]] = 0.0
    grid.remembered[rows[:opened], cols[:opened]] = OCCUPIED
    assert not mapper.probe_opened(edge)
