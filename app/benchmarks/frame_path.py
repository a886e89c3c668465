"""Timing of the daemon's own per-frame path on simulated frames, with a given
configuration (``floornav bench`` passes the shipped one).

Frames come from the simulated camera (`renderer_from_config`) along a short drive: a
right-hand circle of ``PATH_RADIUS_M`` from the world's start pose at the steering's
cruise speed, one frame per camera period. They are rendered before the timing starts:
rendering is the simulator's cost, not the daemon's. Each frame then goes through what
`app.runtime.Runtime` runs for it, in one thread and in the daemon's order:

``perception``
    `FloorSegmenter.segment` (the perception stage).
``map_update``
    `GroundMapper.update` of the floor mask at the frame's pose (the mapping stage),
    handing its due geometric tests (parallax, walls) out as the daemon does; they then
    run apart (`run_geometry_job`, the daemon's geometry thread, off the motors' path:
    timed as ``geometry_thread_ms``) and the next frame adopts the outcome.
``frontier``
    `GroundMapper.frontiers`, which the daemon runs every ``steering.frontier_period_s``
    (the copy of its inputs on the mapping thread, the search beside it).
``map_window``
    `map_window` around the robot, `clearance_ahead_m` of the frame's patch and the
    frontier path as points (the rest of the mapping stage's every-frame work).
``steering``
    `Steering.decide` on that window (the steering stage).
``world_map``
    The whole map classified for the web and other readers, which the daemon copies
    every ``WORLD_MAP_PERIOD_S``.
``floor_odometry``
    `GroundMapper.follow_floor`: a step against the key frame each time the camera has
    moved ``mapping.floor_odometry_step_m`` or turned ``floor_odometry_step_rad``,
    nothing otherwise; ``floor_odometry_steps`` counts the timed frames that ran a step.
    The mapping stage calls it for every frame once its map is out (off the way to the
    motors, but in the mapping thread's frame period).

``parallax``
    `confirm_floor` (`app.perception.planar`), the motion-parallax floor test the
    mapping stage runs at most every ``PARALLAX_PERIOD_S`` with ``mapping.parallax_floor``:
    timed apart on pairs of the drive's frames ``mapping.parallax_baseline_m`` apart, at
    least ``PARALLAX_CALLS`` calls, whether or not the configuration turns it on; also
    asking for what stands up (``return_standing``).

The two periodic stages are timed on every frame (for their statistics) but reported
apart, and amortised per frame by the share of frames that run them at the camera's
rate; steering follows a new frontier path only when the daemon's would.

Per stage: median, p95 and max wall time, and median CPU time of the process. Per frame
(the every-frame stages): wall time, and CPU time of the process
(`time.process_time`, all threads: OpenCV's or numba's helpers count) and of the calling
thread (`time.thread_time`); a difference between the two is work other threads did.
What a frame costs with its share of the periodic stages is set against the camera's
frame period (the budget: 33.3 ms at 30 fps).

A warm-up pass over the first frames, with a throwaway mapper and steering, compiles the
kernels and loads the network first.

``python -m app.benchmarks.frame_path [FRAMES]`` prints the result as JSON, pinned to
one CPU.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from app.benchmarks import pin_to_one_cpu
from app.config import FloornavConfig
from app.control.steering import Steering
from app.mapping.frames import Pose2D
from app.mapping.frontiers import FrontierSearch
from app.mapping.ground_map import (
    PARALLAX_PERIOD_S,
    GeometryOutcome,
    GroundMapper,
    run_geometry_job,
)
from app.perception.pipeline import FloorSegmenter
from app.perception.planar import PlanarParams, confirm_floor
from app.runtime import clearance_ahead_m, map_window, path_to_xy
from app.runtime.drive import premise_broken
from app.runtime.stages import WORLD_MAP_PERIOD_S
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration
from app.sim.world import World

PATH_RADIUS_M = 0.6
"""The drive's turning radius: from the shipped world's start pose the circle stays in
the living room, 0.6 m or more from its walls and boxes all the way round."""
DEFAULT_FRAMES = 60
WARMUP_FRAMES = 5
PER_FRAME_STAGES = ("perception", "map_update", "map_window", "steering", "floor_odometry")
STAGES = (
    "perception",
    "map_update",
    "frontier",
    "map_window",
    "steering",
    "world_map",
    "floor_odometry",
)
PARALLAX_CALLS = 50
"""The parallax test is timed this many times..."""
PARALLAX_PAIRS = 25
"""...round this many pairs of frames."""

_T = TypeVar("_T")


def drive_poses(
    start: Pose2D, n_frames: int, speed_m_s: float, fps_hz: float
) -> list[tuple[float, Pose2D]]:
    """(time s, robot pose in the start pose's frame) of ``n_frames`` camera frames on
    a right-hand circle of ``PATH_RADIUS_M`` driven at ``speed_m_s`` from ``start``.

    The poses are in the odometry frame (fixed at the start pose, as the daemon's
    mapper sees them); ``start.compose(pose)`` puts one in the world's plan frame."""
    poses = []
    for k in range(n_frames):
        t = k / fps_hz
        turned = speed_m_s * t / PATH_RADIUS_M
        arc = Pose2D(
            PATH_RADIUS_M * math.sin(turned), -PATH_RADIUS_M * (1 - math.cos(turned)), -turned
        )
        poses.append((t, arc))
    return poses


def path_min_clearance_m(world: World, plan_poses: list[Pose2D]) -> float:
    """The smallest distance from the robot's centre to a wall or box along the path."""
    return min(world.clearance_m(pose.x_m, pose.y_m) for pose in plan_poses)


@dataclass
class _Samples:
    """Per stage, in frame order: wall ms, CPU ms of the process, CPU ms of this thread."""

    wall_ms: dict[str, list[float]] = field(default_factory=dict)
    process_ms: dict[str, list[float]] = field(default_factory=dict)
    thread_ms: dict[str, list[float]] = field(default_factory=dict)

    def timed(self, stage: str, call: Callable[[], _T]) -> _T:
        wall, process, thread = time.perf_counter(), time.process_time(), time.thread_time()
        result = call()
        self.wall_ms.setdefault(stage, []).append((time.perf_counter() - wall) * 1e3)
        self.process_ms.setdefault(stage, []).append((time.process_time() - process) * 1e3)
        self.thread_ms.setdefault(stage, []).append((time.thread_time() - thread) * 1e3)
        return result

    def per_frame(self, by_stage: dict[str, list[float]]) -> list[float]:
        """Each frame's sum over the every-frame stages (not the periodic ones)."""
        return [
            sum(values) for values in zip(*(by_stage[s] for s in PER_FRAME_STAGES), strict=True)
        ]


def _summary(values: list[float]) -> dict[str, float]:
    data = np.asarray(values, dtype=np.float64)
    return {
        "median": round(float(np.median(data)), 3),
        "p95": round(float(np.percentile(data, 95)), 3),
        "max": round(float(data.max()), 3),
    }


class _FramePath:
    """One mapper and steering fed frame after frame, as the daemon's stages do."""

    def __init__(self, config: FloornavConfig, segmenter: FloorSegmenter) -> None:
        self.config = config
        self.segmenter = segmenter
        calibration = sim_floor_calibration(camera_model(config))
        self.mapper = GroundMapper(calibration, config.mapping, config.camera)
        self.steering = Steering(
            config.steering, config.safety, robot_radius_m=config.mapping.robot_radius_m
        )
        self.frontier: FrontierSearch | None = None
        self.frontier_due_s = 0.0
        self.reasons: dict[str, int] = {}
        self.geometry_outcome: GeometryOutcome | None = None
        self.geometry_ms: list[float] = []
        """Wall ms of each geometry job handed out (the daemon's geometry thread)."""

    def step(self, image: NDArray[np.uint8], t_s: float, pose: Pose2D, samples: _Samples) -> None:
        config, mapper = self.config, self.mapper
        floor = samples.timed("perception", lambda: self.segmenter.segment(image))
        update = samples.timed(
            "map_update",
            lambda: mapper.update(
                floor.floor_mask,
                pose,
                t_s,
                image,
                geometry="defer",
                geometry_outcome=self.geometry_outcome,
                safe_zone_px=floor.safe_zone_mask,
            ),
        )
        self.geometry_outcome = None
        if update.geometry_job is not None:
            start = time.perf_counter()
            self.geometry_outcome = run_geometry_job(update.geometry_job)
            self.geometry_ms.append((time.perf_counter() - start) * 1e3)
        search = samples.timed("frontier", lambda: mapper.frontiers(pose))
        if t_s >= self.frontier_due_s:  # the daemon adopts a search this often
            self.frontier_due_s = t_s + config.steering.frontier_period_s
            self.frontier = search
        frontier = self.frontier

        def window() -> tuple[Any, ...]:
            params = mapper.grid.params
            cells, grid = map_window(
                mapper.grid.log_odds,
                mapper.grid.world_grid,
                (pose.x_m, pose.y_m),
                config.steering.local_window_m,
                free_threshold=params.free_threshold,
                occupied_threshold=params.occupied_threshold,
            )
            clearance_ahead_m(
                update.patch,
                mapper.birdseye.grid,
                config.mapping.robot_radius_m,
                config.mapping.max_range_m,
            )
            goal = frontier.goal if frontier is not None else None
            path = path_to_xy(goal, mapper.grid.world_grid)
            return cells, grid, path

        cells, grid, path = samples.timed("map_window", window)
        # Perception that doubts the safe zone blocks the way ahead, unless the map knows
        # it is floor (`zone_blocks`).
        blocked = premise_broken(
            config.perception, floor.zone_floor_confidence, update.zone_known_floor
        )
        decision = samples.timed(
            "steering",
            lambda: self.steering.decide(cells, grid, pose, path, blocked_ahead=blocked),
        )
        self.reasons[decision.reason] = self.reasons.get(decision.reason, 0) + 1
        samples.timed("world_map", mapper.grid.classify)
        # The bench's poses are exact: a step's correction would be ~0, and it is not
        # fed back (the daemon puts it onto odometry, outside the mapper).
        samples.timed(
            "floor_odometry", lambda: mapper.follow_floor(image, floor.floor_mask, pose, t_s)
        )


def _frames(
    config: FloornavConfig, n_frames: int
) -> tuple[list[tuple[float, Pose2D, NDArray[np.uint8]]], World, float]:
    renderer = renderer_from_config(config)
    world = renderer.world
    drive = drive_poses(
        world.start_pose, n_frames, config.steering.cruise_speed_m_s, config.camera.fps_hz
    )
    plan_poses = [world.start_pose.compose(pose) for _, pose in drive]
    frames = [
        (t, pose, renderer.render(plan).image)
        for (t, pose), plan in zip(drive, plan_poses, strict=True)
    ]
    return frames, world, path_min_clearance_m(world, plan_poses)


def parallax_lag_frames(config: FloornavConfig) -> int:
    """Frames between the two views of the parallax test on the drive: the configured
    baseline at the cruise speed."""
    step_m = config.steering.cruise_speed_m_s / config.camera.fps_hz
    return max(1, round(config.mapping.parallax_baseline_m / step_m))


def _time_parallax(
    config: FloornavConfig,
    segmenter: FloorSegmenter,
    frames: list[tuple[float, Pose2D, NDArray[np.uint8]]],
) -> dict[str, Any]:
    """`confirm_floor` on ``PARALLAX_PAIRS`` frames, each against the one
    `parallax_lag_frames` before it, round the pairs until ``PARALLAX_CALLS`` calls, after
    an untimed call that compiles the kernels; the same again asking for what stands
    up."""
    lag = parallax_lag_frames(config)
    G = sim_floor_calibration(camera_model(config)).H_ground_from_image
    camera_xy = (config.camera.x_m, config.camera.y_m)
    params = PlanarParams()
    grays = [
        np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), np.uint8) for _, _, image in frames
    ]
    poses = [(pose.x_m, pose.y_m, pose.theta_rad) for _, pose, _ in frames]
    pairs = [
        (
            segmenter.segment(frames[k][2]).floor_mask,
            grays[k],
            grays[k - lag],
            poses[k - lag],
            poses[k],
        )
        for k in range(lag, lag + PARALLAX_PAIRS)
    ]
    samples: dict[bool, list[float]] = {False: [], True: []}
    for standing in (False, True):
        floor, cur, ref, ref_pose, cur_pose = pairs[0]
        confirm_floor(
            floor, cur, ref, G, ref_pose, cur_pose, camera_xy, params, return_standing=standing
        )
        while len(samples[standing]) < PARALLAX_CALLS:
            for floor, cur, ref, ref_pose, cur_pose in pairs:
                start = time.perf_counter()
                confirm_floor(
                    floor,
                    cur,
                    ref,
                    G,
                    ref_pose,
                    cur_pose,
                    camera_xy,
                    params,
                    return_standing=standing,
                )
                samples[standing].append((time.perf_counter() - start) * 1e3)
    return {
        **_summary(samples[False]),
        "standing_median": round(float(np.median(samples[True])), 3),
        "calls": len(samples[False]),
        "pairs": len(pairs),
        "baseline_m": round(lag * config.steering.cruise_speed_m_s / config.camera.fps_hz, 3),
        "period_s": PARALLAX_PERIOD_S,
        "configured": config.mapping.parallax_floor,
    }


