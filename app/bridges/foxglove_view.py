"""The Foxglove live view: the running daemon as Foxglove (https://foxglove.dev) shows
robots, over the Foxglove WebSocket protocol (foxglove-sdk's server, its own port).

Topics (Foxglove's schemas, encoded as protobuf by the SDK):

- ``/camera``, ``foxglove.CompressedImage``: the camera with the floor overlay, as the
  dashboard's video shows it (JPEG, every ``image_period_s``: 5 Hz, 10 Hz at most);
- ``/map``, ``foxglove.Grid``: the occupancy grid in ``world``, fields ``red green blue
  alpha`` to draw it and ``occupancy`` (-1 unknown, 0 free, 100 occupied), at most every
  ``map_period_s`` and only when it changed;
- ``/tf``, ``foxglove.FrameTransforms``: ``world`` -> ``robot`` (the odometry pose) and
  ``robot`` -> ``camera`` (the lens, optical axes: z forward, x right, y down), 10 Hz;
- ``/scene``, ``foxglove.SceneUpdate``: the robot's footprint, heading and state, the
  safe zone on the floor, the frontier goal and the planned path, 2 Hz;
- ``/log``, ``foxglove.Log``: the daemon's log records.

Frames: ``world`` is the map's frame (the odometry frame: the start pose, x forward, y
left, z up), ``robot`` is the robot (x forward, between the wheels, on the floor).

**Read-only.** The server advertises no capability (no ``clientPublish``, no
``parameters``, no ``services``, no ``connectionGraph``): a client can subscribe and
watch, and has no way to send the robot anything, so the token rules of the API have
nothing to guard here. The protocol has no token either: the view is bound like the
dashboard (``[foxglove] host``, localhost by default), and anyone who reaches the port
sees the camera.

Costs and isolation: the view reads only immutable snapshots (the `LatestSlot` s'
newest messages, the odometry pose); JPEG and grid encoding run in worker threads
(``asyncio.to_thread``) and only for topics a client subscribed to, so nobody watching
costs nearly nothing. With a client subscribed to everything, at the defaults: ~2 ms
of CPU per camera image (overlay ~1.6, JPEG ~0.5 on a simulated 640x480 frame), ~3 ms
per 400x400 grid, ~0.1 ms per scene, microseconds per transform: ~14 ms a second,
~0.5 ms per 30 fps frame, under 4 % of the daemon's ~12.5 ms of CPU per frame
(docs/performance.md); ``image_period_s = 0.1`` (10 Hz) makes it ~7 %.

Logging only appends to a bounded deque (the logging thread never waits; the oldest
records drop). A publishing error is logged and the view goes on; a server that cannot
start is logged and the daemon runs without it: the view never stops a stage.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import foxglove
import numpy as np
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformsChannel,
    GridChannel,
    LogChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    Color,
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    Grid,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector2,
    Vector3,
)
from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer
from numpy.typing import NDArray

from app.channels import LatestSlot, wait_event
from app.config import FloornavConfig, SafeZoneConfig
from app.logs import escape_control
from app.mapping.occupancy import FREE, OCCUPIED
from app.messages import DriveMsg, FloorMsg, State, WorldMapMsg
from app.perception.pipeline import trapezoid_from_config
from app.web.video import capture_wall_time, encode_jpeg, heading_for, render_overlay

if TYPE_CHECKING:
    from app.control.kinematics import WheelOdometry
    from app.mapping.calibration import FloorCalibration
    from app.mapping.frames import Pose2D

log = logging.getLogger("floornav.foxglove")

WORLD_FRAME = "world"
ROBOT_FRAME = "robot"
CAMERA_FRAME = "camera"

CAMERA_TOPIC = "/camera"
MAP_TOPIC = "/map"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/scene"
LOG_TOPIC = "/log"

SCENE_PERIOD_S = 0.5
"""The scene (goal, path, safe zone, state) at most this often: the frontier search and
the map snapshot it comes from run at 2 Hz."""
TICK_MAX_S = 0.1
"""The publishing loop wakes at least this often; transforms and logs go out each time
(10 Hz: a smooth robot in the 3D panel for ~3 us of CPU per message)."""
LOG_BACKLOG_RECORDS = 1000
"""Log records kept for the view; the oldest drop when nobody drains them."""
LOG_BATCH_RECORDS = 200
"""Log records sent per tick at most (the rest go on the next)."""
MESSAGE_BACKLOG = 64
"""Messages the server buffers per client before dropping the oldest (SDK default
1024: with grids of ~0.8 MB that could hold much memory for one slow client)."""
ERROR_LOG_PERIOD_S = 60.0
"""A failing topic is logged at most this often."""
OVERLAY_Z_M = 0.01
"""Drawings on the floor sit a centimetre above the map so they stay visible."""

# A grid cell's bytes: red, green, blue, alpha, then ``occupancy`` (int8, as a ROS
# OccupancyGrid holds it: -1 unknown, 0 free, 100 occupied).
GRID_UNKNOWN = np.array([128, 128, 128, 60, 255], np.uint8)  # occupancy -1
GRID_FREE = np.array([214, 232, 214, 255, 0], np.uint8)
GRID_OCCUPIED = np.array([45, 45, 55, 255, 100], np.uint8)
GRID_CELL_BYTES = 5

_LOG_LEVELS = (
    (logging.CRITICAL, LogLevel.Fatal),
    (logging.ERROR, LogLevel.Error),
    (logging.WARNING, LogLevel.Warning),
    (logging.INFO, LogLevel.Info),
    (logging.DEBUG, LogLevel.Debug),
)
_STANDARD_RECORD_KEYS = set(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {
    "message",
    "asctime",
}


class LiveSource(Protocol):
    """What the view reads of the daemon (`app.runtime.Runtime` is one): immutable
    snapshots only, never a verb."""

    @property
    def config(self) -> FloornavConfig: ...

    @property
    def state(self) -> State: ...

    @property
    def floors(self) -> LatestSlot[FloorMsg]: ...

    @property
    def drives(self) -> LatestSlot[DriveMsg]: ...

    @property
    def world_maps(self) -> LatestSlot[WorldMapMsg]: ...

    @property
    def odometry(self) -> WheelOdometry: ...

    @property
    def calibration(self) -> FloorCalibration | None: ...


# -- geometry ---------------------------------------------------------------------------


def quaternion_from_matrix(R: NDArray[np.floating]) -> tuple[float, float, float, float]:
    """A rotation matrix -> its unit quaternion ``(x, y, z, w)`` with ``w >= 0``."""
    m = np.asarray(R, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (
            (m[2, 1] - m[1, 2]) / s,
            (m[0, 2] - m[2, 0]) / s,
            (m[1, 0] - m[0, 1]) / s,
            0.25 * s,
        )
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    x, y, z, w = (float(v) for v in q)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    sign = -1.0 if w < 0.0 else 1.0
    return (sign * x / norm, sign * y / norm, sign * z / norm, sign * w / norm)


def yaw_quaternion(theta_rad: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``theta_rad`` about +z."""
    return (0.0, 0.0, math.sin(theta_rad / 2), math.cos(theta_rad / 2))


