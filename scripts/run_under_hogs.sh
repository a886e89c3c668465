#!/usr/bin/env bash
# `floornav run` for DURATION seconds while two busy-loop processes hog both cores the
# whole time (issue 11's robustness check). Usage: scripts/run_under_hogs.sh 120 report.json
# The daemon runs at the priority the shipped systemd unit gives it (deploy/floornav.service,
# Nice=-5); NICE=0 runs it as a plain process (raising priority needs root or
# CAP_SYS_NICE; without it `nice` says so and the run goes on at 0).
set -euo pipefail
cd "$(dirname "$0")/.."
duration="${1:-120}"
report="${2:-hogs-report.json}"
daemon_nice="${NICE:-$(sed -n 's/^Nice=//p' deploy/floornav.service)}"
hogs=()
for _ in 1 2; do
  python3 -c 'while True: pass' &
  hogs+=("$!")
done
trap 'kill "${hogs[@]}" 2>/dev/null || true' EXIT
nice -n "${daemon_nice:-0}" .venv/bin/floornav run --duration-s "$duration" --report "$report"
