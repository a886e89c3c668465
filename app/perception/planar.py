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

`floor_before_standing` is the test's other half: colour cannot tell a floor-coloured
wall panel or box from the floor, but where parallax saw such a surface stand up inside
the colour floor, the floor of that image column ends below it (a column of the image
is a ray along the ground, and a ray ends at the first thing standing on it), so the map
puts the obstacle at its foot and not, as the floor homography would, far behind it.

The test needs the relative pose of the two views to a fraction of a degree, which
wheel odometry does not give (slip errs by a degree or two between frames a hand's
width apart): `align_reference_pose` first lines up the floor both views see.

`confirm_floor` runs the whole test at half resolution (OpenCV downsamples; both release
the GIL) and its search is a numba kernel that holds no GIL either, so the mapping thread
does not stall the others while it runs. It can also return what it found standing up
(`ParallaxResult`): textured pixels well off the floor plane, whatever their colour, for
the mapper to tell a box on the floor from the floor.

Pure functions on numpy arrays. Frames: ``H_ground_from_image`` maps undistorted pixels
(u, v, 1) to the robot frame's floor (x forward, y left, metres).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, replace
from typing import Literal, overload

import cv2
import numba
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class PlanarParams:
    """Thresholds of the parallax test (see the module docstring).

    Attributes
    ----------
    blur_sigma_px : Gaussian smoothing before comparing (noise, aliasing); 0: none.
        Light, as the reference is interpolated once, no blurrier than the current
        frame: more blur spreads an edge's evidence onto its neighbours.
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
    soft_sigma_px : what stands is checked again with the current frame smoothed by
        this much in all: seen from farther away, the reference holds a strong edge
        less sharply (foreshortened by up to (D / (D + baseline))^2 down the image,
        0.6-0.8 at 0.5-1 m), and the sharper current frame mismatches it there whatever
        the shift. On a synthetic threshold strip 0.9 m ahead, 0.9-1.2 leave none of
        its edges standing, 0.7 leaves 38 % and 1.6 all. No more than ``blur_sigma_px``:
        no second check.
    """

    blur_sigma_px: float = 0.5
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
    soft_sigma_px: float = 1.0


SHIFTS_PX = (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)
"""Residual parallax searched along each epipolar line (pixels). Up to `standing_min_px`:
a larger parallax matches nowhere on the line, which `mismatch_min` catches (searching
+-3 px too changed under 1 % of the verdicts on scripts/eval_parallax.py)."""


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

    Each pixel of the current frame is compared with the reference frame where the floor
    homography puts it, shifted along the pixel's epipolar line by each of `SHIFTS_PX`;
    the shift that matches best (a window's mean absolute difference) is the pixel's
    residual parallax. Searching, rather than dividing the residual by the gradient, keeps
    sub-pixel rendering and interpolation error at strong edges from looking like
    parallax. Runs at the images' own resolution (`confirm_floor` downsamples first).

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
    on_floor, standing, _ = _evidence(
        _blurred(gray_cur, p),
        _blurred(gray_ref, p),
        np.asarray(H_cur_from_ref, np.float64),
        epipole,
        (0, gray_cur.shape[0]),
        p,
    )
    return on_floor, standing


def _blurred(gray: NDArray[np.uint8], p: PlanarParams) -> NDArray[np.float32]:
    """Smoothed against noise and aliasing before comparing (OpenCV: no GIL held)."""
    image = np.ascontiguousarray(gray, dtype=np.float32)
    if p.blur_sigma_px <= 0:
        return image
    return np.ascontiguousarray(cv2.GaussianBlur(image, (0, 0), p.blur_sigma_px), dtype=np.float32)


def _evidence(
    cur: NDArray[np.float32],
    ref: NDArray[np.float32],
    H_cur_from_ref: NDArray[np.float64],
    epipole: tuple[float, float],
    rows: tuple[int, int | NDArray[np.int64]],
    p: PlanarParams,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """(on_floor, standing, tested) of the rows ``rows[0]`` up to ``rows[1]`` (excluded;
    one row per column, or one for all) of ``cur``, False elsewhere, from the smoothed
    images."""
    h, w = cur.shape
    on_floor = np.zeros((h, w), np.bool_)
    standing = np.zeros((h, w), np.bool_)
    tested = np.zeros((h, w), np.bool_)
    row_to = np.broadcast_to(np.asarray(rows[1], np.int64), (w,))
    # Sobel: 8 times the gradient in grey levels per pixel (OpenCV: vectorised, no GIL).
    grad_u = np.asarray(cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3), np.float32)
    grad_v = np.asarray(cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3), np.float32)
    extra = math.sqrt(max(p.soft_sigma_px**2 - p.blur_sigma_px**2, 0.0))
    soft = cur
    if extra > 0.0:
        soft = np.ascontiguousarray(cv2.GaussianBlur(cur, (0, 0), extra), dtype=np.float32)
    _parallax_search(
        cur,
        soft,
        grad_u,
        grad_v,
        ref,
        np.ascontiguousarray(np.linalg.inv(H_cur_from_ref), dtype=np.float64),
        float(epipole[0]),
        float(epipole[1]),
        int(rows[0]),
        np.ascontiguousarray(np.clip(row_to, 0, h), dtype=np.int64),
        _SHIFTS,
        int(p.window_px),
        8.0 * float(p.texture_min),
        float(p.planar_max_px),
        float(p.standing_min_px),
        float(p.match_max),
        float(p.mismatch_min),
        extra > 0.0,
        on_floor,
        standing,
        tested,
    )
    return on_floor, standing, tested


_SHIFTS = np.asarray(sorted(SHIFTS_PX, key=abs), dtype=np.float64)
"""`SHIFTS_PX` from the floor hypothesis outward: the kernel's search keeps the first
of equal costs, so a tie goes to the smaller parallax."""


