#!/usr/bin/env python3
"""Which localization keeps the pose, and the map, closest to the truth: wheel odometry
alone, scan matching against the map, or odometry on the floor's motion? An open-loop
A/B on the simulator, free of the daemon's timing and the machine's load: the same
scripted tour (waypoints in the plan frame, driven by a controller that sees the true
pose, with spin turns to look around as exploration does) is driven with the shipped
wheel-slip model; every frame is rendered, segmented by the shipped method and fused by
the mapper at the odometry pose, corrected by the variant.

    .venv/bin/python scripts/measure_localization.py [--world two-rooms] [--seeds 0 1 2]
        [--slip on off] [--localization wheels "floor odometry" "floor odometry + axis"]

prints one line per run and writes docs/measurements/localization.json and the table
docs/localization.md.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.config import FloornavConfig, load_config  # noqa: E402
from app.control.kinematics import WheelOdometry, twist_to_pwm  # noqa: E402
from app.control.mux import Twist  # noqa: E402
from app.devices import robot_params  # noqa: E402
from app.mapping.frames import Pose2D  # noqa: E402
from app.mapping.ground_map import GroundMapper  # noqa: E402
from app.perception.pipeline import FloorSegmenter  # noqa: E402
from app.sim.render import Renderer  # noqa: E402
from app.sim.robot import SimRobot  # noqa: E402
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration  # noqa: E402
from app.sim.truth import map_truth_scores  # noqa: E402

FRAME_S = 1 / 30
PHYSICS_S = 0.01

Leg = str | tuple[float, float]
"""A tour's step: a plan-frame waypoint, or "spin" (a full turn in place)."""

TOURS: dict[str, list[Leg]] = {
    # Plan-frame waypoints; "spin" turns a full circle in place (exploration's look-around).
    "two-rooms": [
        "spin",
        (2.9, 3.0),
        (2.9, 2.2),
        "spin",
        (1.5, 2.0),
        (1.5, 3.3),
        "spin",
        (1.2, 4.5),
        (3.9, 4.6),
        "spin",
        (3.9, 3.4),
        (1.3, 3.2),
    ],
    # The living room: in front of the hallway's door, of the kitchen's, by the armchair.
    "home": [
        "spin",
        (2.0, 3.75),
        "spin",
        (4.7, 6.1),
        "spin",
        (3.3, 5.0),
        (3.4, 7.0),
        "spin",
        (3.4, 5.0),
        (1.5, 4.0),
        "spin",
    ],
    # Down the glossy corridor, into the open-plan office and the meeting room, and back.
    "office": [
        "spin",
        (3.5, 3.5),
        "spin",
        (6.45, 3.5),
        (6.45, 1.6),
        "spin",
        (6.45, 3.5),
        (9.0, 3.6),
        "spin",
        (2.45, 3.5),
        (2.45, 5.4),
        "spin",
        (2.45, 3.5),
        (1.0, 3.5),
    ],
}


def heading_error(pose: Pose2D, target: tuple[float, float]) -> tuple[float, float]:
    dx, dy = target[0] - pose.x_m, target[1] - pose.y_m
    return math.hypot(dx, dy), math.remainder(math.atan2(dy, dx) - pose.theta_rad, math.tau)


LOCALIZATION = {
    # variant: the [mapping] switches it sets
    "wheels": {"scan_matching": False, "floor_odometry": False, "manhattan_heading": False},
    "scan matching": {"scan_matching": True, "floor_odometry": False, "manhattan_heading": False},
    "floor odometry": {"scan_matching": False, "floor_odometry": True, "manhattan_heading": False},
    "axis": {"scan_matching": False, "floor_odometry": False, "manhattan_heading": True},
    # shipped
    "floor odometry + axis": {
        "scan_matching": False,
        "floor_odometry": True,
        "manhattan_heading": True,
    },
}


@dataclass
class Tour:
    """A driven tour: the simulator, the mapper it fed and how the pose kept."""

    renderer: Renderer
    robot: SimRobot
    mapper: GroundMapper
    odometry: WheelOdometry
    start: Pose2D
    errors: list[float]
    """Distance between the estimated and the true pose, every frame."""
    heading_errors: list[float]
    """Angle between the estimated and the true heading, every frame (radians, >= 0)."""
    tour_s: float
    finished: bool
    wall_s: float


