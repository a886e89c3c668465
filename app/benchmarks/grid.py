"""Timing of one occupancy-grid update from a realistic 640x480 camera's ground patch.

The patches are rendered here, not by the IPM module: a pinhole camera (640 x 480,
f = 520 px, 0.25 m above the floor at x = 0.1 m in the robot frame, pitched 25 degrees
down) looks into a 4.2 m x 4 m room with a box and four chair legs; a patch cell
(x 0.1..3.0 m, y -1.5..1.5 m, 1 cm: 290 x 300 cells) is ``UNSEEN`` outside the image,
``NOT_FLOOR`` where the line of sight from the camera to it passes through an obstacle
(what inverse perspective mapping makes of anything standing on the floor), else
``FLOOR``. The robot drives a wavy path through the room; each timed update fuses the
next patch at its pose into a 20 m x 20 m grid of 5 cm cells; the poses are at least
5 cm apart, so the lazy travel decay runs on every update (the worst case).

Timed: `OccupancyGrid.update` (input checks, decay, ray casting, world fusion), after a
warm-up pass that compiles the kernels and builds the ray table (its time is reported
separately). Also timed: the same update on an open floor (every ray runs to the patch's
edge: the worst case).

``python -m app.mapping.grid_bench [repeats]`` prints the result as JSON, pinned to one
CPU.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.benchmarks import pin_to_one_cpu
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D
from app.mapping.occupancy import OccupancyGrid, build_polar_table

PATCH_GRID = GroundGrid.covering(x_min_m=0.1, x_max_m=3.0, y_min_m=-1.5, y_max_m=1.5, cell_m=0.01)
CAMERA_XY_ROBOT = (0.1, 0.0)
N_FRAMES = 12


@dataclass(frozen=True)
class Camera:
    """A pinhole camera on the robot, looking forward and pitched down."""

    width_px: int = 640
    height_px: int = 480
    focal_px: float = 520.0
    height_m: float = 0.25
    pitch_rad: float = math.radians(25.0)


# Obstacles as world boxes (x0, x1, y0, y1, top z), in metres: the room's walls, a box,
# four chair legs.
ROOM: tuple[tuple[float, float, float, float, float], ...] = (
    (-1.0, 3.2, 2.0, 2.1, 1.0),
    (-1.0, 3.2, -2.1, -2.0, 1.0),
    (3.2, 3.3, -2.1, 2.1, 1.0),
    (-1.1, -1.0, -2.1, 2.1, 1.0),
    (1.6, 2.0, -0.9, -0.4, 0.4),
    (2.0, 2.03, 0.5, 0.53, 0.45),
    (2.0, 2.03, 0.9, 0.93, 0.45),
    (2.4, 2.43, 0.5, 0.53, 0.45),
    (2.4, 2.43, 0.9, 0.93, 0.45),
)


def _sight_blocked(
    eye: NDArray[np.float64], points: NDArray[np.float64], box: tuple[float, ...]
) -> NDArray[np.bool_]:
    """(N,) bool: does the segment from ``eye`` (3,) to each floor point (N, 3) cross the
    box (x0, x1, y0, y1, z1), z from 0? Slab test."""
    lo = np.array([box[0], box[2], 0.0])
    hi = np.array([box[1], box[3], box[4]])
    d = points - eye
    t_enter = np.zeros(points.shape[0])
    t_exit = np.ones(points.shape[0])
    for k in range(3):
        dk = d[:, k]
        parallel = np.abs(dk) < 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo[k] - eye[k]) / dk
            t2 = (hi[k] - eye[k]) / dk
        inside = lo[k] <= eye[k] <= hi[k]
        t_near = np.where(parallel, -np.inf if inside else np.inf, np.minimum(t1, t2))
        t_far = np.where(parallel, np.inf if inside else -np.inf, np.maximum(t1, t2))
        t_enter = np.maximum(t_enter, t_near)
        t_exit = np.minimum(t_exit, t_far)
    blocked: NDArray[np.bool_] = t_enter <= t_exit
    return blocked


def render_patch(
    pose: Pose2D,
    camera: Camera = Camera(),
    obstacles: tuple[tuple[float, float, float, float, float], ...] = ROOM,
) -> NDArray[np.uint8]:
    """The ground patch (``PATCH_GRID``) a perfect floor segmentation + IPM would give at
    ``pose`` in the room."""
    x, y = PATCH_GRID.cell_centers()
    dx, dy, dz = x - CAMERA_XY_ROBOT[0], y - CAMERA_XY_ROBOT[1], -camera.height_m
    c, s = math.cos(camera.pitch_rad), math.sin(camera.pitch_rad)
    forward = dx * c - dz * s
    right = -dy
    down = -dx * s - dz * c
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.focal_px * right / forward + camera.width_px / 2
        v = camera.focal_px * down / forward + camera.height_px / 2
    seen = (forward > 0) & (u >= 0) & (u < camera.width_px) & (v >= 0) & (v < camera.height_px)
    patch = np.full(PATCH_GRID.shape, UNSEEN, dtype=np.uint8)
    world = pose.apply(np.column_stack((x[seen], y[seen])))
    floor_pts = np.column_stack((world, np.zeros(world.shape[0])))
    eye_xy = pose.apply(np.array([CAMERA_XY_ROBOT]))[0]
    eye = np.array([eye_xy[0], eye_xy[1], camera.height_m])
    blocked = np.zeros(world.shape[0], dtype=bool)
    for box in obstacles:
        blocked |= _sight_blocked(eye, floor_pts, box)
    patch[seen] = np.where(blocked, NOT_FLOOR, FLOOR).astype(np.uint8)
    return patch


def bench_poses(n: int = N_FRAMES) -> list[Pose2D]:
    """A wavy drive through the room, 5 cm and a few degrees apart."""
    return [Pose2D(0.05 * k, 0.3 * math.sin(k / 4), 0.35 * math.sin(k / 3 + 0.5)) for k in range(n)]


def _time_updates(
    grid: OccupancyGrid, frames: list[tuple[NDArray[np.uint8], Pose2D]], repeats: int
) -> list[float]:
    samples: list[float] = []
    for _ in range(repeats):
        for patch, pose in frames:
            start = time.perf_counter()
            grid.update(patch, PATCH_GRID, pose, CAMERA_XY_ROBOT)
            samples.append((time.perf_counter() - start) * 1e3)
    return samples


def bench_grid_update(repeats: int) -> dict[str, float | int | str]:
    """Time one `OccupancyGrid.update` of a 640x480 camera's ground patch at moving poses.

    Parameters
    ----------
    repeats : int >= 1, passes over the 12 rendered frames (12 * repeats timed updates).

    Returns
    -------
    dict with ``median``, ``min``, ``max`` (ms per update in the room),
    ``open_floor_median`` (ms, the worst case: no obstacle stops a ray), ``updates``,
    ``table_build_ms`` (the one-off ray table, kernels already compiled), and
    descriptions ``patch``, ``world``, ``scene``.
    """
    if repeats < 1:
        raise ValueError(f"repeats: must be >= 1, got {repeats}")
    poses = bench_poses()
    frames = [(render_patch(pose), pose) for pose in poses]
    grid = OccupancyGrid.square(20.0, 0.05)
    _time_updates(grid, frames, 1)  # compile, build and cache the ray table
    start = time.perf_counter()
    table = build_polar_table(PATCH_GRID, CAMERA_XY_ROBOT)
    table_ms = (time.perf_counter() - start) * 1e3
    grid.reset()
    samples = _time_updates(grid, frames, repeats)
    open_floor = np.full(PATCH_GRID.shape, FLOOR, dtype=np.uint8)
    open_floor[frames[0][0] == UNSEEN] = UNSEEN
    grid.reset()
    open_samples = _time_updates(grid, [(open_floor, pose) for pose in poses], repeats)
    seen = int(np.count_nonzero(frames[0][0] != UNSEEN))
    return {
        "median": round(statistics.median(samples), 3),
        "min": round(min(samples), 3),
        "max": round(max(samples), 3),
        "open_floor_median": round(statistics.median(open_samples), 3),
        "updates": len(samples),
        "table_build_ms": round(table_ms, 3),
        "patch": (
            f"{PATCH_GRID.rows}x{PATCH_GRID.cols} cells of {PATCH_GRID.cell_m} m, {seen} seen,"
            f" {table.n_rays} rays"
        ),
        "world": f"{grid.world_grid.rows}x{grid.world_grid.cols} cells of"
        f" {grid.world_grid.cell_m} m",
        "scene": "640x480 pinhole camera, room with walls, a box and chair legs",
    }


def format_grid_bench(result: dict[str, float | int | str]) -> str:
    """One human-readable block for ``floornav bench``."""
    return (
        f"== occupancy grid update ({result['updates']} updates; patch {result['patch']};"
        f" world {result['world']})\n"
        f"  {'room':<12}{result['median']:>9.2f}{result['min']:>9.2f}{result['max']:>9.2f}\n"
        f"  {'open floor':<12}{result['open_floor_median']:>9.2f}\n"
        f"  ray table built once in {result['table_build_ms']:.1f} ms"
    )


def main(argv: list[str]) -> int:  # python -m app.benchmarks.grid [REPEATS]
    repeats = int(argv[0]) if argv else 20
    pin_to_one_cpu()
    print(json.dumps(bench_grid_update(repeats), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
