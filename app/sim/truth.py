"""Score a map against the simulated world's ground truth (pure): how it agrees with the
floor plan (`map_truth_scores`), how many of a layer's marks lie at real obstacles
(`marks_near_truth`), and how much of the floor a robot could reach it has
mapped (`reachable_free_mask`, `coverage_reachable`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
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
    truth_free = _truth_free(world, truth_grid, truth_occ)
    truth_occupied = truth_occ == 1
    mapped = _map_classes_at(classes, map_grid, T_plan_map, truth_grid)
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


def marks_near_truth(
    marks: NDArray[np.bool_],
    map_grid: GroundGrid,
    T_plan_map: Pose2D,
    world: World,
) -> float | None:
    """Of the map cells in ``marks`` (a (rows, cols) bool layer on ``map_grid``, such as
    the cells geometry saw standing), the fraction whose centre lies within one cell of
    a wall or box in the plan (the nearness `map_truth_scores` uses for occupied cells),
    looked up at the world's occupancy of the map's cell size. None when nothing is
    marked; marks off the plan's grid count as far from everything."""
    if marks.shape != map_grid.shape:
        raise ValueError(f"marks: expected shape {map_grid.shape}, got {marks.shape}")
    rows, cols = np.nonzero(marks)
    if rows.size == 0:
        return None
    x, y = map_grid.cell_centers()
    plan = T_plan_map.apply(np.column_stack((x[rows, cols], y[rows, cols])))
    truth_grid, truth_occ = world.occupancy(map_grid.cell_m)
    near_truth = _dilate(truth_occ == 1)
    rc = truth_grid.cell_of(plan)
    on_grid = truth_grid.holds(rc)
    near = np.zeros(rows.size, dtype=bool)
    near[on_grid] = near_truth[rc[on_grid, 0], rc[on_grid, 1]]
    return float(near.mean())


def reachable_free_mask(
    world: World,
    cell_m: float,
    robot_radius_m: float,
    start_xy: tuple[float, float] | None = None,
) -> tuple[GroundGrid, NDArray[np.bool_]]:
    """The free floor a disk robot of ``robot_radius_m`` can cover, driving from
    ``start_xy`` (default: the world's start pose), on the grid of
    ``world.occupancy(cell_m)``.

    The robot's centre may stand on a free cell whose centre is at least the radius from
    every wall and box edge (exact distances to the segments); such cells connected to
    the start's cell (8-neighbours) are where it can go. The reachable floor is then
    every free cell (as `map_truth_scores` counts free floor) whose centre lies within
    the radius of one of those: what the robot's body sweeps. That is the floor a
    coverage run must be able to map; the camera sees further (under a table whose legs
    stop the robot, into a gap narrower than it) and is not counted, so a score against
    this mask stays a fraction of what is achievable by driving.

    Returns
    -------
    grid : the occupancy grid at ``cell_m``
    mask : (rows, cols) bool, True on reachable free floor

    Raises
    ------
    ValueError
        The radius is not above ``cell_m / sqrt(2)`` (one step between neighbouring
        centres could then cross a wall), or no cell at or next to the start has the
        clearance.
    """
    if not robot_radius_m > cell_m / math.sqrt(2):
        raise ValueError(
            f"robot_radius_m ({robot_radius_m:g}) must exceed cell_m / sqrt(2) "
            f"({cell_m / math.sqrt(2):.4g}), or a step between cells could cross a wall"
        )
    grid, occ = world.occupancy(cell_m)
    free = _truth_free(world, grid, occ)
    x, y = grid.cell_centers()
    clearance = np.zeros(grid.shape, np.float64)
    clearance[free] = _clearance_m(world.obstacle_segments, x[free], y[free])
    centres = free & (clearance >= robot_radius_m)
    if start_xy is None:
        start_xy = (world.start_pose.x_m, world.start_pose.y_m)
    row, col = grid.cell_of(np.array([start_xy]))[0]
    _, labels = cv2.connectedComponents(centres.astype(np.uint8), connectivity=8)
    seeds = {
        int(labels[r, c])
        for r in range(row - 1, row + 2)
        for c in range(col - 1, col + 2)
        if 0 <= r < grid.rows and 0 <= c < grid.cols and centres[r, c]
    }
    if not seeds:
        raise ValueError(
            f"no cell at or next to the start ({start_xy[0]:g}, {start_xy[1]:g}) is "
            f"{robot_radius_m:g} m from every wall and box"
        )
    reach = np.isin(labels, sorted(seeds))
    # Distance (cells) from every cell centre to the nearest reachable centre.
    to_reach = cv2.distanceTransform(
        np.where(reach, 0, 1).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
    )
    mask: NDArray[np.bool_] = free & (to_reach * cell_m <= robot_radius_m + 1e-9)
    return grid, mask