@numba.njit(cache=True, nogil=True)
def _shifted_differences(
    cur: NDArray[np.float32],
    flat_ref: NDArray[np.float32],
    hr: int,
    wr: int,
    m: NDArray[np.float64],
    epipole_u: float,
    epipole_v: float,
    needed: NDArray[np.bool_],
    a0: int,
    shifts: NDArray[np.float64],
    off_view: np.float32,
    diff: NDArray[np.float32],
) -> None:
    """``diff[v - a0, u * n + k]``: |cur - ref| at the pixel (v, u) of ``cur`` moved
    ``shifts[k]`` pixels towards the epipole and put in the reference through the
    homography ``m`` (one bilinear sample), for the pixels ``needed[v - a0, u]``;
    ``off_view`` where the sample needs pixels outside the reference."""
    w = cur.shape[1]
    n = shifts.shape[0]
    s_lo = shifts.min()
    s_hi = shifts.max()
    for v in range(a0, a0 + needed.shape[0]):
        ev = epipole_v - v
        x_row = m[0, 1] * v + m[0, 2]
        y_row = m[1, 1] * v + m[1, 2]
        z_row = m[2, 1] * v + m[2, 2]
        for u in range(w):
            if not needed[v - a0, u]:
                continue
            j = u * n
            eu = epipole_u - u
            norm = math.sqrt(eu * eu + ev * ev)
            z0 = m[2, 0] * u + z_row
            if norm < 1e-3 or abs(z0) < 1e-12:
                diff[v - a0, j : j + n] = off_view
                continue
            # Unit direction towards the epipole, over z0 (one division each).
            to_unit = 1.0 / norm
            over_z = 1.0 / z0
            x0 = (m[0, 0] * u + x_row) * over_z
            y0 = (m[1, 0] * u + y_row) * over_z
            step = to_unit * over_z
            zd = (m[2, 0] * eu + m[2, 1] * ev) * step
            dx = (m[0, 0] * eu + m[0, 1] * ev) * step - x0 * zd
            dy = (m[1, 0] * eu + m[1, 1] * ev) * step - y0 * zd
            c = cur[v, u]
            # The samples lie on a segment: inside the reference if both its ends are.
            inside = (
                0.0 <= x0 + s_lo * dx <= wr - 1
                and 0.0 <= x0 + s_hi * dx <= wr - 1
                and 0.0 <= y0 + s_lo * dy <= hr - 1
                and 0.0 <= y0 + s_hi * dy <= hr - 1
            )
            for k in range(n):
                x = x0 + shifts[k] * dx
                y = y0 + shifts[k] * dy
                if not inside and not (0.0 <= x <= wr - 1 and 0.0 <= y <= hr - 1):
                    diff[v - a0, j + k] = off_view
                    continue
                ix = min(int(x), wr - 2)
                iy = min(int(y), hr - 2)
                fx = np.float32(x - ix)
                fy = np.float32(y - iy)
                i = iy * wr + ix
                top = flat_ref[i] + fx * (flat_ref[i + 1] - flat_ref[i])
                low = flat_ref[i + wr] + fx * (flat_ref[i + wr + 1] - flat_ref[i + wr])
                diff[v - a0, j + k] = abs(c - (top + fy * (low - top)))


@numba.njit(cache=True, nogil=True)
def _covered(marked: NDArray[np.bool_], r0: int, a0: int, a1: int, half: int) -> NDArray[np.bool_]:
    """(a1 - a0, w): the pixels the windows (side 2 half + 1) of the pixels ``marked``
    (rows r0 on) cover."""
    rows, w = marked.shape
    spans = np.zeros((rows, w), np.bool_)
    for r in range(rows):
        for u in range(w):
            if marked[r, u]:
                for x in range(max(u - half, 0), min(u + half + 1, w)):
                    spans[r, x] = True
    covered = np.zeros((a1 - a0, w), np.bool_)
    for r in range(rows):
        v = r + r0
        for y in range(max(v - half, a0), min(v + half + 1, a1)):
            for x in range(w):
                covered[y - a0, x] |= spans[r, x]
    return covered


@numba.njit(cache=True, nogil=True)
def _parallax_search(
    cur: NDArray[np.float32],
    cur_soft: NDArray[np.float32],
    grad_u: NDArray[np.float32],
    grad_v: NDArray[np.float32],
    ref: NDArray[np.float32],
    H_ref_from_cur: NDArray[np.float64],
    epipole_u: float,
    epipole_v: float,
    row_from: int,
    row_to: NDArray[np.int64],
    shifts: NDArray[np.float64],
    window: int,
    gradient_min: float,
    planar_max: float,
    standing_min: float,
    match_max: float,
    mismatch_min: float,
    soft_check: bool,
    on_floor: NDArray[np.bool_],
    standing: NDArray[np.bool_],
    tested: NDArray[np.bool_],
) -> None:
    """The search of `parallax_evidence` for the pixels (v, u) of ``cur`` with
    row_from <= v < row_to[u], into the three masks; ``grad_u``, ``grad_v`` are
    ``cur``'s gradient, in the units of ``gradient_min``; ``cur_soft`` is ``cur``
    smoothed to the reference's resolution (`PlanarParams.soft_sigma_px`), used when
    ``soft_check``.

    Most pixels lack texture, so the textured ones are found first and the reference is
    sampled only in their windows. It is sampled straight through the homography (one
    bilinear interpolation, not a warp and then a remap), linearised along each
    epipolar line (a few hundredths of a pixel off at the ends of the search). A sample
    needing pixels outside the reference makes its shift's window unusable."""
    h, w = cur.shape
    hr, wr = ref.shape
    n = shifts.shape[0]
    half = window // 2
    # A difference standing for "outside the reference view": above any window's sum of
    # real differences (window**2 * 255), so a window holding one is recognised.
    off_view = np.float32(max(1e5, 1000.0 * window * window))
    if hr < 2 or wr < 2:
        return
    r0 = max(row_from, 1)
    r1 = 0
    for u in range(w):
        r1 = max(r1, min(row_to[u], h - 1))
    if r1 <= r0:
        return
    a0 = max(r0 - half, 0)  # the rows the windows read
    a1 = min(r1 + half, h)
    flat_ref = ref.reshape(hr * wr)  # a view (C-contiguous)
    # 1. Texture across the epipolar line.
    textured = np.zeros((r1 - r0, w), np.bool_)
    limit = np.float32(gradient_min * gradient_min)
    for v in range(r0, r1):
        to_v = np.float32(epipole_v - v)  # towards the epipole (not normalised)
        for u in range(1, w - 1):
            if v >= row_to[u]:
                continue
            to_u = np.float32(epipole_u - u)
            norm2 = to_u * to_u + to_v * to_v
            along = grad_u[v, u] * to_u + grad_v[v, u] * to_v
            if along * along < limit * norm2 or norm2 < 1e-6:
                continue
            textured[v - r0, u] = True
    # 2. |cur - ref| at every shift along the epipolar line where a judged pixel's
    # window needs it (only those entries are ever read), then 3. each such pixel's
    # window costs and verdict: first every textured pixel; then, with ``soft_check``,
    # what stood for matching nowhere, compared again with the current frame as soft as
    # the reference. Seen from farther away, the reference holds a strong edge (a
    # threshold strip's) less sharply than the current frame does, and the two differ
    # there by more than the mismatch a parallax leaves, wherever the edge is put: such
    # a pixel stands only if it also stands then, and is floor if it matches as floor
    # then. A pixel that matched better displaced has shown its parallax and is left
    # alone.
    diff = np.empty((a1 - a0, w * n), np.float32)
    judged = textured
    for look in range(2 if soft_check else 1):
        _shifted_differences(
            cur if look == 0 else cur_soft,
            flat_ref,
            hr,
            wr,
            H_ref_from_cur,
            epipole_u,
            epipole_v,
            _covered(judged, r0, a0, a1, half),
            a0,
            shifts,
            off_view,
            diff,
        )
        judged = _judge(
            judged,
            diff,
            r0,
            a0,
            shifts,
            window,
            off_view,
            planar_max,
            standing_min,
            match_max,
            mismatch_min,
            on_floor,
            standing,
            tested,
        )


