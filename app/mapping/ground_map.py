"""The mapping stage in one object: floor mask -> bird's-eye ground patch -> world
occupancy grid -> frontiers. Pure computation on arrays; the caller loads the
calibration and supplies poses and times."""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import CameraConfig, MappingConfig
from app.mapping.calibration import FloorCalibration
from app.mapping.floor_memory import FloorMemory, patch_world_index
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D
from app.mapping.frontiers import (
    FrontierParams,
    FrontierSearch,
    find_frontiers,
    inflate_obstacles,
    stamp_disk,
)
from app.mapping.ipm import (
    BirdseyeMap,
    birdseye_floor_patch,
    build_birdseye_map,
    build_ground_lookup,
)
from app.mapping.manhattan import HeadingAxis, ManhattanParams, floor_edge_segments
from app.mapping.occupancy import (
    OCCUPIED,
    OccupancyGrid,
    OccupancyParams,
    SavedMap,
    UpdateSummary,
)
from app.mapping.scan_match import LocalizerParams, MatchParams, ScanLocalizer, view_bearings
from app.perception.planar import (
    PlanarParams,
    RefineParams,
    confirm_floor,
    floor_before_standing,
    reference_pose_from_views,
    refine_reference_pose,
    row_ground_distance_m,
    standing_feet,
    view_homography,
)
from app.perception.standing import horizon_rows, standing_across_horizon, wall_surfaces
from app.perception.upright import UprightView, upright_standing_feet, upright_view

_NO_SECOND_MAP = np.empty((0, 0), dtype=np.uint16)
"""cv2.remap's second map, unused with the fixed-point `BirdseyeMap.nearest_map`."""
PARALLAX_PERIOD_S = 0.2
"""The parallax test runs at most this often (~2-3 ms a frame, nogil)..."""
WALLS_PERIOD_S = 0.2
"""Walls are proven by the horizon (`wall_surfaces`) at most this often: they
stand still, their feet stay in the floor memory, and a frame's test and its marking
cost ~8 ms of the mapping stage."""
PARALLAX_CARRY_S = 0.5
"""...and its confirmed floor (and the floor it cut off behind what stands) is carried to
the frames between for at most this long."""
FLOOR_ODOMETRY_REFINE = RefineParams(iterations=8)
"""Floor odometry's refinement: a key frame's step in a spin turn can leave a degree or
more to find, where the parallax test's four steps per pass stop short."""
FLOOR_ODOMETRY_KEY_TRIES = 3
"""A key frame is tried against frames one, two and three steps on before it is given up."""
_STORED_VIEWS = 24
"""Earlier frames kept for the parallax test (grey, ~0.3 MB each)..."""
_VIEW_STEP_M = 0.02
"""...one per this much camera travel."""
_CORRECTIONS_KEPT = 16
"""Pose corrections remembered for a handed-out geometry job (a few a second come)."""


class _View(NamedTuple):
    """An earlier frame kept for comparison: grey image, robot pose (x, y, heading) when
    it was taken, the camera's world position there, and the frame's time."""

    gray: NDArray[np.uint8]
    pose: tuple[float, float, float]
    cam: NDArray[np.float64]
    time_s: float


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return np.asarray(
        cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image, np.uint8
    )


def birdseye_grid(mapping: MappingConfig) -> GroundGrid:
    """The robot-frame bird's-eye raster the configuration describes."""
    return GroundGrid.covering(
        x_min_m=mapping.birdseye_x_min_m,
        x_max_m=mapping.birdseye_x_max_m,
        y_min_m=-mapping.birdseye_half_width_m,
        y_max_m=mapping.birdseye_half_width_m,
        cell_m=mapping.birdseye_cell_m,
    )


def occupancy_params(mapping: MappingConfig) -> OccupancyParams:
    return OccupancyParams(
        log_odds_free=mapping.log_odds_free,
        log_odds_occupied=mapping.log_odds_occupied,
        clamp_min=mapping.log_odds_min,
        clamp_max=mapping.log_odds_max,
        free_threshold=mapping.free_threshold,
        occupied_threshold=mapping.occupied_threshold,
        obstacle_band_m=mapping.obstacle_band_m,
        free_max_range_m=mapping.free_evidence_range_m,
        occupied_max_range_m=mapping.obstacle_evidence_range_m,
        far_boundary_margin_m=mapping.far_boundary_margin_m,
        half_distance_m=mapping.evidence_half_distance_m,
        turn_radius_m=mapping.evidence_turn_radius_m,
        # The camera never sees under the robot; where the robot stands is floor.
        footprint_free_radius_m=mapping.robot_radius_m,
    )


def localizer_params(mapping: MappingConfig) -> LocalizerParams:
    """The scan matcher for the configured map: a field blurred by one map cell,
    lattices of half and a fifth of a cell, endpoints half the obstacle band deep."""
    cell = mapping.grid_cell_m
    return LocalizerParams(
        period_s=mapping.scan_match_period_s,
        endpoint_depth_m=mapping.obstacle_band_m / 2,
        gain_frac=mapping.scan_match_gain_frac,
        max_step_m=mapping.scan_match_max_step_m,
        max_step_rad=mapping.scan_match_max_step_rad,
        max_range_m=mapping.max_range_m,
        field_sigma_m=cell,
        match=MatchParams(
            window_m=mapping.scan_match_window_m,
            window_rad=mapping.scan_match_window_rad,
            coarse_step_m=cell / 2,
            fine_step_m=cell / 5,
        ),
    )


def frontier_params(mapping: MappingConfig) -> FrontierParams:
    return FrontierParams(
        min_cluster_cells=mapping.frontier_min_cells,
        inflation_radius_m=mapping.inflation_radius_m,
        robot_radius_m=mapping.robot_radius_m,
        exclude_radius_m=mapping.frontier_exclude_radius_m,
        size_penalty_m=mapping.frontier_size_penalty_m,
        turn_penalty_m_per_rad=mapping.frontier_turn_penalty_m_per_rad,
        clearance_preferred_m=mapping.path_clearance_preferred_m,
        clearance_cost=mapping.path_clearance_cost,
    )


def image_horizon_rows(calibration: FloorCalibration) -> NDArray[np.int64]:
    """Per column of the calibrated image, the first row whose ray meets the floor."""
    width, height = calibration.image_size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    ground = calibration.image_to_ground(np.column_stack((u.ravel(), v.ravel())))
    return horizon_rows(np.isfinite(ground).all(axis=1).reshape(height, width))


