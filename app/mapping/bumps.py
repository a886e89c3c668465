"""Where a stalled robot touched something (pure).

When the wheels stall (`app.control.stall`), something the camera missed holds the
robot: right in front of it when it pushed forwards, behind it when it reversed. Where
across its front is not known, so the mark is a band just outside the robot's circle,
``BUMP_DEPTH_M`` deep and ``BUMP_HALF_ANGLE_RAD`` either side of the push's direction.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid, Pose2D

BUMP_DEPTH_M = 0.08
"""Depth of the band a bump marks, outward from the robot's edge."""
BUMP_HALF_ANGLE_RAD = math.pi / 4
"""Half the band's angular width, about the direction the robot pushed."""


def bump_cells(
    grid: GroundGrid, T_world_robot: Pose2D, radius_m: float, *, forward: bool
) -> NDArray[np.int64]:
    """Flat indices (sorted) of the cells of ``grid`` whose centres lie between
    ``radius_m`` and ``radius_m + BUMP_DEPTH_M`` from the robot's centre, within
    ``BUMP_HALF_ANGLE_RAD`` of its heading (``forward``) or of the opposite direction."""
    if radius_m < 0:
        raise ValueError(f"radius_m must be >= 0, got {radius_m}")
    outer = radius_m + BUMP_DEPTH_M
    inv = 1.0 / grid.cell_m
    r0 = (grid.x_max_m - T_world_robot.x_m) * inv
    c0 = (grid.y_max_m - T_world_robot.y_m) * inv
    span = outer * inv
    rows = np.arange(max(math.floor(r0 - span), 0), min(math.ceil(r0 + span) + 1, grid.rows))
    cols = np.arange(max(math.floor(c0 - span), 0), min(math.ceil(c0 + span) + 1, grid.cols))
    if rows.size == 0 or cols.size == 0:
        return np.zeros(0, dtype=np.int64)
    # Cell centres in the world frame (rows run down x, columns down y).
    dx = (grid.x_max_m - (rows[:, None] + 0.5) * grid.cell_m) - T_world_robot.x_m
    dy = (grid.y_max_m - (cols[None, :] + 0.5) * grid.cell_m) - T_world_robot.y_m
    distance = np.hypot(dx, dy)
    heading = T_world_robot.theta_rad + (0.0 if forward else math.pi)
    off = np.abs(np.remainder(np.arctan2(dy, dx) - heading + math.pi, math.tau) - math.pi)
    inside = (distance > radius_m) & (distance <= outer) & (off <= BUMP_HALF_ANGLE_RAD)
    rr, cc = np.nonzero(inside)
    return np.asarray(rows[rr] * grid.cols + cols[cc], dtype=np.int64)
