"""Score the parallax test's standing verdicts with exact, slipped and aligned poses.

Random collision-free view pairs in a shipped world (half driving straight 0.06-0.15 m,
half turning up to 0.15 rad on the spot), rendered by the simulator. The reference
pose the test is given is the true one ("exact"), the true one plus odometry's error
between two such frames ("slipped": heading N(0, 1.3 deg), position N(0, 3 mm) per
axis, what wheel slip gave in the home world against the simulator's truth), or the
slipped one corrected by the bird's-eye `planar.align_reference_pose` alone
("aligned") or by `planar.reference_pose_from_views`, the daemon's (the photometric
refinement, the alignment where that fails: "refined"); pairs a correction cannot align
are counted and left out. For each: the share of the tested true-floor pixels
the test calls standing (false alarms: a floor that stands up blocks the way) and the
share of the tested obstacle pixels it calls standing (what it should find).

    .venv/bin/python scripts/eval_alignment.py --world home
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.config import DEFAULT_CONFIG_PATH, load_config
from app.mapping.frames import Pose2D
from app.perception import planar
from app.perception.pipeline import FloorSegmenter
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

HEADING_SIGMA_RAD = math.radians(1.3)
SHIFT_SIGMA_M = 0.003

Pose = tuple[float, float, float]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="two-rooms")
    parser.add_argument("--pairs", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    config = load_config(DEFAULT_CONFIG_PATH, sim={"world_file": args.world})
    renderer = renderer_from_config(config)
    H_ground_from_image = sim_floor_calibration(camera_model(config)).H_ground_from_image
    camera_xy = (config.camera.x_m, config.camera.y_m)
    segmenter = FloorSegmenter(config.perception)
    world = renderer.world
    rng = np.random.default_rng(args.seed)
    x_min, y_min, x_max, y_max = world.bounds_m
    pairs: list[tuple[Pose, Pose, Pose]] = []
    while len(pairs) < args.pairs:
        x, y = rng.uniform(x_min, x_max), rng.uniform(y_min, y_max)
        heading = rng.uniform(-math.pi, math.pi)
        if world.clearance_m(x, y) < 0.35:
            continue
        turning = rng.random() < 0.5
        turn = rng.uniform(-0.15, 0.15) if turning else 0.0
        back = rng.uniform(0.0, 0.05) if turning else rng.uniform(0.06, 0.15)
        ref = (x - back * math.cos(heading), y - back * math.sin(heading), heading - turn)
        if world.clearance_m(ref[0], ref[1]) < 0.3:
            continue
        slipped = (
            ref[0] + rng.normal(0.0, SHIFT_SIGMA_M),
            ref[1] + rng.normal(0.0, SHIFT_SIGMA_M),
            ref[2] + rng.normal(0.0, HEADING_SIGMA_RAD),
        )
        pairs.append(((x, y, heading), ref, slipped))

    views = []
    for cur_pose, ref_pose, slipped in pairs:
        cur, ref = renderer.render(Pose2D(*cur_pose)), renderer.render(Pose2D(*ref_pose))
        colour = segmenter.segment(cur.image).floor_mask
        gray = [cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) for f in (cur, ref)]
        views.append((cur_pose, ref_pose, slipped, colour, gray, cur.floor_mask))

    for mode in ("exact", "slipped", "aligned", "refined"):
        floor_standing = floor_tested = obstacle_standing = obstacle_tested = 0
        unaligned, heading_errors, shift_errors, times = 0, [], [], []
        for cur_pose, ref_pose, slipped, colour, gray, truth in views:
            given = ref_pose if mode == "exact" else slipped
            if mode in ("aligned", "refined"):
                start = time.perf_counter()
                align = (
                    planar.align_reference_pose
                    if mode == "aligned"
                    else planar.reference_pose_from_views
                )
                aligned = align(gray[0], gray[1], colour, H_ground_from_image, slipped, cur_pose)
                times.append(time.perf_counter() - start)
                if aligned is None:
                    unaligned += 1
                    continue
                given = aligned
                heading_errors.append(abs(math.degrees(aligned[2] - ref_pose[2])))
                shift_errors.append(1000 * math.dist(aligned[:2], ref_pose[:2]))
            result = planar.confirm_floor(
                colour,
                gray[0],
                gray[1],
                H_ground_from_image,
                given,
                cur_pose,
                camera_xy,
                return_standing=True,
            )
            assert isinstance(result, planar.ParallaxResult)
            floor_standing += int((result.standing & truth).sum())
            floor_tested += int((result.tested & truth).sum())
            obstacle_standing += int((result.standing & ~truth).sum())
            obstacle_tested += int((result.tested & ~truth).sum())
        line = (
            f"{args.world} {mode:8s} standing: {floor_standing / max(1, floor_tested):.3f} of "
            f"the tested floor, {obstacle_standing / max(1, obstacle_tested):.3f} of the "
            f"tested obstacles"
        )
        if mode in ("aligned", "refined"):
            line += (
                f"; {unaligned}/{len(views)} pairs not aligned; residual heading p50/p90 "
                f"{np.percentile(heading_errors, 50):.2f}/{np.percentile(heading_errors, 90):.2f}"
                f" deg, position {np.percentile(shift_errors, 50):.1f}/"
                f"{np.percentile(shift_errors, 90):.1f} mm; align median "
                f"{1000 * float(np.median(times)):.1f} ms"
            )
        print(line)


if __name__ == "__main__":
    main()
