"""Inverse perspective mapping: floor pixels to ground coordinates, precomputed once.

The thesis maps each frame through its homography; here the mapping is a look-up table
built once per calibration and image size, so mapping a floor mask to the ground costs
one ``cv2.remap``. Lens distortion is removed inside the tables (the homography applies
to undistorted pixels).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from app.mapping.calibration import FloorCalibration, apply_homography
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid


@dataclass(frozen=True)
class GroundLookup:
    """Robot-frame ground position of every pixel.

    Attributes
    ----------
    x_m, y_m : (H, W) float32, NaN where invalid
    valid : (H, W) bool, below the horizon and within ``max_range_m`` of the robot
    """

    x_m: NDArray[np.float32]
    y_m: NDArray[np.float32]
    valid: NDArray[np.bool_]


def build_ground_lookup(calibration: FloorCalibration, *, max_range_m: float = 5.0) -> GroundLookup:
    """Per-pixel ground coordinates for the calibration's image size."""
    if max_range_m <= 0:
        raise ValueError(f"max_range_m must be positive, got {max_range_m}")
    width, height = calibration.image_size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    ground = calibration.image_to_ground(np.column_stack([u.ravel(), v.ravel()]))
    x = ground[:, 0].reshape(height, width)
    y = ground[:, 1].reshape(height, width)
    valid = np.isfinite(x) & (np.hypot(x, y) <= max_range_m)
    x[~valid] = np.nan
    y[~valid] = np.nan
    return GroundLookup(x.astype(np.float32), y.astype(np.float32), valid)


@dataclass(frozen=True)
class BirdseyeMap:
    """Where each bird's-eye cell comes from in the camera image.

    Attributes
    ----------
    grid : GroundGrid over the robot frame
    map_u, map_v : (rows, cols) float32 source pixel of each cell centre (for cv2.remap)
    visible : (rows, cols) bool, the cell is in front of the camera, inside the image and
        within the range limit
    image_size : (width, height) of the frames it applies to
    """

    grid: GroundGrid
    map_u: NDArray[np.float32]
    map_v: NDArray[np.float32]
    visible: NDArray[np.bool_]
    image_size: tuple[int, int]


def build_birdseye_map(
    calibration: FloorCalibration, grid: GroundGrid, *, max_range_m: float = 5.0
) -> BirdseyeMap:
    """Precompute the remap tables of a bird's-eye raster (see `app.mapping.frames`)."""
    x, y = grid.cell_centers()
    pixels = calibration.ground_to_image(np.column_stack([x.ravel(), y.ravel()]))
    width, height = calibration.image_size
    u = pixels[:, 0].reshape(grid.shape)
    v = pixels[:, 1].reshape(grid.shape)
    inside = np.isfinite(u) & np.isfinite(v)
    inside &= (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
    visible = inside & (np.hypot(x, y) <= max_range_m)
    map_u = np.where(visible, u, -1.0).astype(np.float32)
    map_v = np.where(visible, v, -1.0).astype(np.float32)
    return BirdseyeMap(grid, map_u, map_v, visible, (width, height))


def _check_size(shape: tuple[int, ...], bmap: BirdseyeMap, name: str) -> None:
    width, height = bmap.image_size
    if shape[:2] != (height, width):
        raise ValueError(
            f"{name} is {shape[1]}x{shape[0]} px but the bird's-eye map was built for "
            f"{width}x{height} px"
        )


def birdseye_image(frame: NDArray[np.uint8], bmap: BirdseyeMap) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 frame -> (rows, cols, 3) uint8 view from above (black = unseen)."""
    _check_size(frame.shape, bmap, "frame")
    out = cv2.remap(frame, bmap.map_u, bmap.map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return np.asarray(out, dtype=np.uint8)


def birdseye_floor_patch(floor_mask: NDArray[np.bool_], bmap: BirdseyeMap) -> NDArray[np.uint8]:
    """(H, W) bool floor mask -> (rows, cols) uint8 robot-frame ground patch with values
    `FLOOR`, `NOT_FLOOR` and `UNSEEN` (cells the camera does not see)."""
    _check_size(floor_mask.shape, bmap, "floor mask")
    source = floor_mask.astype(np.uint8)
    sampled = cv2.remap(
        source, bmap.map_u, bmap.map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
    )
    patch = np.where(np.asarray(sampled) > 0, FLOOR, NOT_FLOOR).astype(np.uint8)
    patch[~bmap.visible] = UNSEEN
    return patch


def lookup_error_m(
    calibration: FloorCalibration, lookup: GroundLookup, points_px: NDArray[np.floating]
) -> float:
    """RMS difference between the table and a direct homography at integer pixels (a
    self-check of the table: 0 up to float32 rounding)."""
    pts = np.asarray(points_px, dtype=np.int64).reshape(-1, 2)
    direct = calibration.image_to_ground(pts.astype(np.float64))
    table = np.column_stack([lookup.x_m[pts[:, 1], pts[:, 0]], lookup.y_m[pts[:, 1], pts[:, 0]]])
    ok = np.isfinite(direct).all(axis=1) & np.isfinite(table).all(axis=1)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(((direct[ok] - table[ok]) ** 2).sum(axis=1).mean()))


__all__ = [
    "BirdseyeMap",
    "GroundLookup",
    "apply_homography",
    "birdseye_floor_patch",
    "birdseye_image",
    "build_birdseye_map",
    "build_ground_lookup",
    "lookup_error_m",
]
