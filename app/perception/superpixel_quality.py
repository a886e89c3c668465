"""Quality measures of a superpixel segmentation against a binary floor mask.

* :func:`boundary_recall` -- how much of the true floor boundary a superpixel boundary
  passes close to (an upper bound for how well any per-superpixel classifier can trace
  the floor edge).
* :func:`undersegmentation_error` -- how much area superpixels that straddle the floor
  edge force onto the wrong side, in the corrected form of Neubert and Protzel (2012)
  and Van den Bergh et al. (2012).
* :func:`n_segments` -- number of distinct labels.

All functions are pure and vectorised; labels can be any non-negative integer array.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["boundary_map", "boundary_recall", "n_segments", "undersegmentation_error"]


def _check_pair(labels: NDArray[Any], gt_mask: NDArray[Any]) -> None:
    if labels.ndim != 2:
        raise ValueError(f"labels must be 2-D (H, W), got shape {labels.shape}")
    if gt_mask.shape != labels.shape:
        raise ValueError(
            f"gt_mask shape {gt_mask.shape} does not match labels shape {labels.shape}"
        )
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"labels must have an integer dtype, got {labels.dtype}")


def boundary_map(values: NDArray[Any]) -> NDArray[np.bool_]:
    """Pixels with at least one 4-neighbour of a different value.

    Parameters
    ----------
    values : (H, W) ndarray
        Labels or a mask.

    Returns
    -------
    (H, W) bool ndarray. Both pixels of every differing neighbour pair are marked, so a
    boundary is two pixels wide (one on each side).
    """
    b = np.zeros(values.shape, dtype=bool)
    dx = values[:, 1:] != values[:, :-1]
    dy = values[1:, :] != values[:-1, :]
    b[:, 1:] |= dx
    b[:, :-1] |= dx
    b[1:, :] |= dy
    b[:-1, :] |= dy
    return b


def boundary_recall(
    labels: NDArray[np.integer[Any]], gt_mask: NDArray[np.bool_], *, tolerance_px: int = 2
) -> float:
    """Fraction of ground-truth boundary pixels near a superpixel boundary.

    Parameters
    ----------
    labels : (H, W) int ndarray
        Superpixel labels.
    gt_mask : (H, W) bool ndarray
        Ground truth (True = floor). Non-bool arrays are read as ``!= 0``.
    tolerance_px : int, optional
        A ground-truth boundary pixel counts as recalled if a superpixel boundary pixel
        lies within this chessboard (L-infinity) distance; 0 asks for an exact hit.

    Returns
    -------
    float
        Recall in [0, 1]; ``nan`` if the mask has no boundary (all floor or no floor).

    Notes
    -----
    Boundary pixels are those with a 4-neighbour of a different value, for both the
    mask and the labels (see :func:`boundary_map`).
    """
    _check_pair(labels, gt_mask)
    if tolerance_px < 0:
        raise ValueError(f"tolerance_px must be >= 0, got {tolerance_px}")
    gt_b = boundary_map(np.asarray(gt_mask) != 0)
    n_gt = int(np.count_nonzero(gt_b))
    if n_gt == 0:
        return float("nan")
    near = boundary_map(labels)
    if tolerance_px > 0:
        size = 2 * int(tolerance_px) + 1
        kernel = np.ones((size, size), dtype=np.uint8)
        dilated = cv2.dilate(
            near.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0
        )
        near = dilated > 0
    hits = int(np.count_nonzero(near[gt_b]))
    return hits / n_gt


def undersegmentation_error(labels: NDArray[np.integer[Any]], gt_mask: NDArray[np.bool_]) -> float:
    """Corrected undersegmentation error for a two-class ground truth.

    ``UE = (1 / N) * sum_s min(|s ∩ floor|, |s ∩ not floor|)``: every superpixel that
    straddles the floor edge is charged the smaller of its two parts (Neubert & Protzel
    2012; Van den Bergh et al. 2012). It equals the pixel error of the best possible
    per-superpixel floor labelling.

    Parameters
    ----------
    labels : (H, W) int ndarray
        Superpixel labels, non-negative.
    gt_mask : (H, W) bool ndarray
        Ground truth (True = floor). Non-bool arrays are read as ``!= 0``.

    Returns
    -------
    float
        Error in [0, 0.5].
    """
    _check_pair(labels, gt_mask)
    flat = labels.ravel()
    if flat.size and int(flat.min()) < 0:
        raise ValueError("labels must be non-negative")
    total = np.bincount(flat)
    floor = np.bincount(flat, weights=(np.asarray(gt_mask) != 0).ravel().astype(np.float64))
    floor = floor[: total.size]
    err = np.minimum(floor, total - floor).sum()
    return float(err / flat.size)


def n_segments(labels: NDArray[np.integer[Any]]) -> int:
    """Number of distinct labels in ``labels``."""
    return int(np.unique(labels).size)
