"""Score the parallax floor confirmation (app/perception/planar.py) on simulated views.

Random collision-free poses in the shipped world (plus two facing the doorway), each
with a reference frame 0.08-0.16 m behind; the colour floor of the shipped perception
method is extended by `confirm_floor` and the added pixels are scored against the
renderer's true floor mask. What the test finds standing up (``return_standing``) is
scored too: the share of it off the true floor, and of the rest, the share within
``OUTLINE_PX`` of the floor's outline (an edge's evidence spreads onto its neighbours
in the half-resolution images the test works on).

    .venv/bin/python scripts/eval_parallax.py --seed 0 [--world home] [--soft-sigma-px 0]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from app.config import load_config
from app.mapping.frames import Pose2D
from app.perception import planar
from app.perception.pipeline import FloorSegmenter
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

ROOT = Path(__file__).resolve().parents[1]
OUTLINE_PX = 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--world", default="two-rooms", help="a shipped world or a .toml path")
    parser.add_argument(
        "--soft-sigma-px",
        type=float,
        default=None,
        help="PlanarParams.soft_sigma_px (default: the shipped value; 0: no second look)",
    )
    args = parser.parse_args()
    params = planar.PlanarParams()
    if args.soft_sigma_px is not None:
        params = replace(params, soft_sigma_px=args.soft_sigma_px)
    config = load_config(ROOT / "config.toml", sim={"world_file": args.world})
    renderer = renderer_from_config(config)
    H_ground_from_image = sim_floor_calibration(camera_model(config)).H_ground_from_image
    camera_xy = (config.camera.x_m, config.camera.y_m)
    segmenter = FloorSegmenter(config.perception)
    world = renderer.world
    rng = np.random.default_rng(args.seed)
    # Two views facing the two-room flat's doorway, then random ones inside the walls.
    poses = [(3.95, 3.05, 0.0), (3.7, 2.45, 0.15)] if world.spec.name == "two rooms" else []
    x_min, y_min, x_max, y_max = world.bounds_m
    while len(poses) < args.views:
        x, y = rng.uniform(x_min + 0.4, x_max - 0.4), rng.uniform(y_min + 0.4, y_max - 0.4)
        t = rng.uniform(-math.pi, math.pi)
        if world.clearance_m(x, y) > 0.35:
            poses.append((x, y, t))
    added_true = added_false = colour_true = truth_total = views = 0
    standing_off = standing_on = standing_outline = tested = 0
    times, standing_times = [], []
    near = np.ones((2 * OUTLINE_PX + 1, 2 * OUTLINE_PX + 1), np.uint8)
    for x, y, t in poses:
        baseline = rng.uniform(0.08, 0.16)
        ref = (x - baseline * math.cos(t), y - baseline * math.sin(t), t + rng.uniform(-0.05, 0.05))
        if world.clearance_m(ref[0], ref[1]) < 0.2:
            continue
        cur_frame, ref_frame = renderer.render(Pose2D(x, y, t)), renderer.render(Pose2D(*ref))
        colour = segmenter.segment(cur_frame.image).floor_mask
        gray_cur = cv2.cvtColor(cur_frame.image, cv2.COLOR_BGR2GRAY)
        gray_ref = cv2.cvtColor(ref_frame.image, cv2.COLOR_BGR2GRAY)
        start = time.perf_counter()
        confirmed = planar.confirm_floor(
            colour, gray_cur, gray_ref, H_ground_from_image, ref, (x, y, t), camera_xy, params
        )
        times.append(time.perf_counter() - start)
        start = time.perf_counter()
        result = planar.confirm_floor(
            colour,
            gray_cur,
            gray_ref,
            H_ground_from_image,
            ref,
            (x, y, t),
            camera_xy,
            params,
            return_standing=True,
        )
        standing_times.append(time.perf_counter() - start)
        added, truth = confirmed & ~colour, cur_frame.floor_mask
        added_true += int((added & truth).sum())
        added_false += int((added & ~truth).sum())
        outline = cv2.morphologyEx(truth.astype(np.uint8), cv2.MORPH_GRADIENT, near) > 0
        standing_off += int((result.standing & ~truth).sum())
        standing_on += int((result.standing & truth).sum())
        standing_outline += int((result.standing & truth & outline).sum())
        tested += int(result.tested.sum())
        colour_true += int((colour & truth).sum())
        truth_total += int(truth.sum())
        views += 1
    print(
        f"{views} views: colour method recall {colour_true / truth_total:.3f}; parallax added "
        f"{added_true / truth_total:.3f} of the true floor, {added_false} false pixels, "
        f"precision of the added {added_true / max(1, added_true + added_false):.3f}; "
        f"confirm_floor median {1000 * float(np.median(times)):.1f} ms"
    )
    standing = standing_off + standing_on
    print(
        f"standing: {standing} of {tested} tested pixels, {standing_off / max(1, standing):.3f}"
        f" off the true floor; of the {standing_on} on it, "
        f"{standing_outline / max(1, standing_on):.3f} within {OUTLINE_PX} px of its outline; "
        f"with return_standing median {1000 * float(np.median(standing_times)):.1f} ms"
    )


if __name__ == "__main__":
    main()
