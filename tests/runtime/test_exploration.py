"""A short exploration on the shipped config: the robot drives itself, never collides,
and the map it builds agrees with the floor plan (the full 40 s figures are in the
README; this guards against regressions in CI)."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.config import load_config
from app.devices import open_devices
from app.runtime import Runtime

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.sim
async def test_twenty_seconds_of_exploration() -> None:
    config = load_config(ROOT / "config.toml", runtime={"autostart": True, "log_level": "warning"})
    with open_devices(config) as devices:
        runtime = Runtime(config, devices)
        await runtime.run(duration_s=20.0, install_signals=False)
        report = runtime.report()
    print(
        f"\n20 s exploration: coverage {report['coverage_ratio']}, map IoU {report['map_iou']},"
        f" {report['distance_m']} m, {report['fps']} fps, latency {report['latency_ms']}"
    )
    assert report["collisions"] == 0
    assert report["final_motor_pwm"] == [0, 0]
    assert report["distance_m"] > 0.5
    assert report["map_iou"] >= 0.8
    assert report["coverage_ratio"] >= 0.2
    assert report["fps"] >= 20
