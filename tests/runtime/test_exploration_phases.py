"""Exploration that finishes: the phase logic (`app.runtime.exploration`) and the path
home (`app.mapping.frontiers.path_to_point`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.frontiers import (
    REASON_NO_REACHABLE,
    REASON_OUTSIDE_MAP,
    FrontierParams,
    find_frontiers,
    path_to_point,
)
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN
from app.runtime.exploration import CoverageClock, Exploration, Phase

GRID = GroundGrid(2.0, 1.0, 0.1, 20, 20)  # x 0..2, y -1..1
PARAMS = FrontierParams(
    robot_radius_m=0.05, inflation_radius_m=0.05, exclude_radius_m=0.05, min_cluster_cells=2
)
HOME = Pose2D(1.0, 0.0, 0.0)


def closed_room() -> np.ndarray:
    cells = np.full(GRID.shape, FREE, np.int8)
    cells[[0, -1], :] = OCCUPIED
    cells[:, [0, -1]] = OCCUPIED
    return cells


def search_at(cells: np.ndarray, xy: tuple[float, float]):  # type: ignore[no-untyped-def]
    return find_frontiers(cells, GRID, xy, PARAMS)


def nothing_left():  # type: ignore[no-untyped-def]
    return search_at(closed_room(), (1.0, 0.0))


def with_frontier():  # type: ignore[no-untyped-def]
    cells = closed_room()
    cells[1:6, 1:6] = UNKNOWN
    return search_at(cells, (1.0, 0.0))


def explorer(**kwargs: float) -> Exploration:
    settings = {"explored_after_s": 5.0, "home_tolerance_m": 0.3, "return_timeout_s": 60.0}
    settings.update(kwargs)
    exploration = Exploration(**settings)  # type: ignore[arg-type]
    exploration.set_home(HOME)
    return exploration


def test_nothing_left_for_long_enough_sends_the_robot_home() -> None:
    exploration = explorer()
    away = Pose2D(1.8, 0.8, 0.0)
    assert exploration.observe(nothing_left(), 0.0, away, home_reachable=True) is None
    assert exploration.observe(nothing_left(), 4.9, away, home_reachable=True) is None
    change = exploration.observe(nothing_left(), 5.0, away, home_reachable=True)
    assert change is not None and change.phase is Phase.RETURNING
    assert exploration.phase is Phase.RETURNING


def test_a_frontier_in_between_restarts_the_wait() -> None:
    exploration = explorer()
    away = Pose2D(1.8, 0.8, 0.0)
    exploration.observe(nothing_left(), 0.0, away, home_reachable=True)
    exploration.observe(with_frontier(), 3.0, away, home_reachable=True)
    assert exploration.observe(nothing_left(), 6.0, away, home_reachable=True) is None
    assert exploration.observe(nothing_left(), 11.0, away, home_reachable=True) is not None


def test_outside_the_map_is_not_the_end_of_exploring() -> None:
    exploration = explorer()
    outside = search_at(closed_room(), (50.0, 50.0))
    assert outside.reason == REASON_OUTSIDE_MAP
    for t in (0.0, 10.0, 20.0):
        assert exploration.observe(outside, t, HOME, home_reachable=True) is None
    assert exploration.phase is Phase.EXPLORING


def test_arriving_home_finishes_and_a_new_frontier_on_the_way_explores_again() -> None:
    exploration = explorer(explored_after_s=0.0)
    exploration.observe(nothing_left(), 0.0, Pose2D(1.8, 0.8, 0.0), home_reachable=True)
    change = exploration.observe(with_frontier(), 1.0, Pose2D(1.5, 0.5, 0.0), home_reachable=True)
    assert change is not None and change.phase is Phase.EXPLORING
    exploration.observe(nothing_left(), 2.0, Pose2D(1.5, 0.5, 0.0), home_reachable=True)
    assert exploration.phase is Phase.RETURNING
    assert (
        exploration.observe(nothing_left(), 3.0, Pose2D(1.4, 0.0, 0.0), home_reachable=True) is None
    )
    # 0.27 m: within the 0.3 m tolerance but not the 0.05 m stopping margin inside it.
    assert (
        exploration.observe(nothing_left(), 3.5, Pose2D(1.25, 0.1, 0.0), home_reachable=True)
        is None
    )
    change = exploration.observe(nothing_left(), 4.0, Pose2D(1.2, 0.1, 0.0), home_reachable=True)
    assert change is not None and change.phase is Phase.EXPLORED
    assert "back at the start" in change.reason and exploration.explored_at_s == 4.0
    # Finished stays finished until a restart.
    assert exploration.observe(with_frontier(), 5.0, HOME, home_reachable=True) is None
    exploration.restart()
    assert exploration.phase is Phase.EXPLORING


def test_no_way_home_or_too_long_finishes_where_the_robot_is() -> None:
    far = Pose2D(1.8, 0.8, 0.0)
    exploration = explorer(explored_after_s=2.0)
    exploration.observe(nothing_left(), 0.0, far, home_reachable=True)
    exploration.observe(nothing_left(), 2.0, far, home_reachable=True)
    assert exploration.phase is Phase.RETURNING
    assert exploration.observe(nothing_left(), 3.0, far, home_reachable=False) is None
    change = exploration.observe(nothing_left(), 5.0, far, home_reachable=False)
    assert change is not None and change.phase is Phase.EXPLORED and "no path" in change.reason

    slow = explorer(explored_after_s=0.0, return_timeout_s=30.0)
    slow.observe(nothing_left(), 0.0, far, home_reachable=True)
    assert slow.observe(nothing_left(), 29.0, far, home_reachable=True) is None
    change = slow.observe(nothing_left(), 30.0, far, home_reachable=True)
    assert change is not None and change.phase is Phase.EXPLORED and "not back" in change.reason


def test_without_return_home_it_finishes_where_it_is() -> None:
    exploration = Exploration(explored_after_s=0.0, home_tolerance_m=0.3, return_home=False)
    exploration.set_home(HOME)
    change = exploration.observe(nothing_left(), 0.0, Pose2D(1.8, 0.8, 0.0), home_reachable=True)
    assert change is not None and change.phase is Phase.EXPLORED


def test_home_is_the_first_start() -> None:
    exploration = Exploration(explored_after_s=1.0, home_tolerance_m=0.3)
    exploration.set_home(Pose2D(0.5, 0.2, 1.0))
    exploration.set_home(Pose2D(3.0, 3.0, 0.0))
    assert exploration.home_xy == (0.5, 0.2)
    assert exploration.home_distance_m(Pose2D(0.5, 0.5, 0.0)) == pytest.approx(0.3)


def test_path_to_point_goes_around_a_wall_to_the_nearest_reachable_cell() -> None:
    cells = closed_room()
    cells[1:15, 10] = OCCUPIED  # a wall from the top, open at the bottom rows 15..18
    search = search_at(cells, (1.75, -0.55))  # left of the wall
    goal = path_to_point(search, GRID, (1.75, 0.45), 0.05)  # right of it
    assert goal is not None
    rows = goal.path_cells[:, 0]
    assert rows.max() >= 15  # it went round the wall's open end
    target_cell = tuple(int(v) for v in GRID.cell_of(np.array([[1.75, 0.45]]))[0])
    assert tuple(int(v) for v in goal.path_cells[-1]) == goal.cell == target_cell
    assert goal.path_length_m > 1.0


def test_path_to_point_to_an_unreachable_target_is_none_unless_a_cell_is_near() -> None:
    cells = closed_room()
    cells[:, 10] = OCCUPIED  # the room split in two
    search = search_at(cells, (1.0, -0.55))
    assert path_to_point(search, GRID, (1.0, 0.55), 0.2) is None
    near = path_to_point(search, GRID, (1.0, 0.02), 0.2)  # on the wall: a cell beside it
    assert near is not None and near.xy[1] < -0.05 and near.score <= 0.2
    with pytest.raises(ValueError, match="tolerance_m"):
        path_to_point(search, GRID, (1.0, 0.0), -1.0)


def test_coverage_clock_keeps_the_first_time_each_mark_was_reached() -> None:
    clock = CoverageClock()
    assert clock.summary() == {"50": None, "90": None}
    clock.sample(0.3, 10.0)
    clock.sample(0.55, 20.0)
    clock.sample(0.45, 30.0)  # a map can lose coverage: the first time stays
    clock.sample(0.92, 40.04)
    assert clock.summary() == {"50": 20.0, "90": 40.0}


def test_an_unreached_no_reachable_reason_counts_as_finished() -> None:
    cells = closed_room()
    cells[1:3, 1:3] = UNKNOWN  # behind the walls below, with a free ring around it
    cells[4, 1:5] = OCCUPIED
    cells[1:5, 4] = OCCUPIED
    search = search_at(cells, (1.0, 0.0))
    assert search.reason == REASON_NO_REACHABLE
    exploration = explorer(explored_after_s=0.0)
    change = exploration.observe(search, 0.0, Pose2D(1.8, 0.8, 0.0), home_reachable=True)
    assert change is not None and change.phase is Phase.RETURNING
