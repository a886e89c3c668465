"""Frontiers of a classified occupancy grid and the exploration goal among them.

A *frontier cell* is a free cell next to an unknown one (4-neighbours by default, or 8):
standing there, the camera would see unexplored floor. Frontier cells are clustered into
8-connected components; components smaller than ``min_cluster_cells`` are dropped (gaps
between noisy cells, too narrow to matter).

Reachability and path lengths come from a Dijkstra search from the robot's cell over the
*traversable* cells, with 8-neighbour moves costing 1 or sqrt(2) cells (octile lengths)
and no corner cutting (a diagonal move needs both cells beside it traversable, so a
diagonal wall of single cells is not a door). Traversable cells are free cells farther
than ``inflation_radius_m`` from every occupied cell (the robot's centre must stay that
far from obstacles), plus the robot's *footprint*: the cells within ``robot_radius_m`` of
its position (always including its own cell) that are not occupied. The footprint counts
as known free even when the map has no evidence there, because the camera never sees
under the robot, and it is not a frontier itself; it also lets the search start when the
robot stands in an inflated zone. Given its *track* (the cells its centre has crossed,
`app.mapping.floor_memory`), the free cells on it are traversable too where they are
farther than ``robot_radius_m`` from every occupied cell (the body's clearance without
the inflation's margin): the robot fitted there, so obstacles the map put just inside
the inflation beside a doorway it came through do not shut the way back.

**Clearance.** The shortest path hugs every obstacle at exactly ``inflation_radius_m``,
which leaves the robot's side a centimetre or two from a box once map cells, the pose
and the steering's tracking have each had their error. With ``clearance_cost`` > 0 a
move into a cell whose centre is ``d`` from the nearest occupied cell costs its length
times ``1 + clearance_cost * s**2``, ``s = (preferred - d) / (preferred - inflation)``
clipped to [0, 1] (``preferred`` = ``clearance_preferred_m``): paths keep to the middle
of open floor and pass obstacles wide where there is room, and still take a narrow
doorway when it is the only way (the costmap inflation of ROS navigation, as a cost).
Path lengths and the goal's score are then these weighted lengths (metres plus the
detour a tight passage is worth).

Each kept cluster gets its *representative cell*: its reachable cell with the shortest
path from the robot (ties: first in raster order), with that path's length. The **goal**
is the reachable cluster with the lowest score

    ``score = path_length_m + size_penalty_m * min_cluster_cells / size_cells
              + turn_penalty_m_per_rad * |bearing error|``

(ties: larger cluster, then lower index), so with the default ``size_penalty_m = 0`` it
is the nearest reachable frontier; a positive penalty trades distance for larger openings.
The bearing error is the angle between the robot's heading (when given) and the straight
line to the representative cell: a robot that turns slowly prefers what lies ahead.
The goal's cell is that cluster's representative cell, and the goal carries the path to it.

**Edge probes.** A floor the colour method has not met (a rug, the kitchen's tiles past a
threshold) ends the floor in every frame, and the map keeps its edge as a wall; a plank
seam or a rug's border leaves a thin false wall across floor the map does see. Either
way the search finds no reachable frontier although the home goes on. Given
``probe_cells`` (occupied cells that geometry has not seen standing, from the caller),
the search, when no frontier is reachable, asks where a frontier would be reachable *if
those unproven edges were floor*: it searches again on that relaxed map (other obstacles
and their inflation kept; a move into a cell the true map cannot reach costs
``PROBE_CROSSING_COST`` more, so the way that stays longest on reachable floor wins) for
the nearest frontier cluster of at least ``min_cluster_cells`` cells that the true map
cannot reach. Where the path to it first leaves the reachable floor, the edge it meets
(its cells within ``PROBE_EDGE_SPAN_M``) is the target; the goal is the reachable cell
within ``inflation_radius_m`` + two cells of that target that lies nearest the meeting
point (then nearest by path): it stays put while the robot drives there. Driving
at it gives the motion-parallax test its baseline: a flat edge becomes known floor (its
colour learned, and free evidence wears its false wall away), a standing one is marked
so, and the caller leaves it out of ``probe_cells`` from then on. The goal's ``probe``
is True and its ``edge_cells`` are the target (the caller reads them on arrival: an
edge the look opened is given up alone, and the next edge past it is probed in turn).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from app.mapping.frames import GroundGrid
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN, check_grid, check_xy

REASON_NO_FRONTIER = "no frontier"
"""`FrontierSearch.reason`: no cluster of at least ``min_cluster_cells`` frontier cells."""
REASON_NO_REACHABLE = "no reachable frontier"
"""`FrontierSearch.reason`: clusters exist but none has a traversable path from the robot."""
REASON_OUTSIDE_MAP = "robot outside the map"
"""`FrontierSearch.reason`: the robot's position is not on the grid."""

