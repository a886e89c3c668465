"""The map outlives the run: saved at exit (own format + ROS map_server), continued by
the next run at the pose the robot stood."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from app.devices import open_devices
from app.mapping.map_files import MapFileError, load_map, read_ros_map
from app.runtime import Runtime

from ..conftest import free_port
from .conftest import running, sim_config, wait_for
from .test_cli_run import floornav


async def test_the_map_saved_at_exit_loads_back_equal_and_the_next_run_continues_it(
    tmp_path: Path,
) -> None:
    from app.daemon import continue_map, save_run_map

    config = sim_config()
    map_path = tmp_path / "home.npz"
    async with running(config) as (rt, _):
        await rt.start()
        await wait_for(lambda: rt.odometry.distance_m > 0.3, 15.0, "the robot to drive")
    saved = rt.saved_map()
    assert saved is not None
    assert save_run_map(rt, map_path) == str(map_path)
    loaded = load_map(map_path)
    assert np.array_equal(loaded.log_odds, saved.log_odds)
    assert loaded.T_world_robot == saved.T_world_robot
    assert loaded.travelled_m == saved.travelled_m
    assert np.count_nonzero(loaded.classify() == 0) > 100  # it mapped floor
    ros = read_ros_map(map_path.with_suffix(".yaml"))
    assert np.array_equal(ros.cells, saved.remembered_classes())

    with open_devices(config) as devices:
        assert devices.sim is not None
        again = Runtime(config, devices)
        continue_map(again, devices, loaded, map_path)
        assert again.odometry.pose == loaded.T_world_robot
        assert np.array_equal(again.saved_map().log_odds, loaded.log_odds)  # type: ignore[union-attr]
        # The simulated robot stands where the map says it stood.
        expected = devices.sim.T_plan_odom.compose(loaded.T_world_robot)
        pose = devices.sim.robot.pose
        assert math.dist((pose.x_m, pose.y_m), (expected.x_m, expected.y_m)) < 1e-9


def test_a_map_file_that_is_not_a_map_stops_the_run_before_any_device_and_is_kept(
    tmp_path: Path,
) -> None:
    bad = tmp_path / "home.npz"
    bad.write_bytes(b"not a map at all")
    proc = floornav("run", "--duration-s", "5", "--map", str(bad))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert str(bad) in err and "floornav daemon" not in out
    assert bad.read_bytes() == b"not a map at all"  # never overwritten
    with pytest.raises(MapFileError):
        load_map(bad)


@pytest.mark.sim
def test_run_with_map_saves_it_and_the_next_run_continues_from_it(tmp_path: Path) -> None:
    map_path = tmp_path / "home.npz"
    for run in range(2):
        report = tmp_path / f"r{run}.json"
        proc = floornav(
            "run", "--duration-s", "12", "--map", str(map_path), "--report", str(report),
            env={
                "FLOORNAV_RUNTIME__LOG_JSON": "true",
                "FLOORNAV_WEB__PORT": str(free_port()),
                "FLOORNAV_VISER__PORT": str(free_port()),
                "FLOORNAV_TOKEN": "map-test-token-000000000000",
            },
        )  # fmt: skip
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        events = [
            json.loads(line).get("event") for line in err.splitlines() if line.startswith("{")
        ]
        assert "map_saved" in events
        assert ("map_restored" in events) == (run == 1)
        assert json.loads(report.read_text())["map_file"] == str(map_path)
    assert map_path.with_suffix(".pgm").is_file() and map_path.with_suffix(".yaml").is_file()
