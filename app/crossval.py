"""``floornav eval --cv``: out-of-scene accuracy of every method, by cross-validation.

Each fold holds out whole scenes (`app.scenes`): frames of one video or photos of one
place are never split between fitting and scoring. Whatever a method fits from labelled
images is fitted again in every fold on the other scenes only:

- ``floornet``: the network is trained from scratch (needs the ``train`` extra).
- ``floornav``: both logistic weight vectors, nested as in ``scripts/train_floor_model.py``.
- ``flood_fill``: the colour tolerance, chosen from `FLOOD_FILL_TOLERANCES` by the mean
  IoU on the fold's training scenes.
- ``thesis``, ``thesis_junction``: nothing is fitted; their constants are the thesis's.

Scores are also split by whether the thesis's premise holds: the share of the safe zone
that is floor in the ground truth (``premise_holds``: >= 0.8, ``premise_broken``: < 0.8,
``zone_mostly_not_floor``: < 0.5), since a robot in front of a chair meets the second.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.config import PerceptionConfig
from app.evaluation import list_labelled_images, score_table_lines
from app.imageio import read_bgr, read_mask
from app.perception.image_checks import ImageError
from app.perception.metrics import FloorScores, floor_scores, mean_scores
from app.perception.pipeline import METHODS, FloorSegmenter
from app.scenes import scene_folds, scene_of

FLOOD_FILL_TOLERANCES = (8.0, 12.0, 18.0, 24.0, 32.0)
PREMISE_HOLDS_MIN = 0.8
ZONE_MOSTLY_NOT_FLOOR_BELOW = 0.5


@dataclass(frozen=True)
class CvImage:
    dataset: str
    scene: str
    name: str
    image: NDArray[np.uint8]
    truth: NDArray[np.bool_]
    zone_floor_share: float
    """Share of the safe zone that is floor in the ground truth."""


Predictor = Callable[[CvImage], NDArray[np.bool_]]
Fitter = Callable[[list[CvImage], list[CvImage]], Predictor]
"""``fit(train, test) -> predict``; ``test`` is passed only so a fitter can precompute
fold-independent work for those images; it must never look at their masks."""
ProgressFn = Callable[[str], None]


def load_images(
    folders: Iterable[Path], config: PerceptionConfig
) -> tuple[list[CvImage], list[tuple[str, str]]]:
    """Every labelled image of the folders with its scene; unreadable ones are skipped."""
    zone_segmenter = FloorSegmenter(config, method="flood_fill")
    images: list[CvImage] = []
    skipped: list[tuple[str, str]] = []
    for folder in folders:
        listing = list_labelled_images(Path(folder))
        dataset = listing.folder.resolve().name
        skipped.extend((str(p), reason) for p, reason in listing.skipped)
        for item in listing.items:
            try:
                image = read_bgr(item.image_path)
                truth = read_mask(item.mask_path, image.shape[:2])
            except (ImageError, ValueError) as exc:
                skipped.append((str(item.image_path), str(exc)))
                continue
            zone = zone_segmenter.zone_mask(image.shape[:2])
            stem = item.image_path.stem
            images.append(
                CvImage(
                    dataset=dataset,
                    scene=scene_of(dataset, stem),
                    name=stem,
                    image=image,
                    truth=truth,
                    zone_floor_share=float(truth[zone].mean()),
                )
            )
    return images, skipped


def _fixed(method: str, config: PerceptionConfig) -> Fitter:
    segmenter = FloorSegmenter(config, method=method)
    cache: dict[int, NDArray[np.bool_]] = {}

    def predict(item: CvImage) -> NDArray[np.bool_]:
        key = id(item)
        if key not in cache:
            cache[key] = segmenter.segment(item.image).floor_mask
        return cache[key]

    def fit(train: list[CvImage], test: list[CvImage]) -> Predictor:
        return predict

    return fit


def _flood_fill(config: PerceptionConfig) -> Fitter:
    segmenters = {
        t: FloorSegmenter(
            config.model_copy(update={"flood_fill_tolerance": t}), method="flood_fill"
        )
        for t in FLOOD_FILL_TOLERANCES
    }
    masks: dict[tuple[int, float], NDArray[np.bool_]] = {}
    ious: dict[tuple[int, float], float] = {}

    def mask(item: CvImage, tolerance: float) -> NDArray[np.bool_]:
        key = (id(item), tolerance)
        if key not in masks:
            masks[key] = segmenters[tolerance].segment(item.image).floor_mask
        return masks[key]

    def iou(item: CvImage, tolerance: float) -> float:
        key = (id(item), tolerance)
        if key not in ious:
            ious[key] = floor_scores(mask(item, tolerance), item.truth).iou
        return ious[key]

    def fit(train: list[CvImage], test: list[CvImage]) -> Predictor:
        best = max(FLOOD_FILL_TOLERANCES, key=lambda t: np.mean([iou(i, t) for i in train]))
        return lambda item: mask(item, best)

    return fit


def _floornav(config: PerceptionConfig, images: list[CvImage]) -> Fitter:
    from app.training.floor_model import FloorModelTrainer, make_sample, predict

    samples = {id(i): make_sample(i.scene, i.image, i.truth, config) for i in images}
    trainer = FloorModelTrainer(list(samples.values()))

    def fit(train: list[CvImage], test: list[CvImage]) -> Predictor:
        held_out = frozenset(i.scene for i in test)
        w1, w2 = trainer.train(held_out)
        return lambda item: predict(samples[id(item)], w1, w2)

    return fit


def _floornet(config: PerceptionConfig, progress: ProgressFn | None) -> Fitter:
    from app.perception.floor_net import (
        OUTPUT_HEIGHT_PX,
        OUTPUT_WIDTH_PX,
        FloorNetOutput,
        floor_mask,
    )
    from app.perception.pipeline import trapezoid_from_config
    from app.perception.safe_zone import safe_zone_mask
    from app.training.floor_net import predict_probability, prepare, train

    zone = trapezoid_from_config(config.safe_zone)
    zone_out = safe_zone_mask((OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX), zone)
    prepared: dict[int, object] = {}

    def fit(train_images: list[CvImage], test: list[CvImage]) -> Predictor:
        for item in train_images:
            if id(item) not in prepared:
                prepared[id(item)] = prepare(item.image, item.truth)
        data = [prepared[id(i)] for i in train_images]

        def report(epoch: int, loss: float) -> None:
            if progress is not None and epoch % 10 == 0:
                progress(f"floornet epoch {epoch}, loss {loss:.3f}")

        model = train(data, zone, progress=report)  # type: ignore[arg-type]

        def predict(item: CvImage) -> NDArray[np.bool_]:
            # The same post-processing as the segmenter's (`floor_mask`).
            probability = predict_probability(model, item.image, zone)
            output = FloorNetOutput(probability, float(probability[zone_out].mean()))
            return floor_mask(
                output,
                safe_zone_mask(item.truth.shape, zone),
                min_zone_confidence=config.zone_min_floor_confidence,
            )

        return predict

    return fit


def make_fitter(
    method: str, config: PerceptionConfig, images: list[CvImage], progress: ProgressFn | None
) -> Fitter:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    if method == "floornet":
        return _floornet(config, progress)
    if method == "floornav":
        return _floornav(config, images)
    if method == "flood_fill":
        return _flood_fill(config)
    return _fixed(method, config)


def cross_validate(
    folders: Iterable[Path],
    methods: list[str],
    config: PerceptionConfig,
    *,
    n_folds: int | None = None,
    progress: ProgressFn | None = None,
) -> dict[str, object]:
    """Out-of-scene scores per dataset, method and premise subset (the JSON of
    ``floornav eval --cv --json``). ``n_folds=None`` leaves one scene out at a time."""
    images, skipped = load_images(folders, config)
    if not images:
        raise ValueError("no labelled image could be read")
    folds = scene_folds([i.scene for i in images], n_folds)
    per_image: dict[str, list[tuple[CvImage, FloorScores]]] = {m: [] for m in methods}
    for method in methods:
        fitter = make_fitter(method, config, images, progress)
        for index, fold in enumerate(folds):
            held_out = set(fold)
            test = [i for i in images if i.scene in held_out]
            train = [i for i in images if i.scene not in held_out]
            predict = fitter(train, test)
            for item in test:
                per_image[method].append((item, floor_scores(predict(item), item.truth)))
            if progress is not None:
                progress(f"{method}: fold {index + 1}/{len(folds)} ({', '.join(fold)[:60]})")

    def table(keep: Callable[[CvImage], bool]) -> dict[str, dict[str, float | int]]:
        return {
            m: mean_scores([s for item, s in rows if keep(item)]) for m, rows in per_image.items()
        }

    datasets = sorted({i.dataset for i in images})
    return {
        "cv": {
            "scheme": "leave-one-scene-out"
            if n_folds is None
            else f"{len(folds)} folds of whole scenes",
            "folds": len(folds),
            "scenes": len({i.scene for i in images}),
            "images": len(images),
        },
        "methods": table(lambda item: True),
        "datasets": {d: table(lambda item, d=d: item.dataset == d) for d in datasets},  # type: ignore[misc]
        "premise": {
            "premise_holds": table(lambda item: item.zone_floor_share >= PREMISE_HOLDS_MIN),
            "premise_broken": table(lambda item: item.zone_floor_share < PREMISE_HOLDS_MIN),
            "zone_mostly_not_floor": table(
                lambda item: item.zone_floor_share < ZONE_MOSTLY_NOT_FLOOR_BELOW
            ),
        },
        "per_image": {
            m: [
                {"dataset": i.dataset, "scene": i.scene, "name": i.name, **s.as_dict()}
                for i, s in rows
            ]
            for m, rows in per_image.items()
        },
        "skipped": [{"file": f, "reason": r} for f, r in skipped],
    }


def format_cv_table(summary: dict[str, object]) -> str:
    """Human-readable tables: per dataset, all datasets, and by premise."""
    lines: list[str] = []
    cv = summary["cv"]
    assert isinstance(cv, dict)
    lines.append(
        f"cross-validation: {cv['scheme']} ({cv['folds']} folds, {cv['scenes']} scenes, "
        f"{cv['images']} images); every score is on scenes the method was not fitted on"
    )

    def rows(title: str, table: dict[str, dict[str, float | int]]) -> None:
        lines.append(f"\n== {title}")
        lines.extend(score_table_lines(table))

    datasets = summary["datasets"]
    assert isinstance(datasets, dict)
    for name, table in datasets.items():
        rows(name, table)
    methods = summary["methods"]
    assert isinstance(methods, dict)
    rows("all datasets", methods)
    premise = summary["premise"]
    assert isinstance(premise, dict)
    for name, table in premise.items():
        rows(name.replace("_", " "), table)
    return "\n".join(lines)


def stderr_progress(message: str) -> None:
    sys.stderr.write(f"eval --cv: {message}\n")
    sys.stderr.flush()
