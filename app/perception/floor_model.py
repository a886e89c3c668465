"""The ``floornav`` floor model: what the thesis ignored, added to its superpixels.

The thesis classifies superpixels by colour and shape only, so walls with a floor-like
colour leak in ("Problem" section). This model adds

1. a self-supervised colour model of this frame's floor, fitted robustly to the
   safe-zone superpixels (the dominant colour mode, so an obstacle in the zone does not
   poison it), with a Lab histogram ratio (safe zone vs whole image) as a second cue;
2. position and texture cues (rows, bottom contact, area, gradient energy) the thesis
   left out, weighed by a logistic model fitted offline on labelled images
   (``scripts/train_floor_model.py``; weights in `app.perception.floor_weights`);
3. the free-space structure: per image column, floor runs from the bottom up to the
   first obstacle, found exactly by dynamic programming with an edge reward
   (`app.perception.free_space`);
4. one self-training pass: the colour model is re-fitted on the floor found by the
   first pass (this reaches floor far from the safe zone under other light) and the
   cues are scored again by a second logistic model.

Statistics are taken on an analysis grid of about 160 columns (every ``step``-th pixel
of the superpixel map), so the cues mean the same at any input resolution and cost
about the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from app.perception.free_space import boundary_to_mask, free_space_boundary

GRID_WIDTH_PX = 160
"""Target width of the analysis grid."""

COLOR_SCALE = np.array([12.0, 5.0, 5.0])
"""Lab distances are measured in units of 12 L, 5 a, 5 b (lightness varies more)."""
INLIER_RADIUS = 2.5
"""Safe-zone superpixels within this scaled distance vote for a colour mode."""
MIN_STD_LAB = np.array([4.0, 1.5, 1.5])
"""Floor colour spread never assumed tighter than this (camera noise, shading)."""
HIST_L_BINS, HIST_AB_BINS = 8, 16
"""Lab histogram: 8 L bins over [0, 100], 16 a and b bins over [-64, 64)."""
HIST_RATIO_CAP = 5.0
GRADIENT_NORM = 20.0
"""Sobel magnitude (0..255 grey at grid scale) that counts as a full edge."""
EDGE_REWARD = 6.0
SMOOTHNESS = 1.0
MAX_JUMP_ROWS = 4
LOGIT_CLIP = 4.0
SELF_TRAINING_LOGIT = 0.0
"""Second-pass seeds: superpixels inside the first pass's free space with a logit above."""

CUE_NAMES = (
    "d_prototype",
    "d_mean_sd_over_3",
    "dL_over_10",
    "d_ab_over_5",
    "hist_ratio",
    "y_center",
    "y_top",
    "y_bottom",
    "abs_x_center_minus_half",
    "texture_over_20",
    "texture_rel_log",
    "gray_std_over_20",
    "touches_bottom",
    "area_pct",
    "dL_over_10_sq",
    "y_center_times_d_mean",
    "safe_zone_frac",
    "bias",
)
"""Column order of the cue matrix (`floor_cues`); the weight vectors follow it."""


@dataclass(frozen=True)
class GridStats:
    """Frame statistics on the analysis grid that do not depend on the floor model.

    Attributes
    ----------
    labels : (gh, gw) int32, superpixel labels sampled on the grid
    n : int, number of superpixels
    count : (n,) float64, grid cells per superpixel
    mean_lab : (n, 3) float64
    texture : (n,) float64, mean Sobel magnitude of the grey frame
    gray_std : (n,) float64
    y_center, y_top, y_bottom, x_center : (n,) float64, as fractions of grid height/width
        (``y_bottom`` is one past the lowest row, so 1.0 touches the bottom)
    zone_frac : (n,) float64, fraction of each superpixel's cells inside the safe zone
    zone : (gh, gw) bool, the safe zone on the grid
    lab_code : (gh, gw) int64, joint Lab histogram bin of every cell
    hist_all : (bins,) float64, histogram of the whole grid
    edge_reward : (gh + 1, gw) float64, in [0, 1], for a boundary between rows b-1 and b
    """

    labels: NDArray[np.int32]
    n: int
    count: NDArray[np.float64]
    mean_lab: NDArray[np.float64]
    texture: NDArray[np.float64]
    gray_std: NDArray[np.float64]
    y_center: NDArray[np.float64]
    y_top: NDArray[np.float64]
    y_bottom: NDArray[np.float64]
    x_center: NDArray[np.float64]
    zone_frac: NDArray[np.float64]
    zone: NDArray[np.bool_]
    lab_code: NDArray[np.int64]
    hist_all: NDArray[np.float64]
    edge_reward: NDArray[np.float64]

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.labels.shape[0]), int(self.labels.shape[1]))

    def mean_of(self, values: NDArray[np.floating]) -> NDArray[np.float64]:
        """Per-superpixel mean of a (gh, gw) grid of values."""
        sums = np.bincount(self.labels.ravel(), values.ravel(), self.n)
        return np.asarray(sums / np.maximum(self.count, 1.0), dtype=np.float64)


