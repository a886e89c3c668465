#!/usr/bin/env python3
"""Write docs/runs.md: one table row per run report in docs/measurements/run-*.json
(each written by `floornav run --report`; how it was run is in its file name and in
docs/daemon-runs.md)."""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MEASUREMENTS = ROOT / "docs" / "measurements"


def cell(value: object) -> str:
    return "-" if value is None else str(value)


def main() -> int:
    rows = [
        "# Daemon runs",
        "",
        "Written by `scripts/render_run_reports.py` from the run reports in",
        "[measurements/](measurements/) (`floornav run --report`). Latency is capture to",
        "command; loop lag is the event loop's wake-up delay; RSS in MB.",
        "",
        "| run | s | fps | latency p50/p95/max ms | loop lag p50/p99/max ms | faults | "
        "protective stops | collisions | coverage | RSS start/1 min/end |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for path in sorted(MEASUREMENTS.glob("run-*.json")):
        r = json.loads(path.read_text())
        lat, lag, rss = r["latency_ms"], r.get("loop_lag_ms") or {}, r.get("rss_mb") or {}
        stops = r.get("protective_stops") or {}
        rows.append(
            f"| {path.stem} | {r['duration_s']:.0f} | {r['fps']} | "
            f"{cell(lat.get('p50'))}/{cell(lat.get('p95'))}/{cell(lat.get('max'))} | "
            f"{cell(lag.get('p50'))}/{cell(lag.get('p99'))}/{cell(lag.get('max'))} | "
            f"{r['faults']} | "
            + ", ".join(f"{k} {v}" for k, v in stops.items())
            + f" | {r['collisions']} | {cell(r['coverage_ratio'])} | "
            f"{cell(rss.get('start') and round(rss['start']))}/"
            f"{cell(rss.get('after_first_minute') and round(rss['after_first_minute']))}/"
            f"{cell(rss.get('end') and round(rss['end']))} |"
        )
    (ROOT / "docs" / "runs.md").write_text("\n".join(rows) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
