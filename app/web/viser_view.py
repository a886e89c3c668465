"""A live 3D view of the robot in viser: the occupancy map on the ground, the robot's pose
and trail, what the camera sees of the floor, the safe zone, the steering heading and
the frontier goal with its path.

viser runs its own server (a thread with its own event loop) on a localhost port; the
dashboard reaches it through the proxy in `app.web.viser_proxy`. Its scene API is
synchronous and thread-safe, so `ViserView.run` (a task in the daemon's loop) updates
the scene directly and only moves the map's PNG encoding off the loop.

Frames: viser's world is the odometry/world frame of the map (x forward at start-up,
y left, z up), so poses go in unchanged. Everything attached to the robot (footprint,
camera footprint, safe zone, heading) is a child of ``/robot`` and moves with it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import viser
import viser.transforms as vtf
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import FREE, OCCUPIED
from app.perception.pipeline import trapezoid_from_config
from app.runtime import percentiles_ms

if TYPE_CHECKING:
    from app.mapping.calibration import FloorCalibration
    from app.web.service import RobotService

log = logging.getLogger("floornav.viser")

MAP_PERIOD_S = 0.5
"""The map is one image re-sent at most this often (<= 2 Hz, see measured-facts)."""
UNWATCHED_POSE_PERIOD_S = 1.0
"""Pose (and trail) updates while no viser client is connected."""
POSE_PERIOD_S = 0.1
"""Pose, trail, heading and goal (10 Hz)."""
TRAIL_STEP_M = 0.02
"""A new trail point once the robot moved this far."""
TRAIL_CHUNK_POINTS = 100
"""The trail is sent in chunks: only the newest (growing) chunk is re-sent at 10 Hz, so
the bytes per update stay bounded however long the robot drives."""
TRAIL_MAX_CHUNKS = 60
GROUND_Z_M = 0.0
OVERLAY_Z_M = 0.01
"""Lines drawn on the floor sit a centimetre above the map image so they stay visible."""

MAP_COLOURS_RGBA = {
    "unknown": (0, 0, 0, 0),  # transparent: viser's ground grid shows through
    "free": (214, 232, 214, 255),
    "occupied": (45, 45, 55, 255),
}

# The image plane's local frame has image columns along +x and rows along +y (viser draws
# images like OpenCV, facing -z). A GroundGrid has columns along world -y and rows along
# world -x, so the plane is turned half a turn about the (1, -1, 0) diagonal.
_R_WORLD_IMAGE = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_WXYZ_WORLD_IMAGE: NDArray[np.float64] = np.asarray(
    vtf.SO3.from_matrix(_R_WORLD_IMAGE).wxyz, dtype=np.float64
)


def yaw_wxyz(theta_rad: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by ``theta_rad`` about +z."""
    return (math.cos(theta_rad / 2), 0.0, 0.0, math.sin(theta_rad / 2))


def map_image_rgba(cells: NDArray[np.int8]) -> NDArray[np.uint8]:
    """Occupancy classes (-1 unknown, 0 free, 1 occupied) -> an RGBA image, one pixel a
    cell, in the grid's raster order."""
    image = np.empty((*cells.shape, 4), dtype=np.uint8)
    image[:] = MAP_COLOURS_RGBA["unknown"]
    image[cells == FREE] = MAP_COLOURS_RGBA["free"]
    image[cells == OCCUPIED] = MAP_COLOURS_RGBA["occupied"]
    return image


def grid_center_xy(grid: GroundGrid) -> tuple[float, float]:
    return (grid.x_max_m - grid.rows * grid.cell_m / 2, grid.y_max_m - grid.cols * grid.cell_m / 2)


def polyline_segments(
    points_xy: NDArray[np.floating], z_m: float, *, closed: bool
) -> NDArray[np.float32]:
    """(N, 2) points -> (M, 2, 3) segments for ``add_line_segments``."""
    pts = np.asarray(points_xy, dtype=np.float32)
    if closed:
        pts = np.vstack((pts, pts[:1]))
    xyz = np.column_stack((pts, np.full(len(pts), z_m, dtype=np.float32)))
    return np.ascontiguousarray(np.stack((xyz[:-1], xyz[1:]), axis=1))


def circle_xy(radius_m: float, n: int = 32) -> NDArray[np.float64]:
    angles = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    return np.column_stack((radius_m * np.cos(angles), radius_m * np.sin(angles)))