_R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Columns: the optical axes (x right, y down, z forward) in a forward-looking x-forward,
y-left, z-up camera body."""


@dataclass(frozen=True)
class CameraMount:
    """The lens in the robot frame: position and the optical frame's orientation."""

    position_m: tuple[float, float, float]
    rotation_xyzw: tuple[float, float, float, float]
    source: str
    """``calibration`` (decomposed from the floor homography and the lens model) or
    ``config`` (``[camera] x_m, y_m``, ``[sim] camera_height_m, camera_pitch_rad``)."""


def mount_from_config(config: FloornavConfig) -> CameraMount:
    """The lens from the configuration: ``[camera]`` places it on the robot; height and
    pitch are not part of a floor homography, so the simulator's mounting
    (``[sim] camera_height_m``, ``camera_pitch_rad``) is the best figure there is (the 3D
    view draws the lens there too)."""
    pitch = config.sim.camera_pitch_rad
    c, s = math.cos(pitch), math.sin(pitch)
    R_robot_link = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # pitched down
    return CameraMount(
        (config.camera.x_m, config.camera.y_m, config.sim.camera_height_m),
        quaternion_from_matrix(R_robot_link @ _R_LINK_OPTICAL),
        "config",
    )


def mount_from_homography(
    H_image_from_ground: NDArray[np.floating], camera_matrix: NDArray[np.floating]
) -> CameraMount | None:
    """The lens pose behind a floor homography, given the pinhole matrix of the pixels it
    maps to: ``H ~ K [r1 r2 t]`` for floor points ``(x, y, 0)`` of the robot frame. None
    when the result is no camera above the floor looking at it."""
    B = np.linalg.solve(np.asarray(camera_matrix, np.float64), np.asarray(H_image_from_ground))
    scale = 1.0 / np.linalg.norm(B[:, 0])
    # The sign: a floor point ahead (1 m) must lie in front of the lens (z > 0).
    if (B[:, 0] + B[:, 2])[2] < 0.0:
        scale = -scale
    r1, r2, t = scale * B[:, 0], scale * B[:, 1], scale * B[:, 2]
    U, _, Vt = np.linalg.svd(np.column_stack((r1, r2, np.cross(r1, r2))))
    R_camera_robot = U @ Vt  # the nearest rotation
    if np.linalg.det(R_camera_robot) < 0.0:
        return None
    position = -R_camera_robot.T @ t
    if not np.isfinite(position).all() or position[2] <= 0.0:
        return None
    return CameraMount(
        (float(position[0]), float(position[1]), float(position[2])),
        quaternion_from_matrix(R_camera_robot.T),
        "calibration",
    )


