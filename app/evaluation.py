"""``floornav eval``: accuracy of segmentation methods on folders of labelled images.

A labelled image is ``NAME.jpg`` (or .jpeg/.png) with ``NAME_floor.png`` beside it
(8-bit, 255 = floor). Files that cannot be used are skipped with their reason; the run
goes on.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.config import FloornavConfig, PerceptionConfig
from app.imageio import read_bgr, read_mask
from app.perception.image_checks import ImageError
from app.perception.metrics import FloorScores, floor_scores, mean_scores
from app.perception.pipeline import METHODS, FloorSegmenter

MASK_SUFFIX = "_floor.png"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class LabelledImage:
    image_path: Path
    mask_path: Path


@dataclass
class DatasetListing:
    """Labelled images found in a folder, and files skipped with the reason."""

    folder: Path
    items: list[LabelledImage] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)


def list_labelled_images(folder: Path) -> DatasetListing:
    """Pair every image in ``folder`` with its ``_floor.png`` mask (sorted by name)."""
    listing = DatasetListing(folder)
    if not folder.is_dir():
        listing.skipped.append((folder, "not a folder"))
        return listing
    for path in sorted(folder.iterdir()):
        if path.name.endswith(MASK_SUFFIX) or path.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        mask_path = path.with_name(path.stem + MASK_SUFFIX)
        if mask_path.is_file():
            listing.items.append(LabelledImage(path, mask_path))
        else:
            listing.skipped.append((path, f"no mask {mask_path.name}"))
    return listing


@dataclass
class EvalReport:
    """Scores per folder and method, and what was skipped."""

    methods: list[str]
    per_dataset: dict[str, dict[str, list[FloorScores]]] = field(default_factory=dict)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def summary(self, default_method: str) -> dict[str, object]:
        """The JSON object of ``floornav eval --json``."""
        overall: dict[str, list[FloorScores]] = {m: [] for m in self.methods}
        datasets: dict[str, dict[str, dict[str, float | int]]] = {}
        for name, by_method in self.per_dataset.items():
            datasets[name] = {m: mean_scores(scores) for m, scores in by_method.items()}
            for method, scores in by_method.items():
                overall[method].extend(scores)
        return {
            "default_method": default_method,
            "methods": {m: mean_scores(scores) for m, scores in overall.items()},
            "datasets": datasets,
            "skipped": [{"file": f, "reason": r} for f, r in self.skipped],
        }


ProgressFn = Callable[[int, int, str], None]


def progress_printer(command: str, unit: str, every: int) -> ProgressFn:
    """A one-line progress bar on stderr; when not a TTY, a plain line every ``every``
    items (``eval: 25/121 images``)."""

    def show(done: int, total: int, label: str) -> None:
        if sys.stderr.isatty():
            width = 30
            filled = width * done // max(total, 1)
            bar = "#" * filled + "-" * (width - filled)
            end = "\n" if done == total else ""
            sys.stderr.write(f"\r[{bar}] {done}/{total} {label[:40]:<40}{end}")
            sys.stderr.flush()
        elif done == total or done % every == 0:
            sys.stderr.write(f"{command}: {done}/{total} {unit}\n")

    return show


stderr_progress = progress_printer("eval", "images", 25)


def evaluate(
    folders: Iterable[Path],
    methods: list[str],
    config: PerceptionConfig,
    *,
    progress: ProgressFn | None = None,
) -> EvalReport:
    """Run each method on each labelled image and score it against its mask."""
    for method in methods:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    report = EvalReport(methods=list(methods))
    segmenters = {m: FloorSegmenter(config, method=m) for m in methods}
    listings = [list_labelled_images(Path(f)) for f in folders]
    total = sum(len(listing.items) for listing in listings)
    done = 0
    for listing in listings:
        name = listing.folder.resolve().name
        by_method = report.per_dataset.setdefault(name, {m: [] for m in methods})
        report.skipped.extend((str(p), reason) for p, reason in listing.skipped)
        for item in listing.items:
            try:
                image = read_bgr(item.image_path)
                truth = read_mask(item.mask_path, image.shape[:2])
                for method, segmenter in segmenters.items():
                    result = segmenter.segment(image)
                    by_method[method].append(floor_scores(result.floor_mask, truth))
            except (ImageError, ValueError) as exc:
                report.skipped.append((str(item.image_path), str(exc)))
            done += 1
            if progress is not None:
                progress(done, total, item.image_path.name)
    return report


def score_table_lines(table: dict[str, dict[str, float | int]]) -> list[str]:
    """A header and one row per method of `mean_scores` dicts (``-`` for no images)."""
    lines = [f"{'method':<18}{'iou':>8}{'recall':>9}{'precision':>11}{'near_FF':>9}{'images':>8}"]
    for method, s in table.items():
        if not s.get("images"):
            lines.append(f"{method:<18}{'-':>8}{'-':>9}{'-':>11}{'-':>9}{0:>8d}")
            continue
        lines.append(
            f"{method:<18}{s['iou']:>8.3f}{s['floor_recall']:>9.3f}"
            f"{s['floor_precision']:>11.3f}{s['near_false_floor']:>9.3f}{s['images']:>8d}"
        )
    return lines


def format_table(summary: dict[str, object]) -> str:
    """Human-readable tables: one per dataset, one row per method, then all datasets."""
    lines: list[str] = []

    def rows(table: dict[str, dict[str, float | int]]) -> None:
        lines.extend(score_table_lines(table))

    datasets = summary["datasets"]
    assert isinstance(datasets, dict)
    for name, table in datasets.items():
        lines.append(f"\n== {name}")
        rows(table)
    methods = summary["methods"]
    assert isinstance(methods, dict)
    lines.append(f"\n== all datasets (default method: {summary['default_method']})")
    rows(methods)
    skipped = summary["skipped"]
    assert isinstance(skipped, list)
    if skipped:
        lines.append(f"\nskipped {len(skipped)} file(s):")
        lines.extend(f"  {s['file']}: {s['reason']}" for s in skipped)
    return "\n".join(lines)


def evaluate_superpixels(
    folders: Iterable[Path],
    config: PerceptionConfig,
    *,
    backends: tuple[str, ...] = ("numba", "skimage"),
    progress: ProgressFn | None = None,
) -> dict[str, object]:
    """Boundary recall (2 px) and undersegmentation error of each SLIC backend against
    the floor masks, on the same smoothed colour image, with their SLIC times.

    Returns ``{"datasets": {FOLDER: {BACKEND: {...}}}, "all": {BACKEND: {...}}}`` where
    each entry has ``boundary_recall``, ``undersegmentation_error``, ``segments``,
    ``slic_ms_median`` and ``images``.
    """
    import time

    from app.perception.preprocess import smooth, to_color_space
    from app.perception.slic import slic_superpixels
    from app.perception.superpixel_quality import boundary_recall, undersegmentation_error

    rows: dict[str, dict[str, list[tuple[float, float, int, float]]]] = {}
    listings = [list_labelled_images(Path(f)) for f in folders]
    total = sum(len(listing.items) for listing in listings)
    done = 0
    for listing in listings:
        per_backend = rows.setdefault(listing.folder.resolve().name, {b: [] for b in backends})
        for item in listing.items:
            try:
                image = read_bgr(item.image_path)
                truth = read_mask(item.mask_path, image.shape[:2])
            except ImageError:
                continue
            color = to_color_space(
                smooth(image, sigma_px=config.smoothing_sigma_px), space=config.color_space
            )
            for backend in backends:
                start = time.perf_counter()
                labels = slic_superpixels(
                    color,
                    n_segments=config.n_superpixels,
                    compactness=config.compactness,
                    max_iter=config.slic_max_iter,
                    backend=backend,  # type: ignore[arg-type]
                )
                elapsed_ms = (time.perf_counter() - start) * 1e3
                per_backend[backend].append(
                    (
                        boundary_recall(labels, truth),
                        undersegmentation_error(labels, truth),
                        int(labels.max()) + 1,
                        elapsed_ms,
                    )
                )
            done += 1
            if progress is not None:
                progress(done, total, item.image_path.name)

    def summarise(values: list[tuple[float, float, int, float]]) -> dict[str, float | int]:
        if not values:
            return {"images": 0}
        array = np.array(values, dtype=np.float64)
        return {
            "boundary_recall": float(np.nanmean(array[:, 0])),
            "undersegmentation_error": float(np.mean(array[:, 1])),
            "segments": float(np.mean(array[:, 2])),
            "slic_ms_median": float(np.median(array[:, 3])),
            "images": len(values),
        }

    every: dict[str, list[tuple[float, float, int, float]]] = {b: [] for b in backends}
    for per_backend in rows.values():
        for backend, values in per_backend.items():
            every[backend].extend(values)
    return {
        "datasets": {
            name: {b: summarise(v) for b, v in per_backend.items()}
            for name, per_backend in rows.items()
        },
        "all": {b: summarise(v) for b, v in every.items()},
    }


def format_superpixel_table(summary: dict[str, object]) -> str:
    lines = []
    header = f"{'backend':<10}{'recall@2px':>12}{'underseg':>10}{'segments':>10}{'slic ms':>9}"
    datasets = summary["datasets"]
    assert isinstance(datasets, dict)
    tables = [*datasets.items(), ("all datasets", summary["all"])]
    for name, table in tables:
        lines.append(f"\n== {name}")
        lines.append(header)
        for backend, s in table.items():
            if not s.get("images"):
                continue
            lines.append(
                f"{backend:<10}{s['boundary_recall']:>12.4f}{s['undersegmentation_error']:>10.4f}"
                f"{s['segments']:>10.1f}{s['slic_ms_median']:>9.1f}"
            )
    return "\n".join(lines)


def evaluate_on_simulator(
    config: FloornavConfig, methods: list[str], *, frames: int = 30
) -> dict[str, object]:
    """Floor masks of each method on simulated frames vs the renderer's ground truth.

    The robot follows the benchmark path through the default world (at least 0.3 m from
    every obstacle). Returns ``{"frames": n, "world": name, "methods": {NAME: scores}}``.
    """
    from app.benchmarks.sim import bench_poses
    from app.sim.setup import renderer_from_config

    for method in methods:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    renderer = renderer_from_config(config)
    segmenters = {m: FloorSegmenter(config.perception, method=m) for m in methods}
    scores: dict[str, list[FloorScores]] = {m: [] for m in methods}
    for pose in bench_poses(frames):
        rendered = renderer.render(pose)
        for method, segmenter in segmenters.items():
            mask = segmenter.segment(rendered.image).floor_mask
            scores[method].append(floor_scores(mask, rendered.floor_mask))
    return {
        "frames": frames,
        "world": renderer.world.name,
        "methods": {m: mean_scores(s) for m, s in scores.items()},
    }
