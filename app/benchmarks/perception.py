"""``floornav bench``: per-stage timings of the floor pipeline, compared in one run with
a thesis-faithful reference (scikit-image SLIC, same stages).

Timings drift between machines and minutes, so the useful figure is the ratio measured
in the same process. The run is pinned to one CPU (and OpenCV to one thread) because
the robot's pipeline gets one core per stage.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from app.benchmarks import pin_to_one_cpu
from app.config import PerceptionConfig
from app.evaluation import list_labelled_images
from app.imageio import read_bgr
from app.perception.pipeline import FloorSegmenter

BENCH_FOLDERS = (
    "robot-video-carpet",
    "robot-hand-floor",
    "hospital-ground",
    "umd-drivable-toy",
)
RESOLUTIONS = ((640, 480), (320, 240))
SUPERPIXEL_METHODS = ("floornav", "thesis", "thesis_junction")


@dataclass(frozen=True)
class StageStats:
    median_ms: float
    min_ms: float
    max_ms: float

    def as_dict(self) -> dict[str, float]:
        return {
            "median": round(self.median_ms, 3),
            "min": round(self.min_ms, 3),
            "max": round(self.max_ms, 3),
        }


def bench_images(datasets_dir: Path, limit: int = 12) -> tuple[list[NDArray[np.uint8]], str]:
    """Real images for the benchmark: the robot stills, then labelled dataset images.

    Falls back to a synthetic frame (said so in the returned source) when the shared
    datasets are absent.
    """
    images: list[NDArray[np.uint8]] = []
    carpet = datasets_dir / "robot-video-carpet"
    for still in sorted(carpet.glob("*.jpg")) if carpet.is_dir() else []:
        images.append(read_bgr(still))
    for name in BENCH_FOLDERS[1:]:
        for item in list_labelled_images(datasets_dir / name).items[::7]:
            images.append(read_bgr(item.image_path))
    if images:
        return images[:limit], f"{len(images[:limit])} real images from {datasets_dir}"
    rng = np.random.default_rng(0)
    frame = np.full((480, 640, 3), 120, np.uint8)
    frame[:200] = (200, 180, 160)
    frame += rng.integers(0, 20, frame.shape, dtype=np.uint8)
    return [frame], "synthetic frame (shared datasets not found)"


def resize_u8(image: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    resized = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return np.asarray(resized, dtype=np.uint8)


def _stats(samples: list[float]) -> StageStats:
    return StageStats(statistics.median(samples), min(samples), max(samples))


def time_pipeline(
    segmenter: FloorSegmenter, frames: list[NDArray[np.uint8]], repeats: int
) -> dict[str, StageStats]:
    """Segment every frame ``repeats`` times after one warm-up pass; stats per stage."""
    for frame in frames:
        segmenter.segment(frame)
    samples: dict[str, list[float]] = {}
    for _ in range(repeats):
        for frame in frames:
            for stage, ms in segmenter.segment(frame).timings_ms.items():
                samples.setdefault(stage, []).append(ms)
    return {stage: _stats(values) for stage, values in samples.items()}


def run_bench(
    config: PerceptionConfig,
    datasets_dir: Path,
    *,
    repeats: int = 5,
    reference_repeats: int = 1,
) -> dict[str, object]:
    """Benchmark the configured pipeline and the reference; the ``--json`` object."""
    pinned = pin_to_one_cpu()
    images, source = bench_images(datasets_dir)
    result: dict[str, object] = {"images": source, "pinned": pinned, "method": config.method}
    resolutions: dict[str, object] = {}
    for width, height in RESOLUTIONS:
        frames = [resize_u8(im, width, height) for im in images]
        stats = time_pipeline(FloorSegmenter(config), frames, repeats)
        total = stats.pop("total")
        resolutions[f"{width}x{height}"] = {
            "stages_ms": {stage: s.as_dict() for stage, s in stats.items()},
            "total_ms": round(total.median_ms, 3),
            "total_min_ms": round(total.min_ms, 3),
            "total_max_ms": round(total.max_ms, 3),
            "frames": len(frames) * repeats,
        }
    result["resolutions"] = resolutions
    # The reference is the thesis-faithful superpixel pipeline: scikit-image SLIC with the
    # same stages, or, for a method without superpixels, the floornav stages.
    reference_method = config.method if config.method in SUPERPIXEL_METHODS else "floornav"
    reference_config = config.model_copy(
        update={"slic_backend": "skimage", "method": reference_method}
    )
    frames = [resize_u8(im, 640, 480) for im in images]
    ref = time_pipeline(FloorSegmenter(reference_config), frames, reference_repeats)
    ref_total = ref.pop("total")
    default_total = resolutions["640x480"]
    assert isinstance(default_total, dict)
    result["reference"] = {
        "640x480": {
            "total_ms": round(ref_total.median_ms, 3),
            "stages_ms": {stage: s.as_dict() for stage, s in ref.items()},
            "slic_backend": "skimage",
            "method": reference_method,
        }
    }
    result["speedup_vs_reference_640x480"] = round(
        ref_total.median_ms / default_total["total_ms"], 2
    )
    return result


def format_bench(result: dict[str, object]) -> str:
    lines = [f"images: {result['images']}; {result['pinned']}; method {result['method']}"]
    resolutions = result["resolutions"]
    assert isinstance(resolutions, dict)
    for name, res in resolutions.items():
        lines.append(f"\n== {name}   (median / min / max ms over {res['frames']} frames)")
        for stage, s in res["stages_ms"].items():
            lines.append(f"  {stage:<12}{s['median']:>9.2f}{s['min']:>9.2f}{s['max']:>9.2f}")
        lines.append(f"  {'total':<12}{res['total_ms']:>9.2f}")
    reference = result["reference"]
    assert isinstance(reference, dict)
    ref = reference["640x480"]
    lines.append(
        f"\n== reference 640x480 ({ref['method']} with skimage slic): {ref['total_ms']:.1f} ms"
    )
    lines.append(f"speed-up of {result['method']}: {result['speedup_vs_reference_640x480']}x")
    return "\n".join(lines)
