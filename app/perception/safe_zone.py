"""Stage 4: the trapezoidal safe zone in front of the robot and its histogram sampling."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


class SafeZoneError(ValueError):
    """The safe zone does not fit the image (outside it, or too small to hold a pixel)."""


@dataclass(frozen=True)
class Trapezoid:
    """A trapezoid with horizontal top and bottom edges, in fractions of width/height.

    Origin top-left, x to the right, y down. ``top_y_frac < bottom_y_frac``.
    """

    bottom_left_x_frac: float
    bottom_right_x_frac: float
    top_left_x_frac: float
    top_right_x_frac: float
    top_y_frac: float
    bottom_y_frac: float

    def corners_px(self, width: int, height: int) -> NDArray[np.float64]:
        """(4, 2) float64 corners x, y in pixels: bottom-left, bottom-right, top-right,
        top-left. Fractions map to pixel centres, so 1.0 is the last row or column."""
        w = width - 1
        h = height - 1
        return np.array(
            [
                [self.bottom_left_x_frac * w, self.bottom_y_frac * h],
                [self.bottom_right_x_frac * w, self.bottom_y_frac * h],
                [self.top_right_x_frac * w, self.top_y_frac * h],
                [self.top_left_x_frac * w, self.top_y_frac * h],
            ]
        )

    def seed_xy(self, width: int, height: int) -> tuple[int, int]:
        """The thesis's region-growing seed: the trapezoid's area centroid, in pixels."""
        corners = self.corners_px(width, height)
        x = corners[:, 0]
        y = corners[:, 1]
        cross = x * np.roll(y, -1) - np.roll(x, -1) * y
        area = 0.5 * cross.sum()
        cx = ((x + np.roll(x, -1)) * cross).sum() / (6.0 * area)
        cy = ((y + np.roll(y, -1)) * cross).sum() / (6.0 * area)
        return round(cx), round(cy)


def safe_zone_mask(shape: tuple[int, int], zone: Trapezoid) -> NDArray[np.bool_]:
    """Rasterise the safe zone.

    Parameters
    ----------
    shape : (H, W)
    zone : Trapezoid

    Returns
    -------
    (H, W) bool, True inside the trapezoid (edges included).

    Raises
    ------
    SafeZoneError
        A corner lies outside the image, or the zone covers no pixel.
    """
    height, width = shape
    fractions = (
        zone.bottom_left_x_frac,
        zone.bottom_right_x_frac,
        zone.top_left_x_frac,
        zone.top_right_x_frac,
        zone.top_y_frac,
        zone.bottom_y_frac,
    )
    if not all(0.0 <= f <= 1.0 for f in fractions):
        raise SafeZoneError(f"safe zone corners must be fractions in [0, 1], got {fractions}")
    if zone.top_y_frac >= zone.bottom_y_frac:
        raise SafeZoneError("safe zone: top_y_frac must be above (smaller than) bottom_y_frac")
    mask = np.zeros((height, width), dtype=np.uint8)
    corners = np.round(zone.corners_px(width, height)).astype(np.int32)
    cv2.fillConvexPoly(mask, corners, 1)
    if int(mask.sum()) < 16:
        raise SafeZoneError(
            f"safe zone covers {int(mask.sum())} px of a {width}x{height} image; "
            "the image is too small for it"
        )
    return mask.astype(bool)


def safe_zone_superpixels(
    labels: NDArray[np.int32],
    zone_mask: NDArray[np.bool_],
    n: int,
    *,
    min_overlap_frac: float = 0.0,
) -> NDArray[np.bool_]:
    """Superpixels that intersect the safe zone (thesis, "Safe zone histogram sampling").

    Parameters
    ----------
    labels : (H, W) int32, labels 0..n-1
    zone_mask : (H, W) bool
    n : int
    min_overlap_frac : float
        Keep a superpixel only if more than this fraction of its pixels lie in the zone;
        0 keeps every superpixel with a non-empty intersection (the thesis's rule).

    Returns
    -------
    (n,) bool
    """
    inside = np.bincount(labels[zone_mask], minlength=n)
    if min_overlap_frac <= 0.0:
        return inside > 0
    area = np.bincount(labels.ravel(), minlength=n)
    return inside > min_overlap_frac * np.maximum(area, 1)


def safe_zone_histogram(
    image: NDArray[np.uint8],
    labels: NDArray[np.int32],
    selected: NDArray[np.bool_],
    *,
    bins: int = 32,
) -> NDArray[np.float32]:
    """Per-channel histograms of the pixels of the selected superpixels.

    Parameters
    ----------
    image : (H, W, 3) uint8
        For example the smoothed BGR frame, or 8-bit Lab.
    labels : (H, W) int32
    selected : (n,) bool, from `safe_zone_superpixels`.
    bins : int, divides 256.

    Returns
    -------
    (3, bins) float32, each row normalised to sum 1 (all zeros if nothing is selected).
    """
    if 256 % bins:
        raise ValueError(f"bins must divide 256, got {bins}")
    pixels = image[selected[labels]]
    hist = np.zeros((3, bins), dtype=np.float32)
    if pixels.shape[0] == 0:
        return hist
    shift = int(np.log2(256 // bins))
    for channel in range(3):
        counts = np.bincount(pixels[:, channel] >> shift, minlength=bins)
        hist[channel] = counts / pixels.shape[0]
    return hist