@dataclass(frozen=True)
class MapUpdate:
    """What one frame did to the map: the robot-frame patch and the fusion summary."""

    patch: NDArray[np.uint8]
    summary: UpdateSummary
    corrected_cells: int = 0
    """Patch cells the colour method called not-floor that the memory knows are floor."""
    correction: Pose2D | None = None
    """``T_corrected_odom`` when the frame's scan match corrected the pose (the frame was
    fused at ``correction.compose(T_world_robot)``): left-multiply it onto odometry."""
    match_s: float | None = None
    """Seconds the frame's scan match took (None: none ran)."""
    geometry_job: GeometryJob | None = None
    """The geometric tests the frame made due (parallax, walls), for the caller to run off
    the motors' path (`run_geometry_job`) and hand back to a later
    `GroundMapper.update` (only with ``geometry="defer"``)."""
    zone_known_floor: float | None = None
    """Of the ground the frame's safe zone shows, the share the map knows is floor
    (confirmed flat by parallax or driven over); 0 when geometry saw something standing
    in the zone; None without a ``safe_zone_px`` (`GroundMapper.update`)."""


GeometryMode = Literal["inline", "defer", "hold"]
"""How `GroundMapper.update` runs its due geometric tests (the parallax floor test and
the walls test, ~5-25 ms a test on every fifth frame): ``inline`` on the frame itself
(offline callers: the results are in this frame's map); ``defer`` handed out as
`MapUpdate.geometry_job` for the caller to run in another thread, its outcome adopted
by a later frame; ``hold`` not now (the caller's previous job still runs: the tests
stay due)."""