@numba.njit(cache=True, nogil=True)
def _judge(
    marked: NDArray[np.bool_],
    diff: NDArray[np.float32],
    r0: int,
    a0: int,
    shifts: NDArray[np.float64],
    window: int,
    off_view: np.float32,
    planar_max: float,
    standing_min: float,
    match_max: float,
    mismatch_min: float,
    on_floor: NDArray[np.bool_],
    standing: NDArray[np.bool_],
    tested: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """The verdict of each pixel ``marked`` (rows r0 on) from its window's costs (mean
    absolute difference) at ``shifts`` in ``diff`` (`_shifted_differences`, rows a0
    on), summed from the window's column sums, each computed once per row; the first
    of equal costs wins, so a tie goes to the smaller parallax. A window that leaves the
    reference view gives no evidence. Returns the pixels that stand only for matching
    nowhere near where the floor plane puts them (no better match found)."""
    h, w = on_floor.shape
    n = shifts.shape[0]
    half = window // 2
    rows = marked.shape[0]
    column_sums = np.empty(w * n, np.float32)
    summed = np.empty(w, np.int64)  # the row whose sums column_sums holds, per column
    summed[:] = -1
    cost = np.empty(n, np.float32)
    unmatched = np.zeros((rows, w), np.bool_)
    for v in range(r0, r0 + rows):
        y0_ = max(v - half, 0)
        y1_ = min(v + half + 1, h)
        for u in range(1, w - 1):
            if not marked[v - r0, u]:
                continue
            x0_ = max(u - half, 0)
            x1_ = min(u + half + 1, w)
            cost[:] = 0.0
            for x in range(x0_, x1_):
                j = x * n
                if summed[x] != v:
                    summed[x] = v
                    column_sums[j : j + n] = 0.0
                    for y in range(y0_, y1_):
                        for k in range(n):
                            column_sums[j + k] += diff[y - a0, j + k]
                for k in range(n):
                    cost[k] += column_sums[j + k]
            if cost[0] >= off_view:
                continue
            tested[v, u] = True
            best = 0
            for k in range(1, n):
                if cost[k] < cost[best]:
                    best = k
            area = np.float32((y1_ - y0_) * (x1_ - x0_))
            best_shift = abs(shifts[best])
            # Floor: matches where the floor plane puts it, and well. Standing: matches
            # better elsewhere on its epipolar line, or nowhere near (a parallax beyond
            # the search).
            on_floor[v, u] = best_shift <= planar_max and cost[best] <= match_max * area
            standing[v, u] = best_shift >= standing_min or cost[0] >= mismatch_min * area
            unmatched[v - r0, u] = standing[v, u] and best_shift < standing_min
    return unmatched


def row_ground_distance_m(
    H_ground_from_image: NDArray[np.float64],
    width_px: int,
    height_px: int,
    column_px: float | None = None,
) -> NDArray[np.float64]:
    """(height_px,) forward ground distance of each row at ``column_px`` (default: the
    centre column); NaN at and above the horizon."""
    column = (width_px - 1) / 2.0 if column_px is None else column_px
    v = np.arange(height_px, dtype=np.float64)
    pts = np.stack([np.full_like(v, column), v, np.ones_like(v)])
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


def _check_views(
    floor_mask: NDArray[np.bool_], gray_cur: NDArray[np.uint8], gray_ref: NDArray[np.uint8]
) -> tuple[int, int]:
    """(h, w) of ``floor_mask``, which both grey views must share (else ValueError)."""
    h, w = floor_mask.shape
    if gray_cur.shape != (h, w) or gray_ref.shape != (h, w):
        raise ValueError(
            f"gray_cur {gray_cur.shape} and gray_ref {gray_ref.shape} must match "
            f"floor_mask {floor_mask.shape}"
        )
    return h, w


@dataclass(frozen=True)
class AlignParams:
    """The floor alignment of `align_reference_pose` (see there).

    Attributes
    ----------
    cell_m : side of the bird's-eye raster's cells the views are compared on (the
        camera's own footprint on the floor a metre ahead).
    near_m, far_m, half_width_m : the raster's extent ahead of the robot and to each side.
    texture_sigma_cells : what is smoother than this (Gaussian sigma, cells) is shading,
        not texture, and is taken out before comparing.
    turn_steps : headings tried over +-``max_turn_rad`` before the fine alignment.
    max_shift_m, max_turn_rad : the largest correction believed. Wheel slip errs by a
        degree or two in heading between two frames a hand's width apart, but by
        millimetres in position; a larger shift means the alignment slid along a floor
        with too little texture across it.
    min_correlation : the aligned textures' correlation (ECC's) below which the floor
        gave too little texture to align on.
    min_cells : raster cells on the floor that both views see, at least.
    """

    cell_m: float = 0.01
    near_m: float = 0.25
    far_m: float = 1.5
    half_width_m: float = 0.6
    texture_sigma_cells: float = 4.0
    turn_steps: int = 13
    max_shift_m: float = 0.02
    max_turn_rad: float = 0.06
    min_correlation: float = 0.6
    min_cells: int = 500


ECC_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 15, 1e-3)
"""The fine alignment stops after 15 iterations or when the correlation gains < 0.001
(from the heading search's result it converges in a few; 40 changed nothing on
scripts/eval_alignment.py but the time)."""