PROBE_CROSSING_COST = 4.0
"""Edge probes' relaxed search: the extra step weight of a cell the true map cannot reach
(an unproven edge, its inflation, the floor behind it), so the way that crosses where the
frontier is nearest beats a detour over the unproven side."""
PROBE_EDGE_SPAN_M = 0.3
"""Edge probes: the unproven edge cells this close to where the relaxed path meets the
edge are the probe's target (one look covers about this much of an edge)."""


@dataclass(frozen=True)
class FrontierParams:
    """Parameters of the frontier search.

    Attributes
    ----------
    min_cluster_cells : int >= 1, smaller clusters are dropped.
    inflation_radius_m : float >= 0, least distance of the robot's centre from occupied
        cells (free cells closer than this are not traversable).
    robot_radius_m : float >= 0, radius of the footprint treated as known and traversable.
    size_penalty_m : float >= 0, see the module docstring's score.
    frontier_adjacency : 4 or 8, which unknown neighbours make a free cell a frontier.
    turn_penalty_m_per_rad : float >= 0, see the module docstring's score.
    clearance_preferred_m : float >= 0, centre distance from obstacles below which moves
        cost more (module docstring); no effect unless above ``inflation_radius_m``.
    clearance_cost : float >= 0, the extra cost of a move at ``inflation_radius_m``, as a
        multiple of its length (0: plain shortest paths).
    exclude_radius_m : float >= 0, frontier cells within this distance of the robot are
        ignored: the camera cannot see the floor right beside the robot, so turning to
        look there never resolves them.
    """

    min_cluster_cells: int = 4
    inflation_radius_m: float = 0.15
    robot_radius_m: float = 0.12
    size_penalty_m: float = 0.0
    frontier_adjacency: int = 4
    exclude_radius_m: float = 0.0
    turn_penalty_m_per_rad: float = 0.0
    clearance_preferred_m: float = 0.0
    clearance_cost: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.min_cluster_cells, int) or self.min_cluster_cells < 1:
            raise ValueError(
                f"FrontierParams.min_cluster_cells: must be an int >= 1, got"
                f" {self.min_cluster_cells!r}"
            )
        for name in (
            "inflation_radius_m",
            "robot_radius_m",
            "size_penalty_m",
            "exclude_radius_m",
            "turn_penalty_m_per_rad",
            "clearance_preferred_m",
            "clearance_cost",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and 0 <= value < math.inf):
                raise ValueError(f"FrontierParams.{name}: must be finite and >= 0, got {value!r}")
        if self.frontier_adjacency not in (4, 8):
            raise ValueError(
                "FrontierParams.frontier_adjacency: must be 4 or 8, got"
                f" {self.frontier_adjacency!r}"
            )


@dataclass(frozen=True, eq=False)
class FrontierCluster:
    """One 8-connected cluster of frontier cells.

    Attributes
    ----------
    index : int, position in `FrontierSearch.clusters`.
    cells : (size, 2) int64 (row, col) of its cells, in raster order.
    centroid_xy : (x, y) world metres, mean of its cells' centres (may lie off the cluster).
    representative_cell : (row, col) of its nearest reachable cell, or None if unreachable.
    representative_xy : (x, y) world metres of that cell's centre, or None.
    path_length_m : float, (weighted) path length to the representative cell (inf if
        unreachable).
    """

    index: int
    cells: NDArray[np.int64] = field(repr=False)
    centroid_xy: tuple[float, float]
    representative_cell: tuple[int, int] | None
    representative_xy: tuple[float, float] | None
    path_length_m: float

    @property
    def size_cells(self) -> int:
        return int(self.cells.shape[0])

    @property
    def reachable(self) -> bool:
        return self.representative_cell is not None