def drive_tour(
    config: FloornavConfig,
    legs: list[Leg],
    seed: int,
    max_s: float = 240.0,
    prepare: Callable[[GroundMapper, SimRobot, Pose2D], None] | None = None,
) -> Tour:
    """Drive ``legs`` in ``config``'s world and map every frame as the daemon does (the
    learned floor handed to the segmenter twice a second, floor odometry after each
    frame's map); stops at the end, after ``max_s`` or at a collision. ``prepare`` is
    handed the mapper, the simulated robot and the start pose before the first frame
    (an evaluation's hook: `scripts/eval_scan_match.py` swaps in its own localizer)."""
    renderer = renderer_from_config(config)
    robot = SimRobot(renderer.world, robot_params(config), seed=seed)
    start = renderer.world.start_pose
    odometry = WheelOdometry(config.drive)
    segmenter = FloorSegmenter(config.perception)
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    errors: list[float] = []
    heading_errors: list[float] = []
    t = 0.0
    spun = 0.0
    legs = list(legs)
    last_appearances = -1.0
    cruise = config.steering.cruise_speed_m_s
    turn = config.steering.turn_speed_rad_s
    if prepare is not None:
        prepare(mapper, robot, start)
    started = time.perf_counter()
    while legs and t < max_s and robot.collisions == 0:
        truth = robot.pose
        leg = legs[0]
        if leg == "spin":
            twist = Twist(0.0, turn)
            spun += turn * FRAME_S
            if spun >= math.tau:
                legs.pop(0)
                spun = 0.0
        else:
            assert isinstance(leg, tuple)
            distance, error = heading_error(truth, leg)
            if distance < 0.1:
                legs.pop(0)
                twist = Twist(0.0, 0.0)
            elif abs(error) > 0.5:
                twist = Twist(0.0, math.copysign(turn, error))
            else:
                twist = Twist(cruise * min(1.0, distance / 0.3), 2.0 * error)
        robot.apply_pwm(*twist_to_pwm(twist, config.drive))
        for _ in range(round(FRAME_S / PHYSICS_S)):
            robot.step(PHYSICS_S)
        t += FRAME_S
        odometry.update(*robot.read_encoders(), t)
        frame = renderer.render(robot.pose)
        if t - last_appearances >= 0.5:
            segmenter.learned_floor = mapper.memory.appearances()
            last_appearances = t
        result = segmenter.segment(frame.image)
        pose = odometry.pose
        update = mapper.update(result.floor_mask, pose, t, frame.image)
        if update.correction is not None:
            odometry.correct(update.correction)
            pose = update.correction.compose(pose)
        # As the daemon's mapping stage does, once the frame's map is out.
        step = mapper.follow_floor(frame.image, result.floor_mask, pose, t)
        if step is not None:
            odometry.correct(step)
        # The odometry frame starts at the start pose (as the daemon's T_plan_odom).
        estimate = start.compose(odometry.pose)
        true = robot.pose
        errors.append(math.hypot(estimate.x_m - true.x_m, estimate.y_m - true.y_m))
        heading_errors.append(abs(math.remainder(estimate.theta_rad - true.theta_rad, math.tau)))
    return Tour(
        renderer,
        robot,
        mapper,
        odometry,
        start,
        errors,
        heading_errors,
        round(t, 1),
        not legs,
        round(time.perf_counter() - started, 1),
    )


def percentile(values: list[float], share: float) -> float:
    ordered = sorted(values)
    return ordered[round(share * (len(ordered) - 1))]


