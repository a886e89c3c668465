"""A short exploration on the shipped config: the robot drives itself, never collides,
and the map it builds agrees with the floor plan (the longer runs' figures are in
docs/daemon-runs.md and docs/exploration.md; this guards against regressions in CI).

Twenty seconds of real-time driving do not repeat exactly (which frames the perception
takes depends on scheduling), so the bounds sit below what the shipped code spreads
over: in 15 runs on a quiet 2-core machine map IoU was 0.772-0.840 (median 0.81) and
free-cell precision 0.925-0.978; on the loaded CI machine 0.770 and 0.782 were seen.
A broken camera model or map update costs far more than that."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.config import load_config
from app.devices import open_devices
from app.runtime import Runtime
from app.sim.truth import map_truth_scores, marks_near_truth

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
    assert report["map_iou"] >= 0.72
    assert report["map_truth"]["free_precision"] >= 0.88
    assert report["coverage_ratio"] >= 0.2
    assert report["fps"] >= 20


@pytest.mark.sim
@pytest.mark.parametrize("world", ["home", "office"])
async def test_twenty_seconds_in_each_harder_world(world: str) -> None:
    """The shipped configuration in the other shipped worlds: it drives, never collides,
    maps some reachable floor, and the report carries the exploration's fields."""
    config = load_config(
        ROOT / "config.toml",
        runtime={"autostart": True, "log_level": "warning"},
        sim={"world_file": world},
    )
    with open_devices(config) as devices:
        runtime = Runtime(config, devices)
        await runtime.run(duration_s=20.0, install_signals=False)
        report = runtime.report()
        assert devices.sim is not None
        world_name = devices.sim.world.name
        # The standing layer's scores: the mapper's own layer, taken to the plan frame.
        mapper = runtime.shared.mapper
        assert mapper is not None
        near = marks_near_truth(
            mapper.memory.standing != 0,
            mapper.grid.world_grid,
            devices.sim.T_plan_odom,
            devices.sim.world,
        )
        memory = report["floor_memory"]
        assert memory["standing_near_truth"] == (None if near is None else round(near, 4))
        assert memory["probe_edge_share"] == mapper.probe_edge_share()
        assert memory["standing_m2"] == round(
            float((mapper.memory.standing != 0).sum()) * mapper.grid.world_grid.cell_m**2, 2
        )
        assert memory["driven_m2"] == round(
            float((mapper.memory.driven != 0).sum()) * mapper.grid.world_grid.cell_m**2, 2
        )
        assert memory["driven_m2"] > 0  # it stands on its footprint from the first frame
        seen = mapper.memory.standing_seen()
        assert memory["standing_seen_m2"] == round(
            float(seen.sum()) * mapper.grid.world_grid.cell_m**2, 2
        )
        assert not (seen & (mapper.memory.standing == 0)).any()
        # Scored: the map the robot explores on (faded evidence at its last class);
        # beside it, the evidence alone.
        grid, T_plan_odom = mapper.grid.world_grid, devices.sim.T_plan_odom
        known = map_truth_scores(
            mapper.grid.remembered_classes(), grid, T_plan_odom, devices.sim.world
        )
        live = map_truth_scores(mapper.grid.classify(), grid, T_plan_odom, devices.sim.world)
        assert report["map_truth"] == known.as_dict()
        assert report["map_truth_live"] == live.as_dict()
        assert known.coverage_ratio >= live.coverage_ratio
    print(
        f"\n20 s in {world}: reachable coverage {report['coverage_reachable']}, map IoU"
        f" {report['map_iou']}, {report['distance_m']} m, pose error {report['pose_error_m']},"
        f" {report['exploration']['phase']}"
    )
    assert report["world"] == world_name
    assert report["collisions"] == 0
    assert report["final_motor_pwm"] == [0, 0]
    assert report["distance_m"] > 0.3
    assert report["coverage_reachable"] > 0.03
    assert report["exploration"]["phase"] in {"exploring", "returning", "explored"}
    assert set(report["time_to_coverage_s"]) == {"50", "90"}
    assert set(report["pose_error_m"]) == {"p50", "p95", "final"}
    assert set(report["heading_error_deg"]) == {"p50", "p95", "final"}
    # One row per 5 s: seconds, true x and y, position and heading errors.
    assert 3 <= len(report["pose_error_track"]) <= 5
    assert all(len(row) == 5 for row in report["pose_error_track"])