@dataclass(frozen=True, eq=False)
class FrontierGoal:
    """The chosen exploration goal.

    Attributes
    ----------
    cluster_index : int, into `FrontierSearch.clusters`.
    cell : (row, col) world-grid cell to drive to.
    xy : (x, y) world metres of its centre.
    path_length_m : float, (weighted) octile path length from the robot's cell.
    score : float, see the module docstring.
    path_cells : (n, 2) int64 (row, col) from the robot's cell to ``cell``, inclusive.
    probe : the goal looks at an edge rather than a frontier (module docstring).
    edge_cells : for a probe, (m, 2) int64 (row, col) of the edge cells it looks at;
        None otherwise.
    """

    cluster_index: int
    cell: tuple[int, int]
    xy: tuple[float, float]
    path_length_m: float
    score: float
    path_cells: NDArray[np.int64] = field(repr=False)
    probe: bool = False
    edge_cells: NDArray[np.int64] | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class FrontierSearch:
    """Result of `find_frontiers`.

    Attributes
    ----------
    clusters : tuple of the kept FrontierCluster (at least ``min_cluster_cells`` each).
    dropped_clusters : int, clusters dropped as too small.
    goal : FrontierGoal, or None with ``reason``.
    reason : str, "" when there is a goal, else one of ``REASON_NO_FRONTIER``,
        ``REASON_NO_REACHABLE``, ``REASON_OUTSIDE_MAP``.
    distance_m : (rows, cols) float64 (weighted) path length from the robot's cell, inf where not
        reachable (all inf when the robot is outside the map).
    parent : (rows * cols,) int64 predecessors of the paths behind ``distance_m``
        (`trace_path`; `path_to_point` reads them).
    """

    clusters: tuple[FrontierCluster, ...]
    dropped_clusters: int
    goal: FrontierGoal | None
    reason: str
    distance_m: NDArray[np.float64] = field(repr=False)
    parent: NDArray[np.int64] = field(repr=False)


def check_classes(cells: NDArray[np.int8], grid: GroundGrid) -> None:
    """Raise ValueError unless ``cells`` is an int8 raster of ``grid``'s shape holding only
    ``UNKNOWN``, ``FREE`` and ``OCCUPIED``."""
    if not isinstance(cells, np.ndarray) or cells.dtype != np.int8:
        kind = cells.dtype if isinstance(cells, np.ndarray) else type(cells).__name__
        raise ValueError(f"cells: expected an int8 array (OccupancyGrid.classify), got {kind}")
    if cells.shape != grid.shape:
        raise ValueError(f"cells: expected shape {grid.shape} (grid), got {cells.shape}")
    if cells.size and (int(cells.min()) < UNKNOWN or int(cells.max()) > OCCUPIED):
        raise ValueError(
            f"cells: values must be UNKNOWN ({UNKNOWN}), FREE ({FREE}) or OCCUPIED ({OCCUPIED})"
        )


def disk_kernel(radius_cells: float) -> NDArray[np.uint8]:
    """(2k + 1, 2k + 1) uint8, 1 where a cell's centre is within ``radius_cells`` of the
    middle one's (k = floor(radius_cells)).

    >>> disk_kernel(1.0).tolist()
    [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
    """
    k = math.floor(radius_cells + 1e-9)
    d = np.arange(-k, k + 1)
    inside = d[:, None] ** 2 + d[None, :] ** 2 <= radius_cells**2 + 1e-9
    return inside.astype(np.uint8)


def inflate_obstacles(occupied: NDArray[np.bool_], radius_cells: float) -> NDArray[np.bool_]:
    """(rows, cols) bool: cells whose centre is within ``radius_cells`` of an occupied one's
    (the occupied cells included)."""
    if radius_cells < 1:
        return occupied.copy()
    dilated = cv2.dilate(occupied.astype(np.uint8), disk_kernel(radius_cells))
    return np.asarray(dilated, dtype=bool)


