"""Measure perception with floornav's own commands and write docs/perception.md.

    .venv/bin/python scripts/measure_perception.py [--reuse] [--only NAME...]

Runs, each with ``--json``, and keeps the output in docs/measurements/NAME.json:

- ``cv``: ``floornav eval DATASETS --cv --method flood_fill,thesis,thesis_junction,floornav``
  (leave one scene out)
- ``cv-floornet``: ``floornav eval DATASETS --cv --folds 5 --method floornet`` (the network
  is trained from scratch in each of 5 folds of whole scenes; needs the ``train`` extra;
  about 20 minutes on 2 cores)
- ``sim-eval``: ``floornav sim-eval --method all``
- ``bench``: ``floornav bench``
- ``eval-video``: ``floornav eval-video`` on the shared robot videos, every 2nd frame

then renders docs/perception.md from those files. ``--reuse`` keeps a measurement whose
JSON file already exists; ``--only`` re-runs just the named ones.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from app.benchmarks import cpu_name

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT.parent / "shared" / "datasets"
REL_DATASETS = "../shared/datasets"
LABELLED = ("robot-hand-floor", "hospital-ground", "umd-drivable-toy")
VIDEOS = ("robot-video-carpet/recording.avi", "robot-video-carpet/video2.avi")
OUT_DIR = ROOT / "docs" / "measurements"
DOC = ROOT / "docs" / "perception.md"


def commands() -> dict[str, list[str]]:
    labelled = [f"{REL_DATASETS}/{d}" for d in LABELLED]
    videos = [f"{REL_DATASETS}/{v}" for v in VIDEOS]
    cheap = "flood_fill,thesis,thesis_junction,floornav"
    return {
        "cv": ["eval", *labelled, "--cv", "--method", cheap, "--json"],
        "cv-floornet": [
            "eval",
            *labelled,
            "--cv",
            "--folds",
            "5",
            "--method",
            "floornet",
            "--json",
        ],
        "sim-eval": ["sim-eval", "--method", "all", "--json"],
        "bench": ["bench", "--json"],
        "eval-video": ["eval-video", *videos, "--method", "all", "--stride", "2", "--json"],
    }


def run(name: str, args: list[str]) -> dict[str, Any]:
    command = [str(ROOT / ".venv" / "bin" / "floornav"), *args]
    print(f"== {name}: floornav {' '.join(args)}", file=sys.stderr, flush=True)
    done = subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.PIPE, text=True)
    result: dict[str, Any] = json.loads(done.stdout)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    (OUT_DIR / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def fmt(value: object, digits: int = 3) -> str:
    if value is None:  # NaN in the JSON: no such pixels in the subset
        return "-"
    if isinstance(value, float):
        return "-" if value != value else f"{value:.{digits}f}"  # NaN: no such pixels
    return str(value)


def score_rows(table: dict[str, dict[str, Any]], label: str) -> list[str]:
    rows = []
    for method, s in table.items():
        if not s.get("images"):
            continue
        rows.append(
            f"| {label} | {method} | {fmt(s['iou'])} | {fmt(s['floor_recall'])} | "
            f"{fmt(s['floor_precision'])} | {fmt(s['near_false_floor'])} | {s['images']} |"
        )
    return rows


def cv_section(results: list[tuple[str, dict[str, Any]]]) -> list[str]:
    lines = [
        "## Out-of-scene accuracy (`floornav eval --cv`)",
        "",
        "Every score is on scenes the method was not fitted on: whole video sequences or",
        "places are held out, and whatever a method fits (the network, the logistic",
        "weights, the flood-fill tolerance) is refitted without them in every fold.",
        "near_FF = share of the true non-floor pixels in the bottom 40 % of the image",
        "that are called floor (what the robot would drive into; `-` where a subset has",
        "no such pixel). Premise: the share of the safe zone that is floor in the truth",
        "(holds: >= 0.8; broken: < 0.8; zone mostly not floor: < 0.5).",
        "",
    ]
    header = "| subset | method | IoU | recall | precision | near_FF | images |"
    for name, summary in results:
        cv = summary["cv"]
        lines += [
            f"`floornav {' '.join(commands()[name])}`: {cv['scheme']} ({cv['scenes']} scenes,"
            f" {cv['images']} images).",
            "",
            header,
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for dataset, table in summary["datasets"].items():
            lines += score_rows(table, dataset)
        lines += score_rows(summary["methods"], "**all**")
        for subset, table in summary["premise"].items():
            lines += score_rows(table, subset.replace("_", " "))
        lines.append("")
    return lines


def sim_section(summary: dict[str, Any]) -> list[str]:
    lines = [
        "## The simulated camera (`floornav sim-eval`)",
        "",
        f"`floornav {' '.join(commands()['sim-eval'])}`: {summary['frames']} frames of world"
        f" `{summary['world']}` against the renderer's ground truth.",
        "",
        "| method | IoU | recall | precision | near_FF |",
        "| --- | --- | --- | --- | --- |",
    ]
    for method, s in summary["methods"].items():
        lines.append(
            f"| {method} | {fmt(s['iou'])} | {fmt(s['floor_recall'])} | "
            f"{fmt(s['floor_precision'])} | {fmt(s['near_false_floor'])} |"
        )
    return [*lines, ""]


def bench_section(result: dict[str, Any]) -> list[str]:
    lines = [
        "## Speed (`floornav bench`)",
        "",
        f"`floornav {' '.join(commands()['bench'])}`: method `{result['method']}`,"
        f" {result['images']}; {result['pinned']}. Median ms per stage.",
        "",
    ]
    resolutions = result["resolutions"]
    stages = list(next(iter(resolutions.values()))["stages_ms"])
    lines.append("| stage | " + " | ".join(resolutions) + " |")
    lines.append("| --- |" + " --- |" * len(resolutions))
    for stage in stages:
        cells = [
            fmt(r["stages_ms"].get(stage, {}).get("median", float("nan")), 2)
            for r in resolutions.values()
        ]
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    lines.append(
        "| **total** | "
        + " | ".join(f"**{r['total_ms']:.2f}**" for r in resolutions.values())
        + " |"
    )
    ref = result["reference"]["640x480"]
    lines += [
        "",
        f"Reference in the same run: `{ref['method']}` with scikit-image SLIC at 640x480,"
        f" {ref['total_ms']:.1f} ms; ratio {result['speedup_vs_reference_640x480']}x.",
        "",
    ]
    return lines


def video_section(summary: dict[str, Any]) -> list[str]:
    lines = [
        "## Real robot video, no labels (`floornav eval-video`)",
        "",
        f"`floornav {' '.join(commands()['eval-video'])}`: consecutive-frame IoU (pairs"
        f" {summary['stride']} frames apart; flicker is a phantom obstacle), the floor share"
        " of the bottom half (the carpet fills it in nearly every frame of recording.avi),"
        " ms per frame.",
        "",
        "| video | method | consecutive IoU | p05 | bottom-half floor | ms median | frames |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for path, video in summary["videos"].items():
        for method, m in video["methods"].items():
            lines.append(
                f"| {Path(path).name} | {method} | {fmt(m['consecutive_iou_mean'])} | "
                f"{fmt(m['consecutive_iou_p05'])} | "
                f"{fmt(m['bottom_half_floor_fraction_mean'])} | "
                f"{fmt(m['ms_per_frame_median'], 1)} | {m['frames']} |"
            )
    return [*lines, ""]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reuse", action="store_true", help="keep existing JSON files")
    parser.add_argument("--only", nargs="+", choices=sorted(commands()), default=None)
    args = parser.parse_args()
    if not DATASETS.is_dir():
        print(f"the shared datasets are not at {DATASETS}", file=sys.stderr)
        return 1
    results: dict[str, dict[str, Any]] = {}
    for name, command in commands().items():
        path = OUT_DIR / f"{name}.json"
        wanted = args.only is None or name in args.only
        if path.is_file() and (args.reuse or not wanted):
            results[name] = json.loads(path.read_text())
        elif wanted:
            results[name] = run(name, command)
    lines = [
        "# Perception, measured",
        "",
        "Written by `scripts/measure_perception.py` on "
        f"{datetime.date.today().isoformat()} on {cpu_name()} ({platform.machine()}); the raw"
        " JSON of each command is in `docs/measurements/`. A section re-run alone"
        " (`--only NAME`) leaves the others as they were measured before (their JSON"
        " files' last commits say when).",
        "",
    ]
    cv = [(n, results[n]) for n in ("cv-floornet", "cv") if n in results]
    if cv:
        lines += cv_section(cv)
    if "sim-eval" in results:
        lines += sim_section(results["sim-eval"])
    if "bench" in results:
        lines += bench_section(results["bench"])
    if "eval-video" in results:
        lines += video_section(results["eval-video"])
    DOC.write_text("\n".join(lines))
    print(f"wrote {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