def bench_frame_path(
    config: FloornavConfig, n_frames: int = DEFAULT_FRAMES, *, warmup_frames: int = WARMUP_FRAMES
) -> dict[str, Any]:
    """Time the daemon's per-frame path on ``n_frames`` simulated frames.

    Parameters
    ----------
    config : the configuration (perception method, mapping, steering, camera, sim)
    n_frames : int >= 1, timed frames
    warmup_frames : int >= 1, frames of the untimed warm-up pass (the first of the drive)

    Returns
    -------
    dict: ``stages_ms`` (per stage ``median``, ``p95``, ``max`` wall ms and
    ``cpu_median`` process-CPU ms), ``per_frame_ms`` and ``cpu_per_frame_ms``
    (``process`` and ``thread``, each ``median`` and ``p95``) over the every-frame
    stages, ``periodic`` (per periodic stage its ``period_s``, ``share`` of frames that
    run it, ``amortized_ms`` and ``cpu_amortized_ms``), ``amortized_per_frame_ms`` and
    ``cpu_amortized_per_frame_ms`` (per-frame medians plus the amortised periodic
    stages), ``frame_budget_ms``, ``budget_share`` (``wall``, ``cpu``),
    ``sustainable_fps``, and descriptions.
    """
    if n_frames < 1 or warmup_frames < 1:
        raise ValueError(f"frames: must be >= 1, got {n_frames} timed, {warmup_frames} warm-up")
    pinned = pin_to_one_cpu()
    segmenter = FloorSegmenter(config.perception)
    frames, world, clearance = _frames(
        config, max(n_frames, warmup_frames, parallax_lag_frames(config) + PARALLAX_PAIRS)
    )
    warmup = _FramePath(config, segmenter)
    for t_s, pose, image in frames[:warmup_frames]:
        warmup.step(image, t_s, pose, _Samples())
    measured = _FramePath(config, segmenter)  # a fresh map: the warm-up's frames again
    samples = _Samples()
    for t_s, pose, image in frames[:n_frames]:
        measured.step(image, t_s, pose, samples)
    stages = {
        stage: {
            **_summary(samples.wall_ms[stage]),
            "cpu_median": round(float(np.median(samples.process_ms[stage])), 3),
        }
        for stage in STAGES
    }
    fps = config.camera.fps_hz
    budget_ms = 1e3 / fps
    periods_s = {
        "frontier": config.steering.frontier_period_s,
        "world_map": WORLD_MAP_PERIOD_S,
    }
    periodic = {}
    for stage, period_s in periods_s.items():
        # The daemon runs it at most once a frame, and once per period at most.
        share = min(1.0, 1.0 / (fps * period_s))
        periodic[stage] = {
            "period_s": period_s,
            "share": round(share, 4),
            "amortized_ms": round(stages[stage]["median"] * share, 3),
            "cpu_amortized_ms": round(stages[stage]["cpu_median"] * share, 3),
        }
    per_frame_ms = _summary(samples.per_frame(samples.wall_ms))
    process = _summary(samples.per_frame(samples.process_ms))
    thread = _summary(samples.per_frame(samples.thread_ms))
    amortized = per_frame_ms["median"] + sum(p["amortized_ms"] for p in periodic.values())
    cpu_amortized = process["median"] + sum(p["cpu_amortized_ms"] for p in periodic.values())
    parallax = _time_parallax(config, segmenter, frames)
    return {
        "method": config.perception.method,
        "frames": n_frames,
        "warmup_frames": warmup_frames,
        "pinned": pinned,
        "stages_ms": stages,
        "per_frame_ms": per_frame_ms,
        "cpu_per_frame_ms": {
            "process": {"median": process["median"], "p95": process["p95"]},
            "thread": {"median": thread["median"], "p95": thread["p95"]},
        },
        "periodic": periodic,
        "amortized_per_frame_ms": round(amortized, 3),
        "cpu_amortized_per_frame_ms": round(cpu_amortized, 3),
        "camera_fps": fps,
        "frame_budget_ms": round(budget_ms, 3),
        "budget_share": {
            "wall": round(amortized / budget_ms, 3),
            "cpu": round(cpu_amortized / budget_ms, 3),
        },
        "sustainable_fps": round(1e3 / amortized, 1),
        "steering_reasons": measured.reasons,
        "floor_odometry_steps": measured.mapper.floor_odometry_steps,
        "parallax_ms": parallax,
        "geometry_thread_ms": {**_summary(measured.geometry_ms), "jobs": len(measured.geometry_ms)}
        if measured.geometry_ms
        else None,
        "frame": f"{config.camera.width_px}x{config.camera.height_px} simulated",
        "scene": f"world '{world.name}'",
        "path": (
            f"right-hand circle of {PATH_RADIUS_M} m from the start pose at "
            f"{config.steering.cruise_speed_m_s} m/s, {fps:g} frames/s"
        ),
        "path_min_clearance_m": round(clearance, 3),
    }