def _disk_window(
    grid: GroundGrid, xy: tuple[float, float], cell: tuple[int, int], radius_m: float
) -> tuple[slice, slice, NDArray[np.bool_]] | None:
    """The rows and columns around ``xy`` (in grid ``cell``) that can hold cells whose
    centre is within ``radius_m`` of it, and which of them do; None when none lies on
    the grid."""
    x, y = xy
    row, col = cell
    k = math.ceil(radius_m / grid.cell_m) + 1
    r0, r1 = max(row - k, 0), min(row + k + 1, grid.rows)
    c0, c1 = max(col - k, 0), min(col + k + 1, grid.cols)
    if r0 >= r1 or c0 >= c1:
        return None
    xs = grid.x_max_m - (np.arange(r0, r1) + 0.5) * grid.cell_m
    ys = grid.y_max_m - (np.arange(c0, c1) + 0.5) * grid.cell_m
    near = (xs[:, None] - x) ** 2 + (ys[None, :] - y) ** 2 <= radius_m**2
    return slice(r0, r1), slice(c0, c1), near


def stamp_disk(
    mask: NDArray[np.bool_], grid: GroundGrid, xy: tuple[float, float], radius_m: float
) -> None:
    """Set, in place, the cells of ``mask`` whose centre is within ``radius_m`` of ``xy``
    plus the cell containing it (if on the grid); touches only the disk's window."""
    (row, col) = grid.cell_of(np.array([xy], dtype=np.float64))[0]
    row, col = int(row), int(col)
    window = _disk_window(grid, xy, (row, col), radius_m)
    if window is not None:
        rows, cols, near = window
        mask[rows, cols] |= near
    if 0 <= row < grid.rows and 0 <= col < grid.cols:
        mask[row, col] = True


def footprint_mask(
    grid: GroundGrid, robot_xy: tuple[float, float], radius_m: float
) -> NDArray[np.bool_]:
    """(rows, cols) bool: cells whose centre is within ``radius_m`` of ``robot_xy``, plus
    the cell containing it (if on the grid)."""
    mask = np.zeros(grid.shape, dtype=bool)
    stamp_disk(mask, grid, robot_xy, radius_m)
    return mask


