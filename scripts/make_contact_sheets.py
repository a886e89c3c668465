"""Write docs/contact-sheet-<video-stem>.jpg for each shared robot video: 12 frames spread
evenly over the video with the floor mask of one method tinted on them (4 x 3 tiles, the
frame index on each, the method in a caption strip).

One segmenter per video is fed the chosen frames in order (a method may keep state
across the frames of a video). The videos are read where they are, never copied.

    .venv/bin/python scripts/make_contact_sheets.py [--method NAME] [--config PATH]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import DEFAULT_CONFIG_PATH, load_config
from app.fileio import write_bytes_atomic
from app.perception.pipeline import FloorSegmenter
from app.video_eval import contact_sheet, count_frames, evenly_spaced, read_frames, video_info

ROOT = Path(__file__).resolve().parents[1]
VIDEOS = ROOT.parent / "shared" / "datasets" / "robot-video-carpet"
DOCS = ROOT / "docs"
MAX_BYTES = 300_000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", help="segmentation method (default: from config)")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG_PATH)
    parser.add_argument("--videos", type=Path, default=VIDEOS, help="folder of .avi videos")
    parser.add_argument("--out-dir", type=Path, default=DOCS)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--columns", type=int, default=4)
    parser.add_argument("--quality", type=int, default=85, help="JPEG quality")
    args = parser.parse_args()

    config = load_config(args.config)
    method = args.method or config.perception.method
    videos = sorted(args.videos.glob("*.avi"))
    if not videos:
        print(f"no .avi video in {args.videos}")
        return 1
    for video in videos:
        total = count_frames(video)
        wanted = set(evenly_spaced(total, args.frames))
        fps = float(video_info(video)["fps"]) or 24.0
        segmenter = FloorSegmenter(config.perception, method=method)
        frames: list[NDArray[np.uint8]] = []
        masks: list[NDArray[np.bool_]] = []
        labels: list[str] = []
        for index, frame in read_frames(video):
            if index not in wanted:
                continue
            frames.append(frame)
            masks.append(segmenter.segment(frame).floor_mask)
            labels.append(f"frame {index}  {index / fps:.1f} s")
        caption = (
            f"{video.name}: method {method}, {len(frames)} of {total} frames (floor tinted green)"
        )
        sheet = contact_sheet(frames, masks, labels, columns=args.columns, caption=caption)
        ok, encoded = cv2.imencode(".jpg", sheet, [cv2.IMWRITE_JPEG_QUALITY, args.quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out = args.out_dir / f"contact-sheet-{video.stem}.jpg"
        write_bytes_atomic(out, encoded.tobytes())
        size = len(encoded)
        warning = f"  (over {MAX_BYTES // 1000} KB: lower --quality)" if size > MAX_BYTES else ""
        print(f"{out}: {sheet.shape[1]}x{sheet.shape[0]}, {size / 1000:.0f} KB{warning}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
