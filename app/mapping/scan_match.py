"""Where the robot is in its own map: a virtual range scan read off a bird's-eye floor
patch, and correlative scan matching of that scan against the occupancy grid.

Wheel odometry drifts (slip, tyre scale errors), and a map fused at drifting poses
smears: walls double, free space leaks. A monocular camera has no range sensor, but its
bird's-eye floor patch holds the same information a planar laser scanner would give: along
each bearing from the camera, the floor ends where something stands on it. `virtual_scan`
reads those floor boundaries (the cells the occupancy grid marks occupied, by the same
ray rule as `app.mapping.occupancy.cast_rays`), and `match_scan` finds the pose near the
odometry's at which they best fall on the map's occupied cells.

Matching (Olson, "Real-Time Correlative Scan Matching", ICRA 2009): the map's occupied
cells are blurred into a likelihood field (`likelihood_field`: a Gaussian of the
distance to the nearest occupied cell), and every candidate pose in a window around the
prior (theta steps x an x/y lattice) is scored by the mean field value at the scan's
endpoints. The search is exhaustive, so it cannot get stuck in a local optimum inside
the window: a coarse pass over the whole window, then a fine pass around the coarse
best. The coarse pass's score volume, read as a likelihood, gives the match's
covariance: a scan of one straight wall scores the same anywhere along the wall, and its
covariance is long in that direction, so `ScanMatch.confident` rejects it rather than
letting it drag the pose along the wall.

`ScanLocalizer` puts it together for the mapper: every ``period_s``, once the map holds
enough occupied cells, it matches the frame's scan around the odometry pose and returns
a blended, capped correction to left-multiply onto odometry (``T_corrected_odom``).

Frames: the robot frame and ``T_world_robot`` as in `app.mapping.frames`; the world frame
is the occupancy grid's (odometry's). Pure computation (numpy, numba nogil kernels).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from app.mapping.frames import FLOOR, NOT_FLOOR, GroundGrid, Pose2D

SCAN_BEARING_STEP_RAD = math.radians(1.0)
"""Bearing between neighbouring rays of the mapper's virtual scan: at the patch's 3 m
range neighbouring endpoints are ~5 cm (one map cell) apart, so the scan samples every
wall the map holds about once per cell (~60 rays over the simulated camera's view)."""


# ---------------------------------------------------------------------- virtual scan


@dataclass(frozen=True, eq=False)
class VirtualScan:
    """One range per bearing from ``origin_xy`` (the camera, robot frame).

    Attributes
    ----------
    bearings_rad : (R,) float64, counter-clockwise from the robot's x axis.
    ranges_m : (R,) float64, distance from the origin to the floor boundary; NaN where
        the ray has no return.
    hit : (R,) bool, the ray has a return.
    points_robot : (H,) x 2 float64, the returns' endpoints in the robot frame.
    origin_xy : (x, y) of the rays' origin in the robot frame.
    """

    bearings_rad: NDArray[np.float64] = field(repr=False)
    ranges_m: NDArray[np.float64] = field(repr=False)
    hit: NDArray[np.bool_] = field(repr=False)
    points_robot: NDArray[np.float64] = field(repr=False)
    origin_xy: tuple[float, float]


@numba.njit(cache=True, nogil=True)
def _scan_kernel(
    patch: NDArray[np.uint8],
    a0: float,
    b0: float,
    bearings: NDArray[np.float64],
    max_cells: float,
    max_gap_cells: float,
    ranges: NDArray[np.float64],
) -> None:
    """Amanatides-Woo traversal of each ray ``(a0, b0) + t (-cos, -sin)(bearing)`` in
    continuous (row, col) cell units; writes the entry range (cells) of the first
    not-floor cell after floor, or NaN."""
    rows, cols = patch.shape
    for k in range(bearings.shape[0]):
        ranges[k] = np.nan
        da = -math.cos(bearings[k])
        db = -math.sin(bearings[k])
        t0 = 0.0
        t1 = max_cells
        if da != 0.0:
            ta, tb = (0.0 - a0) / da, (rows - a0) / da
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif a0 < 0.0 or a0 >= rows:
            continue
        if db != 0.0:
            ta, tb = (0.0 - b0) / db, (cols - b0) / db
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif b0 < 0.0 or b0 >= cols:
            continue
        if t0 >= t1:
            continue
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
        seen_floor = False
        gap_from = -1.0
        while t < t1:
            t_next = min(t_max_i, t_max_j)
            v = patch[i, j]
            if v == FLOOR:
                seen_floor = True
                gap_from = -1.0
            elif v == NOT_FLOOR:
                if seen_floor:
                    ranges[k] = t
                break
            elif seen_floor:
                # Unseen after floor: a short gap is tolerated (a ray grazing the view's
                # edge), a long one means the ray ran out of seen floor.
                if gap_from < 0.0:
                    gap_from = t
                if t_next - gap_from > max_gap_cells:
                    break
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


def virtual_scan(
    patch: NDArray[np.uint8],
    patch_grid: GroundGrid,
    origin_xy: tuple[float, float],
    bearings_rad: NDArray[np.floating],
    *,
    max_range_m: float,
    max_gap_m: float = 0.1,
    endpoint_depth_m: float = 0.0,
) -> VirtualScan:
    """The floor boundary along each bearing from ``origin_xy``, like a laser's hits.

    Along a ray, unseen cells before the first floor are passed (the camera does not
    see the floor right in front of it), seen ``FLOOR`` continues the ray, and the first
    ``NOT_FLOOR`` cell after floor is the return (its entry point). No return when the
    ray meets not-floor before any floor (the obstacle's foot is out of view), runs
    through more than ``max_gap_m`` of unseen cells after floor (out of seen floor),
    leaves the patch, or reaches ``max_range_m``.

    Parameters
    ----------
    patch : (rows, cols) uint8 of ``FLOOR`` / ``NOT_FLOOR`` / ``UNSEEN`` on ``patch_grid``
        (robot frame).
    origin_xy : the rays' origin in the robot frame (the camera's foot).
    bearings_rad : (R,) ray directions, counter-clockwise from the robot's x axis.
    endpoint_depth_m : the endpoints lie this far beyond the boundary along their rays
        (``ranges_m`` stay the boundary's). The map marks a band of ``obstacle_band_m``
        beyond the boundary occupied, so its occupied cells centre half a band deep:
        endpoints there match them without bias. A bias would pull every match towards
        the walls in view, and the map fused at the pulled pose further still.
    """
    if patch.shape != patch_grid.shape or patch.dtype != np.uint8:
        raise ValueError(f"patch: expected uint8 of shape {patch_grid.shape}")
    if not (max_range_m > 0 and max_gap_m >= 0 and endpoint_depth_m >= 0):
        raise ValueError("virtual_scan: need max_range_m > 0, max_gap_m, endpoint_depth_m >= 0")
    bearings = np.ascontiguousarray(bearings_rad, dtype=np.float64).ravel()
    cell = patch_grid.cell_m
    ranges = np.empty(bearings.shape[0], dtype=np.float64)
    _scan_kernel(
        np.ascontiguousarray(patch),
        (patch_grid.x_max_m - origin_xy[0]) / cell,
        (patch_grid.y_max_m - origin_xy[1]) / cell,
        bearings,
        max_range_m / cell,
        max_gap_m / cell,
        ranges,
    )
    ranges *= cell
    hit = ~np.isnan(ranges)
    depth = ranges[hit] + endpoint_depth_m
    points = np.column_stack(
        (
            origin_xy[0] + depth * np.cos(bearings[hit]),
            origin_xy[1] + depth * np.sin(bearings[hit]),
        )
    )
    return VirtualScan(bearings, ranges, hit, points, (float(origin_xy[0]), float(origin_xy[1])))


def view_bearings(
    visible: NDArray[np.bool_],
    patch_grid: GroundGrid,
    origin_xy: tuple[float, float],
    step_rad: float = SCAN_BEARING_STEP_RAD,
) -> NDArray[np.float64]:
    """Bearings every ``step_rad`` across the camera's view: the angular extent of the
    patch's ``visible`` cells seen from ``origin_xy`` (rays outside it never return)."""
    x, y = patch_grid.cell_centers()
    angles = np.arctan2(y[visible] - origin_xy[1], x[visible] - origin_xy[0])
    if angles.size == 0:
        return np.zeros(0, dtype=np.float64)
    low, high = float(angles.min()), float(angles.max())
    n = max(1, math.floor((high - low) / step_rad) + 1)
    centre = (low + high) / 2
    return np.asarray(centre + (np.arange(n) - (n - 1) / 2) * step_rad, dtype=np.float64)


# ----------------------------------------------------------------- likelihood field


@dataclass(frozen=True, eq=False)
class LikelihoodField:
    """How well a point at each cell would fit the map: ``exp(-d^2 / 2 sigma^2)`` of
    the distance ``d`` to the nearest occupied cell (1 on one, ~0 beyond 3 sigma).

    Attributes
    ----------
    values : (rows, cols) float32 on ``grid`` (a window of the world grid).
    grid : GroundGrid of the window, in the world frame.
    occupied_cells : occupied cells in the window.
    """

    values: NDArray[np.float32] = field(repr=False)
    grid: GroundGrid
    occupied_cells: int

    @property
    def padded(self) -> NDArray[np.float32]:
        """``values`` with a border of one zero cell (what the scoring kernel reads)."""
        padded = self.__dict__.get("_padded")
        if padded is None:
            padded = np.pad(self.values, 1).astype(np.float32)
            object.__setattr__(self, "_padded", padded)
        return padded


def likelihood_field(
    log_odds: NDArray[np.floating],
    world_grid: GroundGrid,
    center_xy: tuple[float, float],
    radius_m: float,
    *,
    occupied_threshold: float,
    sigma_m: float,
) -> LikelihoodField:
    """The likelihood field of the square of half-side ``radius_m`` around
    ``center_xy`` (clipped to the grid): cells above ``occupied_threshold`` are the
    map's obstacles. ``sigma_m`` is the blur: about the map's cell plus the scan's
    noise."""
    if not (radius_m > 0 and sigma_m > 0):
        raise ValueError("likelihood_field: need radius_m > 0 and sigma_m > 0")
    cell = world_grid.cell_m
    half = math.ceil(radius_m / cell)
    row, col = (int(v) for v in world_grid.cell_of(np.array([center_xy]))[0])
    r0, r1 = max(0, row - half), min(world_grid.rows, row + half + 1)
    c0, c1 = max(0, col - half), min(world_grid.cols, col + half + 1)
    if r0 >= r1 or c0 >= c1:
        r0, r1, c0, c1 = 0, 1, 0, 1
    window = GroundGrid(
        world_grid.x_max_m - r0 * cell, world_grid.y_max_m - c0 * cell, cell, r1 - r0, c1 - c0
    )
    occupied = np.asarray(log_odds[r0:r1, c0:c1] > occupied_threshold)
    n_occupied = int(np.count_nonzero(occupied))
    if n_occupied == 0:
        return LikelihoodField(np.zeros(window.shape, np.float32), window, 0)
    free = np.where(occupied, 0, 255).astype(np.uint8)
    distance = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    scaled = np.asarray(distance, dtype=np.float32) * np.float32(cell / sigma_m)
    values = np.exp(np.float32(-0.5) * scaled * scaled).astype(np.float32)
    return LikelihoodField(values, window, n_occupied)


# ------------------------------------------------------------------------- matching


@dataclass(frozen=True)
class MatchParams:
    """The search window around the prior and its lattices, and what a confident match
    needs.

    Attributes
    ----------
    window_m, window_rad : the search covers prior +- these in x, y and theta.
    coarse_step_m, coarse_step_rad : the coarse lattice over the whole window: half a
        map cell, and half a cell of travel at 3 m, so the lattice point next to the
        true pose always outscores a wrong heading's translation that makes up for it.
    fine_step_m, fine_step_rad : the fine lattice over +- one coarse step around each
        of the ``refine_candidates`` best separate coarse peaks.
    temperature : per-point score difference that counts as a factor e less likely in
        the covariance (the field's 1-cell drop is ~0.4 per point on a wall).
    min_points : fewer scan points give no match.
    min_score : mean field value at the best pose below this is no match (the scan does
        not fit the map there: a new room, a changed one, a bad floor mask).
    max_xy_std_m, max_theta_std_rad : a confident match is at least this sharp in every
        direction (a uniform spread over a +-0.15 m window has a std of 0.087 m).
    """

    window_m: float = 0.15
    window_rad: float = 0.105
    coarse_step_m: float = 0.025
    coarse_step_rad: float = math.radians(0.5)
    fine_step_m: float = 0.01
    fine_step_rad: float = math.radians(0.125)
    refine_candidates: int = 3
    temperature: float = 0.005
    min_points: int = 20
    min_score: float = 0.35
    max_xy_std_m: float = 0.04
    max_theta_std_rad: float = math.radians(2.0)

    def __post_init__(self) -> None:
        positive = (
            "window_m",
            "window_rad",
            "coarse_step_m",
            "coarse_step_rad",
            "fine_step_m",
            "fine_step_rad",
            "temperature",
            "max_xy_std_m",
            "max_theta_std_rad",
        )
        for name in positive:
            value = getattr(self, name)
            if not 0 < value < math.inf:
                raise ValueError(f"MatchParams.{name} must be finite and > 0, got {value}")
        if self.fine_step_m > self.coarse_step_m or self.fine_step_rad > self.coarse_step_rad:
            raise ValueError("MatchParams: fine steps must not exceed the coarse ones")
        if self.refine_candidates < 1:
            raise ValueError("MatchParams.refine_candidates must be >= 1")
        if self.min_points < 1 or not 0 <= self.min_score <= 1:
            raise ValueError("MatchParams: need min_points >= 1 and 0 <= min_score <= 1")


@dataclass(frozen=True)
class ScanMatch:
    """The best pose in the window and how much to trust it.

    Attributes
    ----------
    T_world_robot : the best pose.
    score : mean field value at the scan's points there (0..1).
    prior_score : the same at the prior pose.
    covariance : (3, 3) of (x_m, y_m, theta_rad) from the coarse score volume.
    points : scan points used.
    """

    T_world_robot: Pose2D
    score: float
    prior_score: float
    covariance: NDArray[np.float64] = field(repr=False)
    points: int

    @property
    def xy_std_m(self) -> float:
        """The position's std along its least certain direction."""
        return math.sqrt(max(0.0, float(np.linalg.eigvalsh(self.covariance[:2, :2])[-1])))

    @property
    def theta_std_rad(self) -> float:
        return math.sqrt(max(0.0, float(self.covariance[2, 2])))

    def confident(self, params: MatchParams) -> bool:
        """Enough points, a good fit, and sharp in every direction."""
        return (
            self.points >= params.min_points
            and self.score >= params.min_score
            and self.xy_std_m <= params.max_xy_std_m
            and self.theta_std_rad <= params.max_theta_std_rad
        )


@numba.njit(cache=True, nogil=True)
def _score_kernel(
    padded: NDArray[np.float32],
    x_max: float,
    y_max: float,
    cell: float,
    px: NDArray[np.float64],
    py: NDArray[np.float64],
    x0: float,
    y0: float,
    theta0: float,
    thetas: NDArray[np.float64],
    dxs: NDArray[np.float64],
    dys: NDArray[np.float64],
    scores: NDArray[np.float64],
) -> None:
    """``scores[a, b, c]``: the mean field value of the points ``(px, py)`` (robot frame)
    at the pose ``(x0 + dxs[b], y0 + dys[c], theta0 + thetas[a])``, interpolated
    bilinearly between cell centres. ``padded`` is the field with a border of one zero
    cell, so a point whose 2 x 2 neighbourhood leaves it scores exactly 0 and the inner
    loop needs one range check, not four."""
    rows, cols = padded.shape
    n = px.shape[0]
    # Continuous (row, col) in the padded raster, shifted to put cell centres on integers.
    u = np.empty(n)
    v = np.empty(n)
    for a in range(thetas.shape[0]):
        c = math.cos(theta0 + thetas[a])
        s = math.sin(theta0 + thetas[a])
        for p in range(n):
            u[p] = (x_max - (c * px[p] - s * py[p] + x0)) / cell + 0.5
            v[p] = (y_max - (s * px[p] + c * py[p] + y0)) / cell + 0.5
        for b in range(dxs.shape[0]):
            du = -dxs[b] / cell
            for d in range(dys.shape[0]):
                dv = -dys[d] / cell
                total = 0.0
                for p in range(n):
                    fu = u[p] + du
                    fv = v[p] + dv
                    i = math.floor(fu)
                    j = math.floor(fv)
                    if i < 0 or j < 0 or i >= rows - 1 or j >= cols - 1:
                        continue
                    wu = fu - i
                    wv = fv - j
                    top = padded[i, j] + wv * (padded[i, j + 1] - padded[i, j])
                    bottom = padded[i + 1, j] + wv * (padded[i + 1, j + 1] - padded[i + 1, j])
                    total += top + wu * (bottom - top)
                scores[a, b, d] = total / n


def _lattice(half_width: float, step: float) -> NDArray[np.float64]:
    """Offsets ``k * step`` covering [-half_width, half_width], 0 included."""
    n = math.ceil(half_width / step - 1e-9)
    return np.arange(-n, n + 1, dtype=np.float64) * step


def _scores(
    field_: LikelihoodField,
    points: NDArray[np.float64],
    prior: Pose2D,
    thetas: NDArray[np.float64],
    dxs: NDArray[np.float64],
    dys: NDArray[np.float64],
) -> NDArray[np.float64]:
    scores = np.empty((thetas.size, dxs.size, dys.size), dtype=np.float64)
    grid = field_.grid
    _score_kernel(
        field_.padded,
        grid.x_max_m,
        grid.y_max_m,
        grid.cell_m,
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        prior.x_m,
        prior.y_m,
        prior.theta_rad,
        thetas,
        dxs,
        dys,
        scores,
    )
    return scores


def _covariance(
    scores: NDArray[np.float64],
    thetas: NDArray[np.float64],
    dxs: NDArray[np.float64],
    dys: NDArray[np.float64],
    temperature: float,
    steps: tuple[float, float],
) -> NDArray[np.float64]:
    """Covariance of (x, y, theta) under weights ``exp((score - best) / temperature)``
    over the lattice, plus each lattice step's own uniform variance."""
    weights = np.exp((scores - scores.max()) / temperature)
    weights /= weights.sum()
    t, x, y = np.meshgrid(thetas, dxs, dys, indexing="ij")
    samples = np.stack((x.ravel(), y.ravel(), t.ravel()))
    w = weights.ravel()
    mean = samples @ w
    centred = samples - mean[:, None]
    cov = (centred * w) @ centred.T
    step_m, step_rad = steps
    cov += np.diag([step_m**2 / 12, step_m**2 / 12, step_rad**2 / 12])
    return np.asarray(cov, dtype=np.float64)


def match_scan(
    field_: LikelihoodField,
    points_robot: NDArray[np.floating],
    T_world_robot: Pose2D,
    params: MatchParams | None = None,
) -> ScanMatch:
    """Correlative scan matching: the pose within ``params``' window around the prior
    ``T_world_robot`` at which the scan's points (robot frame) best fit the field.

    A coarse pass scores the whole window (its score volume gives the covariance), fine
    passes score +- one coarse step around its best few separate peaks; ties go to the
    offset nearest the prior. With fewer than ``min_points`` points the prior comes back with
    a score of 0.
    """
    params = params if params is not None else MatchParams()
    points = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
    if points.shape[0] < params.min_points:
        return ScanMatch(T_world_robot, 0.0, 0.0, np.diag([np.inf, np.inf, np.inf]), len(points))
    coarse = (
        _lattice(params.window_rad, params.coarse_step_rad),
        _lattice(params.window_m, params.coarse_step_m),
        _lattice(params.window_m, params.coarse_step_m),
    )
    scores = _scores(field_, points, T_world_robot, *coarse)
    centre = tuple(n // 2 for n in scores.shape)
    prior_score = float(scores[centre])
    covariance = _covariance(
        scores, *coarse, params.temperature, (params.coarse_step_m, params.coarse_step_rad)
    )
    best_score = -math.inf
    offsets = (0.0, 0.0, 0.0)
    for a, b, c in _candidates(scores, coarse, params.refine_candidates):
        fine = (
            coarse[0][a] + _lattice(params.coarse_step_rad, params.fine_step_rad),
            coarse[1][b] + _lattice(params.coarse_step_m, params.fine_step_m),
            coarse[2][c] + _lattice(params.coarse_step_m, params.fine_step_m),
        )
        fine_scores = _scores(field_, points, T_world_robot, *fine)
        fa, fb, fc = _best(fine_scores, fine)
        if fine_scores[fa, fb, fc] > best_score + 1e-9:
            best_score = float(fine_scores[fa, fb, fc])
            offsets = (float(fine[0][fa]), float(fine[1][fb]), float(fine[2][fc]))
    d_theta, dx, dy = offsets
    best = Pose2D(
        T_world_robot.x_m + dx,
        T_world_robot.y_m + dy,
        math.remainder(T_world_robot.theta_rad + d_theta, math.tau),
    )
    return ScanMatch(best, best_score, prior_score, covariance, int(points.shape[0]))


def _candidates(
    scores: NDArray[np.float64],
    lattice: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    count: int,
) -> list[tuple[int, int, int]]:
    """The coarse best (ties to the prior) and the next best lattice points that are
    not next to an earlier one, up to ``count``: a wrong heading's translation that
    makes up for it can outscore the lattice point next to the truth by a little, and
    refining a few separate peaks finds the truth anyway."""
    picked = [_best(scores, lattice)]
    flat_scores = scores.ravel()
    top = min(flat_scores.size, 64 * count)
    head = np.argpartition(flat_scores, flat_scores.size - top)[flat_scores.size - top :]
    for flat in head[np.argsort(flat_scores[head])[::-1]]:
        if len(picked) >= count:
            break
        here = np.unravel_index(int(flat), scores.shape)
        if all(max(abs(int(h) - q) for h, q in zip(here, p, strict=True)) > 1 for p in picked):
            picked.append((int(here[0]), int(here[1]), int(here[2])))
    return picked


def _best(
    scores: NDArray[np.float64],
    lattice: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
) -> tuple[int, int, int]:
    """Index of the highest score; among (near-)equal ones the offset nearest zero, so
    that a flat score (nothing to match) leaves the prior where it is."""
    ties = np.flatnonzero(scores.ravel() >= scores.max() - 1e-9)
    pick = int(ties[0])
    if ties.size > 1:
        ta, tb, tc = np.unravel_index(ties, scores.shape)
        t, x, y = lattice
        # Angles weigh as their arc at 1 m: 1 degree ~ 1.7 cm.
        distance = np.hypot(np.hypot(x[tb], y[tc]), t[ta])
        pick = int(ties[int(np.argmin(distance))])
    a, b, c = np.unravel_index(pick, scores.shape)
    return int(a), int(b), int(c)


# ------------------------------------------------------------------------ localizer


@dataclass(frozen=True)
class LocalizerParams:
    """How the mapper localizes against its map.

    Attributes
    ----------
    period_s : at most one match per this much (frame) time: drift builds up over
        seconds, and a match every frame would cost ~1-3 ms each for nothing.
    endpoint_depth_m : half the map's obstacle band (`virtual_scan`).
    gain_frac : the fraction of the matched offset applied per match (the rest waits
        for the next ones, so one wrong match moves the pose only part of the way).
    max_step_m, max_step_rad : the most one correction moves the pose.
    min_occupied_cells : the map window needs this many occupied cells to match against.
    max_range_m : the scan's range (the patch's trusted range).
    field_sigma_m : the likelihood field's blur.
    known_floor_m : a scan point is used only when the map holds the floor at one of
        these distances before it along its ray as free (`known_to_map`).
    min_score_gain : a match corrects only when it fits this much better (mean field
        value per point) than the odometry pose: within a centimetre or so of the
        truth the score is flat to the map's cells, and moving the pose about there
        would only jitter it (and smear the map of a robot standing still).
    match : the search (`MatchParams`).
    """

    period_s: float = 0.25
    endpoint_depth_m: float = 0.015
    known_floor_m: tuple[float, ...] = (0.1, 0.2, 0.3)
    min_score_gain: float = 0.005
    gain_frac: float = 0.5
    max_step_m: float = 0.03
    max_step_rad: float = 0.02
    min_occupied_cells: int = 40
    max_range_m: float = 3.0
    field_sigma_m: float = 0.05
    match: MatchParams = MatchParams()

    def __post_init__(self) -> None:
        if not (0 < self.gain_frac <= 1):
            raise ValueError(f"LocalizerParams.gain_frac must be in (0, 1], got {self.gain_frac}")
        positive = (
            "period_s",
            "max_step_m",
            "max_step_rad",
            "max_range_m",
            "field_sigma_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not 0 < value < math.inf:
                raise ValueError(f"LocalizerParams.{name} must be finite and > 0, got {value}")
        if self.min_occupied_cells < 1:
            raise ValueError("LocalizerParams.min_occupied_cells must be >= 1")
        if not (self.known_floor_m and all(0 < d < math.inf for d in self.known_floor_m)):
            raise ValueError("LocalizerParams.known_floor_m must hold distances > 0")
        if not 0 <= self.min_score_gain < 1:
            raise ValueError("LocalizerParams.min_score_gain must be in [0, 1)")
        if not 0 <= self.endpoint_depth_m < math.inf:
            raise ValueError("LocalizerParams.endpoint_depth_m must be finite and >= 0")


def known_to_map(
    scan: VirtualScan,
    log_odds: NDArray[np.floating],
    world_grid: GroundGrid,
    T_world_robot: Pose2D,
    *,
    free_threshold: float,
    back_m: tuple[float, ...],
) -> NDArray[np.bool_]:
    """Which of the scan's points (``scan.points_robot``) the map can judge: those whose
    floor before the boundary along the ray is free in the map at ``T_world_robot``, at
    any of the distances ``back_m`` (several, so that a prior a window's width off
    still finds it).

    Why: a wall the robot is just turning to see continues past the map's end. Its new
    points find no obstacle where they fall, but would find the mapped part of the same
    wall if the pose slid along it, so they pull every match along the walls towards
    the mapped part, with odometry right. The floor in front of a wall is mapped by the
    same rays as the wall, so a point whose floor is unknown is one the map cannot
    judge, and it is left out.
    """
    hit = scan.hit
    bearings = scan.bearings_rad[hit]
    known = np.zeros(bearings.size, dtype=bool)
    for back in back_m:
        reach = np.maximum(scan.ranges_m[hit] - back, 0.0)
        robot = np.column_stack(
            (
                scan.origin_xy[0] + reach * np.cos(bearings),
                scan.origin_xy[1] + reach * np.sin(bearings),
            )
        )
        cells = world_grid.cell_of(T_world_robot.apply(robot))
        rows, cols = cells[:, 0], cells[:, 1]
        inside = (rows >= 0) & (rows < world_grid.rows) & (cols >= 0) & (cols < world_grid.cols)
        free = np.zeros(bearings.size, dtype=bool)
        free[inside] = log_odds[rows[inside], cols[inside]] < free_threshold
        known |= free
    return known


@dataclass(frozen=True)
class Localization:
    """One match the localizer ran.

    Attributes
    ----------
    match : the scan match.
    seconds : what the scan, the field and the search took.
    T_corrected_odom : None unless the match was confident; else left-multiply it onto
        odometry poses: ``T_corrected_odom.compose(T_odom_robot)`` is the corrected
        pose (the odometry frame stays the map's).
    """

    match: ScanMatch
    seconds: float
    T_corrected_odom: Pose2D | None


class ScanLocalizer:
    """Matches a frame's virtual scan against the map every ``period_s`` and turns a
    confident match into a blended, capped pose correction. Not thread-safe (the mapper
    owns it).

    Parameters
    ----------
    params : LocalizerParams
    patch_grid : the bird's-eye patch's geometry (robot frame)
    origin_xy : the camera's position in the robot frame (the rays' origin)
    bearings_rad : the scan's ray directions (`view_bearings`)
    """

    def __init__(
        self,
        params: LocalizerParams,
        patch_grid: GroundGrid,
        origin_xy: tuple[float, float],
        bearings_rad: NDArray[np.float64],
    ) -> None:
        self.params = params
        self.patch_grid = patch_grid
        self.origin_xy = origin_xy
        self.bearings_rad = bearings_rad
        self._due_s = -math.inf
        self.attempts = 0
        """Matches run (the scan had enough points and the map enough obstacles)."""
        self.applied = 0
        """Matches confident enough to correct the pose."""

    def due(self, now_s: float) -> bool:
        return now_s >= self._due_s

    def scan_and_field(
        self,
        patch: NDArray[np.uint8],
        log_odds: NDArray[np.floating],
        world_grid: GroundGrid,
        thresholds: tuple[float, float],
        T_world_robot: Pose2D,
    ) -> tuple[NDArray[np.float64], LikelihoodField] | None:
        """What a match at ``T_world_robot`` is made of: the scan's points the map can
        judge (robot frame) and the likelihood field around the pose; None with too
        few of either."""
        p = self.params
        scan = virtual_scan(
            patch,
            self.patch_grid,
            self.origin_xy,
            self.bearings_rad,
            max_range_m=p.max_range_m,
            endpoint_depth_m=p.endpoint_depth_m,
        )
        free_threshold, occupied_threshold = thresholds
        known = known_to_map(
            scan,
            log_odds,
            world_grid,
            T_world_robot,
            free_threshold=free_threshold,
            back_m=p.known_floor_m,
        )
        points = scan.points_robot[known]
        if points.shape[0] < p.match.min_points:
            return None
        reach = p.max_range_m + math.hypot(*self.origin_xy) + p.match.window_m
        field_ = likelihood_field(
            log_odds,
            world_grid,
            (T_world_robot.x_m, T_world_robot.y_m),
            reach + 3 * p.field_sigma_m,
            occupied_threshold=occupied_threshold,
            sigma_m=p.field_sigma_m,
        )
        if field_.occupied_cells < p.min_occupied_cells:
            return None
        return points, field_

    def localize(
        self,
        patch: NDArray[np.uint8],
        log_odds: NDArray[np.floating],
        world_grid: GroundGrid,
        thresholds: tuple[float, float],
        T_world_robot: Pose2D,
        now_s: float,
    ) -> Localization | None:
        """Match the robot at ``T_world_robot`` (odometry) seeing ``patch`` against the
        map (``log_odds`` with its free and occupied ``thresholds``); None when not due,
        or with too little scan or map to match. Call it before the frame is fused: a
        frame must not be matched against its own evidence."""
        if not self.due(now_s):
            return None
        self._due_s = now_s + self.params.period_s
        start_s = time.perf_counter()
        p = self.params
        found = self.scan_and_field(patch, log_odds, world_grid, thresholds, T_world_robot)
        if found is None:
            return None
        points, field_ = found
        self.attempts += 1
        match = match_scan(field_, points, T_world_robot, p.match)
        correction = None
        if match.confident(p.match) and match.score - match.prior_score >= p.min_score_gain:
            self.applied += 1
            corrected = blend(T_world_robot, match.T_world_robot, p)
            correction = corrected.compose(T_world_robot.inverse())
        return Localization(match, time.perf_counter() - start_s, correction)


def blend(prior: Pose2D, matched: Pose2D, params: LocalizerParams) -> Pose2D:
    """``prior`` moved ``gain_frac`` of the way to ``matched`` (position and heading
    separately, about the robot, not the world origin), each step capped."""
    dx = params.gain_frac * (matched.x_m - prior.x_m)
    dy = params.gain_frac * (matched.y_m - prior.y_m)
    step = math.hypot(dx, dy)
    if step > params.max_step_m:
        dx, dy = dx * params.max_step_m / step, dy * params.max_step_m / step
    d_theta = params.gain_frac * math.remainder(matched.theta_rad - prior.theta_rad, math.tau)
    d_theta = max(-params.max_step_rad, min(params.max_step_rad, d_theta))
    return Pose2D(
        prior.x_m + dx, prior.y_m + dy, math.remainder(prior.theta_rad + d_theta, math.tau)
    )