def grid_step(width: int) -> int:
    """Sampling step that gives an analysis grid of about `GRID_WIDTH_PX` columns."""
    return max(1, round(width / GRID_WIDTH_PX))


def grid_stats(
    frame_bgr: NDArray[np.uint8],
    lab: NDArray[np.float32],
    labels: NDArray[np.int32],
    zone_mask: NDArray[np.bool_],
) -> GridStats:
    """Sample the superpixel map and the frame on the analysis grid.

    Parameters
    ----------
    frame_bgr : (H, W, 3) uint8, the unsmoothed frame (texture is measured on it)
    lab : (H, W, 3) float32, CIELAB of the smoothed frame
    labels : (H, W) int32, superpixels 0..n-1
    zone_mask : (H, W) bool, the safe zone
    """
    _height, width = labels.shape
    step = grid_step(width)
    grid_labels = np.ascontiguousarray(labels[::step, ::step])
    grid_lab = lab[::step, ::step]
    zone = zone_mask[::step, ::step]
    gh, gw = grid_labels.shape
    n = int(labels.max()) + 1
    flat = grid_labels.ravel()
    count = np.bincount(flat, minlength=n).astype(np.float64)
    safe_count = np.maximum(count, 1.0)

    def mean(values: NDArray[np.floating]) -> NDArray[np.float64]:
        return np.asarray(np.bincount(flat, values.ravel(), n) / safe_count, dtype=np.float64)

    gray_full = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
    gray = np.asarray(
        cv2.resize(gray_full, (gw, gh), interpolation=cv2.INTER_AREA), dtype=np.float32
    )
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1)
    gradient = np.sqrt(gx * gx + gy * gy)
    mean_lab = np.column_stack([mean(grid_lab[..., c]) for c in range(3)])
    gray_mean = mean(gray)
    gray_std = np.sqrt(np.maximum(mean(gray * gray) - gray_mean**2, 0.0))
    rows = np.repeat(np.arange(gh, dtype=np.float64), gw)
    cols = np.tile(np.arange(gw, dtype=np.float64), gh)
    y_top = np.full(n, float(gh))
    np.minimum.at(y_top, flat, rows)
    y_bottom = np.zeros(n)
    np.maximum.at(y_bottom, flat, rows)
    a_bin = np.clip(((grid_lab[..., 1] + 64.0) * (HIST_AB_BINS / 128.0)).astype(np.int64), 0, 15)
    b_bin = np.clip(((grid_lab[..., 2] + 64.0) * (HIST_AB_BINS / 128.0)).astype(np.int64), 0, 15)
    l_bin = np.clip((grid_lab[..., 0] * (HIST_L_BINS / 100.0)).astype(np.int64), 0, 7)
    lab_code = (l_bin * HIST_AB_BINS + a_bin) * HIST_AB_BINS + b_bin
    n_bins = HIST_L_BINS * HIST_AB_BINS * HIST_AB_BINS
    edge = np.zeros((gh + 1, gw))
    edge[1:gh] = np.minimum(gradient[1:] + gradient[:-1], 2 * GRADIENT_NORM) / (2 * GRADIENT_NORM)
    return GridStats(
        labels=grid_labels,
        n=n,
        count=count,
        mean_lab=mean_lab,
        texture=mean(gradient),
        gray_std=gray_std,
        y_center=mean(rows.reshape(gh, gw)) / gh,
        y_top=y_top / gh,
        y_bottom=(y_bottom + 1.0) / gh,
        x_center=mean(cols.reshape(gh, gw)) / gw,
        zone_frac=mean(zone.astype(np.float64)),
        zone=zone,
        lab_code=lab_code,
        hist_all=np.bincount(lab_code.ravel(), minlength=n_bins).astype(np.float64),
        edge_reward=edge,
    )


@dataclass(frozen=True)
class FloorColorModel:
    """This frame's floor appearance, fitted to seed superpixels.

    Attributes
    ----------
    prototypes : (k,) int, the seed superpixels kept as floor examples
    mean_lab, std_lab : (3,) float64, weighted Gaussian of the prototypes
    hist_ratio : (bins,) float64, seed-cell Lab histogram over the whole-image
        histogram (how much more common each colour is on the floor), capped
    texture_ref : float, median texture of the prototypes
    """

    prototypes: NDArray[np.intp]
    mean_lab: NDArray[np.float64]
    std_lab: NDArray[np.float64]
    hist_ratio: NDArray[np.float64]
    texture_ref: float


