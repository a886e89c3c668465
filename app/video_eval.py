"""``floornav eval-video``: label-free checks of segmentation methods on recorded video.

Without labels a video still shows three things per method:

``consecutive_iou_mean`` / ``consecutive_iou_p05``
    IoU of the floor masks of consecutive processed frames (two empty masks: 1). The
    robot moves a few millimetres between frames, so the mask should barely change: a
    hole that flickers in and out is a phantom obstacle for the map. p05 is the worst
    flicker (5th percentile over frame pairs). With ``stride`` N the pairs are N frames
    apart, so more motion lowers the IoU: compare methods at the same stride.
``bottom_half_floor_fraction_mean``
    Mean over frames of the fraction of rows >= H/2 called floor. A method that is stable
    because it finds no floor scores IoU 1; this one catches it. What it should be
    depends on the video (on the carpet video the carpet fills the bottom half of nearly
    every frame).
``ms_per_frame_median`` / ``ms_per_frame_p95``
    Wall time of `FloorSegmenter.segment` only (no decoding).

One `FloorSegmenter` per (video, method) is fed the frames in order, so a segmenter that
keeps state across frames is measured as the daemon would run it. Videos that cannot be
used are skipped with the reason; the run goes on.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import PerceptionConfig
from app.evaluation import progress_printer
from app.perception.overlay import draw_overlay
from app.perception.pipeline import METHODS, FloorSegmenter

ProgressFn = Callable[[int, int, str], None]


class VideoError(ValueError):
    """A video file is missing, cannot be opened or has no decodable frame."""


def mask_iou(a: NDArray[np.bool_], b: NDArray[np.bool_]) -> float:
    """IoU of two boolean masks of the same shape; 1.0 when both are empty."""
    if a.shape != b.shape:
        raise ValueError(f"mask shapes differ: {a.shape} and {b.shape}")
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(a & b)) / union


def bottom_half_floor_fraction(mask: NDArray[np.bool_]) -> float:
    """Fraction of the pixels in rows >= H/2 that are floor."""
    bottom = mask[(mask.shape[0] + 1) // 2 :]
    return float(bottom.mean()) if bottom.size else float("nan")


def _open(path: Path) -> cv2.VideoCapture:
    if not path.is_file():
        raise VideoError(f"{path}: no such file")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise VideoError(f"{path}: not a readable video (OpenCV cannot open it)")
    return capture


def video_info(path: Path) -> dict[str, float | int]:
    """Width, height, fps and the container's frame count (may be approximate)."""
    capture = _open(path)
    try:
        return {
            "width": int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": float(capture.get(cv2.CAP_PROP_FPS)),
            "frame_count": max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT))),
        }
    finally:
        capture.release()


