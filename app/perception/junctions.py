"""Stage 7: floor-junction masking (thesis, "Floor Junction Masking").

Vertical image lines stay vertical whatever the robot's heading (the camera moves in the
ground plane), so they are taken as possible edges of walls and obstacles. Where such a
line's bottom end meets a non-vertical line, an obstacle meets the floor: a floor
junction. Everything above the junction's non-vertical line is not floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class JunctionResult:
    """Result of `floor_junction_mask`.

    Attributes
    ----------
    mask : (H, W) bool
        False above detected floor junctions, True elsewhere (AND it with a floor mask).
    lines : (L, 4) int32
        Probabilistic Hough segments x1, y1, x2, y2.
    vertical : (L,) bool
        Which segments count as vertical.
    junctions : (J, 2) int32
        Pairs (index of a vertical segment, index of the non-vertical segment at its foot).
    """

    mask: NDArray[np.bool_]
    lines: NDArray[np.int32]
    vertical: NDArray[np.bool_]
    junctions: NDArray[np.int32]


def point_segment_distance(
    points: NDArray[np.float64], segments: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Euclidean distance of every point to every segment.

    Parameters
    ----------
    points : (P, 2) float64 x, y
    segments : (S, 4) float64 x1, y1, x2, y2

    Returns
    -------
    (P, S) float64
    """
    a = segments[None, :, 0:2]
    b = segments[None, :, 2:4]
    p = points[:, None, :]
    ab = b - a
    length_sq = np.maximum((ab * ab).sum(axis=2), 1e-12)
    t = np.clip(((p - a) * ab).sum(axis=2) / length_sq, 0.0, 1.0)
    closest = a + t[:, :, None] * ab
    distance: NDArray[np.float64] = np.sqrt(((p - closest) ** 2).sum(axis=2))
    return distance


def floor_junction_mask(
    gray: NDArray[np.uint8],
    *,
    canny_low: int = 20,
    canny_high: int = 60,
    hough_threshold: int = 20,
    min_line_length_px: int = 30,
    max_line_gap_px: int = 4,
    vertical_tolerance_rad: float = 0.2,
    junction_radius_px: float = 15.0,
) -> JunctionResult:
    """Detect floor junctions and mask the image region above them.

    Canny edges -> contours (``cv2.findContours``, Suzuki & Abe 1985) drawn one pixel
    wide -> probabilistic Hough segments. A segment within ``vertical_tolerance_rad`` of
    the image vertical is vertical; a non-vertical segment passing within
    ``junction_radius_px`` of a vertical segment's bottom end forms a junction with it.

    Parameters
    ----------
    gray : (H, W) uint8
        The smoothed grayscale frame (the thesis runs this stage on the smoothed image,
        which also keeps Canny from returning texture).

    Returns
    -------
    JunctionResult
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray: expected (H, W) uint8, got {gray.shape} {gray.dtype}")
    height, width = gray.shape
    edges = cv2.Canny(gray, canny_low, canny_high)
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    contour_image = np.zeros_like(edges)
    cv2.drawContours(contour_image, contours, -1, 255, 1)
    found = cv2.HoughLinesP(
        contour_image,
        rho=1,
        theta=np.pi / 180,
        threshold=hough_threshold,
        minLineLength=min_line_length_px,
        maxLineGap=max_line_gap_px,
    )
    mask = np.ones((height, width), dtype=bool)
    if found is None:
        empty = np.zeros((0, 4), np.int32)
        return JunctionResult(mask, empty, np.zeros(0, bool), np.zeros((0, 2), np.int32))
    lines = found.reshape(-1, 4).astype(np.int32)
    dx = (lines[:, 2] - lines[:, 0]).astype(np.float64)
    dy = (lines[:, 3] - lines[:, 1]).astype(np.float64)
    # Angle from the image vertical, in [0, pi/2].
    angle_from_vertical = np.arctan2(np.abs(dx), np.abs(dy))
    vertical = angle_from_vertical <= vertical_tolerance_rad
    vertical_idx = np.flatnonzero(vertical)
    other_idx = np.flatnonzero(~vertical)
    if vertical_idx.size == 0 or other_idx.size == 0:
        return JunctionResult(mask, lines, vertical, np.zeros((0, 2), np.int32))
    v = lines[vertical_idx].astype(np.float64)
    bottom_is_second = v[:, 3] >= v[:, 1]
    bottoms = np.where(bottom_is_second[:, None], v[:, 2:4], v[:, 0:2])
    distance = point_segment_distance(bottoms, lines[other_idx].astype(np.float64))
    vi, oi = np.nonzero(distance <= junction_radius_px)
    junctions = np.column_stack((vertical_idx[vi], other_idx[oi])).astype(np.int32)
    if junctions.size:
        floor_lines = lines[np.unique(junctions[:, 1])]
        polygons = [
            np.array([[x1, y1], [x2, y2], [x2, 0], [x1, 0]], dtype=np.int32)
            for x1, y1, x2, y2 in floor_lines.tolist()
        ]
        blocked = np.zeros((height, width), dtype=np.uint8)
        cv2.fillPoly(blocked, polygons, 1)
        mask &= blocked == 0
    return JunctionResult(mask, lines, vertical, junctions)