def fit_floor_color_model(
    stats: GridStats,
    seed_weight: NDArray[np.float64],
    seed_cells: NDArray[np.bool_],
    *,
    dominant_mode: bool,
) -> FloorColorModel:
    """Fit the floor colour model to seed superpixels.

    Parameters
    ----------
    seed_weight : (n,) float in [0, 1], how much each superpixel is a seed (e.g. its
        safe-zone fraction); seeds are those above 0.5, else any above 0.
    seed_cells : (gh, gw) bool, grid cells whose colours form the seed histogram
    dominant_mode : bool
        Keep only the seeds near the colour mode supported by the most seed area
        (robust to an obstacle covering part of the safe zone).
    """
    seeds = np.flatnonzero(seed_weight > 0.5)
    if seeds.size == 0:
        seeds = np.flatnonzero(seed_weight > 0.0)
    if seeds.size == 0:
        raise ValueError("no seed superpixels for the floor colour model")
    scaled = stats.mean_lab / COLOR_SCALE
    if dominant_mode:
        votes = stats.count[seeds] * seed_weight[seeds]
        dist_sq = ((scaled[seeds, None, :] - scaled[None, seeds, :]) ** 2).sum(axis=2)
        mode = int(np.argmax((votes[None, :] * (dist_sq < INLIER_RADIUS**2)).sum(axis=1)))
        prototypes = seeds[dist_sq[mode] < (2 * INLIER_RADIUS) ** 2]
    else:
        prototypes = seeds
    weights = stats.count[prototypes] * seed_weight[prototypes]
    weights = weights / weights.sum()
    mean_lab = (stats.mean_lab[prototypes] * weights[:, None]).sum(axis=0)
    var = ((stats.mean_lab[prototypes] - mean_lab) ** 2 * weights[:, None]).sum(axis=0)
    std_lab = np.maximum(np.sqrt(var), MIN_STD_LAB)
    n_bins = stats.hist_all.shape[0]
    seed_counts = np.bincount(stats.lab_code[seed_cells], minlength=n_bins).astype(np.float32)
    # 3x3 smoothing over neighbouring L and a bins (OpenCV sees the b axis as channels)
    # so that near colours count as floor too.
    hist_seed = np.asarray(
        cv2.GaussianBlur(seed_counts.reshape(HIST_L_BINS, HIST_AB_BINS, HIST_AB_BINS), (3, 3), 0),
        dtype=np.float64,
    ).reshape(-1)
    n_cells = stats.lab_code.size
    ratio = hist_seed / max(int(seed_cells.sum()), 1) / (stats.hist_all / n_cells + 1e-3)
    return FloorColorModel(
        prototypes=prototypes,
        mean_lab=mean_lab,
        std_lab=std_lab,
        hist_ratio=np.minimum(ratio, HIST_RATIO_CAP).astype(np.float64),
        texture_ref=float(np.median(stats.texture[prototypes])),
    )


def floor_cues(stats: GridStats, model: FloorColorModel) -> NDArray[np.float64]:
    """(n, 18) cue matrix in `CUE_NAMES` order (last column the constant 1)."""
    scaled = stats.mean_lab / COLOR_SCALE
    to_prototypes = (
        ((scaled[:, None, :] - scaled[None, model.prototypes, :]) ** 2).sum(axis=2).min(axis=1)
    )
    d_mean = np.sqrt((((stats.mean_lab - model.mean_lab) / model.std_lab) ** 2).sum(axis=1))
    d_l = (stats.mean_lab[:, 0] - model.mean_lab[0]) / 10.0
    d_ab = np.hypot(*(stats.mean_lab[:, 1:] - model.mean_lab[1:]).T) / 5.0
    hist = stats.mean_of(model.hist_ratio[stats.lab_code]) / HIST_RATIO_CAP
    gh = stats.shape[0]
    return np.column_stack(
        [
            np.sqrt(to_prototypes),
            d_mean / 3.0,
            d_l,
            d_ab,
            hist,
            stats.y_center,
            stats.y_top,
            stats.y_bottom,
            np.abs(stats.x_center - 0.5),
            stats.texture / 20.0,
            np.log((stats.texture + 1.0) / (model.texture_ref + 1.0)),
            stats.gray_std / 20.0,
            (stats.y_bottom >= 1.0 - 1.5 / gh).astype(np.float64),
            stats.count / stats.labels.size * 100.0,
            d_l**2,
            stats.y_center * d_mean / 3.0,
            stats.zone_frac,
            np.ones(stats.n),
        ]
    )


