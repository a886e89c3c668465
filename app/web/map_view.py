"""The dashboard's bird's-eye map: ``GET /api/map.png`` (the occupancy grid around the
robot with its pose, recent trail, the frontier goal and the planned path) and
``GET /api/map.json`` (the numbers behind it, to turn pixels into metres).

The picture is north-up in the world frame (the robot's start pose): up is the start's
forward (+x), right is its right (-y), the same raster convention as `GroundGrid`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import cv2
import numpy as np
from fastapi import APIRouter, Query, params
from fastapi.responses import Response
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import FREE, OCCUPIED
from app.runtime import crop_window
from app.web.schemas import ErrorResponse
from app.web.service import RobotService

# BGR
UNKNOWN_BGR = (128, 128, 128)
FREE_BGR = (235, 240, 235)
OCCUPIED_BGR = (50, 45, 40)
TRAIL_BGR = (200, 120, 30)
PATH_BGR = (200, 40, 200)
ROBOT_BGR = (220, 90, 20)
HEADING_BGR = (0, 140, 240)

TRAIL_STEP_M = 0.03
TRAIL_POINTS = 2000


@dataclass(frozen=True)
class MapPicture:
    png: bytes
    window: GroundGrid
    """The cells drawn (clipped to the world grid)."""
    px_per_m: float
    size_px: int
    center_xy: tuple[float, float]
    """World point at the picture's centre."""


class PoseTrail:
    """Recent robot positions, sampled whenever the map is drawn (the dashboard asks
    twice a second), so the trail shows where the robot went while someone watched."""

    def __init__(self, maxlen: int = TRAIL_POINTS) -> None:
        self.points: deque[tuple[float, float]] = deque(maxlen=maxlen)

    def add(self, pose: Pose2D) -> None:
        point = (pose.x_m, pose.y_m)
        if not self.points or math.dist(self.points[-1], point) >= TRAIL_STEP_M:
            self.points.append(point)


def world_to_px(
    points_xy: NDArray[np.floating], center_xy: tuple[float, float], size_px: int, px_per_m: float
) -> NDArray[np.int32]:
    """(N, 2) world metres -> (N, 2) integer pixel (u, v) of the north-up picture."""
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    u = size_px / 2 - (pts[:, 1] - center_xy[1]) * px_per_m
    v = size_px / 2 - (pts[:, 0] - center_xy[0]) * px_per_m
    return np.round(np.column_stack((u, v))).astype(np.int32)


def draw_map(
    service: RobotService, trail: PoseTrail, size_m: float, size_px: int
) -> MapPicture | None:
    """The map picture around the robot, or None without a mapper (no calibration)."""
    snapshot = service.world_maps.peek()
    if snapshot is None:
        return None
    pose = service.odometry.pose
    grid = snapshot.grid
    center = (pose.x_m, pose.y_m)
    rows, cols, window = crop_window(grid, center, size_m)
    cells = snapshot.cells[rows, cols]
    px_per_m = size_px / size_m
    image = np.full((size_px, size_px, 3), UNKNOWN_BGR, dtype=np.uint8)
    # Paint the window's cells: scale the clipped raster and place it where its corner is.
    colours = np.empty((*cells.shape, 3), dtype=np.uint8)
    colours[:] = UNKNOWN_BGR
    colours[cells == FREE] = FREE_BGR
    colours[cells == OCCUPIED] = OCCUPIED_BGR
    u0, v0 = world_to_px(np.array([[window.x_max_m, window.y_max_m]]), center, size_px, px_per_m)[0]
    cell_px = grid.cell_m * px_per_m
    w_px = max(1, round(window.cols * cell_px))
    h_px = max(1, round(window.rows * cell_px))
    scaled = cv2.resize(colours, (w_px, h_px), interpolation=cv2.INTER_NEAREST)
    x0, y0 = max(0, u0), max(0, v0)
    x1, y1 = min(size_px, u0 + w_px), min(size_px, v0 + h_px)
    if x1 > x0 and y1 > y0:
        image[y0:y1, x0:x1] = scaled[y0 - v0 : y1 - v0, x0 - u0 : x1 - u0]
    # One metre grid lines, faint, so distances can be read off.
    for metres in range(-math.ceil(size_m), math.ceil(size_m) + 1):
        gx = world_to_px(
            np.array([[math.floor(center[0]) + metres, 0.0]]), center, size_px, px_per_m
        )[0][1]
        gy = world_to_px(
            np.array([[0.0, math.floor(center[1]) + metres]]), center, size_px, px_per_m
        )[0][0]
        cv2.line(image, (0, int(gx)), (size_px - 1, int(gx)), (170, 170, 170), 1)
        cv2.line(image, (int(gy), 0), (int(gy), size_px - 1), (170, 170, 170), 1)

    trail.add(pose)
    if len(trail.points) >= 2:
        pts = world_to_px(np.array(trail.points), center, size_px, px_per_m)
        cv2.polylines(image, [pts], False, TRAIL_BGR, 2, cv2.LINE_AA)
    path = snapshot.path_xy
    if path is not None and len(path) >= 2:
        cv2.polylines(
            image, [world_to_px(path, center, size_px, px_per_m)], False, PATH_BGR, 2, cv2.LINE_AA
        )
    if snapshot.goal_xy is not None:
        goal = world_to_px(np.array([snapshot.goal_xy]), center, size_px, px_per_m)[0]
        cv2.drawMarker(image, (int(goal[0]), int(goal[1])), PATH_BGR, cv2.MARKER_STAR, 18, 2)
    robot_px = world_to_px(np.array([center]), center, size_px, px_per_m)[0]
    radius_px = max(4, round(service.config.mapping.robot_radius_m * px_per_m))
    nose = (
        center[0] + 2.2 * service.config.mapping.robot_radius_m * math.cos(pose.theta_rad),
        center[1] + 2.2 * service.config.mapping.robot_radius_m * math.sin(pose.theta_rad),
    )
    nose_px = world_to_px(np.array([nose]), center, size_px, px_per_m)[0]
    cv2.circle(image, (int(robot_px[0]), int(robot_px[1])), radius_px, ROBOT_BGR, 2, cv2.LINE_AA)
    cv2.line(
        image,
        (int(robot_px[0]), int(robot_px[1])),
        (int(nose_px[0]), int(nose_px[1])),
        ROBOT_BGR,
        3,
        cv2.LINE_AA,
    )
    drive = service.drives.peek()
    if drive is not None and drive.heading_rad is not None and drive.source == "autonomy":
        heading = pose.theta_rad + drive.heading_rad
        tip = (center[0] + 0.6 * math.cos(heading), center[1] + 0.6 * math.sin(heading))
        tip_px = world_to_px(np.array([tip]), center, size_px, px_per_m)[0]
        cv2.arrowedLine(
            image,
            (int(robot_px[0]), int(robot_px[1])),
            (int(tip_px[0]), int(tip_px[1])),
            HEADING_BGR,
            2,
            cv2.LINE_AA,
            tipLength=0.2,
        )
    ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise RuntimeError("PNG encoding of the map failed")
    return MapPicture(png.tobytes(), window, px_per_m, size_px, center)