def camera_mount(config: FloornavConfig, calibration: FloorCalibration | None) -> CameraMount:
    """From the floor calibration when it has a lens model, else from the config."""
    if calibration is not None and calibration.intrinsics is not None:
        mount = mount_from_homography(
            calibration.H_image_from_ground, calibration.intrinsics.camera_matrix
        )
        if mount is not None:
            return mount
    return mount_from_config(config)


# -- messages ---------------------------------------------------------------------------


def _stamp(wall_s: float) -> Timestamp:
    return Timestamp.from_epoch_secs(wall_s)


def _pose(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(w=1.0))


def _colour(rgb: tuple[int, int, int], alpha: float = 1.0) -> Color:
    return Color(r=rgb[0] / 255, g=rgb[1] / 255, b=rgb[2] / 255, a=alpha)


def _points(xy: NDArray[np.floating], z_m: float) -> list[Point3]:
    return [Point3(x=float(x), y=float(y), z=z_m) for x, y in np.asarray(xy).reshape(-1, 2)]


def grid_message(snapshot: WorldMapMsg, wall_s: float) -> Grid:
    """The occupancy grid as a ``foxglove.Grid`` in ``world``.

    A `GroundGrid` raster runs rows along -x and columns along -y (a mirror image, which
    no pose can express), so the cells are re-ordered: the message's columns run along
    +x and its rows along +y, and its origin is the grid's (x_min, y_min) corner."""
    grid = snapshot.grid
    classes = snapshot.cells[::-1, ::-1].T  # (cols, rows): [y][x]
    data = np.empty((*classes.shape, GRID_CELL_BYTES), np.uint8)
    data[...] = GRID_UNKNOWN
    data[classes == FREE] = GRID_FREE
    data[classes == OCCUPIED] = GRID_OCCUPIED
    u8, i8 = PackedElementFieldNumericType.Uint8, PackedElementFieldNumericType.Int8
    fields = [
        PackedElementField(name=name, offset=offset, type=u8)
        for offset, name in enumerate(("red", "green", "blue", "alpha"))
    ]
    fields.append(PackedElementField(name="occupancy", offset=4, type=i8))
    return Grid(
        timestamp=_stamp(wall_s),
        frame_id=WORLD_FRAME,
        pose=_pose(grid.x_max_m - grid.rows * grid.cell_m, grid.y_max_m - grid.cols * grid.cell_m),
        column_count=grid.rows,
        cell_size=Vector2(x=grid.cell_m, y=grid.cell_m),
        row_stride=grid.rows * GRID_CELL_BYTES,
        cell_stride=GRID_CELL_BYTES,
        fields=fields,
        data=data.tobytes(),
    )


def transforms_message(pose: Pose2D, mount: CameraMount, wall_s: float) -> FrameTransforms:
    """``world`` -> ``robot`` (the odometry pose) and ``robot`` -> ``camera``."""
    stamp = _stamp(wall_s)
    qx, qy, qz, qw = yaw_quaternion(pose.theta_rad)
    cx, cy, cz, cw = mount.rotation_xyzw
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=WORLD_FRAME,
                child_frame_id=ROBOT_FRAME,
                translation=Vector3(x=pose.x_m, y=pose.y_m, z=0.0),
                rotation=Quaternion(x=qx, y=qy, z=qz, w=qw),
            ),
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=ROBOT_FRAME,
                child_frame_id=CAMERA_FRAME,
                translation=Vector3(
                    x=mount.position_m[0], y=mount.position_m[1], z=mount.position_m[2]
                ),
                rotation=Quaternion(x=cx, y=cy, z=cz, w=cw),
            ),
        ]
    )