def camera_floor_footprint(
    calibration: FloorCalibration, max_range_m: float, *, samples: int = 60
) -> NDArray[np.float64] | None:
    """The floor the camera sees, in the robot frame, as a 4-corner polygon: the image's
    bottom corners and, up each side edge, the farthest floor point within
    ``max_range_m`` (the top of the image is above the horizon for a floor camera).
    None when the calibration maps no corner to the floor."""
    width, height = calibration.image_size
    rows = np.linspace(height - 1, 0, samples)
    corners = []
    for u in (0.0, width - 1.0):
        pts = calibration.image_to_ground(np.column_stack((np.full(samples, u), rows)))
        ok = np.isfinite(pts).all(axis=1) & (np.hypot(pts[:, 0], pts[:, 1]) <= max_range_m)
        if not ok.any():
            return None
        seen = pts[ok]
        corners.append((seen[0], seen[-1]))  # nearest (bottom row) and farthest
    (left_near, left_far), (right_near, right_far) = corners
    return np.array([left_near, right_near, right_far, left_far])


def _share_disabled(verbose: bool = True) -> str | None:
    log.info("viser share link refused: disabled", extra={"event": "viser_share_refused"})
    return None


def disable_share(server: viser.ViserServer) -> None:
    """No public share link: viser would open a tunnel through share.viser.studio to
    anyone holding the link. Its ``ShareUrlRequest`` handler calls
    ``server.request_share_url`` (looked up at each call), so that is replaced on the
    instance, and the share button is hidden. (The proxy drops those messages too.)"""
    server.request_share_url = _share_disabled  # type: ignore[method-assign]
    server.gui.configure_theme(show_share_button=False)


@dataclass
class _Trail:
    """Completed chunks (each its own scene node, never re-sent) and the open one."""

    chunks: deque[str]
    points: list[tuple[float, float]]
    next_chunk: int = 0


