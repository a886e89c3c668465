"""Floor beyond a colour edge, confirmed by motion parallax (plane + parallax).

Colour methods end the floor wherever its appearance changes: at a rug, at the
threshold between wood and tiles. Motion tells such an edge from an obstacle's foot. Warp
an earlier frame onto the current one through the floor homography and the odometry
between them: every point on the floor plane lands where it is now, while a point above
the floor is displaced along the line through the epipole (the vanishing point of the
camera's own motion, since the camera moves parallel to the floor), by a parallax that
grows with its height. A pixel whose texture runs across that line and which matches after
the warp is on the floor; one that does not match stands up. Plain surfaces give no
evidence either way.

`extend_floor` then walks each image column upward from where the colour floor ends,
through pixels of floor evidence, stopping at the first one that stands up or after a
stretch of ground with no evidence at all, and keeps the floor up to the last confirmed
pixel. A box's foot is on the floor (its junction confirms a pixel or two), its face gives
nothing and its top edge stands up, so the walk stops at its foot.

Pure functions on numpy arrays. Frames: ``H_ground_from_image`` maps undistorted pixels
(u, v, 1) to the robot frame's floor (x forward, y left, metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class PlanarParams:
    """Thresholds of the parallax test (see the module docstring).

    Attributes
    ----------
    blur_sigma_px : Gaussian smoothing before comparing (noise, aliasing).
    texture_min : gradient along the epipolar line, grey levels per pixel, below which a
        pixel gives no evidence.
    window_px : side of the window matched at each shift.
    planar_max_px : a textured pixel whose best-matching shift along its epipolar line is
        at most this is on the floor.
    standing_min_px : ... at least this, it stands up.
    match_max : mean absolute difference (grey levels) a floor match may have.
    mismatch_min : ... at or above which, unshifted, the pixel stands up whatever the
        search found (its parallax is beyond the search range).
    max_gap_m : ground distance the column walk crosses without evidence.
    min_support_px : confirmed pixels a column needs before it is extended.
    max_range_m : no extension beyond this ground distance (parallax shrinks with range).
    foot_margin_px : a walk that ends at a standing pixel this close above its last
        confirmed one gives these rows back (the foot of what stands).
    downscale : `confirm_floor` works on images this many times smaller.
    """

    blur_sigma_px: float = 1.0
    texture_min: float = 3.0
    window_px: int = 5
    planar_max_px: float = 0.5
    standing_min_px: float = 2.0
    match_max: float = 3.0
    mismatch_min: float = 8.0
    max_gap_m: float = 0.45
    min_support_px: int = 3
    max_range_m: float = 2.5
    foot_margin_px: int = 2
    downscale: int = 2


SHIFTS_PX = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0)
"""Residual parallax searched along each epipolar line (pixels)."""


def view_homography(
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
) -> NDArray[np.float64]:
    """H_cur_from_ref: the image-to-image homography the floor plane induces between a
    reference view and the current one, from the robot poses (x_m, y_m, theta_rad)."""
    G = np.asarray(H_ground_from_image, dtype=np.float64)
    ref, cur = _rigid(*T_world_ref), _rigid(*T_world_cur)
    H = np.linalg.inv(G) @ np.linalg.inv(cur) @ ref @ G
    return np.asarray(H / H[2, 2], dtype=np.float64)


def epipole_px(
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    camera_xy_robot: tuple[float, float],
) -> tuple[float, float] | None:
    """Where parallax points in the current image: the vanishing point of the camera's
    translation (the camera moves parallel to the floor). None without translation or
    when that point is at infinity in the image (sideways motion)."""
    cam = np.array([camera_xy_robot[0], camera_xy_robot[1], 1.0])
    ref_c = _rigid(*T_world_ref) @ cam
    cur_T = _rigid(*T_world_cur)
    cur_c = cur_T @ cam
    d_world = cur_c[:2] - ref_c[:2]
    if float(np.hypot(*d_world)) < 1e-6:
        return None
    d_cur = cur_T[:2, :2].T @ d_world  # the translation in the current robot frame
    p = np.linalg.inv(np.asarray(H_ground_from_image, dtype=np.float64)) @ np.array(
        [d_cur[0], d_cur[1], 0.0]
    )
    if abs(p[2]) < 1e-12:
        return None
    return float(p[0] / p[2]), float(p[1] / p[2])


def parallax_evidence(
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    H_cur_from_ref: NDArray[np.float64],
    epipole: tuple[float, float],
    params: PlanarParams | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(on_floor, standing): (H, W) bool masks of the pixels the parallax test decides.

    The reference frame is warped through the floor homography, then shifted along each
    pixel's epipolar line by each of `SHIFTS_PX`; the shift that matches best (a window's
    mean absolute difference) is the pixel's residual parallax. Searching, rather than
    dividing the residual by the gradient, keeps sub-pixel rendering and interpolation
    error at strong edges from looking like parallax.

    Parameters
    ----------
    gray_cur, gray_ref : (H, W) uint8, the current frame (or a band of its rows) and the
        reference frame (undistorted; sizes may differ).
    H_cur_from_ref : from `view_homography` (into ``gray_cur``'s pixels).
    epipole : from `epipole_px` (in ``gray_cur``'s pixels).
    """
    p = params if params is not None else PlanarParams()
    if gray_cur.ndim != 2 or gray_ref.ndim != 2:
        raise ValueError(
            f"gray_cur and gray_ref: expected (H, W) images, got "
            f"{gray_cur.shape} and {gray_ref.shape}"
        )
    h, w = gray_cur.shape
    cur = cv2.GaussianBlur(gray_cur.astype(np.float32), (0, 0), p.blur_sigma_px)
    ref = cv2.GaussianBlur(gray_ref.astype(np.float32), (0, 0), p.blur_sigma_px)
    warped = cv2.warpPerspective(
        ref, H_cur_from_ref, (w, h), flags=cv2.INTER_LINEAR, borderValue=np.nan
    )
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    eu, ev = np.float32(epipole[0]) - uu, np.float32(epipole[1]) - vv
    norm = np.hypot(eu, ev)
    norm[norm < 1e-3] = 1.0
    eu /= norm
    ev /= norm
    gu = cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gv = cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    along = np.abs(gu * eu + gv * ev)
    window = (p.window_px, p.window_px)
    costs = np.empty((len(SHIFTS_PX), h, w), np.float32)
    for k, shift in enumerate(SHIFTS_PX):
        shifted = cv2.remap(
            warped,
            uu + np.float32(shift) * eu,
            vv + np.float32(shift) * ev,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=np.nan,
        )
        diff = np.abs(cur - shifted)
        diff[~np.isfinite(diff)] = 1e6  # off the reference view: never the best
        costs[k] = cv2.blur(diff, window)
    best = np.argmin(costs, axis=0)
    best_shift = np.abs(np.asarray(SHIFTS_PX, np.float32)[best])
    best_cost = np.take_along_axis(costs, best[None], axis=0)[0]
    floor_cost = costs[SHIFTS_PX.index(0.0)]
    textured = (along >= p.texture_min) & (floor_cost < 1e5)
    # Floor: matches where the floor plane puts it, and well. Standing: matches better
    # elsewhere on its epipolar line, or nowhere near (a parallax beyond the search).
    on_floor = textured & (best_shift <= p.planar_max_px) & (best_cost <= p.match_max)
    standing = textured & ((best_shift >= p.standing_min_px) | (floor_cost >= p.mismatch_min))
    return on_floor, standing


