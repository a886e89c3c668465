"""Fit the floornav floor model's two logistic weight vectors on the labelled dev images
and (optionally) measure the whole method by nested cross-validation.

    .venv/bin/python scripts/train_floor_model.py [--cv] [--write] [--datasets DIR]

Targets: a superpixel is floor when more than half of its grid cells are floor in the
mask. Every image weighs the same (superpixel weight = its share of the image).
Pass-2 weights are fitted on pass-2 cues whose first-pass logits come from a pass-1
model that never saw that image's group (nested), so they see first-pass errors as they
happen on new images.

Groups: robot-hand-floor by video sequence (frames of one sequence never straddle
training and test), hospital-ground in 4 interleaved folds (unrelated stills),
umd-drivable-toy as one group. ``--cv`` prints leave-one-group-out (LOSO) and
leave-one-dataset-out (LODO; umd joins hospital) scores, fully nested.
``--write`` regenerates app/perception/floor_weights.py from all dev images.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.config import PerceptionConfig  # noqa: E402
from app.evaluation import list_labelled_images  # noqa: E402
from app.imageio import read_bgr, read_mask  # noqa: E402
from app.perception.floor_model import (  # noqa: E402
    CUE_NAMES,
    GridStats,
    first_pass_cues,
    free_space_cells,
    grid_stats,
    grid_to_image,
    second_pass_cues,
)
from app.perception.logistic import fit_logistic_regression  # noqa: E402
from app.perception.metrics import floor_scores, mean_scores  # noqa: E402
from app.perception.pipeline import FloorSegmenter, _Stopwatch  # noqa: E402

DATASETS = ("robot-hand-floor", "hospital-ground", "umd-drivable-toy")
WEIGHTS_FILE = ROOT / "app" / "perception" / "floor_weights.py"


@dataclass
class Sample:
    dataset: str
    name: str
    group: str
    domain: str
    stats: GridStats
    cues1: NDArray[np.float64]
    target: NDArray[np.float64]
    weight: NDArray[np.float64]
    truth: NDArray[np.bool_]


def load_samples(datasets_dir: Path) -> list[Sample]:
    segmenter = FloorSegmenter(PerceptionConfig(), method="floornav")
    samples = []
    for dataset in DATASETS:
        items = list_labelled_images(datasets_dir / dataset).items
        for index, item in enumerate(items):
            name = item.image_path.stem
            if dataset == "robot-hand-floor":
                group = "rh:" + name.split("robot_hand_")[1].rsplit("_f", 1)[0]
            elif dataset == "hospital-ground":
                group = f"hg{index % 4}"
            else:
                group = dataset
            frame = read_bgr(item.image_path)
            truth = read_mask(item.mask_path, frame.shape[:2])
            front = segmenter.superpixels(frame, _Stopwatch())
            stats = grid_stats(frame, front.color, front.labels, front.zone_mask)
            step = frame.shape[1] // stats.shape[1] if stats.shape[1] else 1
            step = max(1, round(frame.shape[1] / stats.shape[1]))
            grid_truth = truth[::step, ::step][: stats.shape[0], : stats.shape[1]]
            floor_frac = stats.mean_of(grid_truth.astype(np.float64))
            samples.append(
                Sample(
                    dataset=dataset,
                    name=name,
                    group=group,
                    domain="robot-hand-floor" if dataset == "robot-hand-floor" else "other",
                    stats=stats,
                    cues1=first_pass_cues(stats),
                    target=(floor_frac > 0.5).astype(np.float64),
                    weight=stats.count / stats.count.sum(),
                    truth=truth,
                )
            )
        print(f"loaded {dataset}: {len(items)} images", file=sys.stderr)
    return samples


def fit(samples: list[Sample], cues: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    return fit_logistic_regression(
        np.concatenate(cues),
        np.concatenate([s.target for s in samples]),
        np.concatenate([s.weight for s in samples]),
    )


class Trainer:
    """Fits (pass-1, pass-2) weights on all samples outside a set of groups."""

    def __init__(self, samples: list[Sample]) -> None:
        self.samples = samples
        self._pass1: dict[frozenset[str], NDArray[np.float64]] = {}

    def pass1(self, excluded: frozenset[str]) -> NDArray[np.float64]:
        if excluded not in self._pass1:
            train = [s for s in self.samples if s.group not in excluded]
            self._pass1[excluded] = fit(train, [s.cues1 for s in train])
        return self._pass1[excluded]

    def train(self, excluded: frozenset[str]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        train = [s for s in self.samples if s.group not in excluded]
        cues2 = [
            second_pass_cues(s.stats, s.cues1 @ self.pass1(excluded | {s.group})) for s in train
        ]
        return self.pass1(excluded), fit(train, cues2)


def predict(sample: Sample, w1: NDArray[np.float64], w2: NDArray[np.float64]) -> NDArray[np.bool_]:
    logits = second_pass_cues(sample.stats, sample.cues1 @ w1) @ w2
    grid_floor, _ = free_space_cells(sample.stats, logits)
    return grid_to_image(grid_floor, sample.truth.shape)


def cross_validate(trainer: Trainer, key: str) -> None:
    folds = sorted({getattr(s, key) for s in trainer.samples})
    scores: dict[str, list[object]] = {d: [] for d in DATASETS}
    for fold in folds:
        test = [s for s in trainer.samples if getattr(s, key) == fold]
        w1, w2 = trainer.train(frozenset(s.group for s in test))
        for s in test:
            scores[s.dataset].append(floor_scores(predict(s, w1, w2), s.truth))
    title = "leave-one-group-out" if key == "group" else "leave-one-dataset-out"
    print(f"\n{title} ({len(folds)} folds), nested")
    print(f"{'dataset':<18}{'iou':>8}{'recall':>9}{'precision':>11}{'near_FF':>9}{'images':>8}")
    every = [s for d in DATASETS for s in scores[d]]
    for name, rows in [*scores.items(), ("all", every)]:
        m = mean_scores(rows)  # type: ignore[arg-type]
        print(
            f"{name:<18}{m['iou']:>8.3f}{m['floor_recall']:>9.3f}"
            f"{m['floor_precision']:>11.3f}{m['near_false_floor']:>9.3f}{m['images']:>8d}"
        )


def write_weights(w1: NDArray[np.float64], w2: NDArray[np.float64], n_images: int) -> None:
    def fmt(w: NDArray[np.float64]) -> str:
        rows = [f"        {v: .6f},  # {name}" for v, name in zip(w, CUE_NAMES, strict=True)]
        return "np.array(\n    [\n" + "\n".join(rows) + "\n    ]\n)"

    text = f'''"""Logistic weights of the floornav floor model, one per cue in
