"""`floornav bench --only daemon`: the daemon's per-frame path on simulated frames. The
shape of the result is checked, never the timings (they depend on the machine)."""

from __future__ import annotations

import json
import math

import pytest

from app.benchmarks.frame_path import (
    PATH_RADIUS_M,
    STAGES,
    drive_poses,
    format_frame_path,
    path_min_clearance_m,
)
from app.cli import PROJECT_ROOT, main
from app.config import load_config
from app.sim.setup import world_from_config


def test_the_drive_is_a_clear_circle_in_the_shipped_world() -> None:
    config = load_config(PROJECT_ROOT / "config.toml")
    world = world_from_config(config)
    drive = drive_poses(world.start_pose, 400, 0.35, 30.0)
    times = [t for t, _ in drive]
    assert times[0] == 0.0 and times[1] == pytest.approx(1 / 30)
    for _, pose in drive:  # every pose on the circle round (0, -R) in the odometry frame
        assert math.hypot(pose.x_m, pose.y_m + PATH_RADIUS_M) == pytest.approx(PATH_RADIUS_M)
    step = math.dist((drive[1][1].x_m, drive[1][1].y_m), (drive[0][1].x_m, drive[0][1].y_m))
    assert step == pytest.approx(0.35 / 30, rel=1e-3)
    plan = [world.start_pose.compose(pose) for _, pose in drive]
    assert path_min_clearance_m(world, plan) > config.mapping.robot_radius_m + 0.2


def test_bench_json_has_the_daemon_frame_path(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--only", "daemon", "--frames", "3", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result) == {"method", "pinned", "daemon_frame_path"}
    path = result["daemon_frame_path"]
    assert path["method"] == result["method"] == "floornet"  # the shipped config's
    assert path["frames"] == 3
    assert list(path["stages_ms"]) == list(STAGES)
    for stats in [*path["stages_ms"].values(), path["per_frame_ms"]]:
        assert 0 < stats["median"] <= stats["p95"] <= stats["max"]
    assert all(s["cpu_median"] >= 0 for s in path["stages_ms"].values())
    for clock in ("process", "thread"):
        cpu = path["cpu_per_frame_ms"][clock]
        assert 0 < cpu["median"] <= cpu["p95"]
    assert path["camera_fps"] == 30.0
    assert path["frame_budget_ms"] == pytest.approx(1000 / 30, abs=1e-3)
    periodic = path["periodic"]
    assert set(periodic) == {"frontier", "world_map"}
    assert periodic["frontier"]["share"] == pytest.approx(1 / 15, abs=1e-4)  # 0.5 s at 30 fps
    assert path["amortized_per_frame_ms"] == pytest.approx(
        path["per_frame_ms"]["median"] + sum(p["amortized_ms"] for p in periodic.values()),
        abs=3e-3,
    )
    assert path["budget_share"]["wall"] > 0 and path["budget_share"]["cpu"] > 0
    assert path["sustainable_fps"] > 0
    assert sum(path["steering_reasons"].values()) == 3
    assert path["floor_odometry_steps"] == 0  # 3 frames: 2.3 cm, less than one step
    assert path["path_min_clearance_m"] > 0.3
    parallax = path["parallax_ms"]  # timed whether or not the config turns it on
    assert parallax["calls"] >= 50 and parallax["pairs"] == 25
    assert 0 < parallax["median"] <= parallax["p95"] <= parallax["max"]
    assert parallax["standing_median"] > 0
    assert parallax["baseline_m"] == pytest.approx(0.12, abs=0.02)
    assert parallax["configured"] is True  # the shipped config's
    text = format_frame_path(path)
    assert "daemon per-frame path" in text and "\n  parallax " in text


def test_bench_text_prints_only_the_sections_asked_for(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--only", "daemon", "--frames", "1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("== daemon per-frame path, method floornet (1 frames;")
    assert "occupancy grid" not in out and "reference" not in out
    assert main(["bench", "--only", "daemon", "--frames", "0"]) == 1
