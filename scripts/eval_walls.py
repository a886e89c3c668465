"""Score the walls proven by the horizon (`standing.wall_surfaces`) on simulated views.

Random poses at least 0.3 m from any obstacle in each named world (a shipped world's
name or a .toml path), seen through the shipped perception method's floor mask. Printed
per world, for the walls (not-floor pixels) and for the walls' lower parts the mask took
for floor: the marked pixels on true obstacles, and the marked pixels of true floor more
than ``FOOT_PX`` below any true obstacle pixel of their column (a segmenter's floor ends
a few pixels short of a wall's true foot, and the wall is taken from there), with the
views that have more than 500 of those.

    .venv/bin/python scripts/eval_walls.py two-rooms home office
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.config import DEFAULT_CONFIG_PATH, load_config
from app.mapping.frames import Pose2D
from app.mapping.ground_map import image_horizon_rows
from app.perception.pipeline import FloorSegmenter
from app.perception.standing import wall_surfaces
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

FOOT_PX = 8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("worlds", nargs="+")
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in args.worlds:
        config = load_config(DEFAULT_CONFIG_PATH, sim={"world_file": name})
        renderer = renderer_from_config(config)
        horizon = image_horizon_rows(sim_floor_calibration(camera_model(config)))
        segmenter = FloorSegmenter(config.perception)
        world = renderer.world
        rng = np.random.default_rng(args.seed)
        x_min, y_min, x_max, y_max = world.bounds_m
        views = 0
        scores = {"walls": [0, 0, 0], "lower parts": [0, 0, 0]}  # on, off, views off
        while views < args.views:
            x, y = rng.uniform(x_min, x_max), rng.uniform(y_min, y_max)
            if world.clearance_m(x, y) < 0.3:
                continue
            frame = renderer.render(Pose2D(x, y, rng.uniform(-math.pi, math.pi)))
            mask = segmenter.segment(frame.image).floor_mask
            surfaces = wall_surfaces(mask, frame.image, horizon)
            obstacle = ~frame.floor_mask
            near_foot = obstacle.copy()
            for k in range(1, FOOT_PX + 1):
                near_foot[k:] |= obstacle[:-k]
            for kind, marked in (("walls", surfaces.walls), ("lower parts", surfaces.floor_part)):
                far = int((marked & ~near_foot).sum())
                score = scores[kind]
                score[0] += int((marked & obstacle).sum())
                score[1] += far
                score[2] += far > 500
            views += 1
        for kind, (on_obstacles, off, views_off) in scores.items():
            print(
                f"{name} {kind}: {views} views; marked {on_obstacles} px on true obstacles,"
                f" {off} px of true floor more than {FOOT_PX} px below one"
                f" ({views_off} views with > 500)"
            )


if __name__ == "__main__":
    main()