def run_tour(world: str, seed: int, localization: str, *, slip: bool = True) -> dict[str, object]:
    sim: dict[str, object] = {"world_file": world, "seed": seed}
    if not slip:
        sim.update(slip_sigma_frac=0.0, wheel_scale_sigma_frac=0.0, encoder_tick_noise=0.0)
    config = load_config(ROOT / "config.toml", sim=sim, mapping=LOCALIZATION[localization])
    tour = drive_tour(config, TOURS[world], seed)
    mapper, errors = tour.mapper, tour.errors
    classes = mapper.grid.classify()
    scores = map_truth_scores(
        classes, mapper.grid.world_grid, tour.start, tour.renderer.world
    ).as_dict()
    localizer = mapper.localizer
    return {
        "world": world,
        "seed": seed,
        "localization": localization,
        "slip": slip,
        "tour_s": tour.tour_s,
        "finished": tour.finished,
        "distance_m": round(tour.odometry.distance_m, 2),
        "collisions": tour.robot.collisions,
        "pose_error_m": {
            "p50": round(statistics.median(errors), 3),
            "p95": round(percentile(errors, 0.95), 3),
            "final": round(errors[-1], 3),
        },
        "heading_error_deg": {
            "p50": round(math.degrees(statistics.median(tour.heading_errors)), 2),
            "p95": round(math.degrees(percentile(tour.heading_errors, 0.95)), 2),
        },
        "map_iou": scores["map_iou"],
        "free_precision": scores.get("free_precision"),
        "occupied_near_truth": scores.get("occupied_near_truth"),
        "matches": None
        if localizer is None
        else {"attempts": localizer.attempts, "applied": localizer.applied},
        "floor_steps": None
        if not mapper.floor_odometry
        else {"attempts": mapper.floor_odometry_steps, "applied": mapper.floor_odometry_applied},
        "heading_axis": None if mapper.heading_axis is None else mapper.heading_axis.summary(),
        "wall_s": tour.wall_s,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["two-rooms"], choices=sorted(TOURS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--slip",
        nargs="+",
        choices=["on", "off"],
        default=["on", "off"],
        help="wheel slip; off: ideal wheels (what scan matching adds by itself)",
    )
    parser.add_argument(
        "--localization", nargs="+", choices=sorted(LOCALIZATION), default=list(LOCALIZATION)
    )
    parser.add_argument("--out", type=Path, default=ROOT / "docs/measurements/localization.json")
    parser.add_argument(
        "--doc", type=Path, default=ROOT / "docs/localization.md", help="the table (none: -)"
    )
    args = parser.parse_args()
    if str(args.doc) == "-":
        args.doc = None
    rows = []
    for world in args.worlds:
        for slip in args.slip:
            for seed in args.seeds:
                for localization in args.localization:
                    row = run_tour(world, seed, localization, slip=slip == "on")
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    command = "scripts/measure_localization.py --worlds {} --seeds {} --slip {}".format(
        " ".join(args.worlds), " ".join(map(str, args.seeds)), " ".join(args.slip)
    )
    if args.localization != list(LOCALIZATION):
        command += " --localization " + " ".join(f'"{v}"' for v in args.localization)
    args.out.write_text(json.dumps({"command": command, "runs": rows}, indent=2) + "\n")
    if args.doc is not None:
        args.doc.write_text(table(command, rows))
    return 0


def table(command: str, rows: list[dict[str, object]]) -> str:
    lines = [
        "# Localization, measured",
        "",
        "Written by `scripts/measure_localization.py`: the same scripted tour of a",
        "simulated world (waypoints and full spin turns, driven by a controller that sees",
        "the true pose), every frame rendered, segmented by the shipped method and fused",
        "at the odometry pose, corrected by nothing (wheels), by scan matching against the",
        "map (`[mapping] scan_matching`), by the floor's motion between key frames",
        "(`[mapping] floor_odometry`), by the building's axis (`[mapping]",
        "manhattan_heading`: the heading held to the walls' straight feet), or by the",
        "floor's motion and the axis together (shipped).",
        "Open loop, so every variant sees the same frames; the daemon's timing plays no part.",
        "",
        f"Command: `{command}`",
        "",
        "| world | seed | wheel slip | localization | pose error p50 / p95 / final m |"
        " heading error p50 / p95 deg | map IoU | occupied near truth |"
        " corrections applied / tried |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        pose, heading = r["pose_error_m"], r.get("heading_error_deg")
        assert isinstance(pose, dict)
        turned = (
            "-" if not isinstance(heading, dict) else f"{heading['p50']:.2f} / {heading['p95']:.2f}"
        )
        matches = r["matches"] if r["matches"] is not None else r["floor_steps"]
        applied = (
            "-"
            if not isinstance(matches, dict)
            else (f"{matches['applied']} / {matches['attempts']}")
        )
        lines.append(
            f"| {r['world']} | {r['seed']} | {'on' if r['slip'] else 'off'} |"
            f" {r['localization']} |"
            f" {pose['p50']:.3f} / {pose['p95']:.3f} / {pose['final']:.3f} | {turned} |"
            f" {r['map_iou']:.3f} | {r['occupied_near_truth']:.3f} | {applied} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
