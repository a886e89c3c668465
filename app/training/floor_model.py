"""Fitting the ``floornav`` method's two logistic weight vectors (numpy only).

Targets: a superpixel is floor when more than half of its grid cells are floor in the
mask. Every image weighs the same (superpixel weight = its share of the image). Pass-2
weights are fitted on pass-2 cues whose first-pass logits come from a pass-1 model that
never saw that image's scene (nested, in 5 inner folds of whole scenes), so they see
first-pass errors as they happen on new images. Used by ``scripts/train_floor_model.py``
and ``floornav eval --cv``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.config import PerceptionConfig
from app.perception.floor_model import (
    GridStats,
    first_pass_cues,
    free_space_cells,
    grid_stats,
    grid_to_image,
    second_pass_cues,
)
from app.perception.logistic import fit_logistic_regression
from app.perception.pipeline import FloorSegmenter, _Stopwatch
from app.scenes import scene_folds

INNER_FOLDS = 5


@dataclass
class FloorModelSample:
    """One labelled image, reduced to what the logistic fits need."""

    scene: str
    stats: GridStats
    cues1: NDArray[np.float64]
    target: NDArray[np.float64]
    weight: NDArray[np.float64]
    shape: tuple[int, int]


def make_sample(
    scene: str, frame: NDArray[np.uint8], truth: NDArray[np.bool_], config: PerceptionConfig
) -> FloorModelSample:
    segmenter = FloorSegmenter(config, method="floornav")
    front = segmenter.superpixels(frame, _Stopwatch())
    stats = grid_stats(frame, front.color, front.labels, front.zone_mask)
    step = max(1, round(frame.shape[1] / stats.shape[1]))
    grid_truth = truth[::step, ::step][: stats.shape[0], : stats.shape[1]]
    floor_frac = stats.mean_of(grid_truth.astype(np.float64))
    return FloorModelSample(
        scene=scene,
        stats=stats,
        cues1=first_pass_cues(stats),
        target=(floor_frac > 0.5).astype(np.float64),
        weight=stats.count / stats.count.sum(),
        shape=(int(truth.shape[0]), int(truth.shape[1])),
    )


def _fit(samples: list[FloorModelSample], cues: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    return fit_logistic_regression(
        np.concatenate(cues),
        np.concatenate([s.target for s in samples]),
        np.concatenate([s.weight for s in samples]),
    )


class FloorModelTrainer:
    """Fits (pass-1, pass-2) weights on all samples outside a set of scenes."""

    def __init__(self, samples: list[FloorModelSample]) -> None:
        self.samples = samples
        self._pass1: dict[frozenset[str], NDArray[np.float64]] = {}

    def pass1(self, excluded: frozenset[str]) -> NDArray[np.float64]:
        if excluded not in self._pass1:
            train = [s for s in self.samples if s.scene not in excluded]
            self._pass1[excluded] = _fit(train, [s.cues1 for s in train])
        return self._pass1[excluded]

    def train(self, excluded: frozenset[str]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        train = [s for s in self.samples if s.scene not in excluded]
        # Pass-2 cues of a training image come from a pass-1 model fitted without its
        # scene: inner folds of whole scenes (one fit per inner fold, not per scene).
        inner = scene_folds([s.scene for s in train], INNER_FOLDS)
        fold_of = {scene: frozenset(fold) for fold in inner for scene in fold}
        cues2 = [
            second_pass_cues(s.stats, s.cues1 @ self.pass1(excluded | fold_of[s.scene]))
            for s in train
        ]
        return self.pass1(excluded), _fit(train, cues2)


def predict(
    sample: FloorModelSample, w1: NDArray[np.float64], w2: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """The floornav mask at image size with the given weights."""
    logits = second_pass_cues(sample.stats, sample.cues1 @ w1) @ w2
    grid_floor, _ = free_space_cells(sample.stats, logits)
    return grid_to_image(grid_floor, sample.shape)
