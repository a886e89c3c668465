"""Accuracy of a predicted floor mask against a ground-truth mask (pure functions)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

NEAR_BAND_FRAC = 0.4
"""``near_false_floor`` looks at the bottom 40 % of image rows: the floor just ahead."""


@dataclass(frozen=True)
class FloorScores:
    """Per-image scores. ``near_false_floor`` is NaN when the bottom band holds no
    ground-truth non-floor pixel (the image then does not count for that metric)."""

    iou: float
    floor_recall: float
    floor_precision: float
    near_false_floor: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def floor_scores(predicted: NDArray[np.bool_], truth: NDArray[np.bool_]) -> FloorScores:
    """Compare a predicted floor mask with the ground truth.

    Parameters
    ----------
    predicted, truth : (H, W) bool, True = floor.

    Returns
    -------
    FloorScores
        ``iou`` = TP / (TP + FP + FN) (1 when both are empty); ``floor_recall`` = TP / truth
        (1 when the truth has no floor); ``floor_precision`` = TP / predicted (1 when
        nothing is predicted and the truth has no floor, else 0 for an empty prediction);
        ``near_false_floor`` = fraction of the truth's non-floor pixels in the bottom 40 %
        of rows that are predicted floor.

    Examples
    --------
    >>> t = np.array([[0, 0], [1, 1]], bool)
    >>> floor_scores(np.array([[0, 1], [1, 1]], bool), t).iou
    0.6666666666666666
    """
    if predicted.shape != truth.shape:
        raise ValueError(f"predicted {predicted.shape} and truth {truth.shape} differ in size")
    if predicted.size == 0:
        raise ValueError("empty masks")
    tp = int(np.count_nonzero(predicted & truth))
    n_pred = int(np.count_nonzero(predicted))
    n_true = int(np.count_nonzero(truth))
    union = n_pred + n_true - tp
    iou = tp / union if union else 1.0
    recall = tp / n_true if n_true else 1.0
    precision = tp / n_pred if n_pred else 1.0 if n_true == 0 else 0.0
    height = truth.shape[0]
    band_start = height - round(NEAR_BAND_FRAC * height)
    near_nonfloor = ~truth[band_start:]
    n_near = int(np.count_nonzero(near_nonfloor))
    near_false = (
        int(np.count_nonzero(predicted[band_start:] & near_nonfloor)) / n_near
        if n_near
        else float("nan")
    )
    return FloorScores(iou, recall, precision, near_false)


def mean_scores(scores: list[FloorScores]) -> dict[str, float | int]:
    """Average per-image scores; ``near_false_floor`` over the images that have it.

    Returns a dict with ``iou``, ``floor_recall``, ``floor_precision``,
    ``near_false_floor`` (NaN if no image has it) and ``images``.
    """
    if not scores:
        return {
            "iou": float("nan"),
            "floor_recall": float("nan"),
            "floor_precision": float("nan"),
            "near_false_floor": float("nan"),
            "images": 0,
        }
    near = [s.near_false_floor for s in scores if not np.isnan(s.near_false_floor)]
    return {
        "iou": float(np.mean([s.iou for s in scores])),
        "floor_recall": float(np.mean([s.floor_recall for s in scores])),
        "floor_precision": float(np.mean([s.floor_precision for s in scores])),
        "near_false_floor": float(np.mean(near)) if near else float("nan"),
        "images": len(scores),
    }