`app.perception.floor_model.CUE_NAMES` order.

Generated by ``scripts/train_floor_model.py --write`` from {n_images} labelled dev images
(robot-hand-floor, hospital-ground, umd-drivable-toy); do not edit by hand.
"""

import numpy as np

FIRST_PASS_WEIGHTS = {fmt(w1)}

SECOND_PASS_WEIGHTS = {fmt(w2)}
'''
    text = re.sub(r"\n{3,}", "\n\n\n", text)
    WEIGHTS_FILE.write_text(text)
    print(f"wrote {WEIGHTS_FILE}", file=sys.stderr)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--datasets", type=Path, default=ROOT.parent / "shared" / "datasets")
    parser.add_argument("--cv", action="store_true", help="print nested LOSO and LODO scores")
    parser.add_argument("--write", action="store_true", help="regenerate the weights module")
    args = parser.parse_args()
    samples = load_samples(args.datasets)
    if not samples:
        print(f"no labelled images under {args.datasets}", file=sys.stderr)
        return 1
    trainer = Trainer(samples)
    w1, w2 = trainer.train(frozenset())
    np.set_printoptions(precision=4, suppress=True)
    print("first pass: ", w1)
    print("second pass:", w2)
    if args.write:
        write_weights(w1, w2, len(samples))
    if args.cv:
        cross_validate(trainer, "group")
        cross_validate(trainer, "domain")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
