#!/usr/bin/env python3
"""Regenerate the dashboard's screenshots in docs/screenshots/ (or --out DIR).

The browser tests take them against the real daemon on the simulator (Debian's
chromium, see tests/browser/conftest.py): the dashboard in each stop state (e-stop
latched, protective stop with its cause, blocked by clearance while driving by key,
blocked on a map too old to judge, latched fault, calibration failed), on a phone while
driving with the pad, and the plain dashboard, e-stop and calibration views. They are
256-colour PNGs below 150 KB (tests/browser/shots.py).

    nice -n 19 .venv/bin/python scripts/dashboard_screenshots.py [--out DIR] [PYTEST ARGS]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT_TESTS = (
    "test_stop_reason or test_phone or test_video_frames_arrive or test_estop_button "
    "or test_calibration_wizard"
)
MAX_BYTES = 150_000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    args, pytest_args = parser.parse_known_args()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    before = {p: p.stat().st_mtime for p in out.glob("*.png")}
    command = [
        sys.executable, "-m", "pytest",
        "tests/browser/test_operator_stop.py", "tests/browser/test_dashboard.py",
        "-m", "browser", "-q", "-p", "no:cacheprovider", "-k", SCREENSHOT_TESTS,
        *pytest_args,
    ]  # fmt: skip
    code = subprocess.call(command, cwd=ROOT, env={**os.environ, "FLOORNAV_SCREENSHOTS": str(out)})
    written = sorted(p for p in out.glob("*.png") if before.get(p) != p.stat().st_mtime)
    for path in written:
        size = path.stat().st_size
        flag = "" if size < MAX_BYTES else f"  (over {MAX_BYTES // 1000} KB)"
        shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
        print(f"{shown}: {size // 1000} KB{flag}")
    if not written:
        print(f"no screenshot written to {out}", file=sys.stderr)
        return code or 1
    return code


if __name__ == "__main__":
    sys.exit(main())