def align_reference_pose(
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    floor_mask: NDArray[np.bool_],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    params: AlignParams | None = None,
) -> tuple[float, float, float] | None:
    """The reference view's pose corrected so that the two views' floors line up: the
    parallax test's input, checked against the images.

    The parallax test warps one view onto the other through the floor plane and the
    odometry between them. Wheel slip makes that odometry a degree or two wrong in
    heading, which moves the floor a metre ahead by 2-3 cm; a fine texture (carpet, a
    rug, tiles) then no longer matches itself and half the floor "stands up". So both
    views are first projected onto the floor ahead of the current robot (a bird's-eye
    raster of ``cell_m`` cells), kept only where the current view's colour floor is and
    both views see it, with their smooth shading taken out (the light and the lens's
    vignetting differ between the views). The heading is searched coarsely, on a raster
    of twice the cell, and finely; then OpenCV's ECC (enhanced correlation coefficient)
    refines the turn and the shift in the floor plane together (where it cannot, along
    a texture of parallel lines, the heading stands alone). The current pose is kept;
    the reference's is moved.

    Returns the corrected ``T_world_ref`` (x_m, y_m, theta_rad), or None when the floor
    cannot be aligned: fewer than ``min_cells`` usable cells, too little texture
    (correlation below ``min_correlation``), or a correction beyond ``max_turn_rad`` /
    ``max_shift_m`` (what fills the view is not the floor: a floor-coloured panel).
    """
    p = params if params is not None else AlignParams()
    h, w = _check_views(floor_mask, gray_cur, gray_ref)
    G_inv = np.linalg.inv(np.asarray(H_ground_from_image, dtype=np.float64))
    T_ref_cur = np.linalg.inv(_rigid(*T_world_ref)) @ _rigid(*T_world_cur)
    linear = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    nearest = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP

    def raster(cell_m: float, pad_m: float = 0.0) -> tuple[NDArray[np.float64], tuple[int, int]]:
        """M_ground_from_raster (col, row, 1) -> the current robot frame's floor (row 0
        far, column 0 on the left) and the raster's (cols, rows), ``pad_m`` larger on
        every side."""
        far, left = p.far_m + pad_m, p.half_width_m + pad_m
        M = np.array([[0.0, -cell_m, far], [-cell_m, 0.0, left], [0.0, 0.0, 1.0]])
        size = (round(2 * left / cell_m), round((far - p.near_m + pad_m) / cell_m))
        return M, size

    def texture(
        gray: NDArray[np.uint8],
        H_image_from_raster: NDArray[np.float64],
        size: tuple[int, int],
        cell_m: float,
    ) -> NDArray[np.float32]:
        """``gray`` on a raster of ``cell_m`` cells, less what is smoother than
        ``texture_sigma_cells`` of the fine raster."""
        image = cv2.warpPerspective(gray, H_image_from_raster, size, flags=linear)
        image = image.astype(np.float32)
        sigma = p.texture_sigma_cells * p.cell_m / cell_m
        return np.asarray(image - cv2.GaussianBlur(image, (0, 0), sigma), np.float32)

    def usable(M: NDArray[np.float64], size: tuple[int, int], cell_m: float) -> NDArray[np.bool_]:
        """Cells on the current colour floor that the reference sees too, away from
        the floor's edges (an edge is no floor texture)."""
        floor = cv2.warpPerspective(floor_mask.view(np.uint8), G_inv @ M, size, flags=nearest)
        seen_ref = cv2.warpPerspective(
            np.ones((h, w), np.uint8), G_inv @ T_ref_cur @ M, size, flags=nearest
        )
        margin = 9 if cell_m == p.cell_m else 5
        kernel = np.ones((margin, margin), np.uint8)
        both = np.asarray(floor, np.uint8) & np.asarray(seen_ref, np.uint8)
        return np.asarray(cv2.erode(both, kernel, borderValue=0) > 0, np.bool_)

    def turned(turn_rad: float) -> NDArray[np.float64]:
        """T_ref_cur with the reference robot turned by ``turn_rad`` more."""
        return np.asarray(_rigid(0.0, 0.0, -turn_rad) @ T_ref_cur, dtype=np.float64)

    class Scale:
        """Both views' textures on the raster of one cell size. The reference is
        projected once, on a raster padded by the largest turn's reach, and turned by
        moving that raster (a rigid motion of the floor is an affine map of it)."""

        def __init__(self, cell_m: float) -> None:
            self.M, self.size = raster(cell_m)
            self.valid = usable(self.M, self.size, cell_m)
            pad_m = p.max_turn_rad * math.hypot(p.far_m, p.half_width_m) + 2 * cell_m
            self.M_pad, size_pad = raster(cell_m, pad_m)
            self.ref = texture(gray_ref, G_inv @ T_ref_cur @ self.M_pad, size_pad, cell_m)
            self.cur = texture(gray_cur, G_inv @ self.M, self.size, cell_m)

        def ref_turned(self, turn_rad: float) -> NDArray[np.float32]:
            A = np.linalg.inv(self.M_pad) @ np.linalg.inv(T_ref_cur) @ turned(turn_rad) @ self.M
            return np.asarray(cv2.warpAffine(self.ref, A[:2], self.size, flags=linear), np.float32)

        def best_heading(self, turns: NDArray[np.float64]) -> tuple[float, float]:
            """Of ``turns``, the one whose reference texture correlates best with the
            current one over the usable cells, and that correlation."""
            cur_values = self.cur[self.valid]
            cur_values = cur_values - cur_values.mean()
            cur_norm = float(np.linalg.norm(cur_values)) + 1e-6
            best = (0.0, -math.inf)
            for turn in turns:
                values = self.ref_turned(float(turn))[self.valid]
                values -= values.mean()
                norm = cur_norm * (float(np.linalg.norm(values)) + 1e-6)
                score = float(cur_values @ values) / norm
                if score > best[1]:
                    best = (float(turn), score)
            return best

    fine = Scale(p.cell_m)
    if int(np.count_nonzero(fine.valid)) < p.min_cells:
        return None
    # 1. The heading, coarsely, on a raster of twice the cell (a degree moves the floor
    # a metre ahead by nearly two fine cells, beyond where ECC reliably converges from),
    # 2. then finely, between the coarse step's neighbours.
    coarse = Scale(2 * p.cell_m)
    if not coarse.valid.any():
        return None
    turns = np.linspace(-p.max_turn_rad, p.max_turn_rad, p.turn_steps)
    best_turn, _ = coarse.best_heading(turns)
    step = float(turns[1] - turns[0]) if turns.size > 1 else 0.0
    best_turn, correlation = fine.best_heading(best_turn + np.linspace(-step / 2, step / 2, 7))
    # 3. Turn and shift together with ECC, from there. Along a texture of parallel lines
    # (wood grain) the shift is undetermined and ECC diverges: the heading stands alone.
    W: NDArray[np.float32] = np.eye(2, 3, dtype=np.float32)
    with contextlib.suppress(cv2.error):
        correlation, found = cv2.findTransformECC(
            fine.cur,
            fine.ref_turned(best_turn),
            W.copy(),
            cv2.MOTION_EUCLIDEAN,
            ECC_CRITERIA,
            fine.valid.view(np.uint8),
            5,
        )
        W = np.asarray(found, np.float32)
    if not correlation >= p.min_correlation:
        return None
    # ref(W q) ~ cur(q): the floor point M q of the current robot frame is the point
    # T M W q of the reference's (T: T_ref_cur turned by the heading found), so the true
    # T_ref_cur is T M W M^-1.
    W3 = np.vstack([np.asarray(W, np.float64), [0.0, 0.0, 1.0]])
    correction = fine.M @ W3 @ np.linalg.inv(fine.M)
    turn = best_turn + math.atan2(correction[1, 0], correction[0, 0])
    # The shift that matters: where the correction moves the middle of the raster.
    middle = np.array([(p.near_m + p.far_m) / 2, 0.0, 1.0])
    shift = float(np.hypot(*(correction @ middle - middle)[:2]))
    if abs(turn) > p.max_turn_rad or shift > p.max_shift_m:
        return None
    T_ref_cur_aligned = turned(best_turn) @ correction
    T_world_ref_aligned = _rigid(*T_world_cur) @ np.linalg.inv(T_ref_cur_aligned)
    return (
        float(T_world_ref_aligned[0, 2]),
        float(T_world_ref_aligned[1, 2]),
        float(math.atan2(T_world_ref_aligned[1, 0], T_world_ref_aligned[0, 0])),
    )