@dataclass(frozen=True)
class _FeetGeometry:
    """What `standing_feet` needs for one image size: the upright view of a pitched or
    rolled camera, else the ground distance of each row."""

    upright: UprightView | None
    row_distance_m: NDArray[np.float64]

    def feet(self, standing: NDArray[np.bool_], floor: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Where what stands meets the floor (`standing_feet`), walked along the world's
        verticals (`upright_standing_feet`) when the camera is pitched or rolled: a
        leaning edge's columns otherwise each make a foot that lies far behind it."""
        if self.upright is None:
            return standing_feet(standing, floor, self.row_distance_m)
        return upright_standing_feet(standing, floor, self.upright)

    def seen_feet(self, standing: NDArray[np.bool_], feet: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Of ``feet`` (`feet` of ``standing``), those at a standing run's own lowest
        pixels: seen where the thing stands. The others were placed where the floor below
        ended, across not-floor the tests could not judge: a plain wall's lower part, or
        a floor of another colour under a chair seen beyond it."""
        return feet & self.feet(standing, ~standing)


@dataclass(frozen=True)
class _ParallaxInput:
    """The parallax test's part of a `GeometryJob`."""

    gray: NDArray[np.uint8]
    reference_gray: NDArray[np.uint8]
    reference_pose: tuple[float, float, float]
    H_ground_from_image: NDArray[np.float64]
    camera_xy_robot: tuple[float, float]
    params: PlanarParams


@dataclass(frozen=True)
class GeometryJob:
    """One frame's due geometric tests with everything they read (`run_geometry_job`);
    the arrays are the frames' own and nobody writes them."""

    image: NDArray[np.uint8]
    floor_mask: NDArray[np.bool_]
    here: tuple[float, float, float]
    time_s: float
    parallax: _ParallaxInput | None
    """The motion-parallax floor test against an earlier view (None: not due)."""
    horizon_row: NDArray[np.int64] | None
    """Per column, the first row below the horizon (None: the horizon tests are off)."""
    walls: bool
    """Whether the walls test is due (`wall_surfaces`)."""
    feet: _FeetGeometry
    generation: int
    """The mapper's map generation (`GroundMapper.restore` starts a new one)."""
    corrections_before: int
    """How many pose corrections the mapper had made when the job was cut."""


@dataclass(frozen=True)
class GeometryOutcome:
    """A finished `GeometryJob` (`run_geometry_job`), as image masks of its frame."""

    job: GeometryJob
    added: NDArray[np.bool_] | None
    """Floor parallax confirmed that the colour mask lacked (None: no parallax test)."""
    flat: NDArray[np.bool_] | None
    """Pixels parallax tested flat (known floor from now on)."""
    cut: NDArray[np.bool_] | None
    """Colour floor lying behind something parallax saw standing (not floor seen)."""
    standing: NDArray[np.bool_] | None
    """What parallax saw standing and the walls test proved standing (None: nothing)."""
    feet: NDArray[np.bool_] | None
    """Where what stands meets the floor."""
    seen_feet: NDArray[np.bool_] | None
    """The feet seen where the thing stands (`_FeetGeometry.seen_feet`)."""
    standing_bgr: NDArray[np.uint8] | None
    """Every `STANDING_COLOUR_STRIDE`-th colour of the standing pixels (unlearning)."""
    wall_floor: NDArray[np.bool_] | None
    """Colour floor that is the lower part of a wall (`wall_surfaces`): not floor seen
    (None: the walls test did not run or found none)."""
    unaligned: bool
    """The views' floors could not be aligned; the test ran on odometry's poses."""


def run_geometry_job(job: GeometryJob) -> GeometryOutcome:
    """Run one frame's geometric tests (pure; any thread: the kernels release the GIL):
    the parallax test first, then the walls test on the floor it leaves."""
    floor = job.floor_mask
    added = flat_floor = cut = None
    standing_parts: list[NDArray[np.bool_]] = []
    unaligned = False
    if job.parallax is not None:
        p = job.parallax
        # Odometry's relative pose, checked against the floor both views see: wheel
        # slip alone would make fine floor textures stand up (`reference_pose_from_views`).
        # Where the floor cannot be aligned (too plain, or a floor-coloured panel fills
        # the view) the test runs on odometry: what stands must still be seen.
        ref_pose = reference_pose_from_views(
            p.gray, p.reference_gray, floor, p.H_ground_from_image, p.reference_pose, job.here
        )
        unaligned = ref_pose is None
        result = confirm_floor(
            floor,
            p.gray,
            p.reference_gray,
            p.H_ground_from_image,
            p.reference_pose if ref_pose is None else ref_pose,
            job.here,
            p.camera_xy_robot,
            p.params,
            return_standing=True,
        )
        # Two pixels of the test's own (downscaled) resolution: one is never enough;
        # inside the floor by more than half its matching window; spread over a 32nd of
        # the width (2 degrees for a 60-degree camera) each way.
        flat = result.tested & ~result.standing
        kept = floor_before_standing(
            result.floor,
            result.standing,
            2 * p.params.downscale,
            flat=flat,
            interior_px=(p.params.window_px // 2 + 1) * p.params.downscale,
            spread_px=result.floor.shape[1] // 32,
        )
        all_cut = result.floor & ~kept
        cut = all_cut if all_cut.any() else None
        added = result.floor & ~floor
        flat_floor = result.floor & flat
        floor = result.floor & ~all_cut
        if result.standing.any():
            # Only its foot stands where the homography puts it: the rest of a standing
            # thing lands in a ray behind it, floor that must stay known and keep its
            # edges open to probes (`standing_feet`).
            standing_parts.append(result.standing)
        floor_for_feet = floor | flat
    else:
        floor_for_feet = floor
    across: NDArray[np.bool_] | None = None
    wall_floor: NDArray[np.bool_] | None = None
    if job.horizon_row is not None and job.image.ndim == 3:
        # What stands across the horizon (the mapper marks it on every frame) joins the
        # rest for the feet: one column's box and the wall above it have one foot.
        across = standing_across_horizon(floor, job.image, job.horizon_row)
        floor = floor & ~across
        floor_for_feet = floor_for_feet & ~across
        if job.walls:
            # Not-floor surfaces from where the floor ends to past the horizon: walls,
            # proven standing though plain (the parallax test sees nothing on them),
            # with the lower part of one the segmenter took for floor.
            surfaces = wall_surfaces(floor, job.image, job.horizon_row)
            if surfaces.walls.any():
                standing_parts.append(surfaces.walls)
            if surfaces.floor_part.any():
                wall_floor = surfaces.floor_part
                standing_parts.append(wall_floor)
                floor = floor & ~wall_floor
                floor_for_feet = floor_for_feet & ~wall_floor
    standing = feet = seen_feet = standing_bgr = None
    if standing_parts:
        standing = np.logical_or.reduce(standing_parts)
        stands = standing if across is None else standing | across
        feet = job.feet.feet(stands, floor_for_feet)
        seen_feet = job.feet.seen_feet(stands, feet)
        if job.image.ndim == 3:
            standing_bgr = job.image[standing][::STANDING_COLOUR_STRIDE]
    return GeometryOutcome(
        job=job,
        added=added,
        flat=flat_floor,
        cut=cut,
        standing=standing,
        feet=feet,
        seen_feet=seen_feet,
        standing_bgr=standing_bgr,
        wall_floor=wall_floor,
        unaligned=unaligned,
    )


@dataclass(frozen=True)
class _Adopted:
    """An outcome taken into the map, at its frame's pose as corrected since."""

    outcome: GeometryOutcome
    then: tuple[float, float, float]


STANDING_COLOUR_STRIDE = 4
"""Every this many standing pixels' colours vote on unlearning (thousands per test)."""
PROBE_STANDING_REACH_M = 0.15
"""An occupied cell this close to one geometry saw standing, its foot seen there, is a
real edge: not probed (`FloorMemory.standing_seen`); a wall's foot is marked a cell or
two off where its floor ends. No farther: a doorway's threshold lies on its walls' line,
and 0.3 m from each jamb left a 1 m door no way through for the probe search. A foot
placed where a frame's floor ended, below not-floor the tests could not judge (a
threshold, the tiles past it), does not stop a probe: the look from close up tells a
wall's lower part from another floor."""
PROBE_GIVEN_UP_RADIUS_M = 0.8
"""Edges within this of a given-up edge probe are not probed again (`GroundMapper.frontiers`):
the probe stood within the inflation radius plus two cells of its edge, and an edge
seen from there for the goal's patience has had its look."""
PROBE_OPENED_SHARE = 0.5
"""An edge probe opened its edge when at least this share of the edge's cells is no
longer occupied once the robot has arrived (`GroundMapper.probe_opened`)."""


def blind_zone_cells(birdseye: BirdseyeMap, half_width_m: float) -> NDArray[np.bool_]:
    """Unseen bird's-eye cells straight ahead of the robot (|y| <= half_width_m) that lie
    closer than the nearest cell the camera sees in that strip."""
    x, y = birdseye.grid.cell_centers()
    strip = np.abs(y) <= half_width_m
    seen = strip & birdseye.visible
    if not seen.any():
        return np.zeros(birdseye.grid.shape, dtype=bool)
    nearest_seen_x = float(x[seen].min())
    return np.asarray(strip & ~birdseye.visible & (x < nearest_seen_x), dtype=np.bool_)


GIVEN_UP_RADIUS_M = 0.4
"""Cells this close to a given-up goal make no frontier (floor under where the robot
started, a spot no pose shows)."""


class GivenUpGoals:
    """Goals the robot tried and failed to see, stamped once into world-grid masks, so a
    frontier search costs the same after ten of them or a thousand (the list was walked
    with two whole-grid masks per goal on every search: 58 ms with the 364 of an hour).

    A frontier whose goal fails twice is given up whole: a small disk around each failed
    goal only moved the next goal along the same unreachable frontier (an hour's run gave
    up 85 goals on one such stretch, one every 8 s for 18 minutes)."""

    def __init__(self, grid: GroundGrid) -> None:
        self.grid = grid
        self.points: list[tuple[float, float]] = []
        self.no_frontier = np.zeros(grid.shape, dtype=bool)
        """Cells within `GIVEN_UP_RADIUS_M` of a given-up goal or cluster: no frontier."""
        self.no_probe = np.zeros(grid.shape, dtype=bool)
        """Cells within `PROBE_GIVEN_UP_RADIUS_M` of an edge probe given up: their edges
        are not probed again. A frontier goal that ran out of patience stamps nothing
        here: the frontier it aimed at (the unknown past a doorway) is often behind an
        edge no probe has looked at yet, and that look is what comes next."""
        self.failed = np.zeros(grid.shape, dtype=bool)
        """Cells within `PROBE_GIVEN_UP_RADIUS_M` of a frontier goal that ran out of
        patience (edge probes that had their look are not failures)."""
        self.clusters = 0
        """Frontier clusters given up whole."""

    def add(self, xy: tuple[float, float], cluster_cells: NDArray[np.int64] | None = None) -> bool:
        """Give up the goal at ``xy``. ``cluster_cells`` ((n, 2) row, col), for a frontier
        goal that ran out of patience: its cluster's cells. When one of them already lies
        near an earlier failure, the cluster is given up whole (its cells and what lies
        within the radius of them). Without them ``xy`` is an edge probe given up: the
        edges near it are not probed again. Returns whether a cluster was given up whole."""
        whole = False
        if cluster_cells is None:
            stamp_disk(self.no_probe, self.grid, xy, PROBE_GIVEN_UP_RADIUS_M)
        else:
            cluster = self._mask(cluster_cells)
            whole = bool((self.failed & cluster).any())
            stamp_disk(self.failed, self.grid, xy, PROBE_GIVEN_UP_RADIUS_M)
            if whole:
                cell_m = self.grid.cell_m
                self.no_frontier |= inflate_obstacles(cluster, GIVEN_UP_RADIUS_M / cell_m)
                self.clusters += 1
        self.points.append(xy)
        stamp_disk(self.no_frontier, self.grid, xy, GIVEN_UP_RADIUS_M)
        return whole

    def looked_at(self, edge_cells: NDArray[np.int64]) -> None:
        """An edge probe that opened its edge: only those cells (and the cells beside
        them) are not probed again. The floor it opened may end at the next edge a
        little further on (specks past a threshold, seen close only from it), and that
        one gets its own look."""
        self.no_probe |= inflate_obstacles(self._mask(edge_cells), math.sqrt(2))

    def _mask(self, cells: NDArray[np.int64]) -> NDArray[np.bool_]:
        """(rows, cols) bool, True on ``cells`` ((n, 2) row, col)."""
        rows, cols = np.asarray(cells, dtype=np.int64).reshape(-1, 2).T
        mask = np.zeros(self.grid.shape, dtype=bool)
        mask[rows, cols] = True
        return mask

    def __len__(self) -> int:
        return len(self.points)


class GroundMapper:
    """Owns the bird's-eye tables and the world grid; not thread-safe (one stage owns it).

    Parameters
    ----------
    calibration : the floor homography (and lens model) of the camera
    mapping, camera : configuration sections
    """

    def __init__(
        self, calibration: FloorCalibration, mapping: MappingConfig, camera: CameraConfig
    ) -> None:
        self.calibration = calibration
        self.mapping = mapping
        self.camera_xy_robot = (camera.x_m, camera.y_m)
        self.birdseye: BirdseyeMap = build_birdseye_map(
            calibration, birdseye_grid(mapping), max_range_m=mapping.max_range_m
        )
        self.grid = OccupancyGrid.square(
            mapping.grid_size_m, mapping.grid_cell_m, occupancy_params(mapping)
        )
        self.frontier_params = frontier_params(mapping)
        self.blind_zone = blind_zone_cells(self.birdseye, mapping.robot_radius_m)
        self.memory = FloorMemory(self.grid.world_grid)
        self.given_up = GivenUpGoals(self.grid.world_grid)
        """Frontier goals given up in this run (not saved with the map)."""
        x, _ = self.birdseye.grid.cell_centers()
        # Colours come only from cells the camera sees (the blind zone is floor by
        # assumption, but has no colour).
        self._near_cells = np.asarray(
            (x <= self.memory.params.near_m) & self.birdseye.visible, dtype=np.bool_
        )
        self.horizon_row = image_horizon_rows(calibration) if mapping.standing_by_horizon else None
        """Per image column, the first row below the horizon (None: the test is off)."""
        self.standing_frames = 0
        """Frames in which the horizon test found a standing surface (for the report)."""
        # Parallax needs the floor homography to hold on the frames themselves.
        self.parallax = (
            PlanarParams() if mapping.parallax_floor and calibration.intrinsics is None else None
        )
        # Earlier frames: grey image, robot pose, camera position in the world.
        self._views: deque[_View] = deque(maxlen=_STORED_VIEWS)
        self.floor_odometry = mapping.floor_odometry and calibration.intrinsics is None
        """Visual odometry on the floor (`_floor_odometry`); same frames as parallax."""
        self._keyframe: _View | None = None
        self._key_misses = 0
        """Steps since the key frame whose floors did not line up."""
        self.floor_odometry_steps = 0
        """Key-frame steps whose floors were compared (for the report)..."""
        self.floor_odometry_applied = 0
        """...and of those, the ones that lined up and moved the pose."""
        self.parallax_frames = 0
        """Frames whose floor was tested by parallax (for the report)."""
        self.parallax_unaligned = 0
        """Of those, the tests whose views' floors could not be aligned (for the report)."""
        self._parallax_due_s = -math.inf
        self._walls_due_s = -math.inf
        self._row_distance: tuple[tuple[int, ...], NDArray[np.float64]] | None = None
        self._upright: tuple[tuple[int, ...], _FeetGeometry] | None = None
        self._generation = 0
        """Counts the maps this mapper has held (`restore`): a test cut from one is not
        adopted into another."""
        self._corrections: deque[tuple[Pose2D, float]] = deque(maxlen=_CORRECTIONS_KEPT)
        """The latest pose corrections (`_move_views`: ``T_corrected_odom``, ``after_s``),
        to move a handed-out test's pose as the views were moved meanwhile..."""
        self._corrections_made = 0
        """...and how many there have been."""
        self._confirmed: _Carried | None = None
        self._zone: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None
        """The last safe-zone mask handed to `update` and the bird's-eye cells it shows."""
        self._cut: _Carried | None = None
        """The colour floor the last parallax test found behind something standing (image
        mask), where and when: carried, like ``_confirmed``, to the frames between."""
        self._wall_cut: _Carried | None = None
        """The colour floor the last walls test found to be a wall's lower part, carried
        the same way (the walls test runs on one frame in several)."""
        grid = self.birdseye.grid
        self.localizer = (
            ScanLocalizer(
                localizer_params(mapping),
                grid,
                self.camera_xy_robot,
                view_bearings(self.birdseye.visible, grid, self.camera_xy_robot),
            )
            if mapping.scan_matching
            else None
        )
        self.heading_axis = (
            HeadingAxis(
                ManhattanParams(
                    gate_rad=mapping.manhattan_gate_rad,
                    line_sigma_rad=mapping.manhattan_line_sigma_rad,
                )
            )
            if mapping.manhattan_heading
            else None
        )
        """The building's axis and the heading corrections it gives (`app.mapping.manhattan`;
        None: off)."""
        self._axis_pose: Pose2D | None = None
        """The pose of the last frame the axis read (its travel since widens the gate)."""
        self._axis_range_px = (
            None
            if self.heading_axis is None
            else build_ground_lookup(
                calibration, max_range_m=self.heading_axis.params.max_range_m
            ).valid
        )
        """Pixels whose floor point is near enough for the axis's lines."""

    def update(
        self,
        floor_mask: NDArray[np.bool_],
        T_world_robot: Pose2D,
        now_s: float,
        image: NDArray[np.uint8] | None = None,
        *,
        unsure_mask: NDArray[np.bool_] | None = None,
        geometry: GeometryMode = "inline",
        geometry_outcome: GeometryOutcome | None = None,
        safe_zone_px: NDArray[np.bool_] | None = None,
    ) -> MapUpdate:
        """Fuse one frame's floor mask seen at ``T_world_robot`` (the travel from the
        previous call's pose fades the older evidence; time alone never does). With the
        frame's ``image`` (BGR or grey), geometry goes over colour: the floor is extended
        where motion parallax against an earlier frame confirms it
        (`app.perception.planar`), and what parallax or the horizon shows standing is not
        floor (`app.perception.standing`). ``geometry`` says whether the due tests run on
        this frame or are handed out; ``geometry_outcome`` is a handed-out job's result
        to adopt. ``now_s`` paces those tests and the scan match, which may correct
        ``T_world_robot`` before the frame is fused (`MapUpdate.correction`). Not-floor
        pixels of ``unsure_mask`` (same size as the mask) give no evidence: they count as
        unseen. With ``safe_zone_px`` (the perception's safe zone, same size as the mask)
        the update says how much of the zone's ground the map knows is floor
        (`MapUpdate.zone_known_floor`)."""
        here = (T_world_robot.x_m, T_world_robot.y_m, T_world_robot.theta_rad)
        adopted: _Adopted | None = None
        job: GeometryJob | None = None
        cut_px: NDArray[np.bool_] | None = None
        if image is not None:
            if geometry_outcome is not None:
                adopted = self._adopt(geometry_outcome)
            job = self._geometry_job(floor_mask, image, here, now_s, geometry != "hold")
            if job is not None and geometry == "inline":
                adopted = self._adopt(run_geometry_job(job))
                job = None
        if image is not None:
            if self.parallax is not None:
                floor_mask = self._with_confirmed(floor_mask, here, now_s)
            cut_px = self._cut_behind_standing(floor_mask, here, now_s)
            if cut_px is not None:
                floor_mask = floor_mask & ~cut_px
        standing_px: NDArray[np.bool_] | None = None
        if image is not None and image.ndim == 3 and self.horizon_row is not None:
            standing_px = standing_across_horizon(floor_mask, image, self.horizon_row)
            if standing_px.any():
                self.standing_frames += 1
                floor_mask = floor_mask & ~standing_px
            else:
                standing_px = None
        patch = birdseye_floor_patch(floor_mask, self.birdseye)
        if unsure_mask is not None:
            unsure = birdseye_floor_patch(unsure_mask, self.birdseye) == FLOOR
            patch[unsure & (patch == NOT_FLOOR)] = UNSEEN
        # The thesis's safe-zone assumption: the strip just ahead of the robot, below the
        # camera's view, is free floor.
        patch[self.blind_zone] = FLOOR
        # What the adopted test saw standing, as this frame sees its floor plane (exact
        # at the feet, which is where the homography puts what stands).
        standing_here: NDArray[np.bool_] | None = None
        if adopted is not None and adopted.outcome.standing is not None:
            standing_here = (
                birdseye_floor_patch(
                    self._carried(adopted.outcome.standing, adopted.then, here), self.birdseye
                )
                == FLOOR
            )
        correction: Pose2D | None = None
        match_s: float | None = None
        if self.localizer is not None and self.localizer.due(now_s):
            correction, match_s = self._localize(patch, standing_here, T_world_robot, now_s)
            if correction is not None:
                T_world_robot = correction.compose(T_world_robot)
                self._move_views(correction)
                if adopted is not None:
                    adopted = _Adopted(adopted.outcome, _moved(adopted.then, correction))
        memory = self.memory
        index = patch_world_index(self.birdseye.grid, self.grid.world_grid, T_world_robot)
        if image is not None and image.ndim == 3:
            patch_bgr = np.asarray(
                cv2.remap(
                    image,
                    self.birdseye.nearest_map,
                    _NO_SECOND_MAP,
                    cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0,
                ),
                dtype=np.uint8,
            )
            memory.observe_colours(patch_bgr, patch, index, self._near_cells)
        # Geometry over colour: what parallax or the horizon found standing is not
        # floor, whatever its colour (a floor-coloured box or wall panel); it is no
        # longer known floor (a textureless face can pass parallax as flat) and its
        # colour is unlearned.
        if adopted is not None:
            outcome, then = adopted.outcome, adopted.then
            index_then = (
                index
                if then == here and correction is None
                else patch_world_index(self.birdseye.grid, self.grid.world_grid, Pose2D(*then))
            )
            if outcome.flat is not None:
                # What parallax found flat is known floor from now on.
                flat = birdseye_floor_patch(outcome.flat, self.birdseye) == FLOOR
                memory.confirm_cells(index_then[flat])
            feet = None
            if outcome.feet is not None:
                feet = birdseye_floor_patch(outcome.feet, self.birdseye) == FLOOR
                seen = (
                    None
                    if outcome.seen_feet is None
                    else birdseye_floor_patch(outcome.seen_feet, self.birdseye) == FLOOR
                )
                memory.mark_standing(
                    index_then[feet],
                    outcome.standing_bgr,
                    None if seen is None else index_then[seen],
                )
            if outcome.job.walls:
                # The walls test looked along every column: near floor it saw, a cell
                # clear of its own feet, holds no foot (a threshold marked while the
                # floor beyond it was not yet known loses its mark once it is).
                floor_seen = outcome.job.floor_mask
                if outcome.wall_floor is not None:
                    floor_seen = floor_seen & ~outcome.wall_floor
                seen_floor = birdseye_floor_patch(floor_seen, self.birdseye) == FLOOR
                clear = seen_floor & self._near_cells
                if feet is not None:
                    # A foot found a cell off (diagonals too) is the same foot.
                    clear &= ~inflate_obstacles(feet, math.sqrt(2))
                memory.see_floor(index_then[clear])
            if standing_here is not None:
                patch[standing_here] = NOT_FLOOR
        # Every cell geometry saw standing in this frame (the safe-zone check reads it).
        standing_cells = standing_here
        if standing_px is not None and image is not None:
            standing = birdseye_floor_patch(standing_px, self.birdseye) == FLOOR
            # Only its foot stands where the homography puts it (see `run_geometry_job`).
            feet_geometry = self._feet_geometry(standing_px.shape)
            feet_image = feet_geometry.feet(standing_px, floor_mask)
            feet = birdseye_floor_patch(feet_image, self.birdseye) == FLOOR
            seen = (
                birdseye_floor_patch(
                    feet_geometry.seen_feet(standing_px, feet_image), self.birdseye
                )
                == FLOOR
            )
            memory.mark_standing(
                index[feet], image[standing_px][::STANDING_COLOUR_STRIDE], index[seen]
            )
            patch[standing] = NOT_FLOOR
            standing_cells = standing if standing_cells is None else standing_cells | standing
        memory.drive_over(T_world_robot, self.mapping.robot_radius_m)
        zone_known_floor = None
        if safe_zone_px is not None:
            zone_cells = self._zone_cells(safe_zone_px)
            # Something standing in the zone this frame: nothing the map remembers of the
            # floor there says the way ahead is clear.
            stands = standing_cells is not None and bool((standing_cells & zone_cells).any())
            zone_known_floor = 0.0 if stands else memory.known_share(index[zone_cells])
        corrected = memory.correct_patch(patch, index)
        if cut_px is not None:
            # Geometry over memory too: known floor behind a standing surface is out of
            # sight, not floor seen, so the floor along those rays ends at its foot.
            patch[birdseye_floor_patch(cut_px, self.birdseye) == FLOOR] = NOT_FLOOR
        summary = self.grid.update(
            patch, self.birdseye.grid, T_world_robot, self.camera_xy_robot, standing_cells
        )
        return MapUpdate(patch, summary, corrected, correction, match_s, job, zone_known_floor)

    def _zone_cells(self, safe_zone_px: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """The bird's-eye cells the safe zone's pixels show (kept while the mask is the
        same)."""
        cached = self._zone
        if cached is None or not np.array_equal(cached[0], safe_zone_px):
            cells = birdseye_floor_patch(safe_zone_px, self.birdseye) == FLOOR
            cached = self._zone = (safe_zone_px.copy(), np.asarray(cells, dtype=np.bool_))
        return cached[1]

    def _geometry_job(
        self,
        floor_mask: NDArray[np.bool_],
        image: NDArray[np.uint8],
        here: tuple[float, float, float],
        now_s: float,
        may_start: bool,
    ) -> GeometryJob | None:
        """Keep the frame for later parallax tests, and cut this frame's job when a test
        is due and ``may_start``: parallax when an earlier frame lies at about the
        baseline, walls on a colour image with the horizon known."""
        parallax = self._parallax_input(image, here, now_s) if self.parallax is not None else None
        if not may_start:
            return None
        if parallax is not None and now_s < self._parallax_due_s:
            parallax = None
        walls = image.ndim == 3 and self.horizon_row is not None and now_s >= self._walls_due_s
        if parallax is None and not walls:
            return None
        if parallax is not None:
            self._parallax_due_s = now_s + PARALLAX_PERIOD_S
        if walls:
            self._walls_due_s = now_s + WALLS_PERIOD_S
        return GeometryJob(
            image=image,
            floor_mask=floor_mask,
            here=here,
            time_s=now_s,
            parallax=parallax,
            horizon_row=self.horizon_row,
            walls=walls,
            feet=self._feet_geometry(floor_mask.shape),
            generation=self._generation,
            corrections_before=self._corrections_made,
        )

    def _parallax_input(
        self, image: NDArray[np.uint8], here: tuple[float, float, float], now_s: float
    ) -> _ParallaxInput | None:
        """Keep the frame among the views (one per `_VIEW_STEP_M` of camera travel); the
        parallax test's input against the view nearest the baseline, or None."""
        assert self.parallax is not None
        gray = _gray(image)
        cam = _camera_xy(here, self.camera_xy_robot)
        target = self.mapping.parallax_baseline_m
        best: _View | None = None
        best_error = math.inf
        for view in self._views:
            baseline = float(np.hypot(*(cam - view.cam)))
            turn = abs(math.remainder(here[2] - view.pose[2], math.tau))
            error = abs(baseline - target)
            if (
                0.5 * target <= baseline <= 1.5 * target
                and turn <= self.mapping.parallax_max_turn_rad
                and error < best_error
            ):
                best, best_error = view, error
        if not self._views or float(np.hypot(*(cam - self._views[-1].cam))) >= _VIEW_STEP_M:
            self._views.append(_View(gray, here, cam, now_s))
        if best is None or gray.shape != best.gray.shape:
            return None
        return _ParallaxInput(
            gray=gray,
            reference_gray=best.gray,
            reference_pose=best.pose,
            H_ground_from_image=self.calibration.H_ground_from_image,
            camera_xy_robot=self.camera_xy_robot,
            params=self.parallax,
        )

    def _adopt(self, outcome: GeometryOutcome) -> _Adopted | None:
        """Take a finished job in: the parallax test's confirmed floor and what it cut
        off are carried to the frames from now on. Its frame's pose is moved by the corrections made
        since the job was cut; None (dropped) when the map was replaced meanwhile or
        too many corrections came to replay."""
        job = outcome.job
        since = self._corrections_made - job.corrections_before
        if job.generation != self._generation or since > len(self._corrections):
            return None
        then = job.here
        for T_corrected_odom, after_s in list(self._corrections)[len(self._corrections) - since :]:
            if job.time_s > after_s:
                then = _moved(then, T_corrected_odom)
        if outcome.added is not None:
            self.parallax_frames += 1
            self.parallax_unaligned += int(outcome.unaligned)
            self._confirmed = (outcome.added, then, job.time_s)
            self._cut = (outcome.cut, then, job.time_s) if outcome.cut is not None else None
        if job.walls:
            wall_floor = outcome.wall_floor
            self._wall_cut = (wall_floor, then, job.time_s) if wall_floor is not None else None
        return _Adopted(outcome, then)

    def _with_confirmed(
        self, floor_mask: NDArray[np.bool_], here: tuple[float, float, float], now_s: float
    ) -> NDArray[np.bool_]:
        """The floor mask extended by the last test's confirmed floor, carried here
        exactly: it lies on the floor plane, which the homography between the two poses
        maps (for at most `PARALLAX_CARRY_S`)."""
        if self._confirmed is None or now_s - self._confirmed[2] > PARALLAX_CARRY_S:
            return floor_mask
        added, then, _ = self._confirmed
        return floor_mask | self._carried(added, then, here)

    def _feet_geometry(self, shape: tuple[int, ...]) -> _FeetGeometry:
        """The `_FeetGeometry` of this image size (cached)."""
        shape = shape[:2]
        if self._upright is None or self._upright[0] != shape:
            height, width = shape
            intrinsics = self.calibration.intrinsics
            K = (
                intrinsics.camera_matrix
                if intrinsics is not None and intrinsics.image_size == (width, height)
                else None
            )
            view = upright_view(self.calibration.H_ground_from_image, (width, height), K)
            self._upright = (shape, _FeetGeometry(view, self._row_distance_m(shape)))
        return self._upright[1]

    def _row_distance_m(self, shape: tuple[int, ...]) -> NDArray[np.float64]:
        """Forward ground distance of each image row (`row_ground_distance_m`), cached
        per image size."""
        if self._row_distance is None or self._row_distance[0] != shape[:2]:
            rows_m = row_ground_distance_m(self.calibration.H_ground_from_image, shape[1], shape[0])
            self._row_distance = (shape[:2], rows_m)
        return self._row_distance[1]

    def follow_floor(
        self,
        image: NDArray[np.uint8],
        floor_mask: NDArray[np.bool_],
        T_world_robot: Pose2D,
        now_s: float,
    ) -> Pose2D | None:
        """Floor odometry, then the building's axis, for a frame `update` has fused at
        ``T_world_robot``: ``T_corrected_odom`` to left-multiply onto odometry, or None
        (both off, neither due, the floors did not line up and no straight edge near the
        axis; `floor_odometry_steps` counts the frames compared). Called after the
        frame's map is out, so the steps (~5 ms; the axis's ~2-6 ms, only while it
        learns or floor odometry misses) are not on the way to the motors; the frame
        itself stays fused at its odometry pose, off by at most one step's slip."""
        step = (
            self._floor_odometry(image, floor_mask, T_world_robot, now_s)
            if self.floor_odometry
            else None
        )
        if self.heading_axis is None:
            return step
        pose = T_world_robot if step is None else step.compose(T_world_robot)
        last, self._axis_pose = self._axis_pose, pose
        # The key frame's floors lined up last time: floor odometry holds the heading
        # to hundredths of a degree, better than any line (and lines off the floor plane,
        # a box's top edge seen over many frames, would pull it): the axis only learns.
        floor_held = self.floor_odometry and self._key_misses == 0
        if last is not None:
            self.heading_axis.moved(
                math.hypot(pose.x_m - last.x_m, pose.y_m - last.y_m),
                math.remainder(pose.theta_rad - last.theta_rad, math.tau),
                floor_held=floor_held,
            )
        if floor_held and self.heading_axis.axis_rad is not None:
            return step  # nothing to learn, nothing to correct: the lines are not looked for
        assert self._axis_range_px is not None
        if floor_mask.shape != self._axis_range_px.shape:
            return step  # frames of another size than calibrated: no floor lines to trust
        turn = self.heading_axis.observe(
            floor_edge_segments(
                _gray(image),
                floor_mask,
                self.calibration,
                self._axis_range_px,
                self.heading_axis.params,
            ),
            pose.theta_rad,
            may_correct=not floor_held,
        )
        if turn is None:
            return step
        # About the robot's own position: the heading was off, not the place.
        spin = Pose2D(pose.x_m, pose.y_m, turn).compose(Pose2D(-pose.x_m, -pose.y_m, 0.0))
        self._move_views(spin)
        return spin if step is None else spin.compose(step)

    def _floor_odometry(
        self, image: NDArray[np.uint8], floor_mask: NDArray[np.bool_], pose: Pose2D, now_s: float
    ) -> Pose2D | None:
        """``T_corrected_odom`` from the floor's motion since the key frame, or None.

        Once the camera has moved ``floor_odometry_step_m`` or turned
        ``floor_odometry_step_rad`` since the key frame, the key frame's pose is refined
        against this frame's floor (`refine_reference_pose`, with this frame at its
        odometry pose). The key frame's pose is the one trusted (it was corrected the
        same way), so the refined relative pose moves this frame instead:
        ``T_world_key @ inv(T_world_key_refined)``, and this frame becomes the key frame.
        Where the floors do not line up, the key is tried again a step further on, and
        after `FLOOR_ODOMETRY_KEY_TRIES` misses odometry bridges the gap.
        """
        here = (pose.x_m, pose.y_m, pose.theta_rad)
        cam = _camera_xy(here, self.camera_xy_robot)
        key = self._keyframe
        if key is None or key.gray.shape != image.shape[:2]:
            self._keyframe, self._key_misses = _View(_gray(image), here, cam, now_s), 0
            return None
        travel = float(np.hypot(*(cam - key.cam)))
        turn = abs(math.remainder(here[2] - key.pose[2], math.tau))
        steps = 1 + self._key_misses
        if (
            travel < steps * self.mapping.floor_odometry_step_m
            and turn < steps * self.mapping.floor_odometry_step_rad
        ):
            return None
        self.floor_odometry_steps += 1
        gray = _gray(image)  # only on the frames compared: most are not
        refined = refine_reference_pose(
            gray,
            key.gray,
            floor_mask,
            self.calibration.H_ground_from_image,
            key.pose,
            here,
            FLOOR_ODOMETRY_REFINE,
        )
        if refined is None:
            # A new key frame would take this frame's pose from odometry, errors of the
            # moment (slip, the frame's timing) included, so the key is kept for
            # FLOOR_ODOMETRY_KEY_TRIES steps while the views still overlap.
            self._key_misses += 1
            if self._key_misses >= FLOOR_ODOMETRY_KEY_TRIES:
                self._keyframe, self._key_misses = _View(gray, here, cam, now_s), 0
            return None
        self._key_misses = 0
        self.floor_odometry_applied += 1
        T_corrected_odom = Pose2D(*key.pose).compose(Pose2D(*refined).inverse())
        corrected = T_corrected_odom.compose(pose)
        at = (corrected.x_m, corrected.y_m, corrected.theta_rad)
        self._move_views(T_corrected_odom, after_s=key.time_s)
        self._keyframe = _View(gray, at, _camera_xy(at, self.camera_xy_robot), now_s)
        return T_corrected_odom

    def _localize(
        self,
        patch: NDArray[np.uint8],
        standing: NDArray[np.bool_] | None,
        T_world_robot: Pose2D,
        now_s: float,
    ) -> tuple[Pose2D | None, float | None]:
        """The frame's scan match (`ScanLocalizer.localize`): ``(T_corrected_odom or
        None, seconds)``, or (None, None) when none ran. It reads a copy of the patch as
        it will be fused (what parallax found standing is not floor, floor the memory
        knows is floor), against the map before this frame's evidence goes in."""
        assert self.localizer is not None
        start_s = time.perf_counter()
        scan_patch = patch.copy()
        if standing is not None:
            scan_patch[standing] = NOT_FLOOR
        index = patch_world_index(self.birdseye.grid, self.grid.world_grid, T_world_robot)
        self.memory.correct_patch(scan_patch, index)
        found = self.localizer.localize(
            scan_patch,
            self.grid.log_odds,
            self.grid.world_grid,
            (self.grid.params.free_threshold, self.grid.params.occupied_threshold),
            T_world_robot,
            now_s,
        )
        if found is None:
            return None, None
        return found.T_corrected_odom, time.perf_counter() - start_s

    def _move_views(self, T_corrected_odom: Pose2D, after_s: float = -math.inf) -> None:
        """Move the poses of the frames kept for the parallax test and of floor
        odometry's key frame, taken after ``after_s``, with a correction, as odometry's
        history moves: the relative poses between those frames stay odometry's. (Floor
        odometry moves only the frames since its key frame: the ones before were not
        part of the slip it found.)"""
        self._corrections.append((T_corrected_odom, after_s))
        self._corrections_made += 1
        views = [
            view
            if view.time_s <= after_s
            else view._replace(
                pose=(moved := _moved(view.pose, T_corrected_odom)),
                cam=_camera_xy(moved, self.camera_xy_robot),
            )
            for view in self._views
        ]
        self._views.clear()
        self._views.extend(views)
        key = self._keyframe
        if key is not None and key.time_s > after_s:
            # Floor odometry compares the next frame with the key at this pose.
            moved = _moved(key.pose, T_corrected_odom)
            self._keyframe = key._replace(pose=moved, cam=_camera_xy(moved, self.camera_xy_robot))
        self._confirmed = _carry_moved(self._confirmed, T_corrected_odom, after_s)
        self._cut = _carry_moved(self._cut, T_corrected_odom, after_s)
        self._wall_cut = _carry_moved(self._wall_cut, T_corrected_odom, after_s)

    def snapshot(self) -> SavedMap:
        """A read-only copy of the map for saving (`app.mapping.map_files.save_map`); call
        it in the thread that runs `update`."""
        return replace(self.grid.snapshot(), floor_memory=self.memory.state())

    def restore(self, snapshot: SavedMap) -> None:
        """Continue from a saved map (`app.mapping.map_files.load_map`): the grid takes its
        evidence, travel and robot pose (see `OccupancyGrid.restore`), and the frames kept
        for the parallax test are dropped (their poses belong to the map being replaced).

        Raises
        ------
        ValueError
            The map is of another world grid; the mapper is then unchanged.
        """
        memory = FloorMemory(self.grid.world_grid, self.memory.params)
        if snapshot.floor_memory is not None:
            memory.restore(snapshot.floor_memory)  # checked before the grid changes
        self.grid.restore(snapshot)
        self.memory = memory
        self._generation += 1
        self._views.clear()
        self._keyframe = None
        self._confirmed = None
        self._cut = None
        self._wall_cut = None
        if self.heading_axis is not None:
            # The saved pose's heading is as good as it was; the axis is learned again.
            self.heading_axis.restore(None)
            self._axis_pose = None

    def _cut_behind_standing(
        self, floor_mask: NDArray[np.bool_], here: tuple[float, float, float], now_s: float
    ) -> NDArray[np.bool_] | None:
        """The part of ``floor_mask`` that lies behind something the last parallax test
        saw standing (`floor_before_standing`) or that the last walls test found to be a
        wall's lower part (`wall_surfaces`), moved with the floor homography: exact at the
        surface's foot (on the floor) and off by its parallax above it, for a few frames
        at most. None when there is none."""
        out: NDArray[np.bool_] | None = None
        for carried in (self._cut, self._wall_cut):
            if carried is None or now_s - carried[2] > PARALLAX_CARRY_S:
                continue
            cut, then, _ = carried
            moved = floor_mask & self._carried(cut, then, here)
            out = moved if out is None else out | moved
        return out if out is not None and out.any() else None

    def _carried(
        self,
        mask: NDArray[np.bool_],
        then: tuple[float, float, float],
        here: tuple[float, float, float],
    ) -> NDArray[np.bool_]:
        """A tested frame's image ``mask`` (taken at pose ``then``) as seen from
        ``here``, through the floor homography between the two poses."""
        H = view_homography(self.calibration.H_ground_from_image, then, here)
        h, w = mask.shape
        warped = cv2.warpPerspective(
            mask.astype(np.uint8), H, (w, h), flags=cv2.INTER_NEAREST, borderValue=0
        )
        return np.asarray(warped > 0, dtype=np.bool_)

    def frontiers(self, T_world_robot: Pose2D) -> FrontierSearch:
        """Frontiers and the goal, with no frontier near the goals in `given_up`."""
        return search_frontiers(self.frontier_inputs(T_world_robot))

    def frontier_inputs(self, T_world_robot: Pose2D) -> FrontierInputs:
        """What a frontier search reads, copied (~1 ms; in the thread that runs
        `update`): the search itself (`search_frontiers`) may then run in any thread. It
        plans on the remembered map (`OccupancyGrid.remembered_classes`): floor that has
        faded is explored, and still the way on and home."""
        probe_cells = self.frontier_probe_cells() if self.mapping.frontier_probe_edges else None
        return FrontierInputs(
            self.grid.remembered_classes(),
            self.grid.world_grid,
            (T_world_robot.x_m, T_world_robot.y_m),
            self.frontier_params,
            probe_cells,
            self.given_up.no_frontier.copy(),
            self.memory.track(),
        )

    def frontier_probe_cells(self) -> NDArray[np.bool_]:
        """World cells whose occupied edges the frontier search may probe: not within
        `PROBE_STANDING_REACH_M` of anything seen standing where its foot was seen, nor
        near a probe given up (its edge is not looked at again)."""
        standing = inflate_obstacles(
            self.memory.standing_seen(), PROBE_STANDING_REACH_M / self.grid.world_grid.cell_m
        )
        return np.asarray(~(standing | self.given_up.no_probe), dtype=np.bool_)

    def probe_opened(self, edge_cells: NDArray[np.int64]) -> bool:
        """Whether an edge probe's edge (its goal's ``edge_cells``) is open now: at least
        `PROBE_OPENED_SHARE` of its cells are not occupied on the map the search plans on
        (the look proved it flat, and free evidence wore it away). Read it between
        mapping steps."""
        rows, cols = np.asarray(edge_cells, dtype=np.int64).reshape(-1, 2).T
        if rows.size == 0:
            return False
        occupied = self.grid.remembered_classes()[rows, cols] == OCCUPIED
        return bool(1.0 - occupied.mean() >= PROBE_OPENED_SHARE)

    def probe_edge_share(self) -> float | None:
        """Of the cells the map calls occupied, the fraction the frontier search may probe
        (`frontier_probe_cells`); None without probes or occupied cells. Near zero,
        exploration ends at the first edge the robot cannot prove floor."""
        if not self.mapping.frontier_probe_edges:
            return None
        occupied = self.grid.classify() == OCCUPIED
        n_occupied = int(np.count_nonzero(occupied))
        if n_occupied == 0:
            return None
        probe = int(np.count_nonzero(occupied & self.frontier_probe_cells()))
        return round(probe / n_occupied, 4)


class FrontierInputs(NamedTuple):
    """A frontier search's inputs (`GroundMapper.frontier_inputs`), nobody's to write."""

    cells: NDArray[np.int8]
    grid: GroundGrid
    robot_xy: tuple[float, float]
    params: FrontierParams
    probe_cells: NDArray[np.bool_] | None
    no_frontier: NDArray[np.bool_] | None = None
    track: NDArray[np.bool_] | None = None


def search_frontiers(inputs: FrontierInputs) -> FrontierSearch:
    """`find_frontiers` on copied inputs (pure; any thread)."""
    return find_frontiers(
        inputs.cells,
        inputs.grid,
        inputs.robot_xy,
        inputs.params,
        probe_cells=inputs.probe_cells,
        no_frontier=inputs.no_frontier,
        track=inputs.track,
    )


def _moved(
    pose: tuple[float, float, float], T_corrected_odom: Pose2D
) -> tuple[float, float, float]:
    """A pose (x_m, y_m, theta_rad) moved by a correction."""
    p = T_corrected_odom.compose(Pose2D(*pose))
    return (p.x_m, p.y_m, p.theta_rad)


_Carried = tuple[NDArray[np.bool_], tuple[float, float, float], float]
"""A tested frame's image mask carried to later frames: the mask, its frame's pose, its
time (`GroundMapper._confirmed`, ``_cut``, ``_wall_cut``)."""


def _carry_moved(
    carried: _Carried | None, T_corrected_odom: Pose2D, after_s: float
) -> _Carried | None:
    """``carried`` with its pose moved by a correction when its frame came after
    ``after_s``."""
    if carried is None or carried[2] <= after_s:
        return carried
    mask, then, at_s = carried
    return (mask, _moved(then, T_corrected_odom), at_s)


def _camera_xy(
    pose: tuple[float, float, float], camera_xy: tuple[float, float]
) -> NDArray[np.float64]:
    """Where the camera is in the world for a robot pose (x_m, y_m, theta_rad)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    cx, cy = camera_xy
    return np.array([pose[0] + c * cx - s * cy, pose[1] + s * cx + c * cy])
