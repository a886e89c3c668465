"""The frozen messages the daemon's stages pass on, and the status it exposes.

Every message carries ``capture_s``: the ``time.monotonic()`` at which the camera frame
it derives from was captured, so any consumer knows its age.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from app.control.mux import Twist
from app.mapping.frames import GroundGrid, Pose2D


class State(StrEnum):
    IDLE = "idle"
    RUNNING = "running"  # exploring autonomously
    RETURNING = "returning"  # explored: driving back to where autonomy started
    EXPLORED = "explored"  # exploration finished (back at the start); start explores again
    TELEOP = "teleop"  # a person drives (over autonomy, if it was running)
    ESTOPPED = "estopped"  # latched until reset
    CALIBRATING = "calibrating"
    PROTECTIVE_STOP = "protective_stop"  # a transient cause holds the motors at zero
    FAULT = "fault"  # latched (a cause that repeats, a device gone): needs the operator


@dataclass(frozen=True)
class FrameMsg:
    """A camera frame. ``arrived_s``: when the host had it (`CameraFrame.arrived_s`)."""

    image: NDArray[np.uint8] = field(repr=False)
    capture_s: float
    seq: int
    arrived_s: float | None = None

    def age_s(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.capture_s


@dataclass(frozen=True)
class FloorMsg:
    """Perception's result for one frame (the image is kept for overlays).

    ``zone_floor_confidence`` (0..1) is how sure the segmenter is that the safe zone in
    front of the robot is floor (`app.perception.pipeline.FloorResult`); below
    ``perception.zone_min_floor_confidence`` the way ahead counts as blocked.
    ``unsure_mask`` (or None) is where a deferred learned-floor pass could have found
    floor: the map takes no evidence there from this frame.
    """

    seq: int
    capture_s: float
    done_s: float
    image: NDArray[np.uint8] = field(repr=False)
    floor_mask: NDArray[np.bool_] = field(repr=False)
    method: str
    timings_ms: dict[str, float]
    zone_floor_confidence: float
    unsure_mask: NDArray[np.bool_] | None = field(default=None, repr=False)
    arrived_s: float | None = None
    """When the host had the frame (`FrameMsg.arrived_s`)."""

    def age_s(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.capture_s


@dataclass(frozen=True)
class MapMsg:
    """The mapping stage's output for one frame: the map around the robot for steering.

    Attributes
    ----------
    T_odom_robot : the pose at capture time
    window_cells, window_grid : classes (-1/0/1) of the occupancy grid around the robot
    path_xy : (n, 2) odometry-frame path to the frontier goal, or None
    goal_xy, frontier_reason : the goal, or None and why there is none
    clearance_ahead_m : free floor ahead of the robot's front edge in this frame's
        bird's-eye view (robot-wide corridor)
    zone_known_floor : the share of the safe zone's ground the map knows is floor (0 with
        something standing in it; `app.mapping.ground_map.MapUpdate.zone_known_floor`),
        or None when not computed
    """

    seq: int
    capture_s: float
    done_s: float
    T_odom_robot: Pose2D
    window_cells: NDArray[np.int8] = field(repr=False)
    window_grid: GroundGrid
    path_xy: NDArray[np.float64] | None = field(repr=False)
    goal_xy: tuple[float, float] | None
    frontier_reason: str
    clearance_ahead_m: float
    zone_known_floor: float | None = None
    arrived_s: float | None = None
    """When the host had the frame (`FrameMsg.arrived_s`)."""

    def age_s(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.capture_s


@dataclass(frozen=True)
class WorldMapMsg:
    """The whole map as the web and other readers see it, published at most
    ``WORLD_MAP_PERIOD_S`` apart: a read-only copy, so no reader ever touches the
    mapper's arrays while the mapping thread changes them.

    Attributes
    ----------
    cells : classes (-1 unknown, 0 free, 1 occupied) of the whole world grid as the robot
        knows it (`OccupancyGrid.remembered_classes`: evidence that travel faded keeps
        its last class; the robot has seen it and plans on it), read-only
    grid : the world grid's geometry (odometry frame)
    T_odom_robot : the robot's pose when the snapshot was taken
    path_xy, goal_xy, frontier_reason, frontier_clusters : the newest frontier search
    """

    seq: int
    done_s: float
    cells: NDArray[np.int8] = field(repr=False)
    grid: GroundGrid
    T_odom_robot: Pose2D
    path_xy: NDArray[np.float64] | None = field(repr=False)
    goal_xy: tuple[float, float] | None
    frontier_reason: str
    frontier_clusters: int

    @property
    def free_cells(self) -> int:
        return int(np.count_nonzero(self.cells == 0))

    @property
    def occupied_cells(self) -> int:
        return int(np.count_nonzero(self.cells == 1))


@dataclass(frozen=True)
class DriveMsg:
    """A command as sent to the Uno."""

    twist: Twist
    left_pwm: int
    right_pwm: int
    source: str
    sent_s: float
    origin_s: float
    heading_rad: float | None = None
    """Steering's chosen heading (robot frame) for autonomy commands."""


@dataclass(frozen=True)
class Transition:
    time_s: float
    wall_time: float
    old: State
    new: State
    reason: str
