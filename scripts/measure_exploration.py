#!/usr/bin/env python3
"""Explore every shipped world with several seeds and write docs/exploration.md.

    .venv/bin/python scripts/measure_exploration.py [--duration-s 300] [--seeds 0 1 2]
        [--worlds two-rooms home office] [--keep-maps DIR]

Each run is ``floornav run --world W --seed S --duration-s D --report R --map M``, one at
a time (the runs measure latency: run them on a quiet machine). The reports go to
docs/measurements/explore-W-sS.json, a bird's-eye picture of each world's final map
beside its truth to docs/exploration/W-sS.png (scripts/render_map_truth.py), and the table
to docs/exploration.md. ``--table-only`` rewrites the table from the reports there;
``--keep-maps DIR`` keeps each run's map file in DIR to look into afterwards.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MEASUREMENTS = ROOT / "docs" / "measurements"
PICTURES = ROOT / "docs" / "exploration"
FLOORNAV = ROOT / ".venv" / "bin" / "floornav"
PYTHON = ROOT / ".venv" / "bin" / "python"


def build() -> str:
    """The commit measured ("+dirty" with uncommitted changes to tracked files)."""
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    # The runs' own outputs (docs/) do not make the build dirty: the code does.
    dirty = (
        subprocess.run(["git", "diff", "--quiet", "HEAD", "--", ".", ":!docs"], cwd=ROOT).returncode
        != 0
    )
    return head + ("+dirty" if dirty else "")


def run_one(
    world: str, seed: int, duration_s: float, commit: str, keep_maps: Path | None = None
) -> Path:
    report = MEASUREMENTS / f"explore-{world}-s{seed}.json"
    with tempfile.TemporaryDirectory() as tmp:
        # Kept maps (with their ROS .pgm/.yaml) are for looking into a run afterwards:
        # `scripts/render_map_truth.py`, or `app.mapping.map_files.load_map`.
        folder = Path(tmp) if keep_maps is None else keep_maps
        map_path = folder / f"explore-{world}-s{seed}.npz"
        command = [
            str(FLOORNAV),
            "run",
            "--world",
            world,
            "--seed",
            str(seed),
            "--duration-s",
            str(duration_s),
            "--report",
            str(report),
            "--map",
            str(map_path),
        ]
        print(" ".join(command), flush=True)
        # Ports of their own: a daemon or test elsewhere on the machine keeps its own.
        env = {**os.environ, "FLOORNAV_WEB__PORT": "18080", "FLOORNAV_VISER__PORT": "18081"}
        subprocess.run(command, check=True, cwd=ROOT, stdout=subprocess.DEVNULL, env=env)
        # The table may mix builds (`--seeds`, `--worlds`): each report says its own.
        measured = json.loads(report.read_text())
        measured["build"] = commit
        report.write_text(json.dumps(measured, indent=2) + "\n")
        PICTURES.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [
                str(PYTHON),
                str(ROOT / "scripts" / "render_map_truth.py"),
                str(map_path),
                "--world",
                world,
                "--out",
                str(PICTURES / f"{world}-s{seed}.png"),
            ],
            check=True,
            cwd=ROOT,
        )
    return report


def cell(value: object, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def table(command: str) -> str:
    rows = [
        "# Exploration, measured",
        "",
        "Written by `scripts/measure_exploration.py` from the run reports in",
        "[measurements/](measurements/) (`explore-WORLD-sSEED.json`); the pictures in",
        "[exploration/](exploration/) show each final map (right: free white, occupied",
        "black, unknown grey) beside the world's truth (left), start green, end red.",
        "*Standing near truth*: of the cells geometry marked standing, the share within",
        "one cell of a real wall or box; *probe-able edges*: of the cells the map calls",
        "occupied, the share the frontier search may still probe (near 0, exploration",
        "ends at the first edge the robot cannot prove floor); *premise stops (map",
        "knew)*: stops because the safe zone was not floor, and in brackets the frames",
        "whose zone perception doubted but the map knew was floor; '-' for older",
        "reports. *Build*: the commit each run measured. The coverages and map scores",
        "are of the map as the robot knows it (faded evidence at its last class, as it",
        "plans and saves it); *coverage, evidence alone*: of the evidence that travel",
        "has not faded (`map_truth_live`; '-' for reports before it).",
        "",
        f"Latest command: `{command}` (the rows of other builds are earlier runs of",
        "this script; the build column says which).",
        "",
        "| build | world | seed | s | reachable coverage | coverage | coverage, evidence alone | "
        "time to 50 % / 90 % s | "
        "final state | home m | collisions | occupied near truth | standing near truth | "
        "probe-able edges | goals given up (whole frontiers) | premise stops (map knew) | "
        "map IoU | pose error p95 m | heading error p95 deg | latency p95 ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for path in sorted(MEASUREMENTS.glob("explore-*.json")):
        r = json.loads(path.read_text())
        truth = r.get("map_truth") or {}
        ttc = r.get("time_to_coverage_s") or {}
        pose = r.get("pose_error_m") or {}
        memory = r.get("floor_memory") or {}
        rows.append(
            "| "
            + " | ".join(
                [
                    cell(r.get("build")),
                    cell(r.get("world")),
                    cell(r.get("seed")),
                    f"{r['duration_s']:.0f}",
                    cell(r.get("coverage_reachable")),
                    cell(r.get("coverage_ratio")),
                    cell((r.get("map_truth_live") or {}).get("coverage_ratio")),
                    f"{cell(ttc.get('50'), 0)} / {cell(ttc.get('90'), 0)}",
                    cell(r.get("final_state")),
                    cell((r.get("exploration") or {}).get("home_distance_m"), 2),
                    cell(r.get("collisions")),
                    cell(truth.get("occupied_near_truth")),
                    cell(memory.get("standing_near_truth")),
                    cell(memory.get("probe_edge_share")),
                    f"{cell(r.get('goals_given_up'))} "
                    f"({cell(r.get('frontier_clusters_given_up'))})",
                    f"{cell(r.get('premise_stops'))} ({cell(r.get('zone_known_floor_frames'))})",
                    cell(truth.get("map_iou")),
                    cell(pose.get("p95")),
                    cell((r.get("heading_error_deg") or {}).get("p95"), 2),
                    cell((r.get("latency_ms") or {}).get("p95"), 1),
                ]
            )
            + " |"
        )
    return "\n".join(rows) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=300.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--worlds", nargs="+", default=["two-rooms", "home", "office"])
    parser.add_argument("--table-only", action="store_true")
    parser.add_argument(
        "--keep-maps",
        type=Path,
        metavar="DIR",
        help="also keep each run's map file here (explore-WORLD-sSEED.npz; not in docs/)",
    )
    args = parser.parse_args()
    MEASUREMENTS.mkdir(parents=True, exist_ok=True)
    if args.keep_maps is not None:
        args.keep_maps.mkdir(parents=True, exist_ok=True)
    command = "scripts/measure_exploration.py " + " ".join(sys.argv[1:])
    if not args.table_only:
        commit = build()
        for world in args.worlds:
            for seed in args.seeds:
                run_one(world, seed, args.duration_s, commit, args.keep_maps)
    (ROOT / "docs" / "exploration.md").write_text(table(command.strip()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