ROBOT_RGB = (30, 90, 200)
SAFE_ZONE_RGB = (220, 40, 40)
PATH_RGB = (200, 40, 200)
HEADING_RGB = (240, 140, 0)


def scene_message(source: LiveSource, wall_s: float) -> SceneUpdate:
    """The robot (footprint, heading, state), the safe zone, the frontier goal and path;
    what is gone (no goal, no path, no calibration) is deleted by id."""
    config = source.config
    stamp = _stamp(wall_s)
    entities: list[SceneEntity] = []
    gone: list[str] = []

    radius = config.mapping.robot_radius_m
    angles = np.linspace(0.0, 2 * math.pi, 32, endpoint=False)
    lines = [
        LinePrimitive(
            type=LinePrimitiveLineType.LineLoop,
            pose=_pose(),
            thickness=0.01,
            points=_points(np.column_stack((radius * np.cos(angles), radius * np.sin(angles))), 0.0)
            if radius > 0
            else [],
            color=_colour(ROBOT_RGB),
        )
    ]
    drive = source.drives.peek()
    if drive is not None and drive.heading_rad is not None and drive.source == "autonomy":
        tip = (0.5 * math.cos(drive.heading_rad), 0.5 * math.sin(drive.heading_rad))
        lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip,
                pose=_pose(),
                thickness=0.02,
                points=_points(np.array([(0.0, 0.0), tip]), 2 * OVERLAY_Z_M),
                color=_colour(HEADING_RGB),
            )
        )
    entities.append(
        SceneEntity(
            timestamp=stamp,
            frame_id=ROBOT_FRAME,
            id="robot",
            frame_locked=True,
            lines=lines,
            texts=[
                TextPrimitive(
                    pose=_pose(0.0, 0.0, 0.3),
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=_colour((255, 255, 255)),
                    text=str(source.state.value),
                )
            ],
        )
    )

    calibration = source.calibration
    zone_xy = None
    if calibration is not None:
        width, height = calibration.image_size
        zone = trapezoid_from_config(config.perception.safe_zone)
        zone_xy = calibration.image_to_ground(zone.corners_px(width, height))
    if zone_xy is not None and np.isfinite(zone_xy).all():
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=ROBOT_FRAME,
                id="safe_zone",
                frame_locked=True,
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineLoop,
                        pose=_pose(),
                        thickness=0.012,
                        points=_points(zone_xy, 1.5 * OVERLAY_Z_M),
                        color=_colour(SAFE_ZONE_RGB),
                    )
                ],
            )
        )
    else:
        gone.append("safe_zone")

    snapshot = source.world_maps.peek()
    goal = snapshot.goal_xy if snapshot is not None else None
    if goal is not None:
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD_FRAME,
                id="frontier_goal",
                spheres=[
                    SpherePrimitive(
                        pose=_pose(float(goal[0]), float(goal[1]), 0.08),
                        size=Vector3(x=0.16, y=0.16, z=0.16),
                        color=_colour(PATH_RGB),
                    )
                ],
            )
        )
    else:
        gone.append("frontier_goal")
    path = snapshot.path_xy if snapshot is not None else None
    if path is not None and len(path) >= 2:
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD_FRAME,
                id="frontier_path",
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineStrip,
                        pose=_pose(),
                        thickness=0.015,
                        points=_points(path, OVERLAY_Z_M),
                        color=_colour(PATH_RGB),
                    )
                ],
            )
        )
    else:
        gone.append("frontier_path")
    return SceneUpdate(
        deletions=[
            SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.MatchingId, id=i)
            for i in gone
        ],
        entities=entities,
    )


def log_level(levelno: int) -> LogLevel:
    for threshold, level in _LOG_LEVELS:
        if levelno >= threshold:
            return level
    return LogLevel.Unknown


# -- logs -------------------------------------------------------------------------------


