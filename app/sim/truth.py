"""Score a map against the simulated world's ground truth (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN
from app.sim.world import World


@dataclass(frozen=True)
class MapTruthScores:
    """How a map agrees with the floor plan.

    Attributes
    ----------
    coverage_ratio : the world's free floor area that the map holds as free, over all of it
    map_iou : over the cells the map has seen (free or occupied): IoU of "free" in the map
        and in the plan (free cells the map calls occupied and occupied cells it calls free
        both count against it)
    free_precision : of the cells the map calls free, the fraction that are free in the plan
    occupied_near_truth : of the cells the map calls occupied, the fraction within one cell
        of a wall or box in the plan
    seen_m2, free_truth_m2 : areas behind the ratios
    """

    coverage_ratio: float
    map_iou: float
    free_precision: float
    occupied_near_truth: float
    seen_m2: float
    free_truth_m2: float

    def as_dict(self) -> dict[str, float]:
        return {k: round(float(v), 4) for k, v in self.__dict__.items()}


def map_truth_scores(
    classes: NDArray[np.int8],
    map_grid: GroundGrid,
    T_plan_map: Pose2D,
    world: World,
) -> MapTruthScores:
    """Compare ``classes`` (-1/0/1 on ``map_grid``, in the map frame whose pose in the
    plan frame is ``T_plan_map``) with the world's occupancy at the map's cell size.

    The plan's free floor is every cell inside the world's bounds that no wall or box
    touches; map cells are looked up at the plan cells' centres.
    """
    truth_grid, truth_occ = world.occupancy(map_grid.cell_m)
    x, y = truth_grid.cell_centers()
    x_min, y_min, x_max, y_max = world.bounds_m
    inside = (x > x_min) & (x < x_max) & (y > y_min) & (y < y_max)
    truth_free = inside & (truth_occ == 0)
    truth_occupied = truth_occ == 1
    plan_points = np.column_stack((x.ravel(), y.ravel()))
    map_points = T_plan_map.inverse().apply(plan_points)
    rc = map_grid.cell_of(map_points)
    on_map = (
        (rc[:, 0] >= 0) & (rc[:, 0] < map_grid.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < map_grid.cols)
    )
    mapped = np.full(len(rc), UNKNOWN, dtype=np.int8)
    mapped[on_map] = classes[rc[on_map, 0], rc[on_map, 1]]
    mapped = mapped.reshape(truth_grid.shape)
    map_free = mapped == FREE
    map_occ = mapped == OCCUPIED
    seen = mapped != UNKNOWN
    cell_area = map_grid.cell_m**2
    n_truth_free = int(truth_free.sum())
    union = int(((map_free | truth_free) & seen).sum())
    both = int((map_free & truth_free).sum())
    near_truth = _dilate(truth_occupied)
    return MapTruthScores(
        coverage_ratio=both / n_truth_free if n_truth_free else 0.0,
        map_iou=both / union if union else 0.0,
        free_precision=both / int(map_free.sum()) if map_free.any() else 0.0,
        occupied_near_truth=float((map_occ & near_truth).sum()) / int(map_occ.sum())
        if map_occ.any()
        else 0.0,
        seen_m2=float(seen.sum()) * cell_area,
        free_truth_m2=n_truth_free * cell_area,
    )


def _dilate(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= out[:, :-1].copy()
    out[:, :-1] |= out[:, 1:].copy()
    return out
