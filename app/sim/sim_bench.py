"""Measurements of the simulator: render speed, and the floor pipeline's accuracy on
simulated frames against the renderer's ground truth.

``python -m app.sim.sim_bench [--repeats N] [--frames N]`` prints both as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np

from app.config import PerceptionConfig
from app.mapping.frames import Pose2D
from app.perception.pipeline import FloorSegmenter
from app.sim.render import CameraModel, Renderer
from app.sim.world import World, load_world


@contextmanager
def _one_cpu() -> Iterator[str]:
    """Pin this process (and OpenCV) to one CPU for the duration; yields its name."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    saved: set[int] | None = None
    name = "unpinned"
    if hasattr(os, "sched_setaffinity"):
        saved = os.sched_getaffinity(0)
        cpu = min(saved)
        os.sched_setaffinity(0, {cpu})
        name = f"cpu {cpu}"
    try:
        yield name
    finally:
        cv2.setNumThreads(threads)
        if saved is not None:
            os.sched_setaffinity(0, saved)


def bench_path(world: World, n: int) -> list[Pose2D]:
    """``n`` poses on a loop around the start (1 m radius, looking along the loop and
    swinging left and right), skipping poses where the robot would touch something."""
    start = world.start_pose
    cx, cy = start.x_m + 1.0, start.y_m
    poses: list[Pose2D] = []
    k = 0
    while len(poses) < n and k < 20 * n:
        a = 2 * math.pi * k / max(n, 1)
        x, y = cx - math.cos(a), cy - math.sin(a)
        heading = a - math.pi / 2 + 0.6 * math.sin(3 * a)
        if world.clearance_m(x, y) >= world.robot_radius_m:
            poses.append(Pose2D(x, y, heading))
        k += 1
    return poses


def bench_render(
    repeats: int = 200, *, world: World | None = None, camera: CameraModel | None = None
) -> dict[str, float | int | str]:
    """Time `Renderer.render` of one 640x480 frame (default camera) on one CPU.

    Returns median/min/max milliseconds, the fps of the median, the repeats and the CPU;
    poses cycle along `bench_path` of the default world.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    world = world if world is not None else load_world()
    renderer = Renderer(world, camera)
    poses = bench_path(world, 24)
    with _one_cpu() as cpu:
        for pose in poses[:3]:  # compile and warm caches
            renderer.render(pose)
        samples = []
        for k in range(repeats):
            t0 = time.perf_counter()
            renderer.render(poses[k % len(poses)])
            samples.append((time.perf_counter() - t0) * 1e3)
    median = statistics.median(samples)
    return {
        "width_px": renderer.camera.width_px,
        "height_px": renderer.camera.height_px,
        "repeats": repeats,
        "median_ms": round(median, 3),
        "min_ms": round(min(samples), 3),
        "max_ms": round(max(samples), 3),
        "fps": round(1e3 / median, 1),
        "cpu": cpu,
    }


def perception_iou(
    frames: int = 12,
    *,
    world: World | None = None,
    config: PerceptionConfig | None = None,
) -> dict[str, object]:
    """Segment ``frames`` simulated frames along `bench_path` with `FloorSegmenter` and
    compare each floor mask with the renderer's ground truth.

    Returns the mean IoU, precision and recall (floor = positive) and the per-frame IoU.
    """
    world = world if world is not None else load_world()
    config = config if config is not None else PerceptionConfig()
    renderer = Renderer(world)
    segmenter = FloorSegmenter(config)
    ious, precisions, recalls = [], [], []
    for pose in bench_path(world, frames):
        frame = renderer.render(pose)
        found = segmenter.segment(frame.image).floor_mask
        truth = frame.floor_mask
        both = np.count_nonzero(found & truth)
        ious.append(both / max(1, np.count_nonzero(found | truth)))
        precisions.append(both / max(1, np.count_nonzero(found)))
        recalls.append(both / max(1, np.count_nonzero(truth)))
    return {
        "method": segmenter.method,
        "frames": len(ious),
        "mean_iou": round(float(np.mean(ious)), 4),
        "mean_precision": round(float(np.mean(precisions)), 4),
        "mean_recall": round(float(np.mean(recalls)), 4),
        "iou_per_frame": [round(v, 3) for v in ious],
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=200, help="frames to time")
    parser.add_argument("--frames", type=int, default=12, help="frames to segment")
    parser.add_argument("--method", default=None, help="floor method (default: config's)")
    args = parser.parse_args(argv)
    config = PerceptionConfig() if args.method is None else PerceptionConfig(method=args.method)
    result = {
        "render": bench_render(args.repeats),
        "perception": perception_iou(args.frames, config=config),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