def row_ground_distance_m(
    H_ground_from_image: NDArray[np.float64], width_px: int, height_px: int
) -> NDArray[np.float64]:
    """(height_px,) forward ground distance of each row at the centre column; NaN at and
    above the horizon."""
    v = np.arange(height_px, dtype=np.float64)
    pts = np.stack([np.full_like(v, (width_px - 1) / 2.0), v, np.ones_like(v)])
    g = np.asarray(H_ground_from_image, dtype=np.float64) @ pts
    with np.errstate(invalid="ignore", divide="ignore"):
        x = g[0] / g[2]
    x[(g[2] <= 0) | ~np.isfinite(x) | (x <= 0)] = np.nan
    return np.asarray(x, dtype=np.float64)


def extend_floor(
    floor_mask: NDArray[np.bool_],
    on_floor: NDArray[np.bool_],
    standing: NDArray[np.bool_],
    row_distance_m: NDArray[np.float64],
    params: PlanarParams | None = None,
) -> NDArray[np.bool_]:
    """The floor mask extended upward in each column through parallax-confirmed floor
    (see the module docstring). Columns whose bottom pixel is not floor are left alone.
    Returns a new (H, W) bool mask; the input is not modified."""
    p = params if params is not None else PlanarParams()
    if not (floor_mask.shape == on_floor.shape == standing.shape):
        raise ValueError("floor_mask, on_floor and standing must have one shape")
    if row_distance_m.shape != (floor_mask.shape[0],):
        raise ValueError(f"row_distance_m: expected ({floor_mask.shape[0]},)")
    out = np.array(floor_mask, dtype=np.bool_, copy=True)
    _extend_columns(
        out,
        np.ascontiguousarray(on_floor, dtype=np.bool_),
        np.ascontiguousarray(standing, dtype=np.bool_),
        np.ascontiguousarray(row_distance_m, dtype=np.float64),
        float(p.max_gap_m),
        int(p.min_support_px),
        float(p.max_range_m),
        int(p.foot_margin_px),
    )
    return out