def read_frames(
    path: Path, *, stride: int = 1, max_frames: int | None = None
) -> Iterator[tuple[int, NDArray[np.uint8]]]:
    """Yield ``(frame_index, bgr)`` for frames 0, stride, 2 * stride, ... in order.

    Frames in between are grabbed (not converted). Stops at the end of the video, at
    the first frame that cannot be decoded, or after ``max_frames`` frames. Raises
    `VideoError` if the file cannot be opened or its first frame cannot be decoded.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    capture = _open(path)
    try:
        index = 0
        yielded = 0
        while max_frames is None or yielded < max_frames:
            if index % stride == 0:
                ok, frame = capture.read()
                if not ok or frame is None:
                    break
                yield index, np.asarray(frame, dtype=np.uint8)
                yielded += 1
            elif not capture.grab():
                break
            index += 1
        if yielded == 0:
            raise VideoError(f"{path}: no frame could be decoded")
    finally:
        capture.release()


def count_frames(path: Path) -> int:
    """The number of frames that actually decode (the header's count can be wrong)."""
    capture = _open(path)
    try:
        n = 0
        while capture.grab():
            n += 1
        return n
    finally:
        capture.release()


def evenly_spaced(total: int, count: int) -> list[int]:
    """``count`` distinct frame indices spread over 0..total-1, first and last included."""
    if total <= 0 or count <= 0:
        return []
    spread = np.rint(np.linspace(0, total - 1, min(count, total))).astype(np.int64)
    return sorted({int(i) for i in spread})


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def evaluate_video_method(
    path: Path,
    method: str,
    perception_config: PerceptionConfig,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    on_frame: Callable[[], None] | None = None,
) -> dict[str, float | int]:
    """The metrics of one method on one video (see the module docstring).

    A throwaway segmenter first segments the first frame untimed (numba compilation
    and buffer allocation are not per-frame costs); then a fresh segmenter is fed every
    processed frame in order. Raises `VideoError`, or the segmenter's `ValueError`
    (`ImageError`, `SafeZoneError`) for frames it refuses.
    """
    segmenter = FloorSegmenter(perception_config, method=method)
    ious: list[float] = []
    bottom: list[float] = []
    times_ms: list[float] = []
    previous: NDArray[np.bool_] | None = None
    warmed = False
    for _index, frame in read_frames(path, stride=stride, max_frames=max_frames):
        if not warmed:
            FloorSegmenter(perception_config, method=method).segment(frame)
            warmed = True
        start = time.perf_counter()
        result = segmenter.segment(frame)
        times_ms.append((time.perf_counter() - start) * 1e3)
        mask = np.asarray(result.floor_mask, dtype=bool)
        if previous is not None:
            ious.append(mask_iou(previous, mask))
        bottom.append(bottom_half_floor_fraction(mask))
        previous = mask
        if on_frame is not None:
            on_frame()
    return {
        "consecutive_iou_mean": _mean(ious),
        "consecutive_iou_p05": _percentile(ious, 5),
        "bottom_half_floor_fraction_mean": _mean(bottom),
        "ms_per_frame_median": _percentile(times_ms, 50),
        "ms_per_frame_p95": _percentile(times_ms, 95),
        "frames": len(times_ms),
    }


def evaluate_videos(
    paths: Iterable[Path],
    methods: Sequence[str],
    perception_config: PerceptionConfig,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    progress: ProgressFn | None = None,
) -> dict[str, object]:
    """Run each method over each video; the JSON object of ``floornav eval-video --json``.

    Returns ``{"default_method", "stride", "max_frames", "videos": {PATH: {"width",
    "height", "fps", "frame_count", "methods": {METHOD: metrics}}}, "skipped": [{"file",
    "reason"}], "unavailable_methods": {METHOD: reason}}``; a video appears under
    ``videos`` once at least one method ran on it. A method whose segmenter cannot be
    built here (e.g. a model file that is missing) is listed under
    ``unavailable_methods`` and the others still run; an unknown name is a `ValueError`.
    """
    for method in methods:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    unavailable: dict[str, str] = {}
    for method in methods:
        try:
            FloorSegmenter(perception_config, method=method)
        except (RuntimeError, OSError, ValueError) as exc:
            unavailable[method] = str(exc)
    runnable = [m for m in methods if m not in unavailable]
    videos: dict[str, dict[str, object]] = {}
    skipped: list[dict[str, str]] = []
    readable: list[tuple[Path, dict[str, float | int]]] = []
    seen: set[str] = set()
    for path in (Path(p) for p in paths):
        if str(path) in seen:
            skipped.append({"file": str(path), "reason": "listed twice"})
            continue
        seen.add(str(path))
        try:
            readable.append((path, video_info(path)))
        except VideoError as exc:
            skipped.append({"file": str(path), "reason": str(exc)})

    def planned(info: dict[str, float | int]) -> int:
        n = -(-int(info["frame_count"]) // stride)
        return min(n, max_frames) if max_frames is not None else n

    total = len(runnable) * sum(planned(info) for _, info in readable)
    done = 0
    for path, info in readable:
        by_method: dict[str, dict[str, float | int]] = {}
        for method in runnable:
            label = f"{path.name} {method}"

            def tick(label: str = label) -> None:
                nonlocal done
                done += 1
                if progress is not None:
                    progress(min(done, total), total, label)

            try:
                by_method[method] = evaluate_video_method(
                    path,
                    method,
                    perception_config,
                    stride=stride,
                    max_frames=max_frames,
                    on_frame=tick,
                )
            except (ValueError, RuntimeError) as exc:  # VideoError, ImageError, SafeZoneError
                skipped.append({"file": str(path), "reason": f"{method}: {exc}"})
        if by_method:
            videos[str(path)] = {**info, "methods": by_method}
    if progress is not None and done < total:
        progress(total, total, "done")
    return {
        "default_method": perception_config.method,
        "stride": stride,
        "max_frames": max_frames,
        "videos": videos,
        "skipped": skipped,
        "unavailable_methods": unavailable,
    }


stderr_progress = progress_printer("eval-video", "frames", 200)


def format_video_table(summary: dict[str, object]) -> str:
    """Human-readable: one table per video, one row per method."""
    lines: list[str] = []
    header = (
        f"{'method':<18}{'iou_mean':>9}{'iou_p05':>9}{'bottom_floor':>13}"
        f"{'ms_med':>8}{'ms_p95':>8}{'frames':>8}"
    )
    videos = summary["videos"]
    assert isinstance(videos, dict)
    for path, video in videos.items():
        lines.append(
            f"\n== {path} ({video['width']}x{video['height']}, stride {summary['stride']})"
        )
        lines.append(header)
        for method, m in video["methods"].items():
            lines.append(
                f"{method:<18}{m['consecutive_iou_mean']:>9.3f}{m['consecutive_iou_p05']:>9.3f}"
                f"{m['bottom_half_floor_fraction_mean']:>13.3f}{m['ms_per_frame_median']:>8.2f}"
                f"{m['ms_per_frame_p95']:>8.2f}{m['frames']:>8d}"
            )
    skipped = summary["skipped"]
    assert isinstance(skipped, list)
    if skipped:
        lines.append(f"\nskipped {len(skipped)}:")
        lines.extend(f"  {s['file']}: {s['reason']}" for s in skipped)
    unavailable = summary.get("unavailable_methods")
    if isinstance(unavailable, dict) and unavailable:
        lines.append(f"\nunavailable method(s) {len(unavailable)}:")
        lines.extend(f"  {m}: {reason}" for m, reason in unavailable.items())
    return "\n".join(lines)


# -- contact sheets ----------------------------------------------------------------------

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_GAP_BGR = (40, 40, 40)


def _put_label(image: NDArray[np.uint8], text: str, *, scale: float) -> None:
    """White text on a dark box in the top-left corner, in place."""
    thickness = max(1, round(scale * 2))
    (tw, th), baseline = cv2.getTextSize(text, _FONT, scale, thickness)
    pad = max(2, round(4 * scale))
    x1 = min(image.shape[1], tw + 2 * pad)
    y1 = min(image.shape[0], th + baseline + 2 * pad)
    image[:y1, :x1] = (image[:y1, :x1] // 3).astype(np.uint8)
    cv2.putText(image, text, (pad, pad + th), _FONT, scale, (255, 255, 255), thickness, cv2.LINE_AA)


def contact_sheet(
    frames: Sequence[NDArray[np.uint8]],
    masks: Sequence[NDArray[np.bool_]],
    labels: Sequence[str],
    columns: int = 4,
    *,
    gap_px: int = 4,
    caption: str | None = None,
) -> NDArray[np.uint8]:
    """Tile frames with their floor masks tinted (`draw_overlay`) and a label on each.

    Parameters
    ----------
    frames : N (H, W, 3) uint8 BGR images; all are resized to the first one's size.
    masks : N (H, W) bool floor masks, each the size of its frame.
    labels : N strings drawn in each tile's top-left corner.
    columns : tiles per row; rows = ceil(N / columns), empty cells stay dark.
    gap_px : dark border between and around the tiles.
    caption : optional text in a strip above the tiles.

    Returns
    -------
    (caption_h + rows * H + (rows + 1) * gap, columns * W + (columns + 1) * gap, 3) uint8,
    where caption_h is 0 without a caption.
    """
    if not (len(frames) == len(masks) == len(labels)):
        raise ValueError(
            f"{len(frames)} frames, {len(masks)} masks and {len(labels)} labels: must match"
        )
    if not frames:
        raise ValueError("no frames for the contact sheet")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    height, width = frames[0].shape[:2]
    rows = -(-len(frames) // columns)
    sheet = np.empty(
        (rows * height + (rows + 1) * gap_px, columns * width + (columns + 1) * gap_px, 3),
        np.uint8,
    )
    sheet[:] = _GAP_BGR
    scale = max(0.3, height / 480)
    for i, (frame, mask, label) in enumerate(zip(frames, masks, labels, strict=True)):
        if frame.shape[:2] != mask.shape:
            raise ValueError(f"tile {i}: frame {frame.shape[:2]} but mask {mask.shape}")
        tile = draw_overlay(frame, np.asarray(mask, dtype=bool))
        if tile.shape[:2] != (height, width):
            resized = cv2.resize(tile, (width, height), interpolation=cv2.INTER_AREA)
            tile = np.asarray(resized, dtype=np.uint8)
        _put_label(tile, label, scale=scale)
        y = gap_px + (i // columns) * (height + gap_px)
        x = gap_px + (i % columns) * (width + gap_px)
        sheet[y : y + height, x : x + width] = tile
    if caption is None:
        return sheet
    caption_scale = max(0.4, height / 400)
    thickness = max(1, round(caption_scale * 2))
    (_, th), baseline = cv2.getTextSize(caption, _FONT, caption_scale, thickness)
    strip_h = th + baseline + 2 * max(4, round(8 * caption_scale))
    strip = np.zeros((strip_h, sheet.shape[1], 3), np.uint8)
    strip[:] = _GAP_BGR
    cv2.putText(
        strip,
        caption,
        (gap_px + 4, (strip_h + th) // 2),
        _FONT,
        caption_scale,
        (255, 255, 255),
        thickness,
        cv2.LINE_AA,
    )
    return np.vstack([strip, sheet])
