"""Given-up frontier goals (`app.mapping.ground_map.GivenUpGoals`): stamped once into
world-grid masks, with the same meaning as a disk around each goal."""

from __future__ import annotations

import numpy as np

from app.mapping.frames import GroundGrid
from app.mapping.frontiers import footprint_mask, stamp_disk
from app.mapping.ground_map import (
    GIVEN_UP_RADIUS_M,
    PROBE_GIVEN_UP_RADIUS_M,
    GivenUpGoals,
)

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
    assert np.array_equal(given_up.seen, seen)
    assert np.array_equal(given_up.no_probe, no_probe)
    assert len(given_up) == 3 and given_up.points == points