@numba.njit(cache=True, nogil=True)
def _extend_columns(
    mask: NDArray[np.bool_],
    on_floor: NDArray[np.bool_],
    standing: NDArray[np.bool_],
    dist: NDArray[np.float64],
    max_gap_m: float,
    min_support: int,
    max_range_m: float,
    foot_margin: int,
) -> None:
    h, w = mask.shape
    for u in range(w):
        if not mask[h - 1, u]:
            continue
        b = h - 1
        while b > 0 and mask[b - 1, u]:
            b -= 1
        last_confirmed = -1
        support = 0
        last_d = dist[b] if not math.isnan(dist[b]) else 0.0
        v = b - 1
        stood = False
        while v >= 0:
            d = dist[v]
            if math.isnan(d) or d > max_range_m:
                break
            if standing[v, u]:
                stood = True
                break
            if on_floor[v, u]:
                support += 1
                last_confirmed = v
                last_d = d
            elif d - last_d > max_gap_m:
                break
            v -= 1
        if stood and last_confirmed >= 0 and last_confirmed - v <= foot_margin:
            # Ended at something standing right above: the last confirmed pixels are its
            # foot, where parallax is still too small to tell. Keep them out.
            last_confirmed += foot_margin
        if support >= min_support and 0 <= last_confirmed < b:
            for r in range(last_confirmed, b):
                mask[r, u] = True


def _rigid(x_m: float, y_m: float, theta_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s, x_m], [s, c, y_m], [0.0, 0.0, 1.0]])


def confirm_floor(
    floor_mask: NDArray[np.bool_],
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    camera_xy_robot: tuple[float, float],
    params: PlanarParams | None = None,
) -> NDArray[np.bool_]:
    """The whole test: ``floor_mask`` extended by parallax-confirmed floor, computed at
    1 / ``params.downscale`` resolution (the cost is in the search) and only ever adding
    floor. Returns ``floor_mask`` itself when the views give no parallax to test.

    Parameters
    ----------
    floor_mask : (H, W) bool, the colour method's floor.
    gray_cur, gray_ref : (H, W) uint8, this frame and an earlier one (undistorted).
    H_ground_from_image : the floor homography (full-resolution pixels).
    T_world_ref, T_world_cur : robot poses (x_m, y_m, theta_rad) of the two frames.
    camera_xy_robot : the camera's position on the robot (metres).
    """
    p = params if params is not None else PlanarParams()
    h, w = floor_mask.shape
    if gray_cur.shape != (h, w) or gray_ref.shape != (h, w):
        raise ValueError(
            f"gray_cur {gray_cur.shape} and gray_ref {gray_ref.shape} must match "
            f"floor_mask {floor_mask.shape}"
        )
    k = p.downscale
    # Pixel centres of the small image in the full one: u_full = k * u + (k - 1) / 2.
    S = np.array([[k, 0.0, (k - 1) / 2.0], [0.0, k, (k - 1) / 2.0], [0.0, 0.0, 1.0]])
    G = np.asarray(H_ground_from_image, dtype=np.float64) @ S
    epipole = epipole_px(G, T_world_ref, T_world_cur, camera_xy_robot)
    if epipole is None:
        return floor_mask
    small = (w // k, h // k)
    cur = np.asarray(cv2.resize(gray_cur, small, interpolation=cv2.INTER_AREA), np.uint8)
    ref = np.asarray(cv2.resize(gray_ref, small, interpolation=cv2.INTER_AREA), np.uint8)
    mask = cv2.resize(floor_mask.astype(np.uint8), small, interpolation=cv2.INTER_NEAREST) > 0
    distance = row_ground_distance_m(G, *small)
    # Only the rows a column walk can reach: from the lowest end of the floor seen from
    # the bottom up to the row at max_range_m (the search is the costly part).
    bottom_run = np.logical_and.accumulate(mask[::-1], axis=0).sum(axis=0)
    walks = bottom_run > 0
    reachable = np.flatnonzero(np.isfinite(distance) & (distance <= p.max_range_m))
    if not walks.any() or reachable.size == 0:
        return floor_mask
    pad = p.window_px + 2
    r0 = max(int(reachable[0]) - pad, 0)
    r1 = min(int(small[1] - bottom_run[walks].min()) + pad, small[1])
    if r1 <= r0:
        return floor_mask
    T_band_from_small = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
    band_on, band_standing = parallax_evidence(
        cur[r0:r1],
        ref,
        T_band_from_small @ view_homography(G, T_world_ref, T_world_cur),
        (epipole[0], epipole[1] - r0),
        p,
    )
    on_floor = np.zeros_like(mask)
    standing = np.zeros_like(mask)
    on_floor[r0:r1] = band_on
    standing[r0:r1] = band_standing
    extended = extend_floor(mask, on_floor, standing, distance, p)
    added = cv2.resize((extended & ~mask).astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    return np.asarray(floor_mask | (added > 0), dtype=np.bool_)
