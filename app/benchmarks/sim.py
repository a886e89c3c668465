"""Timing of the simulator's camera renderer: one 640x480 frame of the default world.

The robot drives a wavy path through the living room and the doorway; each timed call is
`Renderer.render` (floor texture sampling, face rasterisation, shading, noise), after a
warm-up frame that compiles the kernels.

``python -m app.benchmarks.sim [repeats]`` prints the result as JSON, pinned to one CPU.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time

from app.benchmarks import pin_to_one_cpu
from app.mapping.frames import Pose2D
from app.sim.render import CameraModel, Renderer
from app.sim.world import load_world

N_POSES = 30


def bench_poses(n: int = N_POSES) -> list[Pose2D]:
    """From the start pose across the living room, weaving and turning, at least
    0.3 m from every wall and box."""
    return [
        Pose2D(1.2 + 1.8 * k / n, 2.9 + 0.15 * math.sin(k / 3), 1.2 * math.sin(k / 5))
        for k in range(n)
    ]


def bench_render(repeats: int) -> dict[str, float | int | str]:
    """Time `Renderer.render` at 640x480.

    Parameters
    ----------
    repeats : int >= 1, passes over the 30 poses

    Returns
    -------
    dict with ``median``, ``min``, ``max`` (ms per frame), ``fps`` (1000 / median),
    ``frames``, and ``scene``.
    """
    if repeats < 1:
        raise ValueError(f"repeats: must be >= 1, got {repeats}")
    world = load_world()
    renderer = Renderer(world, CameraModel())
    poses = bench_poses()
    renderer.render(poses[0])  # compile
    samples: list[float] = []
    for _ in range(repeats):
        for pose in poses:
            start = time.perf_counter()
            renderer.render(pose)
            samples.append((time.perf_counter() - start) * 1e3)
    median = statistics.median(samples)
    return {
        "median": round(median, 3),
        "min": round(min(samples), 3),
        "max": round(max(samples), 3),
        "fps": round(1e3 / median, 1),
        "frames": len(samples),
        "scene": f"default world '{world.name}', {len(world.faces.segments)} faces, 640x480",
    }


def main(argv: list[str]) -> int:  # python -m app.benchmarks.sim [REPEATS]
    repeats = int(argv[0]) if argv else 10
    pin_to_one_cpu()
    print(json.dumps(bench_render(repeats), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
