"""Log-odds occupancy grid in the world frame, fused from robot-frame ground patches.

One update takes a ground patch from inverse perspective mapping (a robot-frame
`GroundGrid` raster of ``FLOOR`` / ``NOT_FLOOR`` / ``UNSEEN``), the robot's pose
``T_world_robot`` and the camera's position in the robot frame, and runs three steps:

1. **Ray casting in the patch, at the patch's resolution** (`cast_rays`). Rays leave the
   camera's position; along each ray, seen ``FLOOR`` cells up to the first ``NOT_FLOOR``
   cell are *free*, the ``NOT_FLOOR`` cells within ``obstacle_band_m`` (measured along the
   ray) of that first one are *occupied*, and nothing after them is touched (occluded).
   ``UNSEEN`` cells never change anything and do not stop a ray. A ray whose first seen
   cell is ``NOT_FLOOR`` (no floor before it: the obstacle's foot is outside the view)
   touches nothing. Why only a band: in a bird's-eye view everything standing on the floor
   is smeared away from the camera, so only the near edge of a ``NOT_FLOOR`` region (its
   foot, the floor boundary) is where the obstacle really is. Floor counts as free only
   within ``free_max_range_m`` of the camera and a boundary as occupied only within
   ``occupied_max_range_m`` (`OccupancyParams`): far away a row of the image spans
   centimetres of floor, so only near boundaries are placed well.

   The rays are precomputed once per patch geometry (`build_polar_table`): for each of R
   rays the exact list of patch cells it crosses (a 4-connected grid traversal, so no ray
   slips diagonally through a wall) ordered by range, with the range at which it enters
   each. R is chosen so that neighbouring rays are at most one cell apart at the farthest
   patch cell, so every cell is crossed by some ray. A cell crossed by several rays is free
   if any ray sees it as floor, occupied if it is in any ray's band (a ``FLOOR`` cell can
   only become free and a ``NOT_FLOOR`` cell only occupied, so rays never disagree).

   Why at the patch's resolution rather than after downsampling it to the world's cells:
   the floor boundary is then found to a patch cell (1 cm) rather than a world cell
   (5 cm); thin obstacles (chair legs, cables) survive, where a 5 x 5 block of mixed
   floor / not-floor would need a vote that either drops them (majority) or turns every
   noisy pixel into a 5 cm obstacle and a hole in the free space (any-not-floor); and the
   occupied band stays a few centimetres thick instead of a whole world cell of smear.
   It is also fast enough: a whole update of a 290 x 300-cell patch takes under 1 ms on
   one core (`app.benchmarks.grid`).

2. **Transform into the world** (`fuse_patch_labels`). The centre of every free or
   occupied patch cell is moved by ``T_world_robot`` and falls into the nearest world cell
   (the one containing it). Many patch cells land on one world cell (25 for 1 cm cells
   into 5 cm cells); the rule is **one update per world cell per frame, occupied wins**:
   the cell gets ``log_odds_occupied`` once if any occupied patch cell lands in it, else
   ``log_odds_free`` once if any free one does, then the sum is clamped to
   ``[clamp_min, clamp_max]``. A frame is one observation, so a cell's evidence must not
   grow with the resolution ratio (summing 25 hits would saturate a cell in one frame and
   defeat fusion over frames), and a cell holding the floor boundary must read as an
   obstacle even if most of it is floor (the conservative choice for driving). The patch's
   cells should be no larger than the world's (ideally half or less), or splatted centres
   leave holes; larger ones are refused.

3. **Decay by travel.** Evidence fades towards 0 (unknown) with the distance the robot
   travels, never with time alone: every log-odds value is multiplied by
   ``0.5 ** (travel / half_distance_m)``. Why travel: the map goes stale because the pose
   it was fused at drifts (odometry error grows with how far the wheels roll, not with the
   clock), while a changed world is corrected by contradicting observations (log-odds
   addition and clamping), not by forgetting. A robot that stands still (stopped, faulted,
   waiting for a start) keeps its map exactly.

   Travel between two poses (`travel_m`) is the mean distance the two wheels of a
   differential drive roll between them, ``max(|Δposition|, turn_radius_m * |Δheading|)``
   with ``turn_radius_m`` half the wheel base. So turning in place counts (a spin turn
   slips the wheels, and heading error is the costliest odometry error: 1° moves a wall
   3 m away by 5 cm), and an arc is not counted twice.

   The decay is global and lazy, and counted from an anchor pose: an update measures the
   travel from the anchor to its pose, and once that reaches ``decay_step_m`` it multiplies
   every log-odds value by the factor for that travel, adds it to
   `OccupancyGrid.travelled_m` and makes its pose the new anchor (before adding the
   frame's evidence). Why an anchor rather than summing every step: a pose that jitters
   about a point (encoder ticks of a vibrating robot, estimator noise) never adds up to
   travel, so a standing robot keeps its map exactly; the price is that the path is
   measured in chords of at least ``decay_step_m`` (5 cm), which cuts corners by
   millimetres and ignores shuffling within 5 cm. The first update after construction
   or `OccupancyGrid.reset` only sets the anchor; a pose jump (an odometry reset) counts
   as travel, which fades the map it misplaces. `OccupancyGrid.snapshot` applies the
   pending travel (anchor to last pose) to its copy.

   Faded is not unexplored: `OccupancyGrid.remembered` keeps each cell's last class
   (free or occupied) from before a decay made it unknown, and
   `OccupancyGrid.remembered_classes` is the map with those memories filled in, which the
   frontier search plans on. The robot has looked there: sending it back each time its
   memory faded kept exploration of even a small room from finishing (a clean-clone CI
   run drove 16.6 m in a 3 x 2.4 m room, 4.6 m on a faster machine, and never came
   home), and faded floor is still the way to the unexplored beyond it and back home.
   New evidence always wins over a memory.

Cell classes (`classify`, int8): ``UNKNOWN = -1``, ``FREE = 0``, ``OCCUPIED = 1``; a cell
is occupied when its log-odds is above ``occupied_threshold``, free when below
``free_threshold``, unknown otherwise (never observed, conflicting, or decayed).

A `SavedMap` is a read-only copy of a grid's state (`OccupancyGrid.snapshot`) that
`OccupancyGrid.restore` puts back; `app.mapping.map_files` saves and loads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from numpy.typing import NDArray

from app.mapping.floor_memory import FloorMemoryState
from app.mapping.frames import (
    FLOOR,
    NOT_FLOOR,
    UNSEEN,
    GroundGrid,
    Pose2D,
    describe_grid,
    same_geometry,
)

UNKNOWN = -1
"""`classify` code: no (or not enough) evidence."""
FREE = 0
"""`classify` code: free floor."""
OCCUPIED = 1
"""`classify` code: obstacle."""
CLASSES = (UNKNOWN, FREE, OCCUPIED)

PATCH_UNTOUCHED = 0
"""`cast_rays` label: the patch cell gives no evidence (unseen, occluded, or before floor)."""
PATCH_FREE = 1
"""`cast_rays` label: seen floor before the first obstacle along a ray."""
PATCH_OCCUPIED = 2
"""`cast_rays` label: in the band of not-floor just beyond the floor along a ray."""
_UNDER_ROBOT = 3
"""`_fuse_kernel`'s mark of a world cell under the robot's footprint."""


@dataclass(frozen=True)
class OccupancyParams:
    """Parameters of the grid update and classification.

    Attributes
    ----------
    log_odds_free : float, < 0, added to a world cell seen free in a frame.
    log_odds_occupied : float, > 0, added to a world cell seen occupied in a frame.
    clamp_min, clamp_max : float, the log-odds are kept in ``[clamp_min, clamp_max]`` so
        that evidence can be overturned in a few frames.
    free_threshold, occupied_threshold : float, `classify` cuts; the defaults make one
        obstacle sighting enough for "occupied" but ask two floor sightings for "free".
    obstacle_band_m : float, >= 0, thickness along a ray of the occupied band, from the
        first not-floor cell (which is always in it).
    free_max_range_m, occupied_max_range_m : float, > 0 (``math.inf``: no limit), range
        from the camera beyond which a frame's floor gives no free evidence and its floor
        boundary no occupied evidence. Why: a mask's boundary is only good to a few image
        rows, and a row covers more floor the farther it looks (on the simulated camera
        1 cm at 1 m, 3 cm at 2 m, 5 cm at 2.5 m), so a far boundary lands cells away from
        the obstacle and a far false one paints a wall across open floor. The robot
        looks again from closer before it gets there.
    far_boundary_margin_m : float, >= 0, floor within this (along the ray) of a boundary
        beyond ``occupied_max_range_m`` gives no free evidence either: that boundary is as
        misplaced as it is unmapped, and free cells leaking past a wall the map does not
        yet hold make frontiers behind it.
    half_distance_m : float, > 0, travel that halves all evidence (``math.inf`` disables
        decay).
    turn_radius_m : float, >= 0, turning by an angle counts as this radius times the
        angle of travel (half the wheel base: the distance each wheel rolls in a spin
        turn); 0 makes turning in place free.
    decay_step_m : float, >= 0, travel from the anchor pose that triggers a global decay
        (smaller pose changes, however many, decay nothing).
    footprint_free_radius_m : float, >= 0; when > 0, world cells whose centres lie within
        this distance of the robot's position get a free update every frame unless the
        frame marks them occupied, and are set at least one ``log_odds_free`` below
        ``free_threshold``: the robot stands there (the camera never sees under it), so
        whatever colour boundaries had put there was wrong, and a few free updates would
        not wear off a boundary seen for seconds before (a threshold strip the robot
        then drove across stayed a wall behind it). Not lower: the pose may be a cell
        off, and a box's edge must come back when it is seen again. 0 disables it.
    """

    log_odds_free: float = -0.4
    log_odds_occupied: float = 0.85
    clamp_min: float = -2.0
    clamp_max: float = 3.5
    free_threshold: float = -0.5
    occupied_threshold: float = 0.5
    obstacle_band_m: float = 0.03
    free_max_range_m: float = math.inf
    occupied_max_range_m: float = math.inf
    far_boundary_margin_m: float = 0.0
    half_distance_m: float = 10.0
    turn_radius_m: float = 0.10
    decay_step_m: float = 0.05
    footprint_free_radius_m: float = 0.0

    def __post_init__(self) -> None:
        values = {name: getattr(self, name) for name in self.__dataclass_fields__}
        for name, value in values.items():
            finite = isinstance(value, int | float) and math.isfinite(value)
            unbounded = name in ("half_distance_m", "free_max_range_m", "occupied_max_range_m")
            if not (finite or (unbounded and value == math.inf)):
                raise ValueError(f"OccupancyParams.{name}: expected a finite number, got {value!r}")
        if not (self.log_odds_free < 0 < self.log_odds_occupied):
            raise ValueError("OccupancyParams: need log_odds_free < 0 < log_odds_occupied")
        if not (self.clamp_min < 0 < self.clamp_max):
            raise ValueError("OccupancyParams: need clamp_min < 0 < clamp_max")
        if not (self.clamp_min <= self.free_threshold <= self.occupied_threshold <= self.clamp_max):
            raise ValueError(
                "OccupancyParams: need clamp_min <= free_threshold <= occupied_threshold"
                " <= clamp_max"
            )
        for name in ("half_distance_m", "free_max_range_m", "occupied_max_range_m"):
            if not values[name] > 0:
                raise ValueError(f"OccupancyParams.{name}: must be > 0, got {values[name]}")
        for name in (
            "obstacle_band_m",
            "far_boundary_margin_m",
            "turn_radius_m",
            "decay_step_m",
            "footprint_free_radius_m",
        ):
            if values[name] < 0:
                raise ValueError(f"OccupancyParams.{name}: must be >= 0, got {values[name]}")


@dataclass(frozen=True, eq=False)
class PolarTable:
    """The rays of one patch geometry, flattened (CSR layout).

    Ray ``k`` crosses the patch cells ``cells[offsets[k]:offsets[k + 1]]`` (flat indices
    ``row * cols + col``) in order of range, entering them at ``range_m[...]`` metres from
    the camera.

    Attributes
    ----------
    patch_grid : GroundGrid the table was built for.
    camera_xy : (float, float), the camera's position in the robot frame.
    offsets : (R + 1,) int64
    cells : (N,) int32
    range_m : (N,) float32
    """

    patch_grid: GroundGrid
    camera_xy: tuple[float, float]
    offsets: NDArray[np.int64] = field(repr=False)
    cells: NDArray[np.int32] = field(repr=False)
    range_m: NDArray[np.float32] = field(repr=False)

    @property
    def n_rays(self) -> int:
        return int(self.offsets.shape[0] - 1)


@dataclass(frozen=True)
class UpdateSummary:
    """What one `OccupancyGrid.update` changed.

    Attributes
    ----------
    patch_free, patch_occupied : int, patch cells labelled free / occupied by the rays.
    world_free, world_occupied : int, world cells that got a free / occupied update
        (including the footprint's, if enabled).
    decayed : bool, whether the global decay ran before the update.
    """

    patch_free: int
    patch_occupied: int
    world_free: int
    world_occupied: int
    decayed: bool


# --------------------------------------------------------------------------- checks


def check_grid(grid: GroundGrid, name: str = "grid") -> None:
    """Raise ValueError unless ``grid`` has a finite positive cell size, finite corner and
    at least one row and column."""
    if not isinstance(grid, GroundGrid):
        raise ValueError(f"{name}: expected a GroundGrid, got {type(grid).__name__}")
    if not (math.isfinite(grid.cell_m) and grid.cell_m > 0):
        raise ValueError(f"{name}: cell size must be finite and > 0, got {grid.cell_m}")
    if not (math.isfinite(grid.x_max_m) and math.isfinite(grid.y_max_m)):
        raise ValueError(f"{name}: corner must be finite, got ({grid.x_max_m}, {grid.y_max_m})")
    if grid.rows < 1 or grid.cols < 1:
        raise ValueError(f"{name}: need at least one row and column, got {grid.shape}")


def check_pose(pose: Pose2D, name: str = "T_world_robot") -> None:
    """Raise ValueError unless ``pose`` is a `Pose2D` with finite fields."""
    if not isinstance(pose, Pose2D):
        raise ValueError(f"{name}: expected a Pose2D, got {type(pose).__name__}")
    if not all(math.isfinite(v) for v in (pose.x_m, pose.y_m, pose.theta_rad)):
        raise ValueError(f"{name}: pose must be finite, got {pose}")


def check_xy(xy: tuple[float, float], name: str) -> tuple[float, float]:
    """A finite (x, y) pair as floats, or ValueError."""
    try:
        x, y = (float(v) for v in xy)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (x, y), got {xy!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"{name}: must be finite, got ({x}, {y})")
    return x, y


def check_cell_sizes(patch_grid: GroundGrid, world_grid: GroundGrid) -> None:
    """Raise ValueError if the patch's cells are larger than the world's (splatting their
    centres would leave holes in the world)."""
    if patch_grid.cell_m > world_grid.cell_m * (1 + 1e-9):
        raise ValueError(
            f"patch_grid: cell {patch_grid.cell_m} m is larger than the world's"
            f" {world_grid.cell_m} m (splatted centres would leave holes)"
        )


@numba.njit(cache=True, nogil=True)
def _count_invalid(patch: NDArray[np.uint8]) -> int:
    bad = 0
    for i in range(patch.shape[0]):
        for j in range(patch.shape[1]):
            v = patch[i, j]
            if v != FLOOR and v != NOT_FLOOR and v != UNSEEN:
                bad += 1
    return bad


def check_patch(patch: NDArray[np.uint8], patch_grid: GroundGrid) -> None:
    """Raise ValueError unless ``patch`` is a uint8 raster of ``patch_grid``'s shape holding
    only ``FLOOR``, ``NOT_FLOOR`` and ``UNSEEN``."""
    if not isinstance(patch, np.ndarray) or patch.dtype != np.uint8:
        kind = patch.dtype if isinstance(patch, np.ndarray) else type(patch).__name__
        raise ValueError(f"patch: expected a uint8 array, got {kind}")
    if patch.shape != patch_grid.shape:
        raise ValueError(
            f"patch: expected shape {patch_grid.shape} (patch_grid), got {patch.shape}"
        )
    bad = int(_count_invalid(patch))
    if bad:
        raise ValueError(
            f"patch: {bad} cells are not FLOOR ({FLOOR}), NOT_FLOOR ({NOT_FLOOR}) or UNSEEN"
            f" ({UNSEEN})"
        )


# ----------------------------------------------------------------------- polar table


@numba.njit(cache=True, nogil=True)
def _walk_ray(
    a0: float,
    b0: float,
    da: float,
    db: float,
    rows: int,
    cols: int,
    cell_m: float,
    cells: NDArray[np.int32],
    range_m: NDArray[np.float32],
    start: int,
    write: bool,
) -> int:
    """Grid traversal (Amanatides-Woo) of the ray ``(a0, b0) + t (da, db)``, t >= 0, in
    continuous (row, col) cell units over ``[0, rows] x [0, cols]``. Returns the number of
    cells crossed; writes them from ``start`` when ``write``."""
    t0 = 0.0
    t1 = np.inf
    if da != 0.0:
        ta, tb = (0.0 - a0) / da, (rows - a0) / da
        t0 = max(t0, min(ta, tb))
        t1 = min(t1, max(ta, tb))
    elif a0 < 0.0 or a0 > rows:
        return 0
    if db != 0.0:
        ta, tb = (0.0 - b0) / db, (cols - b0) / db
        t0 = max(t0, min(ta, tb))
        t1 = min(t1, max(ta, tb))
    elif b0 < 0.0 or b0 > cols:
        return 0
    if t0 >= t1:
        return 0
    t_in = t0 + 1e-9
    i = min(max(math.floor(a0 + t_in * da), 0), rows - 1)
    j = min(max(math.floor(b0 + t_in * db), 0), cols - 1)
    if da > 0.0:
        step_i, t_max_i, t_delta_i = 1, (i + 1 - a0) / da, 1.0 / da
    elif da < 0.0:
        step_i, t_max_i, t_delta_i = -1, (i - a0) / da, -1.0 / da
    else:
        step_i, t_max_i, t_delta_i = 0, np.inf, np.inf
    if db > 0.0:
        step_j, t_max_j, t_delta_j = 1, (j + 1 - b0) / db, 1.0 / db
    elif db < 0.0:
        step_j, t_max_j, t_delta_j = -1, (j - b0) / db, -1.0 / db
    else:
        step_j, t_max_j, t_delta_j = 0, np.inf, np.inf
    t = t0
    n = 0
    while True:
        if write:
            cells[start + n] = i * cols + j
            range_m[start + n] = t * cell_m
        n += 1
        if t_max_i < t_max_j:
            t = t_max_i
            i += step_i
            t_max_i += t_delta_i
            if i < 0 or i >= rows:
                break
        else:
            t = t_max_j
            j += step_j
            t_max_j += t_delta_j
            if j < 0 or j >= cols:
                break
    return n


@numba.njit(cache=True, nogil=True)
def _trace_rays(
    a0: float, b0: float, rows: int, cols: int, cell_m: float, n_rays: int
) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float32]]:
    dummy_cells = np.empty(0, dtype=np.int32)
    dummy_range = np.empty(0, dtype=np.float32)
    offsets = np.zeros(n_rays + 1, dtype=np.int64)
    for k in range(n_rays):
        theta = 2.0 * math.pi * k / n_rays
        # Robot x forward maps to decreasing rows, robot y to decreasing columns.
        n = _walk_ray(
            a0,
            b0,
            -math.cos(theta),
            -math.sin(theta),
            rows,
            cols,
            cell_m,
            dummy_cells,
            dummy_range,
            0,
            False,
        )
        offsets[k + 1] = offsets[k] + n
    cells = np.empty(offsets[n_rays], dtype=np.int32)
    range_m = np.empty(offsets[n_rays], dtype=np.float32)
    for k in range(n_rays):
        theta = 2.0 * math.pi * k / n_rays
        _walk_ray(
            a0,
            b0,
            -math.cos(theta),
            -math.sin(theta),
            rows,
            cols,
            cell_m,
            cells,
            range_m,
            offsets[k],
            True,
        )
    return offsets, cells, range_m


def build_polar_table(
    patch_grid: GroundGrid,
    camera_xy_robot: tuple[float, float],
    *,
    ray_spacing_cells: float = 1.0,
) -> PolarTable:
    """Precompute the rays from the camera through every cell of a patch geometry.

    Parameters
    ----------
    patch_grid : GroundGrid of the robot-frame patch.
    camera_xy_robot : (x, y) metres, the camera's position on the floor in the robot frame
        (inside or outside the patch).
    ray_spacing_cells : float in (0, 1], the largest gap between neighbouring rays, in
        cells, at the farthest patch cell; <= 1 makes every cell crossed by some ray.

    Returns
    -------
    PolarTable, about ``2 pi r_max / ray_spacing_cells`` rays (those missing the patch are
    empty).

    Examples
    --------
    >>> grid = GroundGrid(x_max_m=0.03, y_max_m=0.01, cell_m=0.01, rows=3, cols=2)
    >>> table = build_polar_table(grid, (0.0, 0.0))
    >>> table.cells[table.offsets[0] : table.offsets[1]].tolist()  # straight ahead
    [5, 3, 1]
    """
    check_grid(patch_grid, "patch_grid")
    cx, cy = check_xy(camera_xy_robot, "camera_xy_robot")
    if not (0 < ray_spacing_cells <= 1):
        raise ValueError(f"ray_spacing_cells: must be in (0, 1], got {ray_spacing_cells}")
    cell = patch_grid.cell_m
    a0 = (patch_grid.x_max_m - cx) / cell
    b0 = (patch_grid.y_max_m - cy) / cell
    rows, cols = patch_grid.rows, patch_grid.cols
    r_max = max(math.hypot(a0 - a, b0 - b) for a in (0, rows) for b in (0, cols))
    n_rays = max(8, math.ceil(2 * math.pi * r_max / ray_spacing_cells))
    offsets, cells, range_m = _trace_rays(float(a0), float(b0), rows, cols, float(cell), n_rays)
    return PolarTable(patch_grid, (cx, cy), offsets, cells, range_m)


# ----------------------------------------------------------------------- ray casting


@numba.njit(cache=True, nogil=True)
def _cast_kernel(
    patch: NDArray[np.uint8],
    offsets: NDArray[np.int64],
    cells: NDArray[np.int32],
    range_m: NDArray[np.float32],
    band_m: float,
    free_max_m: float,
    occupied_max_m: float,
    far_margin_m: float,
    standing: NDArray[np.bool_],
    labels: NDArray[np.uint8],
) -> None:
    has_standing = standing.shape[0] > 0
    for k in range(offsets.shape[0] - 1):
        start, stop = offsets[k], offsets[k + 1]
        # The ray's first not-floor cell (its boundary), and whether floor came before it.
        boundary = stop
        seen_floor = False
        for e in range(start, stop):
            v = patch[cells[e]]
            if v == NOT_FLOOR:
                boundary = e
                break
            if v == FLOOR:
                seen_floor = True
        if not seen_floor:
            continue  # the obstacle's foot is outside the view: nothing is known
        free_limit = free_max_m
        band_max = occupied_max_m
        placed = False
        if boundary < stop:
            r_boundary = range_m[boundary]
            # What geometry saw standing is mapped as far as floor is.
            if has_standing and standing[cells[boundary]]:
                band_max = max(occupied_max_m, free_max_m)
            placed = r_boundary <= band_max
            if not placed:
                # Too far to map, and as uncertain: the floor just before it is not sure.
                free_limit = min(free_limit, r_boundary - far_margin_m)
        # Floor past the free range still hides nothing: the ray goes on to its boundary.
        for e in range(start, boundary):
            if patch[cells[e]] == FLOOR and range_m[e] <= free_limit:
                labels[cells[e]] = PATCH_FREE
        if placed:
            band_end = range_m[boundary] + band_m
            for e in range(boundary, stop):
                r = range_m[e]
                if r >= band_end or r > band_max:
                    break
                if patch[cells[e]] == NOT_FLOOR:
                    labels[cells[e]] = PATCH_OCCUPIED


def cast_rays(
    patch: NDArray[np.uint8],
    table: PolarTable,
    *,
    obstacle_band_m: float = 0.03,
    free_max_range_m: float = math.inf,
    occupied_max_range_m: float = math.inf,
    far_boundary_margin_m: float = 0.0,
    standing: NDArray[np.bool_] | None = None,
) -> NDArray[np.uint8]:
    """Free and occupied cells of one patch, in the robot frame (see the module docstring).

    Parameters
    ----------
    patch : (rows, cols) uint8 of ``FLOOR`` / ``NOT_FLOOR`` / ``UNSEEN`` on
        ``table.patch_grid``.
    table : PolarTable from `build_polar_table` for this patch geometry and camera.
    obstacle_band_m : float >= 0, thickness of the occupied band along each ray.
    free_max_range_m, occupied_max_range_m : float > 0, ranges from the camera beyond
        which floor gives no free label and not-floor no occupied one (see
        `OccupancyParams`); a ray still ends at its first not-floor cell, labelled or not.
    far_boundary_margin_m : float >= 0, a ray whose first not-floor cell lies beyond the
        occupied range (its boundary is not mapped) gives no free label to floor within
        this of that boundary.
    standing : (rows, cols) bool or None, not-floor cells geometry saw standing (parallax,
        the horizon): a ray whose first not-floor cell is one of them gets its occupied
        band out to the larger of the two ranges. The range limits are for colour
        boundaries, whose place is only as good as the mask's rows.

    Returns
    -------
    (rows, cols) uint8 labels: ``PATCH_UNTOUCHED``, ``PATCH_FREE`` or ``PATCH_OCCUPIED``.

    Examples
    --------
    >>> grid = GroundGrid(x_max_m=0.05, y_max_m=0.005, cell_m=0.01, rows=5, cols=1)
    >>> patch = np.array([[FLOOR], [NOT_FLOOR], [NOT_FLOOR], [FLOOR], [FLOOR]], np.uint8)
    >>> table = build_polar_table(grid, (0.0, 0.0))
    >>> cast_rays(patch, table, obstacle_band_m=0.015).ravel().tolist()  # camera at row 5
    [0, 2, 2, 1, 1]
    >>> cast_rays(patch, table, obstacle_band_m=0.015, occupied_max_range_m=0.015).ravel().tolist()
    [0, 0, 0, 1, 1]
    >>> cast_rays(patch, table, obstacle_band_m=0.015, free_max_range_m=0.005).ravel().tolist()
    [0, 2, 2, 0, 1]
    """
    check_patch(patch, table.patch_grid)
    if not (0 <= obstacle_band_m < math.inf):
        raise ValueError(f"obstacle_band_m: must be finite and >= 0, got {obstacle_band_m}")
    for name, value in (
        ("free_max_range_m", free_max_range_m),
        ("occupied_max_range_m", occupied_max_range_m),
    ):
        if not value > 0:
            raise ValueError(f"{name}: must be > 0, got {value}")
    if not (0 <= far_boundary_margin_m < math.inf):
        raise ValueError(
            f"far_boundary_margin_m: must be finite and >= 0, got {far_boundary_margin_m}"
        )
    _check_standing(standing, table.patch_grid)
    return _cast_checked(
        patch,
        table,
        float(obstacle_band_m),
        float(free_max_range_m),
        float(occupied_max_range_m),
        float(far_boundary_margin_m),
        standing,
    )


def _check_standing(standing: NDArray[np.bool_] | None, patch_grid: GroundGrid) -> None:
    """Raise ValueError unless ``standing`` is None or a bool raster of the patch's shape."""
    if standing is not None and (
        not isinstance(standing, np.ndarray)
        or standing.dtype != np.bool_
        or standing.shape != patch_grid.shape
    ):
        raise ValueError(f"standing: expected a bool array of shape {patch_grid.shape}")


_NO_STANDING = np.zeros(0, dtype=np.bool_)


def _cast_checked(
    patch: NDArray[np.uint8],
    table: PolarTable,
    obstacle_band_m: float,
    free_max_range_m: float,
    occupied_max_range_m: float,
    far_boundary_margin_m: float,
    standing: NDArray[np.bool_] | None,
) -> NDArray[np.uint8]:
    labels = np.zeros(patch.size, dtype=np.uint8)
    _cast_kernel(
        np.ascontiguousarray(patch).ravel(),
        table.offsets,
        table.cells,
        table.range_m,
        obstacle_band_m,
        free_max_range_m,
        occupied_max_range_m,
        far_boundary_margin_m,
        _NO_STANDING if standing is None else np.ascontiguousarray(standing).ravel(),
        labels,
    )
    return labels.reshape(patch.shape)


# --------------------------------------------------------------------- world fusion


@numba.njit(cache=True, nogil=True)
def _fuse_kernel(
    labels: NDArray[np.uint8],
    patch_x: NDArray[np.float64],
    patch_y: NDArray[np.float64],
    cos_t: float,
    sin_t: float,
    tx: float,
    ty: float,
    log_odds: NDArray[np.float32],
    world_x_max: float,
    world_y_max: float,
    world_cell: float,
    footprint_radius: float,
    l_free: float,
    l_occ: float,
    lo: float,
    hi: float,
    under_robot: float,
) -> tuple[int, int]:
    w_rows, w_cols = log_odds.shape
    mark = np.zeros(w_rows * w_cols, dtype=np.uint8)
    # Each world cell is listed at most once, and only for a labelled or footprint cell.
    footprint_side = 2 * math.ceil(footprint_radius / world_cell) + 3
    capacity = min(w_rows * w_cols, labels.size + footprint_side * footprint_side)
    touched = np.empty(capacity, dtype=np.int64)
    n_touched = 0
    inv = 1.0 / world_cell
    for i in range(labels.shape[0]):
        # World (row, col) in continuous units is affine in the patch cell's (x, y).
        row_base = (world_x_max - (cos_t * patch_x[i] + tx)) * inv
        col_base = (world_y_max - (sin_t * patch_x[i] + ty)) * inv
        for j in range(labels.shape[1]):
            lab = labels[i, j]
            if lab == PATCH_UNTOUCHED:
                continue
            r = math.floor(row_base + sin_t * patch_y[j] * inv)
            c = math.floor(col_base - cos_t * patch_y[j] * inv)
            if r < 0 or r >= w_rows or c < 0 or c >= w_cols:
                continue
            w = r * w_cols + c
            if mark[w] == 0:
                touched[n_touched] = w
                n_touched += 1
            if lab > mark[w]:
                mark[w] = lab
    if footprint_radius > 0.0:
        r_lo = max(math.floor((world_x_max - tx - footprint_radius) * inv), 0)
        r_hi = min(math.floor((world_x_max - tx + footprint_radius) * inv), w_rows - 1)
        c_lo = max(math.floor((world_y_max - ty - footprint_radius) * inv), 0)
        c_hi = min(math.floor((world_y_max - ty + footprint_radius) * inv), w_cols - 1)
        for r in range(r_lo, r_hi + 1):
            dx = world_x_max - (r + 0.5) * world_cell - tx
            for c in range(c_lo, c_hi + 1):
                dy = world_y_max - (c + 0.5) * world_cell - ty
                if dx * dx + dy * dy > footprint_radius * footprint_radius:
                    continue
                w = r * w_cols + c
                if mark[w] == 0:
                    touched[n_touched] = w
                    n_touched += 1
                if mark[w] != PATCH_OCCUPIED:
                    mark[w] = _UNDER_ROBOT
    flat = log_odds.reshape(-1)
    n_free = 0
    n_occ = 0
    for k in range(n_touched):
        w = touched[k]
        if mark[w] == PATCH_OCCUPIED:
            value = flat[w] + l_occ
            n_occ += 1
        elif mark[w] == _UNDER_ROBOT:
            # Nothing stands where the robot stands: what boundaries said there was wrong.
            # Free at once, but no surer than one sighting past the threshold: the pose
            # may be a cell off, and a box's edge must come back when it is seen again.
            value = min(flat[w] + l_free, under_robot)
            n_free += 1
        else:
            value = flat[w] + l_free
            n_free += 1
        flat[w] = min(max(value, lo), hi)
    return n_free, n_occ


def fuse_patch_labels(
    log_odds: NDArray[np.float32],
    world_grid: GroundGrid,
    labels: NDArray[np.uint8],
    patch_grid: GroundGrid,
    T_world_robot: Pose2D,
    params: OccupancyParams,
) -> tuple[int, int]:
    """Add one frame's robot-frame labels to the world log-odds, in place.

    Every ``PATCH_FREE`` / ``PATCH_OCCUPIED`` cell's centre is moved into the world by
    ``T_world_robot`` and lands in the world cell containing it; each world cell reached
    gets one update, ``log_odds_occupied`` if any occupied cell landed in it, else
    ``log_odds_free``, then is clamped. With ``params.footprint_free_radius_m > 0`` the
    world cells within that distance of the robot that no occupied cell reached get a
    free update and at most ``free_threshold + log_odds_free``.

    Parameters
    ----------
    log_odds : (world_grid.rows, world_grid.cols) float32, C-contiguous; updated in place.
    world_grid : GroundGrid of the world frame.
    labels : (patch_grid.rows, patch_grid.cols) uint8 from `cast_rays`.
    patch_grid : GroundGrid of the robot-frame patch; its cells must be no larger than the
        world's.
    T_world_robot : Pose2D of the robot in the world.
    params : OccupancyParams

    Returns
    -------
    (world cells given a free update, world cells given an occupied update)
    """
    check_grid(world_grid, "world_grid")
    check_grid(patch_grid, "patch_grid")
    check_pose(T_world_robot)
    check_cell_sizes(patch_grid, world_grid)
    if (
        not isinstance(log_odds, np.ndarray)
        or log_odds.dtype != np.float32
        or log_odds.shape != world_grid.shape
        or not log_odds.flags.c_contiguous
    ):
        raise ValueError(
            f"log_odds: expected a C-contiguous float32 array of shape {world_grid.shape}"
        )
    if labels.dtype != np.uint8 or labels.shape != patch_grid.shape:
        raise ValueError(f"labels: expected uint8 of shape {patch_grid.shape}, got {labels.shape}")
    patch_x = (
        patch_grid.x_max_m
        - (np.arange(patch_grid.rows, dtype=np.float64) + 0.5) * patch_grid.cell_m
    )
    patch_y = (
        patch_grid.y_max_m
        - (np.arange(patch_grid.cols, dtype=np.float64) + 0.5) * patch_grid.cell_m
    )
    n_free, n_occ = _fuse_kernel(
        labels,
        patch_x,
        patch_y,
        math.cos(T_world_robot.theta_rad),
        math.sin(T_world_robot.theta_rad),
        float(T_world_robot.x_m),
        float(T_world_robot.y_m),
        log_odds,
        float(world_grid.x_max_m),
        float(world_grid.y_max_m),
        float(world_grid.cell_m),
        float(params.footprint_free_radius_m),
        float(params.log_odds_free),
        float(params.log_odds_occupied),
        float(params.clamp_min),
        float(params.clamp_max),
        float(params.free_threshold + params.log_odds_free),
    )
    return int(n_free), int(n_occ)


# ------------------------------------------------------------- decay, classification


def decay_factor(travel_m: float, half_distance_m: float) -> float:
    """``0.5 ** (travel_m / half_distance_m)``: the multiplier of log-odds after
    ``travel_m`` metres of travel (1 for an infinite half-distance).

    >>> decay_factor(10.0, 10.0)
    0.5
    """
    if not (travel_m >= 0 and math.isfinite(travel_m)):
        raise ValueError(f"travel_m: must be finite and >= 0, got {travel_m}")
    if not half_distance_m > 0:
        raise ValueError(f"half_distance_m: must be > 0, got {half_distance_m}")
    return float(0.5 ** (travel_m / half_distance_m))


def travel_m(previous: Pose2D, current: Pose2D, turn_radius_m: float) -> float:
    """Travel between two successive poses: the mean distance the wheels of a
    differential drive roll, ``max(|Δposition|, turn_radius_m * |Δheading|)`` (each wheel
    rolls the centre's distance plus or minus ``turn_radius_m`` times the turn; the mean of
    the two magnitudes is the larger term). The heading change is wrapped to [-pi, pi].

    >>> travel_m(Pose2D(), Pose2D(3.0, 4.0, 0.1), 0.1)
    5.0
    >>> round(travel_m(Pose2D(), Pose2D(0.0, 0.0, -math.pi / 2), 0.1), 4)  # spin turn
    0.1571
    """
    check_pose(previous, "previous")
    check_pose(current, "current")
    if not (0 <= turn_radius_m < math.inf):
        raise ValueError(f"turn_radius_m: must be finite and >= 0, got {turn_radius_m}")
    moved = math.hypot(current.x_m - previous.x_m, current.y_m - previous.y_m)
    turned = abs(math.remainder(current.theta_rad - previous.theta_rad, math.tau))
    return max(moved, turn_radius_m * turned)


def classify_log_odds(
    log_odds: NDArray[np.floating], *, free_threshold: float, occupied_threshold: float
) -> NDArray[np.int8]:
    """(rows, cols) log-odds -> (rows, cols) int8 of ``UNKNOWN`` (-1), ``FREE`` (0) and
    ``OCCUPIED`` (1): occupied above ``occupied_threshold``, free below ``free_threshold``.

    >>> classify_log_odds(np.array([[-1.0, 0.0, 1.0]]), free_threshold=-0.5,
    ...                   occupied_threshold=0.5).tolist()
    [[0, -1, 1]]
    """
    if free_threshold > occupied_threshold:
        raise ValueError("classify_log_odds: need free_threshold <= occupied_threshold")
    out = np.full(log_odds.shape, UNKNOWN, dtype=np.int8)
    out[log_odds < free_threshold] = FREE
    out[log_odds > occupied_threshold] = OCCUPIED
    return out


def fill_remembered(
    classes: NDArray[np.int8], remembered: NDArray[np.int8] | None
) -> NDArray[np.int8]:
    """In place and returned: each ``UNKNOWN`` cell of ``classes`` that has a
    ``remembered`` class (module docstring, 3) takes it; ``remembered`` None changes
    nothing.

    >>> fill_remembered(np.array([-1, -1, 0], np.int8), np.array([1, -1, -1], np.int8))
    array([ 1, -1,  0], dtype=int8)
    """
    if remembered is not None:
        faded = classes == UNKNOWN
        classes[faded] = remembered[faded]
    return classes


def log_odds_to_probability(log_odds: NDArray[np.floating]) -> NDArray[np.float32]:
    """Occupancy probability ``1 / (1 + exp(-l))`` as float32 (0.5 = unknown)."""
    l32 = np.asarray(log_odds, dtype=np.float32)
    return np.asarray(1.0 / (1.0 + np.exp(-l32)), dtype=np.float32)


# ------------------------------------------------------------------------ the grid


@dataclass(frozen=True, eq=False)
class SavedMap:
    """A consistent, read-only copy of a grid's state: what a map file holds.

    Attributes
    ----------
    log_odds : (world_grid.rows, world_grid.cols) float32, finite, read-only; the pending
        travel decay is already applied.
    world_grid : GroundGrid of the world frame (the map's frame).
    free_threshold, occupied_threshold : float, the cuts the map was classified with.
    T_world_robot : Pose2D, the robot's pose in the map's frame at the last update (the
        world origin, its start pose, if there was none).
    travelled_m : float >= 0, the robot's travel fused into the map so far.
    floor_memory : the confirmed-floor layer and learned floor appearances
        (`app.mapping.floor_memory`), or None for a map without them.
    remembered : (rows, cols) int8, read-only, the grid's `OccupancyGrid.remembered`; None
        for a map saved without it.
    """

    log_odds: NDArray[np.float32] = field(repr=False)
    world_grid: GroundGrid
    free_threshold: float
    occupied_threshold: float
    T_world_robot: Pose2D
    travelled_m: float
    floor_memory: FloorMemoryState | None = field(default=None, repr=False)
    remembered: NDArray[np.int8] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        check_grid(self.world_grid, "world_grid")
        check_pose(self.T_world_robot)
        log_odds = self.log_odds
        if (
            not isinstance(log_odds, np.ndarray)
            or log_odds.dtype != np.float32
            or log_odds.shape != self.world_grid.shape
        ):
            kind = (
                f"{log_odds.dtype} {log_odds.shape}"
                if isinstance(log_odds, np.ndarray)
                else type(log_odds).__name__
            )
            raise ValueError(
                f"log_odds: expected float32 of shape {self.world_grid.shape}, got {kind}"
            )
        if not np.isfinite(log_odds).all():
            raise ValueError(
                f"log_odds: {np.count_nonzero(~np.isfinite(log_odds))} cells are not finite"
            )
        thresholds = (self.free_threshold, self.occupied_threshold)
        if not (all(math.isfinite(v) for v in thresholds) and thresholds[0] <= thresholds[1]):
            raise ValueError(
                f"thresholds: need finite free_threshold <= occupied_threshold, got {thresholds}"
            )
        if not (math.isfinite(self.travelled_m) and self.travelled_m >= 0):
            raise ValueError(f"travelled_m: must be finite and >= 0, got {self.travelled_m}")
        # A read-only view: holders of the snapshot cannot change it (the grid's snapshot()
        # hands over a fresh copy nobody else holds).
        view = log_odds.view()
        view.setflags(write=False)
        object.__setattr__(self, "log_odds", view)
        remembered = self.remembered
        if remembered is not None:
            if (
                not isinstance(remembered, np.ndarray)
                or remembered.dtype != np.int8
                or remembered.shape != self.world_grid.shape
                or (remembered.size and not np.isin(remembered, CLASSES).all())
            ):
                raise ValueError(
                    f"remembered: expected int8 {UNKNOWN}/{FREE}/{OCCUPIED} of shape"
                    f" {self.world_grid.shape}, got"
                    f" {getattr(remembered, 'dtype', type(remembered).__name__)}"
                    f" {getattr(remembered, 'shape', '')}"
                )
            remembered_view = remembered.view()
            remembered_view.setflags(write=False)
            object.__setattr__(self, "remembered", remembered_view)

    def classify(self) -> NDArray[np.int8]:
        """(rows, cols) int8: ``UNKNOWN`` (-1), ``FREE`` (0), ``OCCUPIED`` (1)."""
        return classify_log_odds(
            self.log_odds,
            free_threshold=self.free_threshold,
            occupied_threshold=self.occupied_threshold,
        )

    def remembered_classes(self) -> NDArray[np.int8]:
        """`classify` with faded cells at their remembered class
        (`OccupancyGrid.remembered_classes`); `classify` for a map saved without memory."""
        return fill_remembered(self.classify(), self.remembered)


class OccupancyGrid:
    """A world-frame log-odds occupancy grid (see the module docstring).

    Parameters
    ----------
    world_grid : GroundGrid over the world frame, e.g. `OccupancyGrid.square`'s.
    params : OccupancyParams

    Attributes
    ----------
    log_odds : (rows, cols) float32, 0 = unknown; may be read (and, in tests, written).
    remembered : (rows, cols) int8, each cell's class (``FREE`` / ``OCCUPIED``) when it was
        last known before a decay, ``UNKNOWN`` if never (module docstring, 3).
    travelled_m : float, the robot's travel counted so far (metres, up to the anchor pose
        of the last decay).
    world_grid, params
    """

    def __init__(self, world_grid: GroundGrid, params: OccupancyParams | None = None) -> None:
        check_grid(world_grid, "world_grid")
        self.world_grid = world_grid
        self.params = params if params is not None else OccupancyParams()
        self.log_odds: NDArray[np.float32] = np.zeros(world_grid.shape, dtype=np.float32)
        self.remembered: NDArray[np.int8] = np.full(world_grid.shape, UNKNOWN, dtype=np.int8)
        self.travelled_m = 0.0
        self._anchor: Pose2D | None = None
        self._last_pose: Pose2D | None = None
        self._table: PolarTable | None = None

    @classmethod
    def square(
        cls, size_m: float = 20.0, cell_m: float = 0.05, params: OccupancyParams | None = None
    ) -> OccupancyGrid:
        """A ``size_m`` x ``size_m`` grid centred on the world origin (the robot's start)."""
        if not (size_m > 0 and cell_m > 0 and math.isfinite(size_m) and math.isfinite(cell_m)):
            raise ValueError(f"square: need size_m > 0 and cell_m > 0, got {size_m}, {cell_m}")
        half = size_m / 2
        grid = GroundGrid.covering(
            x_min_m=-half, x_max_m=half, y_min_m=-half, y_max_m=half, cell_m=cell_m
        )
        return cls(grid, params)

    def polar_table(
        self, patch_grid: GroundGrid, camera_xy_robot: tuple[float, float]
    ) -> PolarTable:
        """The rays for this patch geometry (built on first use, then reused)."""
        camera = check_xy(camera_xy_robot, "camera_xy_robot")
        table = self._table
        if table is None or table.patch_grid != patch_grid or table.camera_xy != camera:
            table = build_polar_table(patch_grid, camera)
            self._table = table
        return table

    def _advance(self, T_world_robot: Pose2D) -> bool:
        """Decay by the travel from the anchor pose once it reaches ``decay_step_m`` (see
        the module docstring). Returns whether the log-odds were multiplied."""
        self._last_pose = T_world_robot
        if self._anchor is None:
            self._anchor = T_world_robot
            return False
        step_m = self._pending_travel_m()
        if step_m < self.params.decay_step_m:
            return False
        self.travelled_m += step_m
        self._anchor = T_world_robot
        factor = decay_factor(step_m, self.params.half_distance_m)
        if factor == 1.0:
            return False
        # Only decay turns a known cell unknown without new evidence: remember it first.
        self._remember(self.remembered)
        self.log_odds *= np.float32(factor)
        return True

    def _remember(self, remembered: NDArray[np.int8]) -> None:
        """Write the grid's known classes (`classify`) into ``remembered``."""
        classes = self.classify()
        known = classes != UNKNOWN
        remembered[known] = classes[known]

    def _pending_travel_m(self) -> float:
        """Travel from the anchor to the last pose, not yet decayed."""
        if self._anchor is None or self._last_pose is None:
            return 0.0
        return travel_m(self._anchor, self._last_pose, self.params.turn_radius_m)

    def update(
        self,
        patch: NDArray[np.uint8],
        patch_grid: GroundGrid,
        T_world_robot: Pose2D,
        camera_xy_robot: tuple[float, float],
        standing: NDArray[np.bool_] | None = None,
    ) -> UpdateSummary:
        """Fuse one robot-frame ground patch seen at ``T_world_robot``; the travel from the
        previous update's pose decays the evidence first (see the module docstring).

        Parameters
        ----------
        patch : (patch_grid.rows, patch_grid.cols) uint8 of ``FLOOR`` / ``NOT_FLOOR`` /
            ``UNSEEN``.
        patch_grid : GroundGrid of the patch in the robot frame.
        T_world_robot : Pose2D, the robot's pose in the world when the frame was taken.
        camera_xy_robot : (x, y) metres, the camera's position on the floor in the robot
            frame (the rays' origin).
        standing : (patch_grid.rows, patch_grid.cols) bool or None, not-floor cells
            geometry saw standing: mapped out to the free range (see `cast_rays`).

        Returns
        -------
        UpdateSummary
        """
        check_grid(patch_grid, "patch_grid")
        check_cell_sizes(patch_grid, self.world_grid)
        check_pose(T_world_robot)
        check_patch(patch, patch_grid)
        _check_standing(standing, patch_grid)
        table = self.polar_table(patch_grid, camera_xy_robot)
        decayed = self._advance(T_world_robot)
        labels = _cast_checked(
            patch,
            table,
            float(self.params.obstacle_band_m),
            float(self.params.free_max_range_m),
            float(self.params.occupied_max_range_m),
            float(self.params.far_boundary_margin_m),
            standing,
        )
        world_free, world_occ = fuse_patch_labels(
            self.log_odds, self.world_grid, labels, patch_grid, T_world_robot, self.params
        )
        patch_occ = int(np.count_nonzero(labels == PATCH_OCCUPIED))
        patch_free = int(np.count_nonzero(labels)) - patch_occ
        return UpdateSummary(patch_free, patch_occ, world_free, world_occ, decayed)

    def classify(self) -> NDArray[np.int8]:
        """(rows, cols) int8: ``UNKNOWN`` (-1), ``FREE`` (0), ``OCCUPIED`` (1)."""
        return classify_log_odds(
            self.log_odds,
            free_threshold=self.params.free_threshold,
            occupied_threshold=self.params.occupied_threshold,
        )

    def remembered_classes(self) -> NDArray[np.int8]:
        """`classify`, with each cell that decay has made unknown given its last known
        class (`remembered`): the map to plan and explore on (module docstring, 3)."""
        return fill_remembered(self.classify(), self.remembered)

    def probabilities(self) -> NDArray[np.float32]:
        """(rows, cols) float32 occupancy probabilities, 0.5 where unknown."""
        return log_odds_to_probability(self.log_odds)

    def snapshot(self) -> SavedMap:
        """A consistent read-only copy of the grid for saving, with the pending travel
        (anchor to last pose) decayed and counted in the copy; the grid itself is not
        changed. Take it in the thread that updates the grid; the copy may then be used
        anywhere."""
        pending_m = self._pending_travel_m()
        factor = np.float32(decay_factor(pending_m, self.params.half_distance_m))
        remembered = self.remembered.copy()
        if factor != 1:
            self._remember(remembered)
        log_odds = self.log_odds * factor if factor != 1 else self.log_odds.copy()
        return SavedMap(
            log_odds=log_odds,
            world_grid=self.world_grid,
            free_threshold=self.params.free_threshold,
            occupied_threshold=self.params.occupied_threshold,
            T_world_robot=self._last_pose if self._last_pose is not None else Pose2D(),
            travelled_m=self.travelled_m + pending_m,
            remembered=remembered,
        )

    def restore(self, snapshot: SavedMap) -> None:
        """Replace the grid's state with ``snapshot``'s: its log-odds (clamped to this
        grid's ``[clamp_min, clamp_max]``), its travel, and its robot pose as the anchor the
        next update's travel is measured from. The caller places the robot at
        ``snapshot.T_world_robot`` in the map's frame (or the jump counts as travel).

        Raises
        ------
        ValueError
            Not a `SavedMap`, or one of another world grid (the message names both);
            the grid is then unchanged.
        """
        if not isinstance(snapshot, SavedMap):
            raise ValueError(f"snapshot: expected a SavedMap, got {type(snapshot).__name__}")
        if not same_geometry(snapshot.world_grid, self.world_grid):
            raise ValueError(
                f"snapshot: the map's grid is {describe_grid(snapshot.world_grid)} but this"
                f" grid is {describe_grid(self.world_grid)}"
            )
        np.clip(snapshot.log_odds, self.params.clamp_min, self.params.clamp_max, out=self.log_odds)
        if snapshot.remembered is not None:
            self.remembered[...] = snapshot.remembered
        else:  # a map saved before the layer existed: what it knows now
            self.remembered.fill(UNKNOWN)
            self._remember(self.remembered)
        self.travelled_m = snapshot.travelled_m
        self._anchor = snapshot.T_world_robot
        self._last_pose = snapshot.T_world_robot

    def reset(self) -> None:
        """Forget all evidence, the travel and the poses (the ray table is kept)."""
        self.log_odds.fill(0.0)
        self.remembered.fill(UNKNOWN)
        self.travelled_m = 0.0
        self._anchor = None
        self._last_pose = None