@dataclass(frozen=True)
class LogEntry:
    created_s: float
    levelno: int
    name: str
    message: str
    file: str
    line: int

    def message_for_foxglove(self) -> Log:
        return Log(
            timestamp=_stamp(self.created_s),
            level=log_level(self.levelno),
            message=self.message,
            name=self.name,
            file=self.file,
            line=self.line,
        )


class _LineFormatter(logging.Formatter):
    """The message with the record's fields as ``key=value`` (as the daemon's text log
    writes them, without time and level, which the Log message carries)."""

    def format(self, record: logging.LogRecord) -> str:
        fields = " ".join(
            f"{escape_control(k)}={escape_control(str(v))}"
            for k, v in record.__dict__.items()
            if k not in _STANDARD_RECORD_KEYS
        )
        text = escape_control(record.getMessage())
        if fields:
            text += f"  [{fields}]"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


class LogForwarder(logging.Handler):
    """Keeps the newest log records for the view. ``emit`` formats the record and
    appends it to a bounded deque: no lock is waited for and nothing is sent from the
    logging thread; when the deque is full, the oldest record drops (counted)."""

    def __init__(self, maxlen: int = LOG_BACKLOG_RECORDS) -> None:
        super().__init__()
        self.setFormatter(_LineFormatter())
        self.records: deque[LogEntry] = deque(maxlen=maxlen)
        self.received = 0
        self.taken = 0

    @property
    def dropped(self) -> int:
        return self.received - self.taken - len(self.records)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            entry = LogEntry(
                record.created,
                record.levelno,
                record.name,
                self.format(record),
                record.pathname,
                record.lineno,
            )
        except Exception:
            self.handleError(record)
            return
        self.records.append(entry)  # atomic, never waits; drops the oldest when full
        self.received += 1

    def take(self, limit: int) -> list[LogEntry]:
        out: list[LogEntry] = []
        with contextlib.suppress(IndexError):
            while len(out) < limit:
                out.append(self.records.popleft())
        self.taken += len(out)
        return out

    def createLock(self) -> None:
        """No lock: `emit` only appends to a deque, which is thread-safe by itself, so
        the logging thread never waits for the view."""
        self.lock = None


# -- the service ------------------------------------------------------------------------


class _Subscriptions(ServerListener):
    """Counts subscriptions (the SDK calls it from its own thread) so a client that
    subscribes gets the map and scene at once, not when they next change."""

    def __init__(self) -> None:
        self.count = 0

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.count += 1


