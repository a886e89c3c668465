#!/usr/bin/env python3
"""How true is the map's standing layer, and does it leave the frontier search an edge
to probe? Exploration of the home ends in its living room when every occupied edge lies
near a cell geometry marked standing (`GroundMapper.frontier_probe_cells`): this drives
the same scripted tour as `scripts/measure_localization.py` (open loop, every frame
rendered, segmented and mapped as the daemon does; the daemon's timing plays no part)
with the shipped geometry and with the parallax test alone, and scores the layer
against the world's truth.

    .venv/bin/python scripts/measure_standing.py [--world home] [--seeds 0]

prints one line per run and writes docs/measurements/standing.json and the table
docs/standing.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from measure_localization import TOURS, drive_tour  # noqa: E402

from app.config import load_config  # noqa: E402
from app.mapping.frontiers import FrontierSearch  # noqa: E402
from app.mapping.ground_map import PROBE_STANDING_REACH_M, search_frontiers  # noqa: E402
from app.sim.truth import map_truth_scores, marks_near_truth  # noqa: E402

GEOMETRY = {
    # variant: the [mapping] switches it sets
    "shipped": {},
    "parallax alone": {"standing_by_horizon": False},
}


def goal_text(search: FrontierSearch) -> str:
    if search.goal is None:
        return f"none ({search.reason})"
    return "edge probe" if search.goal.probe else "frontier"


def run(world: str, seed: int, geometry: str) -> dict[str, object]:
    config = load_config(
        ROOT / "config.toml", sim={"world_file": world, "seed": seed}, mapping=GEOMETRY[geometry]
    )
    tour = drive_tour(config, TOURS[world], seed)
    mapper = tour.mapper
    grid = mapper.grid.world_grid
    standing = mapper.memory.standing != 0
    near = marks_near_truth(standing, grid, tour.start, tour.renderer.world)
    scores = map_truth_scores(mapper.grid.classify(), grid, tour.start, tour.renderer.world)
    inputs = mapper.frontier_inputs(tour.odometry.pose)
    search = search_frontiers(inputs)
    # The same map with every unproven edge probe-able: what the standing layer rules out.
    unruled = inputs._replace(probe_cells=np.asarray(~mapper.given_up.no_probe, dtype=np.bool_))
    return {
        "world": world,
        "seed": seed,
        "geometry": geometry,
        "tour_s": tour.tour_s,
        "finished": tour.finished,
        "collisions": tour.robot.collisions,
        "standing_m2": round(float(standing.sum()) * grid.cell_m**2, 2),
        "standing_near_truth": None if near is None else round(near, 3),
        "occupied_near_truth": round(scores.occupied_near_truth, 3),
        "map_iou": round(scores.map_iou, 3),
        "probe_edge_share": mapper.probe_edge_share(),
        "search": goal_text(search),
        "search_every_edge_probeable": goal_text(search_frontiers(unruled)),
        "wall_s": tour.wall_s,
    }


def table(command: str, rows: list[dict[str, object]]) -> str:
    lines = [
        "# The standing layer, measured",
        "",
        "Written by `scripts/measure_standing.py`: the scripted tour of",
        "`scripts/measure_localization.py` (open loop, every frame mapped as the daemon",
        "does), with the shipped geometry and with the parallax test alone",
        "(`[mapping] standing_by_horizon = false`). *Standing near truth*: of the cells",
        "marked standing, the share within one cell of a real wall or box. *Probe-able",
        "edges*: of the occupied cells, the share the frontier search may probe (an edge",
        f"within {PROBE_STANDING_REACH_M:g} m of a cell seen standing is taken for a real one).",
        "*Search*: what the",
        "frontier search at the tour's end picks, as shipped and with every edge",
        "probe-able.",
        "",
        f"Command: `{command}`",
        "",
        "| world | seed | geometry | standing m2 | standing near truth |"
        " occupied near truth | map IoU | probe-able edges | search | every edge probe-able |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['world']} | {r['seed']} | {r['geometry']} | {r['standing_m2']} |"
            f" {r['standing_near_truth']} | {r['occupied_near_truth']} | {r['map_iou']} |"
            f" {r['probe_edge_share']} | {r['search']} | {r['search_every_edge_probeable']} |"
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="home", choices=sorted(TOURS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs/measurements/standing.json")
    parser.add_argument(
        "--doc", type=Path, default=ROOT / "docs/standing.md", help="the table (none: -)"
    )
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        for geometry in GEOMETRY:
            row = run(args.world, seed, geometry)
            rows.append(row)
            print(json.dumps(row), flush=True)
    command = "scripts/measure_standing.py --world {} --seeds {}".format(
        args.world, " ".join(map(str, args.seeds))
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": command, "runs": rows}, indent=2) + "\n")
    if str(args.doc) != "-":
        args.doc.write_text(table(command, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