def format_frame_path(result: dict[str, Any]) -> str:
    """One human-readable block for ``floornav bench``."""
    stages = result["stages_ms"]
    per_frame, cpu = result["per_frame_ms"], result["cpu_per_frame_ms"]
    lines = [
        f"== daemon per-frame path, method {result['method']} ({result['frames']} frames;"
        f" {result['frame']}, {result['scene']}; median / p95 / max ms, CPU median)"
    ]
    for stage, s in stages.items():
        lines.append(
            f"  {stage:<12}{s['median']:>9.2f}{s['p95']:>9.2f}{s['max']:>9.2f}"
            f"{s['cpu_median']:>9.2f}"
        )
    periodic = ", ".join(
        f"{stage} every {p['period_s']:g} s +{p['amortized_ms']:.2f}"
        for stage, p in result["periodic"].items()
    )
    lines += [
        f"  {'per frame':<12}{per_frame['median']:>9.2f}{per_frame['p95']:>9.2f}"
        f"{per_frame['max']:>9.2f}   (every-frame stages)",
        f"  CPU per frame: process {cpu['process']['median']:.2f} (p95"
        f" {cpu['process']['p95']:.2f}), thread {cpu['thread']['median']:.2f} ms",
        f"  amortised ({periodic} ms a frame): {result['amortized_per_frame_ms']:.2f} ms,"
        f" CPU {result['cpu_amortized_per_frame_ms']:.2f} ms",
        f"  budget {result['frame_budget_ms']:.1f} ms at {result['camera_fps']:g} fps: wall"
        f" {result['budget_share']['wall']:.0%}, CPU {result['budget_share']['cpu']:.0%}"
        f" (sustains {result['sustainable_fps']:.0f} fps)",
    ]
    if "parallax_ms" in result:
        p = result["parallax_ms"]
        lines.append(
            f"  {'parallax':<12}{p['median']:>9.2f}{p['p95']:>9.2f}{p['max']:>9.2f}"
            f"   (every {p['period_s']:g} s when mapping.parallax_floor, now"
            f" {'on' if p['configured'] else 'off'}; {p['calls']} calls on {p['pairs']} pairs"
            f" {p['baseline_m']:g} m apart; with what stands up {p['standing_median']:.2f})"
        )
    thread = result.get("geometry_thread_ms")
    if thread:
        lines.append(
            f"  {'geometry':<12}{thread['median']:>9.2f}{thread['p95']:>9.2f}"
            f"{thread['max']:>9.2f}   ({thread['jobs']} jobs (parallax, walls) handed out by"
            " map_update, run beside the mapping thread)"
        )
    return "\n".join(lines)


def main(argv: list[str]) -> int:  # python -m app.benchmarks.frame_path [FRAMES]
    from app.cli import PROJECT_ROOT
    from app.config import load_config

    n_frames = int(argv[0]) if argv else DEFAULT_FRAMES
    pin_to_one_cpu()
    config = load_config(PROJECT_ROOT / "config.toml")
    print(json.dumps(bench_frame_path(config, n_frames), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