def free_space_cells(
    stats: GridStats, logits: NDArray[np.float64]
) -> tuple[NDArray[np.bool_], NDArray[np.int32]]:
    """Floor cells on the grid from superpixel logits, by the column DP.

    Returns the (gh, gw) bool free-space mask and the (gw,) boundary rows.
    """
    cost = -np.clip(logits, -LOGIT_CLIP, LOGIT_CLIP)[stats.labels]
    boundary = free_space_boundary(
        cost,
        edge_reward=EDGE_REWARD * stats.edge_reward,
        smoothness=SMOOTHNESS,
        max_jump=MAX_JUMP_ROWS,
    )
    return boundary_to_mask(boundary, stats.shape[0]), boundary


@dataclass(frozen=True)
class FloorModelResult:
    """Output of `floor_model_segment`.

    Attributes
    ----------
    grid_floor : (gh, gw) bool, free space on the analysis grid
    boundary_rows : (gw,) int32, per grid column the first floor row
    logits : (n,) float64, final per-superpixel floor logits (pass 2)
    first_pass_logits : (n,) float64
    """

    grid_floor: NDArray[np.bool_]
    boundary_rows: NDArray[np.int32]
    logits: NDArray[np.float64]
    first_pass_logits: NDArray[np.float64]


def second_pass_cues(stats: GridStats, first_logits: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cues after self-training: the colour model re-fitted on the first pass's floor."""
    grid_floor, _ = free_space_cells(stats, first_logits)
    in_free_space = stats.mean_of(grid_floor.astype(np.float64))
    confident = first_logits > SELF_TRAINING_LOGIT
    seed_weight = ((in_free_space > 0.5) & confident).astype(np.float64)
    seed_cells = grid_floor & confident[stats.labels]
    if not seed_weight.any():
        # The first pass found no floor: stay with the safe zone.
        seed_weight, seed_cells = stats.zone_frac, stats.zone
    model = fit_floor_color_model(stats, seed_weight, seed_cells, dominant_mode=False)
    return floor_cues(stats, model)


def first_pass_cues(stats: GridStats) -> NDArray[np.float64]:
    """Cues with the colour model fitted to the safe zone's dominant colour mode."""
    model = fit_floor_color_model(stats, stats.zone_frac, stats.zone, dominant_mode=True)
    return floor_cues(stats, model)


def floor_model_segment(
    stats: GridStats,
    first_weights: NDArray[np.float64],
    second_weights: NDArray[np.float64],
) -> FloorModelResult:
    """Run both passes: safe-zone model -> DP -> self-trained model -> DP."""
    first_logits = first_pass_cues(stats) @ first_weights
    logits = second_pass_cues(stats, first_logits) @ second_weights
    grid_floor, boundary = free_space_cells(stats, logits)
    return FloorModelResult(grid_floor, boundary, logits, first_logits)


def grid_to_image(grid_mask: NDArray[np.bool_], shape: tuple[int, int]) -> NDArray[np.bool_]:
    """Nearest-neighbour upsampling of a grid mask to the (H, W) image."""
    height, width = shape
    step = grid_step(width)
    rows = np.minimum((np.arange(height) + step // 2) // step, grid_mask.shape[0] - 1)
    cols = np.minimum((np.arange(width) + step // 2) // step, grid_mask.shape[1] - 1)
    return np.asarray(grid_mask[rows[:, None], cols[None, :]], dtype=np.bool_)


def boundary_to_image(
    boundary_rows: NDArray[np.int32], shape: tuple[int, int]
) -> NDArray[np.bool_]:
    """Floor mask at image size from per-grid-column boundary rows.

    Equal to nearest-neighbour upsampling of the grid mask (`grid_to_image`) but made
    by one comparison per pixel: pixel (y, x) is floor when its nearest grid row is at or
    below the boundary of its nearest grid column.
    """
    height, width = shape
    step = grid_step(width)
    cols = np.minimum((np.arange(width) + step // 2) // step, boundary_rows.shape[0] - 1)
    grid_height = (height + step - 1) // step
    boundary = boundary_rows[cols]
    first_row = np.where(boundary >= grid_height, height, boundary * step - step // 2)
    rows = np.arange(height, dtype=np.int32)[:, None]
    return np.asarray(rows >= first_row[None, :], dtype=np.bool_)
