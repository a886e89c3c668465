"""Frames, poses and raster conventions shared by the mapping modules.

Frames
------
image
    Pixels, origin at the top-left pixel centre, u to the right, v down.
robot (also "ground" for the floor homography)
    Metres on the floor plane, origin under the robot's centre (between the wheels),
    x forward, y to the left, z up; right-handed. ``H_ground_from_image`` maps image
    pixels (u, v, 1) of floor points to (x, y, 1) in this frame.
world
    Metres on the floor plane, fixed at the robot's start pose, x/y as the robot's were
    then. ``T_world_robot`` (a `Pose2D`) places the robot in it.

Rasters
-------
A `GroundGrid` is a north-up raster of square cells over a rectangle of a frame:
cell (row, col) covers ``x in [x_max - (row + 1) * cell, x_max - row * cell)`` and
``y in [y_max - (col + 1) * cell, y_max - col * cell)``, so rows grow backwards
(smaller x) and columns grow to the right (smaller y). For a robot-frame patch this is
the view from above with the robot looking up the image, as a person expects of a
bird's-eye view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FLOOR = 1
"""Ground-patch cell value: seen, and floor (free)."""
NOT_FLOOR = 0
"""Ground-patch cell value: seen, and not floor."""
UNSEEN = 255
"""Ground-patch cell value: outside the camera's view (or beyond its trusted range)."""


@dataclass(frozen=True)
class Pose2D:
    """A planar pose: position (x_m, y_m) and heading theta_rad (counter-clockwise
    from the x axis). As ``T_a_b`` it maps points of frame b into frame a."""

    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0

    def matrix(self) -> NDArray[np.float64]:
        """3x3 homogeneous transform."""
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return np.array([[c, -s, self.x_m], [s, c, self.y_m], [0.0, 0.0, 1.0]])

    def apply(self, points_xy: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) points of frame b -> (N, 2) points of frame a."""
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        pts = np.asarray(points_xy, dtype=np.float64)
        x = c * pts[:, 0] - s * pts[:, 1] + self.x_m
        y = s * pts[:, 0] + c * pts[:, 1] + self.y_m
        return np.column_stack((x, y))

    def compose(self, other: Pose2D) -> Pose2D:
        """``T_a_b.compose(T_b_c) == T_a_c``."""
        x, y = self.apply(np.array([[other.x_m, other.y_m]]))[0]
        theta = math.atan2(
            math.sin(self.theta_rad + other.theta_rad), math.cos(self.theta_rad + other.theta_rad)
        )
        return Pose2D(float(x), float(y), theta)

    def inverse(self) -> Pose2D:
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return Pose2D(-(c * self.x_m + s * self.y_m), s * self.x_m - c * self.y_m, -self.theta_rad)


@dataclass(frozen=True)
class GroundGrid:
    """A raster over a rectangle of a planar frame (see the module docstring).

    Attributes
    ----------
    x_max_m, y_max_m : float, the far-left corner (top-left of the raster)
    cell_m : float, cell size
    rows, cols : int
    """

    x_max_m: float
    y_max_m: float
    cell_m: float
    rows: int
    cols: int

    @classmethod
    def covering(
        cls, *, x_min_m: float, x_max_m: float, y_min_m: float, y_max_m: float, cell_m: float
    ) -> GroundGrid:
        if not (x_max_m > x_min_m and y_max_m > y_min_m and cell_m > 0):
            raise ValueError("GroundGrid.covering: need x_max > x_min, y_max > y_min, cell > 0")
        rows = math.ceil((x_max_m - x_min_m) / cell_m - 1e-9)
        cols = math.ceil((y_max_m - y_min_m) / cell_m - 1e-9)
        return cls(x_max_m, y_max_m, cell_m, rows, cols)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    def cell_centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(rows, cols) arrays of the x and y of every cell centre."""
        x = self.x_max_m - (np.arange(self.rows) + 0.5) * self.cell_m
        y = self.y_max_m - (np.arange(self.cols) + 0.5) * self.cell_m
        return np.meshgrid(x, y, indexing="ij")

    def cell_of(self, points_xy: NDArray[np.floating]) -> NDArray[np.int64]:
        """(N, 2) points -> (N, 2) integer (row, col); may lie outside the raster."""
        pts = np.asarray(points_xy, dtype=np.float64)
        row = np.floor((self.x_max_m - pts[:, 0]) / self.cell_m).astype(np.int64)
        col = np.floor((self.y_max_m - pts[:, 1]) / self.cell_m).astype(np.int64)
        return np.column_stack((row, col))

    def holds(self, rc: NDArray[np.integer]) -> NDArray[np.bool_]:
        """(N, 2) integer (row, col), as from `cell_of` -> (N,) bool: which lie on the
        raster."""
        return np.asarray(
            (rc[:, 0] >= 0) & (rc[:, 0] < self.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < self.cols),
            dtype=np.bool_,
        )


def same_geometry(a: GroundGrid, b: GroundGrid, tol_m: float = 1e-6) -> bool:
    """Whether two rasters cover the same cells: equal shapes, and cell size and corner
    equal within ``tol_m`` (the numbers may have passed through a text file)."""
    return (
        a.shape == b.shape
        and abs(a.cell_m - b.cell_m) <= tol_m
        and abs(a.x_max_m - b.x_max_m) <= tol_m
        and abs(a.y_max_m - b.y_max_m) <= tol_m
    )


def describe_grid(grid: GroundGrid) -> str:
    """``'400 x 400 cells of 0.05 m over x [-10, 10] m, y [-10, 10] m'``, for messages."""
    x_min = grid.x_max_m - grid.rows * grid.cell_m
    y_min = grid.y_max_m - grid.cols * grid.cell_m
    return (
        f"{grid.rows} x {grid.cols} cells of {grid.cell_m:g} m over"
        f" x [{x_min:g}, {grid.x_max_m:g}] m, y [{y_min:g}, {grid.y_max_m:g}] m"
    )