@dataclass(frozen=True)
class RefineParams:
    """The photometric pose refinement of `refine_reference_pose` (see there).

    Attributes
    ----------
    downscale : works on images this many times smaller (the parallax test's own).
    sigmas_px : Gaussian smoothing of each pass, coarse to fine, in pixels of the small
        images: the first pass widens the basin (odometry's degree or two), the last
        sees the texture the test compares.
    iterations : Gauss-Newton steps per pass at most (it stops earlier once a step
        moves the pose by less than a hundredth of a millimetre).
    max_points : samples at most: textured floor pixels, evenly spread over those found.
    min_points : fewer textured floor pixels than this: nothing to align on.
    gradient_min : grey levels per pixel a sample's gradient needs.
    huber_grey : residuals beyond this are down-weighted (Huber): what is not floor in
        the colour floor (a box's face, a reflection) does not pull the pose.
    min_inlier_share : of the samples, the share that must match within ``huber_grey``
        at the end; below it the views' floors did not line up (a floor-coloured panel
        fills the view, or the floor mirrors what stands on it).
    max_turn_rad, max_shift_m : the largest correction of odometry believed.
    """

    downscale: int = 2
    sigmas_px: tuple[float, ...] = (1.5, 0.5)
    iterations: int = 4
    max_points: int = 3000
    min_points: int = 200
    gradient_min: float = 2.0
    huber_grey: float = 6.0
    min_inlier_share: float = 0.75
    max_turn_rad: float = 0.06
    max_shift_m: float = 0.02


