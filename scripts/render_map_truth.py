"""A saved map beside the simulated world's truth, as one bird's-eye PNG.

    .venv/bin/python scripts/render_map_truth.py MAP.npz --world NAME --out PNG

Left: the world's truth (floor colour from the world's own floor texture, walls and
boxes black). Right: the map as the robot knows it (`SavedMap.remembered_classes`; free
white, occupied black, unknown grey) in the same plan frame, with the robot's start (green)
and its last pose (red). The map is in the odom frame, which is the world's start pose
(the simulator starts there).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.config import DEFAULT_CONFIG_PATH, load_config
from app.mapping.map_files import load_map
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN
from app.sim.setup import world_from_config

PIXELS_PER_CELL = 4


def plan_view(raster: NDArray[np.generic]) -> NDArray[np.generic]:
    """`GroundGrid` layout (row 0 at x_max, column 0 at y_max) -> a picture with x to the
    right and y up."""
    return np.ascontiguousarray(np.swapaxes(raster, 0, 1)[:, ::-1])


def render(map_path: Path, config_path: Path | None, world_name: str, out: Path) -> None:
    overrides = {"sim": {"world_file": world_name}} if world_name else {}
    config = load_config(config_path if config_path else DEFAULT_CONFIG_PATH, **overrides)
    world = world_from_config(config)
    saved = load_map(map_path)
    classes = saved.remembered_classes()
    truth_grid, truth_occ = world.occupancy(saved.world_grid.cell_m)
    x, y = truth_grid.cell_centers()
    plan_points = np.column_stack((x.ravel(), y.ravel()))
    T_plan_odom = world.start_pose
    rc = saved.world_grid.cell_of(T_plan_odom.inverse().apply(plan_points))
    rows, cols = saved.world_grid.shape
    on_map = (rc[:, 0] >= 0) & (rc[:, 0] < rows) & (rc[:, 1] >= 0) & (rc[:, 1] < cols)
    mapped = np.full(len(rc), UNKNOWN, np.int8)
    mapped[on_map] = classes[rc[on_map, 0], rc[on_map, 1]]
    mapped = mapped.reshape(truth_grid.shape)

    texture = world.floor_raster(saved.world_grid.cell_m)
    tex = texture.levels[0]
    # The texture covers a slightly different extent: look it up at the truth cells.
    trc = texture.grid.cell_of(plan_points)
    tex_rgb = np.full((len(trc), 3), 60, np.uint8)
    ok = (
        (trc[:, 0] >= 0)
        & (trc[:, 0] < tex.shape[0])
        & (trc[:, 1] >= 0)
        & (trc[:, 1] < tex.shape[1])
    )
    tex_rgb[ok] = tex[trc[ok, 0], trc[ok, 1]]
    truth_img = tex_rgb.reshape(*truth_grid.shape, 3)
    truth_img[truth_occ == 1] = 0

    map_img = np.full((*truth_grid.shape, 3), 160, np.uint8)
    map_img[mapped == FREE] = 255
    map_img[mapped == OCCUPIED] = 0

    def to_picture(raster: NDArray[np.uint8]) -> NDArray[np.uint8]:
        pic = plan_view(raster)
        return cv2.resize(
            pic,
            None,
            fx=PIXELS_PER_CELL,
            fy=PIXELS_PER_CELL,
            interpolation=cv2.INTER_NEAREST,
        )

    left, right = to_picture(truth_img), to_picture(map_img)

    def pixel(xy: tuple[float, float]) -> tuple[int, int]:
        r, c = truth_grid.cell_of(np.array([xy]))[0]
        # plan_view: picture row = column index, picture column = rows - 1 - row
        return (
            int((truth_grid.rows - 1 - r + 0.5) * PIXELS_PER_CELL),
            int((c + 0.5) * PIXELS_PER_CELL),
        )

    start = world.start_pose
    end = T_plan_odom.compose(saved.T_world_robot)
    for img in (left, right):
        for pose, colour in ((start, (0, 170, 0)), (end, (0, 0, 220))):
            centre = pixel((pose.x_m, pose.y_m))
            tip = (
                int(centre[0] + 10 * math.cos(pose.theta_rad)),
                int(centre[1] - 10 * math.sin(pose.theta_rad)),
            )
            cv2.circle(img, centre, 6, colour, 2)
            cv2.line(img, centre, tip, colour, 2)
    gap = np.full((left.shape[0], 8, 3), 255, np.uint8)
    picture = np.hstack([left, gap, right])
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), picture):
        raise SystemExit(f"cannot write {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", type=Path, help="a map saved by `floornav run --map FILE`")
    parser.add_argument("--world", default="", help="the world it was made in (default: config)")
    parser.add_argument("--config", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    render(args.map, args.config, args.world, args.out)


if __name__ == "__main__":
    main()
