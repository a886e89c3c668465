"""Measure floornav's speed with `floornav bench` and write docs/performance.md.

    .venv/bin/python scripts/measure_performance.py [--reuse] [--note TEXT]

Runs, each with ``--json``:

- ``floornav bench --json``: the configured (shipped) method's perception on photos at
  640x480 and 320x240 against its reference in the same run, the occupancy-grid update,
  the simulator's renderer, and the daemon's per-frame path on simulated frames;
- ``floornav bench --json --only perception --method M`` for every other method;

keeps them, with the machine they ran on, in docs/measurements/performance.json, and
renders docs/performance.md from that file. ``--reuse`` renders the page again from the
existing JSON without measuring. Timings are only comparable within one run: run it on a
quiet machine (the page says how loaded this one was).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from app.benchmarks import cpu_name

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "measurements" / "performance.json"
DOC = ROOT / "docs" / "performance.md"
SCRIPT = "scripts/measure_performance.py"
LOADED_PER_CORE = 0.3
"""A 1-minute load average above this per core (beside the run itself) counts as a
loaded machine: other work then competes for the cores and the timings spread."""


def floornav(args: list[str]) -> dict[str, Any]:
    command = [str(ROOT / ".venv" / "bin" / "floornav"), *args]
    print(f"== floornav {' '.join(args)}", file=sys.stderr, flush=True)
    done = subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.PIPE, text=True)
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def machine() -> dict[str, Any]:
    """What the figures depend on, read in this script's interpreter (the project's venv,
    the same one ``floornav`` runs in)."""
    import cv2
    import numpy

    return {
        "cpu": cpu_name(),
        "arch": platform.machine(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "opencv": cv2.__version__,
        "kernel": platform.release(),
    }


def measure(note: str) -> dict[str, Any]:
    from app.perception.pipeline import METHODS

    started = datetime.datetime.now(datetime.UTC)
    load_before = load_average()
    bench = floornav(["bench", "--json"])
    others = {
        method: floornav(["bench", "--json", "--only", "perception", "--method", method])
        for method in sorted(set(METHODS) - {bench["method"]})
    }
    return {
        "date": started.date().isoformat(),
        "started_utc": started.isoformat(timespec="seconds"),
        "duration_s": round((datetime.datetime.now(datetime.UTC) - started).total_seconds()),
        "machine": machine(),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "note": note,
        "commands": {
            "all": "floornav bench --json",
            "method": "floornav bench --json --only perception --method METHOD",
        },
        "bench": bench,
        "other_methods": others,
    }


def ms(value: float) -> str:
    return f"{value:.2f}"


def machine_section(data: dict[str, Any]) -> list[str]:
    m = data["machine"]
    load = data["load_average_1min"]
    loads = [v for v in (load["before"], load["after"]) if v is not None]
    cores = m["cores"] or 1
    lines = [
        "## The machine",
        "",
        "| | |",
        "| --- | --- |",
        f"| CPU | {m['cpu']} ({m['arch']}) |",
        f"| cores | {m['cores']} |",
        f"| Python, numpy, OpenCV | {m['python']}, {m['numpy']}, {m['opencv']} |",
        f"| kernel | {m['kernel']} |",
        f"| date | {data['started_utc']} ({data['duration_s']} s) |",
        "| load average (1 min) before, after | "
        + ", ".join("-" if v is None else f"{v:.2f}" for v in (load["before"], load["after"]))
        + " |",
        "",
    ]
    if loads and max(loads) / cores > LOADED_PER_CORE:
        lines += [
            f"**Taken on a shared, loaded machine** (load average up to {max(loads):.2f} on"
            f" {cores} cores before or after the run): other work competed for the cores, so"
            " the figures are noisier and likely slower than on a quiet one; ratios measured"
            " in the same run and CPU times hold up better than wall times.",
            "",
        ]
    if data.get("note"):
        lines += [f"Note: {data['note']}", ""]
    return lines


def perception_section(data: dict[str, Any]) -> list[str]:
    bench = data["bench"]
    lines = [
        "## Perception per method",
        "",
        f"Median ms per frame of `FloorSegmenter.segment` on {bench['images']}, one CPU"
        " (OpenCV single-threaded). The reference is timed in the same run:",
        "the thesis-faithful superpixel pipeline with scikit-image SLIC (for a method without"
        " superpixels, `floornav`'s stages with it); ratio = reference / method at 640x480.",
        "",
        "| method | 640x480 | 320x240 | reference at 640x480 | ratio |",
        "| --- | --- | --- | --- | --- |",
    ]
    for result in [bench, *data["other_methods"].values()]:
        res = result["resolutions"]
        ref = result["reference"]["640x480"]
        method = result["method"]
        name = f"**{method}** (default)" if result is bench else method
        lines.append(
            f"| {name} | {ms(res['640x480']['total_ms'])} | {ms(res['320x240']['total_ms'])} |"
            f" {ms(ref['total_ms'])} (`{ref['method']}`, skimage) |"
            f" {result['speedup_vs_reference_640x480']}x |"
        )
    resolutions = bench["resolutions"]
    stages = list(next(iter(resolutions.values()))["stages_ms"])
    lines += [
        "",
        f"Stages of the default method, `{bench['method']}` (median / max ms):",
        "",
        "| stage | " + " | ".join(resolutions) + " |",
        "| --- |" + " --- |" * len(resolutions),
    ]
    for stage in stages:
        cells = []
        for r in resolutions.values():
            s = r["stages_ms"].get(stage)
            cells.append("-" if s is None else f"{ms(s['median'])} / {ms(s['max'])}")
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def daemon_section(data: dict[str, Any]) -> list[str]:
    path = data["bench"]["daemon_frame_path"]
    stages = path["stages_ms"]
    per_frame = path["per_frame_ms"]
    periodic = path["periodic"]
    runs = "; ".join(
        f"`{stage}` every {p['period_s']:g} s, a share of {p['share']:.3f} of the frames"
        for stage, p in periodic.items()
    )
    lines = [
        "## The daemon's per-frame path",
        "",
        "What the daemon runs for each camera frame, with the shipped `config.toml`"
        f" (method `{path['method']}`), on {path['frames']} {path['frame']} frames of"
        f" {path['scene']} ({path['path']}), after {path['warmup_frames']} warm-up frames;"
        " one thread, one CPU. `app/benchmarks/frame_path.py` says what each stage covers."
        f" Two stages do not run every frame ({runs} at the camera's rate): they are timed"
        " on every frame but count per frame only amortised, median times share.",
        "",
        "| stage | median ms | p95 ms | max ms | CPU median ms | amortised ms |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for stage, s in stages.items():
        amortised = ms(periodic[stage]["amortized_ms"]) if stage in periodic else ""
        lines.append(
            f"| {stage} | {ms(s['median'])} | {ms(s['p95'])} | {ms(s['max'])} |"
            f" {ms(s['cpu_median'])} | {amortised} |"
        )
    lines += [
        f"| **per frame** (every-frame stages) | **{ms(per_frame['median'])}** |"
        f" **{ms(per_frame['p95'])}** | **{ms(per_frame['max'])}** | | |",
        "| per frame with the periodic stages amortised | | | | |"
        f" **{ms(path['amortized_per_frame_ms'])}** |",
        "",
    ]
    geometry = path.get("geometry_thread_ms")
    if geometry:
        lines += [
            f"Beside the path: `map_update` handed out {geometry['jobs']} geometry jobs (the"
            " parallax and walls tests), which the daemon runs on its background worker, off"
            f" the way to the motors: median {ms(geometry['median'])} ms, p95"
            f" {ms(geometry['p95'])} ms, max {ms(geometry['max'])} ms each (not in the sums).",
            "",
        ]
    return lines


def cpu_section(data: dict[str, Any]) -> list[str]:
    path = data["bench"]["daemon_frame_path"]
    cpu = path["cpu_per_frame_ms"]
    budget = path["budget_share"]
    return [
        "## CPU per frame",
        "",
        "CPU time of the every-frame stages: `process` counts every thread of the process"
        " (`time.process_time`), `thread` only the one running the path"
        " (`time.thread_time`); the difference is work helper threads did (thread pools of"
        " the numerical libraries, started before the run pinned its own thread to one"
        " CPU). The budget is one camera frame period.",
        "",
        "| | median ms | p95 ms |",
        "| --- | --- | --- |",
        f"| process CPU | {ms(cpu['process']['median'])} | {ms(cpu['process']['p95'])} |",
        f"| thread CPU | {ms(cpu['thread']['median'])} | {ms(cpu['thread']['p95'])} |",
        "",
        "| | value |",
        "| --- | --- |",
        f"| frame budget at {path['camera_fps']:g} fps | {ms(path['frame_budget_ms'])} ms |",
        f"| wall time per frame, periodic stages amortised |"
        f" {ms(path['amortized_per_frame_ms'])} ms ({budget['wall']:.0%} of the budget) |",
        f"| process CPU per frame, periodic stages amortised |"
        f" {ms(path['cpu_amortized_per_frame_ms'])} ms ({budget['cpu']:.0%} of the budget) |",
        f"| frames a second at that wall time, on one core | {path['sustainable_fps']:.0f} |",
        "",
        "In the running daemon perception and mapping run in two threads, so they overlap"
        " and each has the whole frame period; the figures above are their sum on one core.",
        "",
        *waiting_note(path),
    ]


def waiting_note(path: dict[str, Any]) -> list[str]:
    """A word when wall time far exceeds CPU time: the path waited for a core."""
    wall = path["per_frame_ms"]["median"]
    cpu = path["cpu_per_frame_ms"]["process"]["median"]
    if wall <= 1.3 * cpu:
        return []
    return [
        f"Wall time per frame ({ms(wall)} ms) is well above its CPU time ({ms(cpu)} ms): the"
        " run waited for a core that other processes held, so the CPU figures are the ones"
        " to trust from this run.",
        "",
    ]


def other_section(data: dict[str, Any]) -> list[str]:
    bench = data["bench"]
    grid, render = bench["grid_update"], bench["sim_render"]
    return [
        "## Kernels",
        "",
        "| what | median ms | min | max |",
        "| --- | --- | --- | --- |",
        f"| occupancy-grid update ({grid['patch']} into {grid['world']}) |"
        f" {ms(grid['median'])} | {ms(grid['min'])} | {ms(grid['max'])} |",
        f"| the same on open floor (every ray to the patch's edge) |"
        f" {ms(grid['open_floor_median'])} | | |",
        f"| simulator render ({render['scene']}) | {ms(render['median'])} |"
        f" {ms(render['min'])} | {ms(render['max'])} |",
        "",
    ]


def render_doc(data: dict[str, Any]) -> str:
    lines = [
        "# Performance, measured",
        "",
        f"Written by `{SCRIPT}` on {data['date']}; do not edit by hand. The raw JSON is in"
        " [measurements/performance.json](measurements/performance.json); the commands are"
        f" `{data['commands']['all']}` and `{data['commands']['method']}` for every other"
        " method. Run it again on a quiet machine for figures to quote.",
        "",
        "The daemon has to keep up with the camera: at 30 fps a frame's path has 33 ms. The"
        " targets of a whole run (`floornav run --report`, see"
        " [daemon-runs.md](daemon-runs.md)) are >= 25 fps and capture-to-command latency"
        " p95 <= 50 ms.",
        "",
    ]
    for section in (
        machine_section,
        perception_section,
        daemon_section,
        cpu_section,
        other_section,
    ):
        lines += section(data)
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reuse", action="store_true", help="render from the existing JSON")
    parser.add_argument("--note", default="", help="a sentence for the page (e.g. the machine)")
    args = parser.parse_args()
    if args.reuse:
        data = json.loads(OUT.read_text())
        if args.note:
            data["note"] = args.note
    else:
        data = measure(args.note)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(data, indent=1) + "\n")
    DOC.write_text(render_doc(data))
    print(f"wrote {DOC.relative_to(ROOT)} and {OUT.relative_to(ROOT)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