class ViserView:
    """The viser server and the task that keeps its scene in step with ``service``.

    Parameters
    ----------
    service : the running daemon (`app.runtime.Runtime`, or any `RobotService`); read only
    port : the port to bind; viser silently takes the next free one when it is busy, so
        the bound port is read back (`port` after `start`)
    host : keep the default: the view is meant to be reached through the API's proxy
    """

    def __init__(self, service: RobotService, *, port: int, host: str = "127.0.0.1") -> None:
        self.service = service
        self.requested_port = port
        self.host = host
        self.server: viser.ViserServer | None = None
        self.timings_ms: dict[str, deque[float]] = {
            "map": deque(maxlen=2000),
            "pose": deque(maxlen=2000),
        }
        self.map_updates = 0
        self.map_bytes_last = 0
        self._map_handle: viser.ImageHandle | None = None
        self._map_key: tuple[float, float, float, int, int] | None = None
        self._last_cells: NDArray[np.int8] | None = None
        self._robot: viser.FrameHandle | None = None
        self._heading: viser.LineSegmentsHandle | None = None
        self._goal: viser.IcosphereHandle | None = None
        self._path: viser.LineSegmentsHandle | None = None
        self._open_chunk: viser.LineSegmentsHandle | None = None
        self._trail = _Trail(deque(), [])
        self._robot_overlays_key: tuple[Any, ...] | None = None

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("ViserView.port: not started")
        return self.server.get_port()

    def start(self) -> int:
        """Start the viser server and build the scene's fixed parts; returns the port."""
        server = viser.ViserServer(host=self.host, port=self.requested_port, verbose=False)
        disable_share(server)
        self.server = server
        port = server.get_port()
        if port != self.requested_port:
            log.warning(
                "viser port %d busy, bound %d instead",
                self.requested_port,
                port,
                extra={"event": "viser_port"},
            )
        server.scene.set_up_direction("+z")
        server.initial_camera.position = (-2.5, 0.0, 3.5)
        server.initial_camera.look_at = (1.0, 0.0, 0.0)
        size = self.service.config.mapping.grid_size_m
        server.scene.add_grid(
            "/ground_grid",
            width=size,
            height=size,
            cell_size=0.5,
            section_size=1.0,
            position=(0.0, 0.0, GROUND_Z_M - 0.002),
        )
        self._robot = server.scene.add_frame(
            "/robot", axes_length=0.25, axes_radius=0.012, origin_radius=0.03
        )
        radius = self.service.config.mapping.robot_radius_m
        server.scene.add_line_segments(
            "/robot/footprint",
            polyline_segments(circle_xy(radius), OVERLAY_Z_M, closed=True),
            colors=(30, 90, 200),
            thickness=0.012,
        )
        self._heading = server.scene.add_line_segments(
            "/robot/heading",
            np.zeros((1, 2, 3), np.float32),
            colors=(240, 140, 0),
            thickness=0.02,
            visible=False,
        )
        self._goal = server.scene.add_icosphere(
            "/frontier_goal", radius=0.08, color=(200, 40, 200), visible=False
        )
        self._path = server.scene.add_line_segments(
            "/frontier_path",
            np.zeros((1, 2, 3), np.float32),
            colors=(200, 40, 200),
            thickness=0.015,
            visible=False,
        )
        log.info("viser view on http://%s:%d/", self.host, port, extra={"event": "viser_started"})
        return port

    def stop(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            server.stop()

    async def run(self) -> None:
        """Update the scene until cancelled: robot at 10 Hz, map at <= 2 Hz."""
        if self.server is None:
            self.start()
        next_map_s = next_pose_s = 0.0
        while True:
            started = time.monotonic()
            watched = self.server is not None and bool(self.server.get_clients())
            # Nobody watching: the scene's setters cost ~4 ms of GIL per update (py-spy),
            # so the pose (and the trail it records) goes at 1 Hz until someone looks;
            # viser replays the scene to a new client and the next update is 0.1 s away.
            if watched or started >= next_pose_s:
                next_pose_s = started + UNWATCHED_POSE_PERIOD_S
                self.update_pose()
            # Nobody watching: skip the map (the next update follows within MAP_PERIOD_S).
            if started >= next_map_s and watched:
                next_map_s = started + MAP_PERIOD_S
                # classify + PNG encoding of a 400x400 grid: keep it off the event loop.
                await asyncio.to_thread(self.update_map)
            await asyncio.sleep(max(0.0, POSE_PERIOD_S - (time.monotonic() - started)))

    # -- the map (<= 2 Hz) -------------------------------------------------------------

    def update_map(self) -> None:
        """Re-send the occupancy map image when it changed, and the frontier path."""
        server = self.server
        if server is None:
            return
        with self._timed("map"):
            snapshot = self.service.world_maps.peek()
            if snapshot is None:  # no floor calibration (or no frame mapped yet): no map
                if self._map_handle is not None:
                    self._map_handle.visible = False
                return
            cells = snapshot.cells
            grid = snapshot.grid
            key = (grid.x_max_m, grid.y_max_m, grid.cell_m, grid.rows, grid.cols)
            if self._map_handle is None or key != self._map_key:
                if self._map_handle is not None:
                    self._map_handle.remove()
                cx, cy = grid_center_xy(grid)
                self._map_handle = server.scene.add_image(
                    "/map",
                    map_image_rgba(cells),
                    render_width=grid.cols * grid.cell_m,
                    render_height=grid.rows * grid.cell_m,
                    format="png",
                    cast_shadow=False,
                    receive_shadow=False,
                    wxyz=_WXYZ_WORLD_IMAGE,
                    position=(cx, cy, GROUND_Z_M),
                )
                self._map_key = key
                self.map_updates += 1
            elif self._last_cells is None or not np.array_equal(cells, self._last_cells):
                self._map_handle.image = map_image_rgba(cells)
                self._map_handle.visible = True
                self.map_updates += 1
            self.map_bytes_last = len(self._map_handle._data)
            self._last_cells = cells
            self._update_path(snapshot.path_xy)

    def _update_path(self, path: NDArray[np.float64] | None) -> None:
        assert self._path is not None
        if path is None or len(path) < 2:
            self._path.visible = False
            return
        self._path.points = polyline_segments(path, OVERLAY_Z_M, closed=False)
        self._path.visible = True

    # -- the robot (10 Hz) -------------------------------------------------------------

    def update_pose(self) -> None:
        """Robot pose, trail, heading, frontier goal; the camera's floor footprint and the
        safe zone when the calibration or the configuration changed."""
        server = self.server
        if server is None:
            return
        with self._timed("pose"), server.atomic():
            pose = self.service.odometry.pose
            assert self._robot is not None
            self._robot.position = (pose.x_m, pose.y_m, 0.0)
            self._robot.wxyz = yaw_wxyz(pose.theta_rad)
            self._update_trail(pose)
            self._update_heading()
            self._update_goal()
            self._update_robot_overlays()

    def _update_heading(self) -> None:
        assert self._heading is not None
        drive = self.service.drives.peek()
        heading = drive.heading_rad if drive is not None else None
        if heading is None or drive is None or drive.source != "autonomy":
            self._heading.visible = False
            return
        tip = (0.5 * math.cos(heading), 0.5 * math.sin(heading))
        self._heading.points = np.array(
            [[[0.0, 0.0, OVERLAY_Z_M * 2], [tip[0], tip[1], OVERLAY_Z_M * 2]]], np.float32
        )
        self._heading.visible = True

    def _update_goal(self) -> None:
        assert self._goal is not None
        snapshot = self.service.world_maps.peek()
        goal_xy = snapshot.goal_xy if snapshot is not None else None
        if goal_xy is None:
            self._goal.visible = False
            return
        self._goal.position = (float(goal_xy[0]), float(goal_xy[1]), 0.08)
        self._goal.visible = True

    def _update_trail(self, pose: Pose2D) -> None:
        server = self.server
        assert server is not None
        trail = self._trail
        point = (pose.x_m, pose.y_m)
        if trail.points and math.dist(trail.points[-1], point) < TRAIL_STEP_M:
            return
        trail.points.append(point)
        if len(trail.points) < 2:
            return
        segments = polyline_segments(np.array(trail.points), OVERLAY_Z_M, closed=False)
        if self._open_chunk is None:
            self._open_chunk = server.scene.add_line_segments(
                f"/trail/{trail.next_chunk}", segments, colors=(30, 90, 200), thickness=0.01
            )
        else:
            self._open_chunk.points = segments
        if len(trail.points) >= TRAIL_CHUNK_POINTS:
            # Freeze this chunk; the next starts where it ended so the line is unbroken.
            trail.chunks.append(f"/trail/{trail.next_chunk}")
            trail.next_chunk += 1
            trail.points = [trail.points[-1]]
            self._open_chunk = None
            while len(trail.chunks) > TRAIL_MAX_CHUNKS:
                server.scene.remove_by_name(trail.chunks.popleft())

    def _update_robot_overlays(self) -> None:
        """Robot-frame drawings that only change with the calibration or the config."""
        server = self.server
        assert server is not None
        config = self.service.config
        calibration = self.service.calibration
        key = (id(calibration), config.perception.safe_zone, config.mapping.max_range_m)
        if key == self._robot_overlays_key:
            return
        self._robot_overlays_key = key
        for name in ("/robot/camera_view", "/robot/camera_rays", "/robot/safe_zone"):
            server.scene.remove_by_name(name)
        if calibration is None:
            return
        footprint = camera_floor_footprint(calibration, config.mapping.max_range_m)
        if footprint is not None:
            server.scene.add_line_segments(
                "/robot/camera_view",
                polyline_segments(footprint, OVERLAY_Z_M, closed=True),
                colors=(120, 120, 120),
                thickness=0.008,
            )
            # Rays from the lens to the footprint's corners: the frustum cut by the floor.
            # The lens height is not part of a floor homography; the simulator's mounting
            # height is the best available figure for the drawing.
            lens = np.array(
                [config.camera.x_m, config.camera.y_m, config.sim.camera_height_m], np.float32
            )
            ends = np.column_stack((footprint, np.full(4, OVERLAY_Z_M))).astype(np.float32)
            rays = np.stack((np.broadcast_to(lens, ends.shape), ends), axis=1)
            server.scene.add_line_segments(
                "/robot/camera_rays",
                np.ascontiguousarray(rays),
                colors=(120, 120, 120),
                thickness=0.005,
            )
        width, height = calibration.image_size
        zone = trapezoid_from_config(config.perception.safe_zone)
        zone_xy = calibration.image_to_ground(zone.corners_px(width, height))
        if np.isfinite(zone_xy).all():
            server.scene.add_line_segments(
                "/robot/safe_zone",
                polyline_segments(zone_xy, OVERLAY_Z_M * 1.5, closed=True),
                colors=(220, 40, 40),
                thickness=0.012,
            )

    # -- timings -----------------------------------------------------------------------

    @contextlib.contextmanager
    def _timed(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings_ms[name].append((time.perf_counter() - start) * 1000.0)

    def timing_summary(self) -> dict[str, dict[str, float | int | None]]:
        """p50/p95/max milliseconds of the map and pose updates (for reports and tests)."""
        return {
            name: percentiles_ms([v / 1000.0 for v in values])
            for name, values in self.timings_ms.items()
        }