def map_router(service: RobotService, *, dependencies: Sequence[params.Depends] = ()) -> APIRouter:
    """``GET /api/map.png`` and ``GET /api/map.json``; ``dependencies`` are added to both
    (pass the API's read-auth dependency when status reads need the token)."""
    router = APIRouter(dependencies=list(dependencies), tags=["status"])
    trail = PoseTrail()

    @router.get(
        "/api/map.png",
        response_class=Response,
        responses={
            200: {"content": {"image/png": {}}},
            409: {"model": ErrorResponse, "description": "no map (no floor calibration)"},
        },
    )
    async def map_png(
        size_m: Annotated[float, Query(ge=1.0, le=40.0)] = 8.0,
        px: Annotated[int, Query(ge=64, le=1200)] = 480,
    ) -> Response:
        """The occupancy map, ``size_m`` wide around the robot, ``px`` pixels square:
        free light, obstacles dark, unknown grey; the robot (circle, nose), its trail
        (blue), the frontier goal (star) and the path to it (magenta), steering's
        heading (orange arrow); one-metre grid lines."""
        picture = await asyncio.to_thread(draw_map, service, trail, size_m, px)
        if picture is None:
            return Response(
                b'{"detail":"no map: the floor calibration is missing"}',
                status_code=409,
                media_type="application/json",
            )
        return Response(picture.png, media_type="image/png", headers={"Cache-Control": "no-store"})

    @router.get("/api/map.json")
    async def map_json() -> dict[str, Any]:
        """The world grid's geometry and counts, the pose, the frontier goal and reason."""
        snapshot = service.world_maps.peek()
        pose = service.odometry.pose
        out: dict[str, Any] = {
            "pose": {"x_m": pose.x_m, "y_m": pose.y_m, "theta_rad": pose.theta_rad},
            "frontier": None
            if snapshot is None
            else {
                "goal_xy": list(snapshot.goal_xy) if snapshot.goal_xy is not None else None,
                "reason": snapshot.frontier_reason,
                "clusters": snapshot.frontier_clusters,
            },
            "grid": None,
            "convention": "north-up: picture up = world +x, picture right = world -y",
        }
        if snapshot is not None:
            grid = snapshot.grid
            out["grid"] = {
                "x_max_m": grid.x_max_m,
                "y_max_m": grid.y_max_m,
                "cell_m": grid.cell_m,
                "rows": grid.rows,
                "cols": grid.cols,
                "free_cells": snapshot.free_cells,
                "occupied_cells": snapshot.occupied_cells,
                "age_s": round(max(0.0, time.monotonic() - snapshot.done_s), 2),
            }
        return out

    return router