def refine_reference_pose(
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    floor_mask: NDArray[np.bool_],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    params: RefineParams | None = None,
) -> tuple[float, float, float] | None:
    """The reference view's pose, corrected until the two views' floors match pixel for
    pixel: the parallax test's own comparison, minimised over the reference pose.

    Textured pixels of the current view's colour floor are placed on the world's floor
    through the floor homography and the current pose; each is looked up in the
    reference view through that pose. Gauss-Newton (Huber-weighted, coarse to fine)
    moves the reference pose (x, y, heading) until the looked-up grey levels match the
    current ones. This works in the test's own images, at its resolution, so what is
    left matches to a few hundredths of a degree (`scripts/eval_alignment.py`), where
    the bird's-eye `align_reference_pose` leaves a tenth or two: enough at a metre for a
    fine texture to stand up. A shift along a texture of parallel lines is left as it
    was: it changes nothing the test could see either.

    Returns the corrected ``T_world_ref`` (x_m, y_m, theta_rad), or None: too few
    textured floor pixels, too few of them matching in the end, or a correction beyond
    ``max_turn_rad`` / ``max_shift_m``.
    """
    p = params if params is not None else RefineParams()
    h, w = _check_views(floor_mask, gray_cur, gray_ref)
    k = p.downscale
    small = (w // k, h // k)
    G = _downscaled_homography(H_ground_from_image, k)
    # Away from the colour floor's edges by the comparison's reach.
    mask = cv2.erode(
        np.ascontiguousarray(floor_mask[::k, ::k][: small[1], : small[0]], np.uint8),
        np.ones((5, 5), np.uint8),
        borderValue=0,
    )
    cur_small = _small_gray(gray_cur, small).astype(np.float32)
    ref_small = _small_gray(gray_ref, small).astype(np.float32)
    cur_fine = np.asarray(cv2.GaussianBlur(cur_small, (0, 0), p.sigmas_px[-1]), np.float32)
    grad_u = np.asarray(cv2.Sobel(cur_fine, cv2.CV_32F, 1, 0, ksize=3), np.float32)
    grad_v = np.asarray(cv2.Sobel(cur_fine, cv2.CV_32F, 0, 1, ksize=3), np.float32)
    # Sobel is 8 times the gradient.
    textured = (mask > 0) & (grad_u * grad_u + grad_v * grad_v > (8.0 * p.gradient_min) ** 2)
    vs, us = np.nonzero(textured)
    if vs.size < p.min_points:
        return None
    if vs.size > p.max_points:
        pick = np.linspace(0, vs.size - 1, p.max_points).astype(np.int64)
        vs, us = vs[pick], us[pick]
    # Where the current view puts each sample on the world's floor.
    X = (_rigid(*T_world_cur) @ G) @ np.stack(
        [us.astype(np.float64), vs.astype(np.float64), np.ones(vs.size)]
    )
    floor_x, floor_y = np.ascontiguousarray(X[0] / X[2]), np.ascontiguousarray(X[1] / X[2])
    G_inv = np.ascontiguousarray(np.linalg.inv(G))
    pose = np.array(T_world_ref, dtype=np.float64)
    normal = np.empty((3, 3), np.float64)
    rhs = np.empty(3, np.float64)
    for sigma in p.sigmas_px:
        cur = cur_fine if sigma == p.sigmas_px[-1] else cv2.GaussianBlur(cur_small, (0, 0), sigma)
        ref = np.ascontiguousarray(cv2.GaussianBlur(ref_small, (0, 0), sigma), np.float32)
        values = np.ascontiguousarray(np.asarray(cur, np.float32)[vs, us])
        for _ in range(p.iterations):
            _, inside = _gauss_newton_system(
                ref, floor_x, floor_y, values, G_inv, pose, p.huber_grey, normal, rhs
            )
            if inside < p.min_points:
                return None
            try:
                step = -np.linalg.solve(normal + 1e-6 * np.trace(normal) * np.eye(3), rhs)
            except np.linalg.LinAlgError:
                return None
            pose += step
            if math.hypot(step[0], step[1]) < 1e-5 and abs(step[2]) < 1e-5:
                break
    # The last pose's share (the last step is tiny, or the iterations ran out).
    inlier_share, inside = _gauss_newton_system(
        ref, floor_x, floor_y, values, G_inv, pose, p.huber_grey, normal, rhs
    )
    turn = math.remainder(float(pose[2]) - T_world_ref[2], math.tau)
    shift = math.hypot(float(pose[0]) - T_world_ref[0], float(pose[1]) - T_world_ref[1])
    if (
        abs(turn) > p.max_turn_rad
        or shift > p.max_shift_m
        or inside < p.min_points
        or inlier_share < p.min_inlier_share
    ):
        return None
    return float(pose[0]), float(pose[1]), float(pose[2])


def reference_pose_from_views(
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    floor_mask: NDArray[np.bool_],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    params: RefineParams | None = None,
) -> tuple[float, float, float] | None:
    """The parallax test's reference pose from odometry's, checked against the views:
    `refine_reference_pose` from odometry; where that fails (a slip beyond its basin, a
    texture it slid along), the bird's-eye `align_reference_pose` with its wide heading
    search first, then the refinement's finest pass from there (or the alignment alone).
    None when neither lines the floors up: the caller decides what odometry alone is
    worth.
    """
    p = params if params is not None else RefineParams()
    refined = refine_reference_pose(
        gray_cur, gray_ref, floor_mask, H_ground_from_image, T_world_ref, T_world_cur, p
    )
    if refined is not None:
        return refined
    aligned = align_reference_pose(
        gray_cur, gray_ref, floor_mask, H_ground_from_image, T_world_ref, T_world_cur
    )
    if aligned is None:
        return None
    finest = replace(p, sigmas_px=p.sigmas_px[-1:])
    again = refine_reference_pose(
        gray_cur, gray_ref, floor_mask, H_ground_from_image, aligned, T_world_cur, finest
    )
    return aligned if again is None else again


@numba.njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _gauss_newton_system(
    ref: NDArray[np.float32],
    floor_x: NDArray[np.float64],
    floor_y: NDArray[np.float64],
    values: NDArray[np.float32],
    G_inv: NDArray[np.float64],
    pose: NDArray[np.float64],
    huber: float,
    normal: NDArray[np.float64],
    rhs: NDArray[np.float64],
) -> tuple[float, int]:
    """One Gauss-Newton system of `refine_reference_pose`: the Huber-weighted normal
    equations (``normal`` @ step = -``rhs``) of the residuals ref(q) - values, q being
    where the reference pose ``pose`` sees the world floor points (floor_x, floor_y).
    Returns the share of the samples inside the reference view that match within
    ``huber`` grey levels, and how many are inside. The reference's gradient is its
    central difference at q."""
    hr, wr = ref.shape
    cs, sn = math.cos(pose[2]), math.sin(pose[2])
    normal[:, :] = 0.0
    rhs[:] = 0.0
    inside = 0
    matched = 0
    for i in range(floor_x.shape[0]):
        d0 = floor_x[i] - pose[0]
        d1 = floor_y[i] - pose[1]
        # The floor point in the reference robot's frame, then in its image.
        r0 = cs * d0 + sn * d1
        r1 = -sn * d0 + cs * d1
        h2 = G_inv[2, 0] * r0 + G_inv[2, 1] * r1 + G_inv[2, 2]
        if abs(h2) < 1e-12:
            continue
        qx = (G_inv[0, 0] * r0 + G_inv[0, 1] * r1 + G_inv[0, 2]) / h2
        qy = (G_inv[1, 0] * r0 + G_inv[1, 1] * r1 + G_inv[1, 2]) / h2
        if not (1.0 <= qx < wr - 2.0 and 1.0 <= qy < hr - 2.0):
            continue
        ix = int(qx)
        iy = int(qy)
        fx = qx - ix
        fy = qy - iy
        # Bilinear value and central-difference gradient from the 4x4 block around q.
        a = ref[iy, ix] + fx * (ref[iy, ix + 1] - ref[iy, ix])
        b = ref[iy + 1, ix] + fx * (ref[iy + 1, ix + 1] - ref[iy + 1, ix])
        value = a + fy * (b - a)
        gu0 = 0.5 * (ref[iy, ix + 1] - ref[iy, ix - 1])
        gu1 = 0.5 * (ref[iy, ix + 2] - ref[iy, ix])
        gu2 = 0.5 * (ref[iy + 1, ix + 1] - ref[iy + 1, ix - 1])
        gu3 = 0.5 * (ref[iy + 1, ix + 2] - ref[iy + 1, ix])
        top = gu0 + fx * (gu1 - gu0)
        low = gu2 + fx * (gu3 - gu2)
        g_u = top + fy * (low - top)
        gv0 = 0.5 * (ref[iy + 1, ix] - ref[iy - 1, ix])
        gv1 = 0.5 * (ref[iy + 1, ix + 1] - ref[iy - 1, ix + 1])
        gv2 = 0.5 * (ref[iy + 2, ix] - ref[iy, ix])
        gv3 = 0.5 * (ref[iy + 2, ix + 1] - ref[iy, ix + 1])
        top = gv0 + fx * (gv1 - gv0)
        low = gv2 + fx * (gv3 - gv2)
        g_v = top + fy * (low - top)
        # d(grey) / d(the floor point in the reference robot's frame) ...
        e0 = (g_u * (G_inv[0, 0] - qx * G_inv[2, 0]) + g_v * (G_inv[1, 0] - qy * G_inv[2, 0])) / h2
        e1 = (g_u * (G_inv[0, 1] - qx * G_inv[2, 1]) + g_v * (G_inv[1, 1] - qy * G_inv[2, 1])) / h2
        # ... and of that point with respect to the reference pose (x, y, heading).
        j0 = -cs * e0 + sn * e1
        j1 = -sn * e0 - cs * e1
        j2 = r1 * e0 - r0 * e1
        residual = value - values[i]
        inside += 1
        weight = 1.0
        if abs(residual) > huber:
            weight = huber / abs(residual)
        else:
            matched += 1
        normal[0, 0] += weight * j0 * j0
        normal[0, 1] += weight * j0 * j1
        normal[0, 2] += weight * j0 * j2
        normal[1, 1] += weight * j1 * j1
        normal[1, 2] += weight * j1 * j2
        normal[2, 2] += weight * j2 * j2
        rhs[0] += weight * j0 * residual
        rhs[1] += weight * j1 * residual
        rhs[2] += weight * j2 * residual
    normal[1, 0] = normal[0, 1]
    normal[2, 0] = normal[0, 2]
    normal[2, 1] = normal[1, 2]
    return (matched / inside if inside > 0 else 0.0), inside


@dataclass(frozen=True)
class ParallaxResult:
    """What one parallax test found, as (H, W) bool masks of the current frame.

    Attributes
    ----------
    floor : the colour floor extended by parallax-confirmed floor (never less).
    standing : pixels confidently off the floor plane: textured across their epipolar
        line, and matching the earlier view only displaced (or not at all) where the
        floor would put them. What stands up (a box's edges, its texture), whatever
        its colour.
    tested : pixels the test could decide (textured across their epipolar line, seen in
        the earlier view, in the rows tested); the rest gave no evidence either way.
    """

    floor: NDArray[np.bool_]
    standing: NDArray[np.bool_]
    tested: NDArray[np.bool_]


@overload
def confirm_floor(
    floor_mask: NDArray[np.bool_],
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    camera_xy_robot: tuple[float, float],
    params: PlanarParams | None = None,
    *,
    return_standing: Literal[False] = False,
) -> NDArray[np.bool_]: ...


@overload
def confirm_floor(
    floor_mask: NDArray[np.bool_],
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    camera_xy_robot: tuple[float, float],
    params: PlanarParams | None = None,
    *,
    return_standing: Literal[True],
) -> ParallaxResult: ...


def confirm_floor(
    floor_mask: NDArray[np.bool_],
    gray_cur: NDArray[np.uint8],
    gray_ref: NDArray[np.uint8],
    H_ground_from_image: NDArray[np.float64],
    T_world_ref: tuple[float, float, float],
    T_world_cur: tuple[float, float, float],
    camera_xy_robot: tuple[float, float],
    params: PlanarParams | None = None,
    *,
    return_standing: bool = False,
) -> NDArray[np.bool_] | ParallaxResult:
    """The whole test: ``floor_mask`` extended by parallax-confirmed floor, computed at
    1 / ``params.downscale`` resolution (the cost is in the search) and only ever adding
    floor. Returns ``floor_mask`` itself when the views give no parallax to test.

    With ``return_standing``, a `ParallaxResult` instead, whose ``standing`` and
    ``tested`` cover every row below the horizon (not just the rows the floor's
    extension can reach, which is all the floor needs); its ``floor`` is the same mask.

    Parameters
    ----------
    floor_mask : (H, W) bool, the colour method's floor.
    gray_cur, gray_ref : (H, W) uint8, this frame and an earlier one (undistorted).
    H_ground_from_image : the floor homography (full-resolution pixels).
    T_world_ref, T_world_cur : robot poses (x_m, y_m, theta_rad) of the two frames.
    camera_xy_robot : the camera's position on the robot (metres).
    """
    p = params if params is not None else PlanarParams()
    h, w = _check_views(floor_mask, gray_cur, gray_ref)

    def result(
        floor: NDArray[np.bool_],
        standing: NDArray[np.bool_] | None = None,
        tested: NDArray[np.bool_] | None = None,
    ) -> NDArray[np.bool_] | ParallaxResult:
        if not return_standing:
            return floor
        nothing = np.zeros((h, w), np.bool_)
        return ParallaxResult(
            floor,
            nothing if standing is None else _upsampled(standing, (w, h)),
            nothing if tested is None else _upsampled(tested, (w, h)),
        )

    k = p.downscale
    G = _downscaled_homography(H_ground_from_image, k)
    epipole = epipole_px(G, T_world_ref, T_world_cur, camera_xy_robot)
    if epipole is None:
        return result(floor_mask)
    small = (w // k, h // k)
    mask = np.ascontiguousarray(floor_mask[::k, ::k][: small[1], : small[0]], dtype=np.bool_)
    distance = row_ground_distance_m(G, *small)
    from_bottom = mask[::-1]
    bottom_run = np.where(from_bottom.all(axis=0), small[1], np.argmin(from_bottom, axis=0))
    walks = bottom_run > 0
    below_horizon = np.flatnonzero(np.isfinite(distance))
    reachable = np.flatnonzero(np.isfinite(distance) & (distance <= p.max_range_m))
    # The pixels a column walk can reach: in a column whose bottom pixel is floor, from
    # the top of that floor up to the row at max_range_m (the search is the costly
    # part)...
    r0: int = small[1]
    row_to = np.where(walks, small[1] - bottom_run, 0).astype(np.int64)
    if walks.any() and reachable.size > 0:
        r0 = int(reachable[0])
    if return_standing and below_horizon.size > 0:
        # ... or, for what stands, every pixel below the horizon.
        r0 = min(r0, int(below_horizon[0]))
        row_to[:] = small[1]
    if int(row_to.max()) <= r0:
        return result(floor_mask)
    cur = _small_gray(gray_cur, small)
    ref = _small_gray(gray_ref, small)
    on_floor, standing, tested = _evidence(
        _blurred(cur, p),
        _blurred(ref, p),
        view_homography(G, T_world_ref, T_world_cur),
        epipole,
        (r0, row_to),
        p,
    )
    if not walks.any():
        return result(floor_mask, standing, tested)
    extended = extend_floor(mask, on_floor, standing, distance, p)
    return result(_with_added(floor_mask, extended & ~mask, k), standing, tested)


def floor_before_standing(
    floor_mask: NDArray[np.bool_],
    standing: NDArray[np.bool_],
    min_standing_px: int,
    *,
    flat: NDArray[np.bool_] | None = None,
    interior_px: int = 0,
    spread_px: int = 0,
) -> NDArray[np.bool_]:
    """``floor_mask`` with the floor each column holds beyond something standing removed.

    A column's cut row is its lowest pixel that parallax saw standing
    (`ParallaxResult.standing`) at least ``interior_px`` inside the colour floor (a
    surface the colour method took for floor; a standing pixel on the floor's edge is the
    edge of something the mask already leaves out, and at the test's resolution half of
    it lies on the floor), in columns with at least ``min_standing_px`` of them (one
    stray pixel cuts nothing). Given ``flat`` (pixels the test found on the floor plane),
    only standing pixels above a flat one of their column count: a surface stands on
    floor, and a column without floor seen before it (an obstacle's corner at the image's
    bottom edge) says nothing about where the floor ends. The columns within
    ``spread_px`` of a cut take the lowest of their neighbours' cut rows if they hold one
    such pixel of their own: parallax sees a surface only where its texture runs across
    the epipolar lines, so its evidence on a panel or a box face comes in gaps.
    The cut removes the run of floor pixels through the cut row, up to the first
    not-floor pixel above it: floor seen past a gap (over a low box) is left alone.

    Examples
    --------
    >>> floor = np.ones((5, 4), bool)
    >>> floor[0, 0] = False
    >>> standing = np.zeros((5, 4), bool)
    >>> standing[[2, 3], 0] = True   # column 0: two standing pixels, the lowest in row 3
    >>> standing[1, 1] = True        # column 1: one, too few
    >>> floor_before_standing(floor, standing, 2).astype(int).tolist()
    [[0, 1, 1, 1], [0, 1, 1, 1], [0, 1, 1, 1], [0, 1, 1, 1], [1, 1, 1, 1]]
    >>> floor_before_standing(floor, standing, 2, spread_px=1).astype(int).tolist()
    [[0, 0, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1], [0, 0, 1, 1], [1, 1, 1, 1]]
    """
    if standing.shape != floor_mask.shape:
        raise ValueError(f"standing {standing.shape} must match floor_mask {floor_mask.shape}")
    inside = floor_mask
    if interior_px > 0:
        kernel = np.ones((2 * interior_px + 1, 2 * interior_px + 1), np.uint8)
        # Outside the image is no floor: the matching window does not fit there either.
        inside = cv2.erode(floor_mask.view(np.uint8), kernel, borderValue=0) > 0
    on_floor = standing & inside
    height = floor_mask.shape[0]
    if flat is not None:
        if flat.shape != floor_mask.shape:
            raise ValueError(f"flat {flat.shape} must match floor_mask {floor_mask.shape}")
        flat_in_floor = flat & floor_mask
        lowest_flat = np.where(
            flat_in_floor.any(axis=0), height - 1 - np.argmax(flat_in_floor[::-1], axis=0), -1
        )
        on_floor &= np.arange(height)[:, None] < lowest_flat[None, :]
    count = on_floor.sum(axis=0)
    cut = count >= max(1, min_standing_px)
    if not cut.any():
        return floor_mask
    # The row each column's cut starts at (-1: none).
    lowest = np.where(cut, height - 1 - np.argmax(on_floor[::-1], axis=0), -1)
    if spread_px > 0:
        # The largest row among the neighbours (a 1-D dilation; -1 shifted to 0), for the
        # columns with some evidence of their own (none: the floor beside a box's edge).
        kernel = np.ones((1, 2 * spread_px + 1), np.uint8)
        shifted = (lowest + 1).astype(np.uint16)[None, :]
        borrowed = cv2.dilate(shifted, kernel)[0].astype(np.int64) - 1
        lowest = np.where(count > 0, borrowed, lowest)
    cols = np.flatnonzero(lowest >= 0)
    rows = lowest[cols]
    # Not-floor pixels in rows 0..i of each column, and in rows 0..i-1: a pixel is in the
    # cut row's run when no not-floor pixel lies between them.
    not_floor = (~floor_mask[:, cols]).astype(np.int64)
    gaps_through = np.cumsum(not_floor, axis=0)
    gaps_before: NDArray[np.int64] = gaps_through - not_floor
    at_cut = gaps_through[rows, np.arange(cols.size)]
    row_index = np.arange(height)[:, None]
    in_run = (
        floor_mask[:, cols]
        & floor_mask[rows, cols][None, :]
        & (row_index <= rows[None, :])
        & (gaps_before == at_cut[None, :])
    )
    kept = floor_mask.copy()
    kept[:, cols] &= ~in_run
    return np.asarray(kept, dtype=np.bool_)


FOOT_DEPTH_M = 0.05
"""`standing_feet`: how far past its foot (along the floor) a standing thing's pixels are
kept: its base and a few centimetres of its face, where the floor homography puts them
within the obstacle band of the map's cells."""


@numba.njit(cache=True, nogil=True)
def _standing_feet(
    standing: NDArray[np.bool_],
    floor: NDArray[np.bool_],
    row_distance_m: NDArray[np.float64],
    foot_depth_m: float,
) -> NDArray[np.bool_]:
    height, width = standing.shape
    feet = np.zeros((height, width), dtype=np.bool_)
    for c in range(width):
        floor_below = False
        edge = -1
        r = height - 1
        while r >= 0:
            if standing[r, c]:
                # With no floor seen below it (since the last run), the run's lowest
                # pixel is not its foot: that is hidden (behind a nearer thing, or a
                # wall's plain lower part above unknown ground), and the lowest pixel
                # lands behind it. Only a run at the image's bottom row is known to
                # stand at least that near.
                if floor_below or r == height - 1:
                    foot = edge if edge >= 0 else r  # an edge is only set above floor
                    base = row_distance_m[foot]
                    k = foot
                    while k >= 0 and (standing[k, c] or not floor[k, c]):
                        if not (row_distance_m[k] - base <= foot_depth_m):
                            break  # also at the horizon, where the distance is NaN
                        feet[k, c] = True
                        k -= 1
                # The rest of this standing run lands behind it: skip it.
                while r >= 0 and standing[r, c]:
                    r -= 1
                floor_below = False
                edge = -1
                continue
            if floor[r, c]:
                floor_below = True
                edge = -1
            elif floor_below and edge < 0:
                edge = r
            r -= 1
    return feet


def standing_feet(
    standing: NDArray[np.bool_],
    floor: NDArray[np.bool_],
    row_distance_m: NDArray[np.float64],
    foot_depth_m: float = FOOT_DEPTH_M,
) -> NDArray[np.bool_]:
    """The pixels of ``standing`` that the floor homography puts where the thing stands.

    Only a standing thing's foot lies on the floor; every pixel above it projects through
    the floor homography to a point behind it, in a ray across the floor beyond (a table
    leg's crosses the room). Walking each column up from the bottom, a standing run's
    *foot* is where the floor below it ends: the first not-floor pixel above the
    ``floor`` (colour or parallax-flat floor) when only not-floor pixels lie between (the
    lower part of a plain wall, which parallax cannot test, stands too), else the run's
    own lowest pixel. A run with no floor below it since the run beneath (or the bottom
    of the image) has no foot the camera sees: a wall above a box, or one whose plain
    lower part rises from ground the mask does not call floor, would put its lowest
    pixel behind itself, in a ray across the room beyond; it keeps nothing. A run that
    reaches the image's bottom row stands there. Kept: the pixels from the foot up,
    through not-floor or standing ones, whose forward ground distance
    (``row_distance_m``, per row; NaN above the horizon) is within ``foot_depth_m`` of
    the foot's. Returns a new (H, W) bool mask.

    Examples
    --------
    >>> standing = np.zeros((6, 1), bool); standing[1:3, 0] = True
    >>> floor = np.zeros((6, 1), bool); floor[4:, 0] = True
    >>> rows_m = np.array([np.nan, 3.0, 2.0, 1.2, 1.15, 1.1])
    >>> standing_feet(standing, floor, rows_m).astype(int).ravel().tolist()
    [0, 0, 0, 1, 0, 0]
    """
    if not (standing.shape == floor.shape and row_distance_m.shape == (standing.shape[0],)):
        raise ValueError(
            f"standing {standing.shape}, floor {floor.shape} and row_distance_m"
            f" {row_distance_m.shape} must agree"
        )
    return np.asarray(
        _standing_feet(
            np.ascontiguousarray(standing, dtype=np.bool_),
            np.ascontiguousarray(floor, dtype=np.bool_),
            np.ascontiguousarray(row_distance_m, dtype=np.float64),
            float(foot_depth_m),
        ),
        dtype=np.bool_,
    )


def _downscaled_homography(H_ground_from_image: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """The floor homography of images ``k`` times smaller (pixel centres of the small
    image in the full one: u_full = k * u + (k - 1) / 2)."""
    S = np.array([[k, 0.0, (k - 1) / 2.0], [0.0, k, (k - 1) / 2.0], [0.0, 0.0, 1.0]])
    return np.asarray(np.asarray(H_ground_from_image, dtype=np.float64) @ S, np.float64)


def _small_gray(gray: NDArray[np.uint8], size: tuple[int, int]) -> NDArray[np.uint8]:
    """``gray`` at ``size`` (width, height): area averaging, which also antialiases."""
    if (gray.shape[1], gray.shape[0]) == size:
        return gray
    return np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_AREA), np.uint8)


def _with_added(
    floor_mask: NDArray[np.bool_], added: NDArray[np.bool_], k: int
) -> NDArray[np.bool_]:
    """A copy of ``floor_mask`` with the small mask ``added`` (1 / k of its size) set,
    upsampled only over the rows that add anything."""
    out = np.array(floor_mask, dtype=np.bool_, copy=True)
    rows = np.flatnonzero(added.any(axis=1))
    if rows.size > 0:
        a, b = int(rows[0]), int(rows[-1]) + 1
        h, w = out.shape
        band = _upsampled(added[a:b], (w, min(k * b, h) - k * a))
        out[k * a : k * a + band.shape[0]] |= band
    return out


def _upsampled(mask: NDArray[np.bool_], size: tuple[int, int]) -> NDArray[np.bool_]:
    """A small mask back at ``size`` (width, height), each pixel as the block it stands
    for."""
    big = cv2.resize(mask.view(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    return np.asarray(big > 0, dtype=np.bool_)