def coverage_reachable(
    classes: NDArray[np.int8],
    map_grid: GroundGrid,
    T_plan_map: Pose2D,
    world: World,
    robot_radius_m: float,
) -> float:
    """The fraction of the floor the robot can reach (`reachable_free_mask` from the
    world's start, at the map's cell size) that the map calls free; the map is looked up
    as in `map_truth_scores`."""
    truth_grid, reachable = reachable_free_mask(world, map_grid.cell_m, robot_radius_m)
    return coverage_of_mask(classes, map_grid, T_plan_map, truth_grid, reachable)


def coverage_of_mask(
    classes: NDArray[np.int8],
    map_grid: GroundGrid,
    T_plan_map: Pose2D,
    truth_grid: GroundGrid,
    mask: NDArray[np.bool_],
) -> float:
    """The fraction of ``mask`` (on ``truth_grid``, in the plan frame) that the map calls
    free: `coverage_reachable` with the mask computed once (it takes ~0.1 s)."""
    mapped = _map_classes_at(classes, map_grid, T_plan_map, truth_grid)
    n_mask = int(mask.sum())
    return int(((mapped == FREE) & mask).sum()) / n_mask if n_mask else 0.0


def _truth_free(world: World, grid: GroundGrid, occ: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """The plan's free floor on the occupancy grid: inside the world's bounds, touching
    no wall or box."""
    x, y = grid.cell_centers()
    x_min, y_min, x_max, y_max = world.bounds_m
    inside = (x > x_min) & (x < x_max) & (y > y_min) & (y < y_max)
    out: NDArray[np.bool_] = inside & (occ == 0)
    return out


def _map_classes_at(
    classes: NDArray[np.int8], map_grid: GroundGrid, T_plan_map: Pose2D, truth_grid: GroundGrid
) -> NDArray[np.int8]:
    """The map's class (UNKNOWN off the map) at each cell centre of ``truth_grid``, a
    plan-frame grid; the map frame's pose in the plan is ``T_plan_map``."""
    x, y = truth_grid.cell_centers()
    plan_points = np.column_stack((x.ravel(), y.ravel()))
    rc = map_grid.cell_of(T_plan_map.inverse().apply(plan_points))
    on_map = map_grid.holds(rc)
    mapped = np.full(len(rc), UNKNOWN, dtype=np.int8)
    mapped[on_map] = classes[rc[on_map, 0], rc[on_map, 1]]
    return mapped.reshape(truth_grid.shape)


def _clearance_m(
    segments: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance from each point to the nearest of the (N, 4) segments (inf if none)."""
    best = np.full(x.shape, np.inf)
    for x0, y0, x1, y1 in segments:
        ex, ey = x1 - x0, y1 - y0
        t = np.clip(((x - x0) * ex + (y - y0) * ey) / max(ex * ex + ey * ey, 1e-18), 0.0, 1.0)
        np.minimum(best, np.hypot(x - (x0 + t * ex), y - (y0 + t * ey)), out=best)
    return best


def _dilate(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= out[:, :-1].copy()
    out[:, :-1] |= out[:, 1:].copy()
    return out