def frontier_mask(
    cells: NDArray[np.int8], *, adjacency: int = 4, exclude: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """(rows, cols) bool: ``FREE`` cells with an ``UNKNOWN`` 4- (or 8-) neighbour, minus
    ``exclude``. Cells beyond the raster's edge are not unknown.

    >>> c = np.array([[-1, -1, -1], [0, 0, 0], [0, 0, 1]], np.int8)
    >>> frontier_mask(c).astype(int).tolist()
    [[0, 0, 0], [1, 1, 1], [0, 0, 0]]
    """
    if adjacency not in (4, 8):
        raise ValueError(f"adjacency: must be 4 or 8, got {adjacency}")
    unknown = np.pad(cells == UNKNOWN, 1, constant_values=False)
    rows, cols = cells.shape
    near = np.zeros(cells.shape, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if (dr == 0 and dc == 0) or (adjacency == 4 and dr != 0 and dc != 0):
                continue
            near |= unknown[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
    mask: NDArray[np.bool_] = (cells == FREE) & near
    if exclude is not None:
        mask &= ~exclude
    return mask


@numba.njit(cache=True, nogil=True)
def _dijkstra(
    traversable: NDArray[np.bool_], step_weight: NDArray[np.float64], start: int, cell_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    rows, cols = traversable.shape
    dist = np.full(rows * cols, np.inf)
    parent = np.full(rows * cols, -1, dtype=np.int64)
    dist[start] = 0.0
    diagonal = math.sqrt(2.0) * cell_m
    heap = [(0.0, start)]
    while len(heap) > 0:
        d, idx = heapq.heappop(heap)
        if d > dist[idx]:
            continue
        r = idx // cols
        c = idx - r * cols
        for dr in range(-1, 2):
            nr = r + dr
            if nr < 0 or nr >= rows:
                continue
            for dc in range(-1, 2):
                nc = c + dc
                if (dr == 0 and dc == 0) or nc < 0 or nc >= cols or not traversable[nr, nc]:
                    continue
                if dr != 0 and dc != 0:
                    if not (traversable[r, nc] and traversable[nr, c]):
                        continue
                    nd = d + diagonal * step_weight[nr, nc]
                else:
                    nd = d + cell_m * step_weight[nr, nc]
                n_idx = nr * cols + nc
                if nd < dist[n_idx]:
                    dist[n_idx] = nd
                    parent[n_idx] = idx
                    heapq.heappush(heap, (nd, n_idx))
    return dist.reshape(rows, cols), parent


def path_distances(
    traversable: NDArray[np.bool_],
    start_cell: tuple[int, int],
    cell_m: float,
    step_weight: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Octile shortest paths over traversable cells from ``start_cell`` (always allowed).

    Parameters
    ----------
    traversable : (rows, cols) bool
    start_cell : (row, col) on the raster.
    cell_m : float > 0, cell size.
    step_weight : (rows, cols) float64 >= 1, a move into a cell costs its length times the
        cell's weight (`clearance_weights`); None: all 1 (plain lengths).

    Returns
    -------
    distance_m : (rows, cols) float64 weighted path length, inf where unreachable.
    parent : (rows * cols,) int64 flat index of each cell's predecessor, -1 for the start
        and unreached cells (see `trace_path`).

    Examples
    --------
    >>> d, _ = path_distances(np.array([[True, False, True]]), (0, 0), 1.0)
    >>> d.tolist()
    [[0.0, inf, inf]]
    """
    if traversable.ndim != 2 or traversable.size == 0:
        raise ValueError(f"traversable: expected a non-empty 2-D array, got {traversable.shape}")
    rows, cols = traversable.shape
    row, col = start_cell
    if not (0 <= row < rows and 0 <= col < cols):
        raise ValueError(f"start_cell: {start_cell} is outside the {rows}x{cols} raster")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m: must be finite and > 0, got {cell_m}")
    if step_weight is None:
        weight = np.ones((rows, cols), dtype=np.float64)
    else:
        if step_weight.shape != traversable.shape:
            raise ValueError(
                f"step_weight: expected shape {traversable.shape}, got {step_weight.shape}"
            )
        weight = np.ascontiguousarray(step_weight, dtype=np.float64)
        if not (np.isfinite(weight).all() and float(weight.min(initial=1.0)) >= 1.0):
            raise ValueError("step_weight: every weight must be finite and >= 1")
    grid = np.ascontiguousarray(traversable, dtype=np.bool_)
    dist, parent = _dijkstra(grid, weight, int(row * cols + col), float(cell_m))
    return dist, parent


def clearance_weights(
    occupied: NDArray[np.bool_],
    cell_m: float,
    inflation_radius_m: float,
    preferred_m: float,
    cost: float,
) -> NDArray[np.float64]:
    """(rows, cols) float64 >= 1: the step weight of each cell (module docstring,
    *Clearance*), from the distance of its centre to the nearest occupied cell's centre.

    >>> w = clearance_weights(np.array([[True, False, False, False, False]]), 1.0, 1.0, 3.0, 2.0)
    >>> w.round(3).tolist()
    [[3.0, 3.0, 1.5, 1.0, 1.0]]
    """
    weight = np.ones(occupied.shape, dtype=np.float64)
    span = preferred_m - inflation_radius_m
    if cost <= 0 or span <= 0 or not occupied.any():
        return weight
    free = np.ascontiguousarray(~occupied, dtype=np.uint8)
    # DIST_MASK_PRECISE: exact Euclidean distances (in cells) to the nearest zero.
    distance_m = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell_m
    shortfall = np.clip((preferred_m - distance_m) / span, 0.0, 1.0)
    weight += cost * shortfall**2
    return weight


def trace_path(parent: NDArray[np.int64], cols: int, cell: tuple[int, int]) -> NDArray[np.int64]:
    """(n, 2) int64 (row, col) from the search's start to ``cell``, inclusive (``cell``
    alone if it is the start or was not reached)."""
    chain = [cell[0] * cols + cell[1]]
    while parent[chain[-1]] >= 0:
        chain.append(int(parent[chain[-1]]))
    flat = np.array(chain[::-1], dtype=np.int64)
    return np.column_stack((flat // cols, flat % cols))


def find_frontiers(
    cells: NDArray[np.int8],
    grid: GroundGrid,
    robot_xy_world: tuple[float, float],
    params: FrontierParams | None = None,
    *,
    robot_heading_rad: float | None = None,
    probe_cells: NDArray[np.bool_] | None = None,
    no_frontier: NDArray[np.bool_] | None = None,
    track: NDArray[np.bool_] | None = None,
) -> FrontierSearch:
    """Frontier clusters of a classified grid and the goal to explore next.

    Parameters
    ----------
    cells : (rows, cols) int8 from `OccupancyGrid.classify` (``UNKNOWN`` -1, ``FREE`` 0,
        ``OCCUPIED`` 1).
    grid : GroundGrid of ``cells`` (the world frame).
    robot_xy_world : (x, y) metres, the robot's position (``T_world_robot.x_m, .y_m``).
    params : FrontierParams
    robot_heading_rad : the robot's heading in the world frame, for the turn penalty.
    probe_cells : (rows, cols) bool, occupied cells whose edge may be probed when no
        frontier is reachable (module docstring); None: no probes.
    no_frontier : (rows, cols) bool, cells that make no frontier (around goals given up).
        They stay what they are: counting them as free floor instead put a new frontier
        on their rim, a step further into the unknown, and the next goal there.
    track : (rows, cols) bool, the cells the robot's centre has crossed: traversable
        where free and clear of obstacles by ``robot_radius_m`` (module docstring);
        None: no track.

    Returns
    -------
    FrontierSearch: the kept clusters, the goal (or None and the reason), and the path
    lengths from the robot.
    """
    params = params if params is not None else FrontierParams()
    check_grid(grid)
    check_classes(cells, grid)
    robot_xy = check_xy(robot_xy_world, "robot_xy_world")
    cell_m = grid.cell_m

    footprint = footprint_mask(grid, robot_xy, params.robot_radius_m)
    occupied = cells == OCCUPIED
    known = cells.copy()
    known[footprint & ~occupied] = FREE
    excluded = footprint if no_frontier is None else footprint | no_frontier
    if params.exclude_radius_m > params.robot_radius_m:
        excluded = excluded | footprint_mask(grid, robot_xy, params.exclude_radius_m)
    frontier = frontier_mask(known, adjacency=params.frontier_adjacency, exclude=excluded)
    if track is not None and track.shape != cells.shape:
        raise ValueError(f"track: expected shape {cells.shape}, got {track.shape}")
    # The footprint is crossed whatever the inflation; the free track with the body's
    # clearance alone.
    fitted = footprint
    if track is not None:
        body = inflate_obstacles(occupied, params.robot_radius_m / cell_m)
        fitted = footprint | (track & (known == FREE) & ~body)
    traversable, weight = _traversable(known == FREE, occupied, fitted, cell_m, params)

    (row, col) = (int(v) for v in grid.cell_of(np.array([robot_xy]))[0])
    on_map = 0 <= row < grid.rows and 0 <= col < grid.cols
    if on_map:
        distance, parent = path_distances(traversable, (row, col), cell_m, weight)
    else:
        distance = np.full(grid.shape, np.inf)
        parent = np.full(cells.size, -1, dtype=np.int64)

    labels, n_labels = ndimage.label(frontier, structure=np.ones((3, 3), dtype=bool))
    flat_idx = np.flatnonzero(labels)
    flat_lab = labels.ravel()[flat_idx]
    order = np.argsort(flat_lab, kind="stable")
    flat_idx, flat_lab = flat_idx[order], flat_lab[order]
    sizes = np.bincount(flat_lab, minlength=n_labels + 1)
    starts = np.concatenate(([0], np.cumsum(sizes[1:])))
    flat_dist = distance.ravel()

    clusters: list[FrontierCluster] = []
    dropped = 0
    for label in range(1, n_labels + 1):
        size = int(sizes[label])
        if size < params.min_cluster_cells:
            dropped += 1
            continue
        members = flat_idx[starts[label - 1] : starts[label - 1] + size]
        rc = np.column_stack((members // grid.cols, members % grid.cols)).astype(np.int64)
        xs = grid.x_max_m - (rc[:, 0] + 0.5) * cell_m
        ys = grid.y_max_m - (rc[:, 1] + 0.5) * cell_m
        centroid = (float(xs.mean()), float(ys.mean()))
        member_dist = flat_dist[members]
        best = int(np.argmin(member_dist))
        if math.isfinite(member_dist[best]):
            rep_cell: tuple[int, int] | None = (int(rc[best, 0]), int(rc[best, 1]))
            rep_xy: tuple[float, float] | None = (float(xs[best]), float(ys[best]))
            length = float(member_dist[best])
        else:
            rep_cell, rep_xy, length = None, None, math.inf
        clusters.append(FrontierCluster(len(clusters), rc, centroid, rep_cell, rep_xy, length))

    def result(goal: FrontierGoal | None, reason: str) -> FrontierSearch:
        return FrontierSearch(tuple(clusters), dropped, goal, reason, distance, parent)

    if not on_map:
        return result(None, REASON_OUTSIDE_MAP)
    reachable = [c for c in clusters if c.representative_cell is not None]
    if not reachable or not clusters:
        probe = (
            None
            if probe_cells is None
            else _probe_goal(
                known, grid, probe_cells, distance, parent, params, (row, col), fitted, excluded
            )
        )
        if probe is not None:
            return result(probe, "")
        return result(None, REASON_NO_REACHABLE if clusters else REASON_NO_FRONTIER)

    def score(c: FrontierCluster) -> float:
        value = c.path_length_m + params.size_penalty_m * params.min_cluster_cells / c.size_cells
        if robot_heading_rad is not None and c.representative_xy is not None:
            dx, dy = c.representative_xy[0] - robot_xy[0], c.representative_xy[1] - robot_xy[1]
            if dx or dy:
                bearing = math.remainder(math.atan2(dy, dx) - robot_heading_rad, math.tau)
                value += params.turn_penalty_m_per_rad * abs(bearing)
        return value

    chosen = min(reachable, key=lambda c: (score(c), -c.size_cells, c.index))
    assert chosen.representative_cell is not None and chosen.representative_xy is not None
    goal = FrontierGoal(
        cluster_index=chosen.index,
        cell=chosen.representative_cell,
        xy=chosen.representative_xy,
        path_length_m=chosen.path_length_m,
        score=score(chosen),
        path_cells=trace_path(parent, grid.cols, chosen.representative_cell),
    )
    return result(goal, "")


def _traversable(
    free: NDArray[np.bool_],
    obstacles: NDArray[np.bool_],
    fitted: NDArray[np.bool_],
    cell_m: float,
    params: FrontierParams,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """The cells the robot's centre may cross (``free`` cells outside the ``obstacles``'
    inflation, plus the ``fitted`` ones: its footprint, its track) and their step weights
    (`clearance_weights`)."""
    inflated = inflate_obstacles(obstacles, params.inflation_radius_m / cell_m)
    traversable = (free & ~inflated) | (fitted & ~obstacles)
    weight = clearance_weights(
        obstacles,
        cell_m,
        params.inflation_radius_m,
        params.clearance_preferred_m,
        params.clearance_cost,
    )
    return np.asarray(traversable, dtype=np.bool_), weight


def _probe_goal(
    known: NDArray[np.int8],
    grid: GroundGrid,
    probe_cells: NDArray[np.bool_],
    distance: NDArray[np.float64],
    parent: NDArray[np.int64],
    params: FrontierParams,
    robot_cell: tuple[int, int],
    fitted: NDArray[np.bool_],
    excluded: NDArray[np.bool_],
) -> FrontierGoal | None:
    """The nearest reachable cell from which to look at the unproven edge that stands
    between the robot and the nearest frontier it cannot reach (module docstring).
    ``known`` is the classified grid with the robot's footprint free; ``fitted`` the
    cells crossed whatever the inflation (the footprint and the track's free cells clear
    of obstacles by the robot's radius)."""
    if probe_cells.shape != known.shape:
        raise ValueError(f"probe_cells: expected shape {known.shape}, got {probe_cells.shape}")
    occupied = known == OCCUPIED
    edge = probe_cells & occupied
    if not edge.any():
        return None
    cell_m = grid.cell_m
    hard = occupied & ~edge
    relaxed = known.copy()
    relaxed[edge] = FREE
    reachable = np.isfinite(distance)
    frontier = frontier_mask(relaxed, adjacency=params.frontier_adjacency, exclude=excluded)
    frontier &= ~reachable
    labels, n_labels = ndimage.label(frontier, structure=np.ones((3, 3), dtype=bool))
    if n_labels == 0:
        return None
    sizes = np.bincount(labels.ravel(), minlength=n_labels + 1)
    kept = sizes >= params.min_cluster_cells
    kept[0] = False
    frontier = kept[labels]
    if not frontier.any():
        return None
    traversable, weight = _traversable(relaxed == FREE, hard, fitted, cell_m, params)
    weight[~reachable] += PROBE_CROSSING_COST
    relaxed_distance, relaxed_parent = path_distances(traversable, robot_cell, cell_m, weight)
    ahead = np.where(frontier, relaxed_distance, np.inf)
    flat = int(np.argmin(ahead))
    if not math.isfinite(ahead.flat[flat]):
        return None
    cols = known.shape[1]
    way = trace_path(relaxed_parent, cols, (flat // cols, flat % cols))
    rows_, cols_ = way[:, 0], way[:, 1]
    # The frontier is unreachable, so the way leaves the reachable floor somewhere.
    leaving = int(np.flatnonzero(~reachable[rows_, cols_])[0])
    on_edge = np.flatnonzero(edge[rows_[leaving:], cols_[leaving:]])
    x, y = grid.cell_centers()
    if on_edge.size:
        meet = tuple(way[leaving + int(on_edge[0])])
    else:
        # It slipped past the edge's end through its inflation: the nearest edge cell.
        r0, c0 = way[leaving]
        gap = np.where(edge, np.hypot(x - x[r0, c0], y - y[r0, c0]), np.inf)
        meet = np.unravel_index(int(np.argmin(gap)), gap.shape)
    (mr, mc) = (int(meet[0]), int(meet[1]))
    targets = edge & (np.hypot(x - x[mr, mc], y - y[mr, mc]) <= PROBE_EDGE_SPAN_M + 1e-9)
    reach_cells = params.inflation_radius_m / cell_m + 2.0
    candidates = inflate_obstacles(targets, reach_cells) & reachable
    if not candidates.any():
        return None
    # The reachable cell nearest where the way meets the edge (then the nearest by path):
    # it stays put while the robot drives to it, so the robot gets there.
    offset = np.where(candidates, np.hypot(x - x[mr, mc], y - y[mr, mc]), np.inf)
    nearest = candidates & (offset <= offset.min() + 1e-9)
    flat = int(np.argmin(np.where(nearest, distance, np.inf)))
    cell = (flat // cols, flat % cols)
    return FrontierGoal(
        cluster_index=-1,
        cell=cell,
        xy=(float(x[cell]), float(y[cell])),
        path_length_m=float(distance[cell]),
        score=float(distance[cell]),
        path_cells=trace_path(parent, cols, cell),
        probe=True,
        edge_cells=np.argwhere(targets).astype(np.int64),
    )


def path_to_point(
    search: FrontierSearch,
    grid: GroundGrid,
    target_xy: tuple[float, float],
    tolerance_m: float,
) -> FrontierGoal | None:
    """The shortest path in ``search`` (from the robot's cell, over the same traversable
    cells as the frontier goals) to the reachable cell nearest ``target_xy`` within
    ``tolerance_m``, as a goal (``cluster_index`` -1, ``score`` its distance to the
    target), or None when no cell within the tolerance is reachable.

    Why nearest and not exact: the target (the robot's start, say) may have become
    non-traversable in the map since (an obstacle's inflation reaching over it); any cell
    within the tolerance will do.

    Examples
    --------
    >>> g = GroundGrid(1.0, 0.0, 0.1, 3, 3)
    >>> cells = np.zeros((3, 3), np.int8)
    >>> s = find_frontiers(cells, g, (0.95, -0.05), FrontierParams(robot_radius_m=0.05,
    ...     inflation_radius_m=0.05, exclude_radius_m=0.05, min_cluster_cells=1))
    >>> path_to_point(s, g, (0.75, -0.25), 0.01).cell
    (2, 2)
    """
    check_grid(grid)
    target = check_xy(target_xy, "target_xy")
    if not (math.isfinite(tolerance_m) and tolerance_m >= 0):
        raise ValueError(f"tolerance_m: must be finite and >= 0, got {tolerance_m}")
    near = footprint_mask(grid, target, max(tolerance_m, grid.cell_m / 2))
    candidates = near & np.isfinite(search.distance_m)
    if not candidates.any():
        return None
    x, y = grid.cell_centers()
    offset = np.hypot(x - target[0], y - target[1])
    offset[~candidates] = np.inf
    flat = int(np.argmin(offset))
    cell = (flat // grid.cols, flat % grid.cols)
    return FrontierGoal(
        cluster_index=-1,
        cell=cell,
        xy=(float(x[cell]), float(y[cell])),
        path_length_m=float(search.distance_m[cell]),
        score=float(offset[cell]),
        path_cells=trace_path(search.parent, grid.cols, cell),
    )