def route_sdk_logs() -> None:
    """Have the SDK's own log (clients connecting and leaving, invalid messages) go
    through Python logging at INFO and up, so through the daemon's handlers, which
    escape control characters: the SDK quotes what a client sent (an invalid message's
    text), which must not forge log lines. The SDK takes the level only before the
    process's first Foxglove sink starts, hence called when a view is built; repeating
    it is harmless."""
    foxglove.set_log_level(logging.INFO)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class FoxgloveView:
    """The Foxglove WebSocket server and the task that publishes the daemon's state to
    it; a `app.runtime.core.Service`. Read-only (see the module docstring).

    Parameters
    ----------
    source : the running daemon (`app.runtime.Runtime`); only read
    host, port : where to listen (``port=0``: any free port, read back from `port`)
    image_period_s, map_period_s : see `app.config.FoxgloveConfig`
    """

    name = "foxglove"

    def __init__(
        self,
        source: LiveSource,
        *,
        host: str,
        port: int,
        image_period_s: float = 0.2,
        map_period_s: float = 1.0,
    ) -> None:
        route_sdk_logs()
        self.source = source
        self.host = host
        self.requested_port = port
        self.image_period_s = image_period_s
        self.map_period_s = map_period_s
        self.context = foxglove.Context()
        self.logs = LogForwarder()
        self.server: WebSocketServer | None = None
        self.published: dict[str, int] = dict.fromkeys(
            (CAMERA_TOPIC, MAP_TOPIC, TF_TOPIC, SCENE_TOPIC, LOG_TOPIC), 0
        )
        self.failures: dict[str, int] = dict.fromkeys(self.published, 0)
        self._listener = _Subscriptions()
        self._stop = asyncio.Event()
        self._last_error_log_s: dict[str, float] = {}
        self._image_seq = -1
        self._map_key: tuple[int, int] = (-1, -1)
        self._scene_subscriptions = -1
        self._mount_key: tuple[int, FloornavConfig] | None = None
        self._mount: CameraMount | None = None
        self.camera: CompressedImageChannel | None = None
        self.map: GridChannel | None = None
        self.tf: FrameTransformsChannel | None = None
        self.scene: SceneUpdateChannel | None = None
        self.log_channel: LogChannel | None = None

    @property
    def port(self) -> int:
        """The port the server listens on (after it started)."""
        if self.server is None:
            raise RuntimeError("FoxgloveView.port: not serving")
        return self.server.port

    @property
    def serving(self) -> bool:
        return self.server is not None

    def request_stop(self) -> None:
        self._stop.set()

    async def serve(self) -> None:
        """Serve until `request_stop` (or cancellation); never raises an error: a server
        that cannot start, or fails, is logged and the daemon goes on without it."""
        if self._stop.is_set():
            return
        # Binding may resolve a host name: off the loop, and a cancellation meanwhile
        # still closes what the thread started.
        starting = asyncio.ensure_future(asyncio.to_thread(self._start))
        try:
            await asyncio.shield(starting)
        except asyncio.CancelledError:
            starting.add_done_callback(self._close_after_start)
            raise
        except Exception as exc:
            log.error(
                "Foxglove live view could not start on %s:%d: %s; the daemon runs without it",
                self.host,
                self.requested_port,
                exc,
                extra={"event": "foxglove_failed"},
            )
            self._close()
            return
        root = logging.getLogger()
        root.addHandler(self.logs)
        try:
            await self._publish_until_stopped()
        except Exception:
            log.exception(
                "Foxglove live view failed; it stops, the daemon runs on",
                extra={"event": "foxglove_failed"},
            )
        finally:
            root.removeHandler(self.logs)
            self._close()
            log.info("Foxglove live view stopped", extra={"event": "foxglove_stopped"})

    def _start(self) -> None:
        context = self.context
        self.camera = CompressedImageChannel(CAMERA_TOPIC, context=context)
        self.map = GridChannel(MAP_TOPIC, context=context)
        self.tf = FrameTransformsChannel(TF_TOPIC, context=context)
        self.scene = SceneUpdateChannel(SCENE_TOPIC, context=context)
        self.log_channel = LogChannel(LOG_TOPIC, context=context)
        self.server = foxglove.start_server(
            name="floornav",
            host=self.host,
            port=self.requested_port,
            capabilities=[],  # read-only: no clientPublish, parameters, services
            server_listener=self._listener,
            context=context,
            message_backlog_size=MESSAGE_BACKLOG,
        )
        log.info(
            "Foxglove live view on ws://%s:%d (read-only; open it in the Foxglove app)",
            self.host,
            self.server.port,
            extra={"event": "foxglove_started"},
        )
        web = self.source.config.web
        if web.require_token_for_status and not is_loopback(self.host):
            log.warning(
                "[web] require_token_for_status is set, but the Foxglove view on %s has "
                "no token: anyone who reaches port %d sees the camera",
                self.host,
                self.server.port,
                extra={"event": "foxglove_open"},
            )

    def _close_after_start(self, task: asyncio.Future[None]) -> None:
        if not task.cancelled():
            task.exception()  # retrieved: the start's error, if any, no longer matters
        self._close()

    def _close(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            with contextlib.suppress(Exception):
                server.stop()
        for channel in (self.camera, self.map, self.tf, self.scene, self.log_channel):
            if channel is not None:
                with contextlib.suppress(Exception):
                    channel.close()

    async def _publish_until_stopped(self) -> None:
        tick_s = min(self.image_period_s, TICK_MAX_S)
        next_image_s = next_map_s = next_scene_s = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            await self._guarded(TF_TOPIC, self._publish_tf)
            if now >= next_image_s:
                next_image_s = now + self.image_period_s
                await self._guarded(CAMERA_TOPIC, self._publish_camera)
            if now >= next_map_s and await self._guarded(MAP_TOPIC, self._publish_map):
                next_map_s = now + self.map_period_s
            if now >= next_scene_s or self._listener.count != self._scene_subscriptions:
                next_scene_s = now + SCENE_PERIOD_S
                await self._guarded(SCENE_TOPIC, self._publish_scene)
            await self._guarded(LOG_TOPIC, self._publish_logs)
            await wait_event(self._stop, max(0.0, tick_s - (time.monotonic() - now)))

    async def _guarded(self, topic: str, publish: Callable[[], Any]) -> bool:
        """Run one topic's publishing; an error is counted and logged (at most once a
        minute per topic), never raised. True if something was published."""
        try:
            return bool(await publish())
        except Exception as exc:
            self.failures[topic] += 1
            now = time.monotonic()
            if now - self._last_error_log_s.get(topic, -math.inf) >= ERROR_LOG_PERIOD_S:
                self._last_error_log_s[topic] = now
                log.warning(
                    "Foxglove view: publishing %s failed (%d so far): %s: %s",
                    topic,
                    self.failures[topic],
                    type(exc).__name__,
                    exc,
                    extra={"event": "foxglove_error", "topic": topic},
                )
            return False

    def _count(self, topic: str, n: int = 1) -> None:
        self.published[topic] += n

    # -- topics -----------------------------------------------------------------------

    async def _publish_camera(self) -> bool:
        channel = self.camera
        floor = self.source.floors.peek()
        if channel is None or floor is None or floor.seq == self._image_seq:
            return False
        if not channel.has_sinks():
            return False
        self._image_seq = floor.seq
        config = self.source.config
        heading = heading_for(floor, self.source.drives.peek())
        await asyncio.to_thread(
            self._encode_camera,
            channel,
            floor,
            heading,
            config.perception.safe_zone,
            config.web.jpeg_quality,
        )
        return True

    def _encode_camera(
        self,
        channel: CompressedImageChannel,
        floor: FloorMsg,
        heading_rad: float | None,
        safe_zone: SafeZoneConfig,
        quality: int,
    ) -> None:
        jpeg = encode_jpeg(render_overlay(floor, safe_zone, heading_rad), quality)
        wall_s = capture_wall_time(floor.capture_s)
        channel.log(
            CompressedImage(
                timestamp=_stamp(wall_s), frame_id=CAMERA_FRAME, data=jpeg, format="jpeg"
            ),
            log_time=int(wall_s * 1e9),
        )
        self._count(CAMERA_TOPIC)

    def _camera_mount(self) -> CameraMount:
        config, calibration = self.source.config, self.source.calibration
        key = (id(calibration), config)
        if self._mount is None or key != self._mount_key:
            self._mount, self._mount_key = camera_mount(config, calibration), key
        return self._mount

    async def _publish_tf(self) -> bool:
        channel = self.tf
        if channel is None or not channel.has_sinks():
            return False
        wall_s = time.time()
        message = transforms_message(self.source.odometry.pose, self._camera_mount(), wall_s)
        channel.log(message, log_time=int(wall_s * 1e9))
        self._count(TF_TOPIC)
        return True

    async def _publish_map(self) -> bool:
        channel = self.map
        snapshot = self.source.world_maps.peek()
        if channel is None or snapshot is None or not channel.has_sinks():
            return False
        key = (snapshot.seq, self._listener.count)
        if key == self._map_key:
            return False
        self._map_key = key
        await asyncio.to_thread(self._encode_map, channel, snapshot)
        return True

    def _encode_map(self, channel: GridChannel, snapshot: WorldMapMsg) -> None:
        wall_s = time.time()
        channel.log(grid_message(snapshot, wall_s), log_time=int(wall_s * 1e9))
        self._count(MAP_TOPIC)

    async def _publish_scene(self) -> bool:
        channel = self.scene
        self._scene_subscriptions = self._listener.count
        if channel is None or not channel.has_sinks():
            return False
        wall_s = time.time()
        channel.log(scene_message(self.source, wall_s), log_time=int(wall_s * 1e9))
        self._count(SCENE_TOPIC)
        return True

    async def _publish_logs(self) -> bool:
        channel = self.log_channel
        if channel is None or not self.logs.records or not channel.has_sinks():
            return False
        entries = self.logs.take(LOG_BATCH_RECORDS)
        for entry in entries:
            channel.log(entry.message_for_foxglove(), log_time=int(entry.created_s * 1e9))
        self._count(LOG_TOPIC, len(entries))
        return bool(entries)


def foxglove_view(runtime: LiveSource) -> FoxgloveView | None:
    """The view ``[foxglove]`` configures, or None when ``port`` is unset (off)."""
    section = runtime.config.foxglove
    if section.port is None:
        return None
    return FoxgloveView(
        runtime,
        host=section.host,
        port=section.port,
        image_period_s=section.image_period_s,
        map_period_s=section.map_period_s,
    )
