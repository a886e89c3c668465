#!/usr/bin/env bash
# `floornav run` for DURATION seconds while two busy-loop processes hog both cores the
# whole time (issue 11's robustness check). Usage: scripts/run_under_hogs.sh 120 report.json
set -euo pipefail
cd "$(dirname "$0")/.."
duration="${1:-120}"
report="${2:-hogs-report.json}"
hogs=()
for _ in 1 2; do
  python3 -c 'while True: pass' &
  hogs+=("$!")
done
trap 'kill "${hogs[@]}" 2>/dev/null || true' EXIT
.venv/bin/floornav run --duration-s "$duration" --report "$report"
