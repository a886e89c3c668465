#!/usr/bin/env python3
"""How close the scan matcher (`app.mapping.scan_match`) brings a pose to the truth.

Each world's scripted tour (`scripts/measure_localization.py`) is driven with ideal
wheels, so the map is fused at the true pose (within the frames' timing), and scan
matching on. Every time a match is due, the matcher starts from the true pose moved by
a random offset in the robot's frame (uniform within +-``--offset-m`` in x and y and
+-``--offset-deg`` in heading), and nothing it finds is applied. Per world:

- the error of that prior and of the match against the truth (position and heading,
  median and p90), over all matches and over those the matcher calls confident;
- whether the match's own covariance explains its error: the median squared
  Mahalanobis distance (a calibrated covariance gives 2.37, the chi-square median of
  three degrees of freedom);
- a heading-only search from the true position (+-1 mm), the prior's heading offset
  kept: what the scan says about the heading alone;
- where the scan's returns lie at the true pose against the map, per range band: the
  share with an occupied cell within 0.3 m along their ray, and the median signed
  distance to the nearest one (positive: the map's obstacle lies past the return).

    .venv/bin/python scripts/eval_scan_match.py [--worlds two-rooms home office]

prints one JSON line per world and writes docs/measurements/scan_match.json and the
table docs/scan-matching.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import measure_localization as tours

from app.config import load_config
from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.ground_map import GroundMapper
from app.mapping.scan_match import (
    Localization,
    ScanLocalizer,
    known_to_map,
    match_scan,
    virtual_scan,
)
from app.sim.robot import SimRobot

ROOT = Path(__file__).resolve().parents[1]
RANGE_BANDS_M = ((0.0, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 2.5), (2.5, 3.0))
ALONG_RAY_M = np.round(np.arange(-0.3, 0.3001, 0.01), 3)
CHI2_3DOF_MEDIAN = 2.366


@dataclass
class Record:
    prior_error: tuple[float, float, float]
    match_error: tuple[float, float, float]
    heading_only_error_rad: float
    mahalanobis2: float
    confident: bool


class ObservingLocalizer(ScanLocalizer):
    """The mapper's localizer, matching from the truth moved by a random offset and
    applying nothing; it keeps what it found against the truth."""

    def __init__(
        self,
        base: ScanLocalizer,
        robot: SimRobot,
        start: Pose2D,
        offset: tuple[float, float],
        seed: int,
    ) -> None:
        super().__init__(base.params, base.patch_grid, base.origin_xy, base.bearings_rad)
        self.robot = robot
        self.start = start
        self.offset_m, self.offset_rad = offset
        self.rng = np.random.default_rng(seed)
        self.records: list[Record] = []
        self.returns: list[tuple[float, float]] = []
        """(range m, signed distance to the nearest occupied cell along the ray or NaN)"""
        self.heading_only = replace(
            base.params.match, window_m=1e-3, coarse_step_m=1e-3, fine_step_m=1e-3
        )

    def localize(
        self,
        patch: NDArray[np.uint8],
        log_odds: NDArray[np.floating],
        world_grid: GroundGrid,
        thresholds: tuple[float, float],
        T_world_robot: Pose2D,
        now_s: float,
    ) -> Localization | None:
        if not self.due(now_s):
            return None
        self._due_s = now_s + self.params.period_s
        # The frame was rendered at the robot's pose; odometry's frame starts at the start.
        truth = self.start.inverse().compose(self.robot.pose)
        self._returns_at_truth(patch, log_odds, world_grid, thresholds, truth)
        unit = self.rng.uniform(-1.0, 1.0, 3)
        prior = truth.compose(
            Pose2D(unit[0] * self.offset_m, unit[1] * self.offset_m, unit[2] * self.offset_rad)
        )
        found = self.scan_and_field(patch, log_odds, world_grid, thresholds, prior)
        if found is None:
            return None
        points, field_ = found
        match = match_scan(field_, points, prior, self.params.match)
        start_heading = Pose2D(truth.x_m, truth.y_m, prior.theta_rad)
        heading = match_scan(field_, points, start_heading, self.heading_only)
        error = truth.inverse().compose(match.T_world_robot)
        # The covariance is in the world frame's (x, y, theta).
        c, s = math.cos(truth.theta_rad), math.sin(truth.theta_rad)
        world_error = np.array(
            [c * error.x_m - s * error.y_m, s * error.x_m + c * error.y_m, error.theta_rad]
        )
        covariance = match.covariance + np.diag([1e-10, 1e-10, 1e-10])
        prior_error = truth.inverse().compose(prior)
        self.records.append(
            Record(
                (prior_error.x_m, prior_error.y_m, prior_error.theta_rad),
                (error.x_m, error.y_m, error.theta_rad),
                math.remainder(heading.T_world_robot.theta_rad - truth.theta_rad, math.tau),
                float(world_error @ np.linalg.solve(covariance, world_error)),
                match.confident(self.params.match),
            )
        )
        return None

    def _returns_at_truth(
        self,
        patch: NDArray[np.uint8],
        log_odds: NDArray[np.floating],
        world_grid: GroundGrid,
        thresholds: tuple[float, float],
        truth: Pose2D,
    ) -> None:
        p = self.params
        scan = virtual_scan(
            patch, self.patch_grid, self.origin_xy, self.bearings_rad, max_range_m=p.max_range_m
        )
        known = known_to_map(
            scan,
            log_odds,
            world_grid,
            truth,
            free_threshold=thresholds[0],
            back_m=p.known_floor_m,
        )
        bearings = scan.bearings_rad[scan.hit][known]
        ranges = scan.ranges_m[scan.hit][known]
        if ranges.size == 0:
            return
        along = np.maximum(ranges[:, None] + ALONG_RAY_M[None, :], 0.0)
        x = self.origin_xy[0] + along * np.cos(bearings)[:, None]
        y = self.origin_xy[1] + along * np.sin(bearings)[:, None]
        cells = world_grid.cell_of(truth.apply(np.column_stack((x.ravel(), y.ravel()))))
        inside = world_grid.holds(cells)
        occupied = np.zeros(inside.size, dtype=bool)
        occupied[inside] = log_odds[cells[inside, 0], cells[inside, 1]] > thresholds[1]
        occupied = occupied.reshape(along.shape)
        distance = np.where(occupied, np.abs(ALONG_RAY_M)[None, :], np.inf)
        nearest = np.argmin(distance, axis=1)
        found = occupied[np.arange(ranges.size), nearest]
        signed = np.where(found, ALONG_RAY_M[nearest], np.nan)
        self.returns.extend(zip(ranges.tolist(), signed.tolist(), strict=True))


def evaluate(world: str, offset: tuple[float, float], seed: int) -> dict[str, object]:
    sim = {
        "world_file": world,
        "seed": seed,
        "slip_sigma_frac": 0.0,
        "wheel_scale_sigma_frac": 0.0,
        "encoder_tick_noise": 0.0,
    }
    mapping = {"scan_matching": True, "floor_odometry": False}
    config = load_config(ROOT / "config.toml", sim=sim, mapping=mapping)
    observers: list[ObservingLocalizer] = []

    def prepare(mapper: GroundMapper, robot: SimRobot, start: Pose2D) -> None:
        assert mapper.localizer is not None
        observer = ObservingLocalizer(mapper.localizer, robot, start, offset, seed)
        mapper.localizer = observer
        observers.append(observer)

    tour = tours.drive_tour(config, tours.TOURS[world], seed, prepare=prepare)
    observer = observers[0]
    records = observer.records
    confident = [r for r in records if r.confident]
    returns = np.array(observer.returns, dtype=np.float64).reshape(-1, 2)
    bands = []
    for low, high in RANGE_BANDS_M:
        band = returns[(returns[:, 0] >= low) & (returns[:, 0] < high)]
        near = band[np.isfinite(band[:, 1]), 1]
        bands.append(
            {
                "range_m": [low, high],
                "returns": int(band.shape[0]),
                "with_obstacle_within_0_3_m": round(near.size / band.shape[0], 3)
                if band.shape[0]
                else None,
                "median_signed_m": round(float(np.median(near)), 3) if near.size else None,
            }
        )
    return {
        "world": world,
        "seed": seed,
        "offset": {"m": offset[0], "deg": round(math.degrees(offset[1]), 3)},
        "tour_s": tour.tour_s,
        "matches": len(records),
        "confident": len(confident),
        "prior": errors([r.prior_error for r in records]),
        "match": errors([r.match_error for r in records]),
        "confident_prior": errors([r.prior_error for r in confident]),
        "confident_match": errors([r.match_error for r in confident]),
        "heading_only_deg": spread([math.degrees(abs(r.heading_only_error_rad)) for r in records]),
        "mahalanobis2_median": round(float(np.median([r.mahalanobis2 for r in records])), 1)
        if records
        else None,
        "returns_at_truth": bands,
    }


def spread(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    return {
        "p50": round(float(np.median(values)), 3),
        "p90": round(float(np.percentile(values, 90)), 3),
    }


def errors(rows: list[tuple[float, float, float]]) -> dict[str, object]:
    return {
        "position_m": spread([math.hypot(x, y) for x, y, _ in rows]),
        "heading_deg": spread([math.degrees(abs(t)) for _, _, t in rows]),
    }


def table(command: str, rows: list[dict[str, object]]) -> str:
    def cell(e: object) -> str:
        assert isinstance(e, dict)
        pos, head = e["position_m"], e["heading_deg"]
        if pos is None or head is None:
            return "-"
        return f"{pos['p50']:.3f} / {pos['p90']:.3f} m, {head['p50']:.2f} / {head['p90']:.2f}°"

    lines = [
        "# Scan matching against the truth",
        "",
        "Written by `scripts/eval_scan_match.py`: each world's scripted tour with ideal",
        "wheels (the map fused at the true pose), every due match started from the true",
        "pose moved by a random offset and nothing applied. Errors are median / p90.",
        "",
        f"Command: `{command}`",
        "",
        "| world | matches (confident) | prior | match | confident: prior | confident: match |"
        f" heading only | Mahalanobis² median (calibrated: {CHI2_3DOF_MEDIAN:.2f}) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        head = r["heading_only_deg"]
        assert isinstance(head, dict) or head is None
        heading = "-" if head is None else f"{head['p50']:.2f} / {head['p90']:.2f}°"
        lines.append(
            f"| {r['world']} | {r['matches']} ({r['confident']}) | {cell(r['prior'])} |"
            f" {cell(r['match'])} | {cell(r['confident_prior'])} |"
            f" {cell(r['confident_match'])} |"
            f" {heading} |"
            f" {r['mahalanobis2_median']} |"
        )
    lines += [
        "",
        "The scan's returns at the true pose against the map: the share with an occupied",
        "cell within 0.3 m along their ray, and the median signed distance to it",
        "(positive: the map's obstacle lies past the return).",
        "",
        "| world | " + " | ".join(f"{a:.1f}-{b:.1f} m" for a, b in RANGE_BANDS_M) + " |",
        "|---|" + "---|" * len(RANGE_BANDS_M),
    ]
    for r in rows:
        bands = r["returns_at_truth"]
        assert isinstance(bands, list)
        cells = []
        for band in bands:
            share, signed = band["with_obstacle_within_0_3_m"], band["median_signed_m"]
            cells.append(
                "-"
                if share is None
                else f"{share:.2f}, {'-' if signed is None else f'{signed:+.2f} m'}"
                f" ({band['returns']})"
            )
        lines.append(f"| {r['world']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--worlds", nargs="+", default=["two-rooms", "home", "office"], choices=sorted(tours.TOURS)
    )
    parser.add_argument("--offset-m", type=float, default=0.05)
    parser.add_argument("--offset-deg", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "docs/measurements/scan_match.json")
    parser.add_argument(
        "--doc", type=Path, default=ROOT / "docs/scan-matching.md", help="the table (none: -)"
    )
    args = parser.parse_args()
    offset = (args.offset_m, math.radians(args.offset_deg))
    rows = []
    for world in args.worlds:
        row = evaluate(world, offset, args.seed)
        rows.append(row)
        print(json.dumps(row), flush=True)
    command = (
        "scripts/eval_scan_match.py --worlds {} --offset-m {} --offset-deg {} --seed {}".format(
            " ".join(args.worlds), args.offset_m, args.offset_deg, args.seed
        )
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": command, "worlds": rows}, indent=2) + "\n")
    if str(args.doc) != "-":
        args.doc.write_text(table(command, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
