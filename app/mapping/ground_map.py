"""The mapping stage in one object: floor mask -> bird's-eye ground patch -> world
occupancy grid -> frontiers. Pure computation on arrays; the caller loads the
calibration and supplies poses and times."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.config import CameraConfig, MappingConfig
from app.mapping.calibration import FloorCalibration
from app.mapping.frames import FLOOR, GroundGrid, Pose2D
from app.mapping.frontiers import FrontierParams, FrontierSearch, find_frontiers, footprint_mask
from app.mapping.ipm import BirdseyeMap, birdseye_floor_patch, build_birdseye_map
from app.mapping.occupancy import FREE, UNKNOWN, OccupancyGrid, OccupancyParams, UpdateSummary


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
        half_life_s=mapping.evidence_half_life_s,
        # The camera never sees under the robot; where the robot stands is floor.
        footprint_free_radius_m=mapping.robot_radius_m,
    )


def frontier_params(mapping: MappingConfig) -> FrontierParams:
    return FrontierParams(
        min_cluster_cells=mapping.frontier_min_cells,
        inflation_radius_m=mapping.inflation_radius_m,
        robot_radius_m=mapping.robot_radius_m,
        exclude_radius_m=mapping.frontier_exclude_radius_m,
        size_penalty_m=mapping.frontier_size_penalty_m,
        turn_penalty_m_per_rad=mapping.frontier_turn_penalty_m_per_rad,
    )


@dataclass(frozen=True)
class MapUpdate:
    """What one frame did to the map: the robot-frame patch and the fusion summary."""

    patch: NDArray[np.uint8]
    summary: UpdateSummary


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

    def update(
        self, floor_mask: NDArray[np.bool_], T_world_robot: Pose2D, now_s: float
    ) -> MapUpdate:
        """Fuse one frame's floor mask seen at ``T_world_robot``."""
        patch = birdseye_floor_patch(floor_mask, self.birdseye)
        # The thesis's safe-zone assumption: the strip just ahead of the robot, below the
        # camera's view, is free floor.
        patch[self.blind_zone] = FLOOR
        summary = self.grid.update(
            patch, self.birdseye.grid, T_world_robot, self.camera_xy_robot, now_s
        )
        return MapUpdate(patch, summary)

    def frontiers(
        self,
        T_world_robot: Pose2D,
        *,
        given_up_xy: Sequence[tuple[float, float]] = (),
        given_up_radius_m: float = 0.4,
    ) -> FrontierSearch:
        """Frontiers and the goal. Unknown cells within ``given_up_radius_m`` of a point in
        ``given_up_xy`` are treated as known (goals the robot tried and failed to see,
        e.g. floor under where it started), so they make no frontier."""
        cells = self.grid.classify()
        world = self.grid.world_grid
        for xy in given_up_xy:
            near = footprint_mask(world, xy, given_up_radius_m)
            cells[near & (cells == UNKNOWN)] = FREE
        return find_frontiers(
            cells, world, (T_world_robot.x_m, T_world_robot.y_m), self.frontier_params
        )
