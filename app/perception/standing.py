"""Standing surfaces found by the horizon: floor never appears above it.

A calibrated floor camera sees the floor plane only below its horizon (the image of the
plane's line at infinity). Where a floor mask runs up a column past the horizon, the
segmenter has taken a surface that stands up (a floor-coloured box, cupboard or wall
panel taller than the camera) for floor. Colour cannot tell such a surface from the
floor; geometry can, and here it needs no motion (the parallax test, `planar`, does).

In each such column the standing surface is the upper part of the mask's run, and its
base, where it meets the floor, is where the run's colour changes: the best two-segment
split of the column's colour profile (least squares, as a change-point). The split is
searched only below the horizon (the part above is standing whatever its colour). If the
two parts differ by less than ``min_step`` in colour, nothing in the run looks like
floor below a standing surface: the whole run is standing (a box filling the view).

Pure numpy on arrays; `standing_across_horizon` is the entry point.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

NEIGHBOUR_COLUMNS = 8
"""A column without a clear base of its own borrows the median base of the columns
this near (at the search's resolution) that have one."""


MIN_FOOT_RUN = 3
"""A wall's foot found below the mask's floor end (`wall_surfaces`) holds in at least
this many adjacent columns at the search's resolution."""
MAX_SPLITS = 3
"""Splits per column at most (floor, rug, threshold under one surface)."""
BASE_MEDIAN_HALF = 2
"""Base rows are smoothed over this many columns either side."""


@dataclass(frozen=True)
class HorizonParams:
    """Constants of the test, fixed from geometry before looking at any result."""

    min_above_frac: float = 0.02
    """A run must reach this far above the horizon (a share of the image height, about
    a degree for a webcam): a camera pitched by a rocking start, or a calibration off by
    a little, must not turn far floor into a standing surface."""
    min_step: float = 4.0
    """Smallest colour difference (CIELAB units, mean of each part) between the floor
    below a standing surface and the surface itself; less: the whole run is standing."""
    min_floor_frac: float = 0.01
    """The floor part below a split holds at least this share of the image height."""
    grow_tolerance: float = 6.0
    """Beside the columns that cross the horizon, a mask pixel joins a standing surface
    within this colour distance (CIELAB, plus twice the surface's own spread) of it..."""
    grow_reach_frac: float = 0.15
    """...and only this far (a share of the image width) beside them."""
    search_rows: int = 120
    """The colour profiles are searched at about this many rows (the frame shrunk by a
    whole factor; base lines are found to within that factor's pixels)."""


def horizon_rows(
    image_to_ground_valid: NDArray[np.bool_],
) -> NDArray[np.int64]:
    """Per column, the first row below the horizon.

    ``image_to_ground_valid`` : (H, W) bool, True where a pixel's ray meets the floor in
    front of the camera (finite ground coordinates). Columns without any such pixel get
    H (all of the column is above the horizon)."""
    valid = np.asarray(image_to_ground_valid, dtype=bool)
    height = valid.shape[0]
    # The horizon is a line: below it every pixel is valid, so the first valid row is it.
    first = valid.argmax(axis=0)
    rows: NDArray[np.int64] = np.where(valid.any(axis=0), first, height).astype(np.int64)
    return rows


def standing_across_horizon(
    floor_mask: NDArray[np.bool_],
    image_bgr: NDArray[np.uint8],
    horizon_row: NDArray[np.int64],
    params: HorizonParams | None = None,
) -> NDArray[np.bool_]:
    """The pixels of ``floor_mask`` that belong to surfaces standing up (see the module).

    Parameters
    ----------
    floor_mask : (H, W) bool, True = floor (the segmenter's mask)
    image_bgr : (H, W, 3) uint8 BGR, the frame the mask came from
    horizon_row : (W,) first row below the horizon per column (`horizon_rows`)

    Returns
    -------
    (H, W) bool: True where the mask says floor but the pixel is a standing surface.
    """
    p = params if params is not None else HorizonParams()
    mask = _checked_mask(floor_mask, image_bgr, horizon_row)
    height, width = mask.shape
    standing = np.zeros_like(mask)
    leak_row = horizon_row - max(1, round(p.min_above_frac * height))
    # The cheap check first: most frames have no floor above the horizon at all.
    highest = np.where(mask.any(axis=0), mask.argmax(axis=0), height)
    if not (highest < leak_row).any():
        return standing
    s = max(1, round(height / p.search_rows))
    small_mask = mask[::s, ::s]
    small_h, small_w = small_mask.shape
    lab = _small_lab(image_bgr, (small_w, small_h))
    small_horizon = np.ceil(horizon_row[::s] / s).astype(np.int64)
    small_leak = np.floor(leak_row[::s] / s).astype(np.int64)
    small_rows = np.arange(small_h)[:, None]
    leaking = (small_mask & (small_rows < small_leak[None, :])).any(axis=0)
    cols = np.flatnonzero(leaking)
    if cols.size == 0:
        return standing
    # Each leaking column's run: from its highest floor row above the horizon down to
    # the first non-floor row below it (the run the segmenter grew up the surface).
    sub = small_mask[:, cols]
    top = sub.argmax(axis=0)
    below_top = small_rows >= top[None, :]
    gap = below_top & ~sub
    bottom = np.where(gap.any(axis=0), gap.argmax(axis=0), small_h)
    in_run = below_top & (small_rows < bottom[None, :])
    # Rows below every run's bottom take no part.
    last = int(bottom.max())
    in_run = in_run[:last]
    profile = lab[:last, cols, :] * in_run[..., None]
    csum = np.cumsum(profile, axis=0)
    csq = np.cumsum((profile**2).sum(axis=2), axis=0)
    count = np.cumsum(in_run, axis=0).astype(np.float32)
    # Sums over the run's rows < k, for every row k (k = 0: nothing).
    upper_sum = np.concatenate([np.zeros((1, len(cols), 3), np.float32), csum[:-1]], axis=0)
    upper_sq = np.concatenate([np.zeros((1, len(cols)), np.float32), csq[:-1]], axis=0)
    upper_n = np.concatenate([np.zeros((1, len(cols))), count[:-1]], axis=0)
    index = np.arange(len(cols))
    run_rows = small_rows[:last]
    min_floor_rows = max(1, round(p.min_floor_frac * height / s))
    searchable = (run_rows >= small_horizon[cols][None, :]) & (run_rows > top[None, :])
    # Binary segmentation from the bottom up: split the run [top, end) in two where the
    # colour changes most, and while the upper part still holds a real change below the
    # horizon, split it again. The surface is the topmost part; the first split alone
    # could fall between two floors (a rug on wood) under the surface.
    end = bottom.copy()
    clear = np.zeros(len(cols), bool)
    for _ in range(MAX_SPLITS):
        end_rows = np.maximum(end - 1, 0)
        total_sum = csum[end_rows, index]
        total_sq = csq[end_rows, index]
        total_n = count[end_rows, index]
        lower_sum = total_sum[None] - upper_sum
        lower_sq = total_sq[None] - upper_sq
        lower_n = total_n[None] - upper_n
        with np.errstate(divide="ignore", invalid="ignore"):
            cost = (
                upper_sq
                - (upper_sum**2).sum(axis=2) / upper_n
                + lower_sq
                - (lower_sum**2).sum(axis=2) / lower_n
            )
            allowed = searchable & (run_rows < end[None, :]) & (lower_n >= min_floor_rows)
            cost = np.where(allowed & np.isfinite(cost), cost, np.inf)
            split = cost.argmin(axis=0)
            found = np.isfinite(cost[split, index])
            upper_mean = upper_sum[split, index] / upper_n[split, index][:, None]
            lower_mean = lower_sum[split, index] / lower_n[split, index][:, None]
            step = np.linalg.norm(upper_mean - lower_mean, axis=1)
        real = found & (step >= p.min_step)
        if not real.any():
            break
        end = np.where(real, split, end)
        clear |= real
    # A column whose run shows no real colour step takes the median base of the columns
    # near it that do (the same surface's base line); with none near, nothing in its run
    # looks like floor below a standing surface: the whole run stands.
    base = np.where(clear, _running_median(end, clear), bottom)
    if clear.any() and not clear.all():
        clear_cols, clear_base = cols[clear], base[clear]
        for i in np.flatnonzero(~clear):
            near = np.abs(clear_cols - cols[i]) <= NEIGHBOUR_COLUMNS
            if near.any():
                base[i] = min(int(np.median(clear_base[near])), int(bottom[i]))
    small_standing = np.zeros_like(small_mask)
    small_standing[:, cols] = sub & (small_rows < base[None, :])
    # The floor the surface stands on: the run's rows just below its base.
    floor_below = (
        in_run
        & clear[None, :]
        & (run_rows >= base[None, :])
        & (run_rows < base[None, :] + 2 * min_floor_rows)
    )
    lowest_base = int(base[clear].max()) if clear.any() else small_h
    small_standing = _grow_sideways(
        small_standing, small_mask, lab, lab[:last, cols][floor_below], lowest_base, p
    )
    up = cv2.resize(
        small_standing.view(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST
    ).astype(bool)
    standing[...] = mask & up
    return standing


def _checked_mask(
    floor_mask: NDArray[np.bool_], image_bgr: NDArray[np.uint8], horizon_row: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """``floor_mask`` as bool, once the image and the horizon are checked to match it."""
    mask = np.asarray(floor_mask, dtype=bool)
    if image_bgr.shape[:2] != mask.shape or horizon_row.shape != (mask.shape[1],):
        raise ValueError(
            f"image {image_bgr.shape[:2]}, mask {mask.shape} and horizon {horizon_row.shape} "
            "must agree"
        )
    return mask


def _small_lab(image_bgr: NDArray[np.uint8], size: tuple[int, int]) -> NDArray[np.float32]:
    """``image_bgr`` shrunk to ``size`` (width, height) by area, in CIELAB (float32)."""
    lab = cv2.cvtColor(
        cv2.resize(image_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2LAB
    ).astype(np.float32)
    # OpenCV's 8-bit Lab: L scaled by 255/100, a and b offset by 128. Back to CIELAB.
    lab[..., 0] *= 100.0 / 255.0
    return np.asarray(lab, np.float32)


def _running_median(values: NDArray[np.int64], use: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Each used value replaced by the median of it and its used neighbours up to
    `BASE_MEDIAN_HALF` places either side (a plank seam under one column does not move
    the base line there)."""
    out = values.copy()
    picked = np.flatnonzero(use)
    if picked.size < 3:
        return out
    padded = np.pad(values[picked], BASE_MEDIAN_HALF, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * BASE_MEDIAN_HALF + 1)
    out[picked] = np.median(windows, axis=1).astype(np.int64)
    return out


def _grow_sideways(
    seeds: NDArray[np.bool_],
    mask: NDArray[np.bool_],
    lab: NDArray[np.float32],
    floor_lab: NDArray[np.float32],
    lowest_base_row: int,
    params: HorizonParams,
) -> NDArray[np.bool_]:
    """The standing surface found in the columns that cross the horizon, grown through
    the mask into the columns beside them that do not (the same box's lower corners):
    mask pixels connected to it, no lower than its base, whose colour is nearer the
    surface's than that of the floor just below it (``floor_lab``), within
    `HorizonParams.grow_tolerance` and half the way to that floor's colour."""
    rows = slice(0, min(lowest_base_row, mask.shape[0]))
    seeds_part, mask_part = seeds[rows], mask[rows]
    surface = lab[rows][seeds_part]
    if len(surface) == 0:
        return seeds
    mean = surface.mean(axis=0)
    spread = float(np.sqrt(((surface - mean) ** 2).sum(axis=1).mean()))
    # Pixel by pixel, sensor noise makes single floor pixels look like the surface; a
    # median keeps the surface's edges where they are.
    lab_part = cv2.medianBlur(np.ascontiguousarray(lab[rows]), 5)
    distance = np.linalg.norm(lab_part - mean, axis=2)
    tolerance = params.grow_tolerance
    if len(floor_lab):
        floor_mean = floor_lab.mean(axis=0)
        # Never past halfway to the floor's colour: the surface is floor-coloured.
        tolerance = min(tolerance, float(np.linalg.norm(floor_mean - mean)) / 2)
    alike = mask_part & (distance <= tolerance + 2.0 * spread)
    # Only beside the columns it was found in: the surface's lower corners are there,
    # while floor of a like colour may be anywhere.
    seed_cols = np.flatnonzero(seeds_part.any(axis=0))
    reach = max(1, round(params.grow_reach_frac * mask.shape[1]))
    cols = np.arange(mask.shape[1])
    alike[:, (cols < seed_cols.min() - reach) | (cols > seed_cols.max() + reach)] = False
    if len(floor_lab):
        alike &= distance < np.linalg.norm(lab_part - floor_mean, axis=2)
    alike |= seeds_part
    count, labels = cv2.connectedComponents(alike.view(np.uint8), connectivity=4)
    touching = np.zeros(count, dtype=bool)
    touching[labels[seeds_part]] = True
    touching[0] = False
    grown = seeds.copy()
    grown[rows] |= touching[labels]
    return grown


@dataclass(frozen=True)
class WallSurfaces:
    """What `wall_surfaces` proved standing, as image masks of its frame."""

    walls: NDArray[np.bool_]
    """Not-floor pixels of surfaces standing where the floor mask ends."""
    floor_part: NDArray[np.bool_]
    """Floor-mask pixels that are the lower part of such a surface: its colour runs on
    unchanged below where the mask's floor ends, down to its true foot."""


def wall_surfaces(
    floor_mask: NDArray[np.bool_],
    image_bgr: NDArray[np.uint8],
    horizon_row: NDArray[np.int64],
    params: HorizonParams | None = None,
) -> WallSurfaces:
    """Surfaces standing where the floor ends: in each column whose floor runs up from
    the bottom of the image, the not-floor run above it, when that run reaches past the
    horizon and is one surface from its foot up (its colour profile, foot to horizon,
    splits nowhere by ``min_step`` or more).

    Floor never reaches the horizon, so one surface that runs from where the floor ends
    to above the horizon stands there: a plain wall, whose lower part gives the parallax
    test no texture to tell it from a change of floor. A rug, a threshold or another
    room's floor under the run changes colour somewhere below the horizon and is left
    unproven (a floor of exactly the wall's colour behind an edge would be taken for
    the wall).

    The segmenter can take the lower part of such a surface for floor (a floor-coloured
    box side: the mask stops halfway up it, where its shading drifts from the floor's).
    Then the surface's colour runs on unchanged below the mask's floor end, and the one
    real colour step of the whole column, horizon to bottom, lies lower: the surface's
    true foot. When that step is ``min_step`` or more and everything above it is still
    one surface, the mask's floor between its end and that foot stands (``floor_part``).
    A wall on a real floor has its step where the mask ends, and a rug below changes
    colour under a step already, so neither moves the foot.

    Returns `WallSurfaces`, the walls' pixels below the horizon.
    """
    p = params if params is not None else HorizonParams()
    mask = _checked_mask(floor_mask, image_bgr, horizon_row)
    height, width = mask.shape
    walls = np.zeros_like(mask)
    floor_part = np.zeros_like(mask)
    s = max(1, round(height / p.search_rows))
    small_mask = mask[::s, ::s]
    small_h, small_w = small_mask.shape
    small_rows = np.arange(small_h)[:, None]
    # Each column's floor from the bottom up, and the not-floor run above it.
    from_bottom = small_mask[::-1]
    bottom_run = np.where(from_bottom.all(axis=0), small_h, np.argmin(from_bottom, axis=0))
    foot = small_h - 1 - bottom_run  # the run's lowest row (-1: floor to the top)
    above_foot = (small_rows <= foot[None, :]) & small_mask
    # The run ends under the next floor pixel above the foot (or at the top).
    run_top = np.where(
        above_foot.any(axis=0), small_h - 1 - np.argmax(above_foot[::-1], axis=0) + 1, 0
    )
    above = max(1, round(p.min_above_frac * height))
    small_leak = np.floor((horizon_row[::s] - above) / s).astype(np.int64)
    small_horizon = np.ceil(horizon_row[::s] / s).astype(np.int64)
    candidate = (bottom_run > 0) & (foot >= 0) & (run_top <= small_leak) & (foot >= small_horizon)
    cols = np.flatnonzero(candidate)
    if cols.size == 0:
        return WallSurfaces(walls, floor_part)
    lab = _small_lab(image_bgr, (small_w, small_h))
    # The profile tested: from just above the horizon (by the leak margin) down to the
    # foot, less the rows just above it: shrunk, the foot's own row mixes the surface
    # with the floor, and a segmenter's floor ends a few pixels off the true junction.
    junction = 1 + max(1, round(p.min_above_frac * height / s))
    min_rows = max(1, round(p.min_floor_frac * height / s))
    lo, hi = small_leak[cols], np.maximum(foot[cols] - junction, 0)
    profile = _ColumnProfiles.of(lab[:, cols, :])
    _, step, total_n = profile.best_split(lo, hi, min_rows)
    # A run whose foot is too near the horizon to show its colour profile proves nothing.
    one_surface = (total_n >= 2 * min_rows) & ~(step >= p.min_step)
    # Where the mask's floor ends with no edge (one colour across it) on such a surface,
    # the whole column, horizon to bottom, is searched: its one real step, when it lies
    # lower with one surface above it, is the surface's true foot.
    lower_foot = one_surface & ~(profile.step_across(foot[cols], junction) >= p.min_step)
    low_best = np.zeros_like(cols)
    if lower_foot.any():
        which = np.flatnonzero(lower_foot)
        sub, sub_lo = profile.subset(which), lo[which]
        best_row, low_step, _ = sub.best_split(sub_lo, np.full_like(sub_lo, small_h - 1), min_rows)
        _, upper_step, _ = sub.best_split(sub_lo, np.maximum(best_row - junction, 0), min_rows)
        lower_foot[which] = (
            (low_step >= p.min_step)
            # A foot is an edge: its step shows across a few rows, where a reflection in
            # a glossy floor or a shadow fades over many.
            & (sub.step_across(best_row, junction) >= p.min_step)
            & (best_row > foot[cols[which]] + junction)
            & ~(upper_step >= p.min_step)
        )
        low_best[which] = best_row
        # A surface has width: a lone column is an edge's streak (a reflection's rim).
        lower_foot &= _in_runs(cols[lower_foot], small_w, MIN_FOOT_RUN)[cols]
    small_walls = np.zeros_like(small_mask)
    wall_cols = cols[one_surface]
    small_walls[:, wall_cols] = (small_rows >= small_horizon[wall_cols][None, :]) & (
        small_rows <= foot[wall_cols][None, :]
    )
    small_part = np.zeros_like(small_mask)
    part_cols = cols[lower_foot]
    small_part[:, part_cols] = (small_rows > foot[part_cols][None, :]) & (
        small_rows <= low_best[lower_foot][None, :]
    )
    size = (width, height)
    walls[...] = _upsampled(small_walls, size) & ~mask
    floor_part[...] = _upsampled(small_part, size) & mask
    return WallSurfaces(walls, floor_part)


class _ColumnProfiles:
    """Cumulative colour sums down each column of a (rows, columns, 3) CIELAB array
    (``csum``, `of`), for the best two-part split of any span of rows (least squares)."""

    def __init__(self, csum: NDArray[np.float64]) -> None:
        self.csum = csum
        self.index = np.arange(csum.shape[1])
        self.rows = np.arange(csum.shape[0])[:, None]

    @classmethod
    def of(cls, lab: NDArray[np.float32]) -> _ColumnProfiles:
        return cls(np.cumsum(lab, axis=0, dtype=np.float64))

    def subset(self, which: NDArray[np.int64]) -> _ColumnProfiles:
        """The profiles of the columns ``which`` only."""
        return _ColumnProfiles(self.csum[:, which])

    def best_split(
        self, lo: NDArray[np.int64], hi: NDArray[np.int64], min_rows: int
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
        """Per column, the split row k of its rows [lo, hi] (the upper part [lo, k], the
        lower part (k, hi], each at least ``min_rows`` long) that removes the most of
        the span's sum of squares; the colour step (CIELAB distance of the two parts'
        means) there, NaN where no split fits; and the span's length."""
        index, rows = self.index, self.rows
        before_lo = np.where(lo > 0, lo - 1, 0)
        start = np.where((lo > 0)[:, None], self.csum[before_lo, index], 0.0)
        total_n = np.maximum(hi - lo + 1, 0)
        total_sum = self.csum[hi, index] - start
        upper_n = (rows - lo[None, :] + 1).astype(np.float64)
        upper_sum = self.csum - start[None]
        lower_n = total_n[None, :] - upper_n
        lower_sum = total_sum[None] - upper_sum
        splittable = (
            (rows >= lo[None, :])
            & (rows <= hi[None, :])
            & (upper_n >= min_rows)
            & (lower_n >= min_rows)
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.linalg.norm(
                upper_sum / upper_n[..., None] - lower_sum / lower_n[..., None], axis=2
            )
            gain = np.where(splittable, upper_n * lower_n / total_n[None] * step**2, -1.0)
        best = gain.argmax(axis=0)
        found = splittable[best, index]
        return best, np.where(found, step[best, index], np.nan), total_n

    def step_across(self, row: NDArray[np.int64], rows: int) -> NDArray[np.float64]:
        """Per column, the colour step between the ``rows`` rows ending at ``row`` and
        the ``rows`` rows after it (fewer at the array's ends)."""
        last = self.csum.shape[0] - 1
        top = np.clip(row - rows, -1, last)
        bottom = np.clip(row + rows, 0, last)
        row = np.clip(row, 0, last)
        index = self.index

        def upto(r: NDArray[np.int64]) -> NDArray[np.float64]:
            return np.where((r >= 0)[:, None], self.csum[np.maximum(r, 0), index], 0.0)

        above = (upto(row) - upto(top)) / np.maximum(row - top, 1)[:, None]
        below = (upto(bottom) - upto(row)) / np.maximum(bottom - row, 1)[:, None]
        return np.asarray(np.linalg.norm(above - below, axis=1), np.float64)


def _in_runs(columns: NDArray[np.int64], width: int, length: int) -> NDArray[np.bool_]:
    """(width,) bool: True on the given columns that lie in runs of at least ``length``
    adjacent given columns."""
    picked = np.zeros(width + 2, dtype=bool)
    picked[columns + 1] = True
    edges = np.flatnonzero(np.diff(picked.view(np.int8)))  # run starts, then ends
    out = np.zeros(width, dtype=bool)
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        if end - start >= length:
            out[start:end] = True
    return out


def _upsampled(small: NDArray[np.bool_], size: tuple[int, int]) -> NDArray[np.bool_]:
    return np.asarray(
        cv2.resize(small.view(np.uint8), size, interpolation=cv2.INTER_NEAREST), dtype=bool
    )
