"""Exploration that finishes, end to end on the simulator: in a small closed room the
robot runs out of frontiers, drives back to its start, stops in state ``explored`` and
the map is saved."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest

from app.config import load_config
from app.devices import open_devices
from app.mapping.map_files import load_map
from app.messages import State
from app.runtime import Runtime

ROOT = Path(__file__).resolve().parents[2]

SMALL_ROOM = """
name = "small room"
description = "One closed 3 m x 2.4 m room, nothing in it"

[start]
x_m = 0.8
y_m = 1.2
theta_rad = 0.0

[floor]
pattern = "wood"
color = "#a47a52"
seam_color = "#5c4430"
plank_width_m = 0.14
plank_length_m = 1.2

[[rooms]]
rect_m = [0.0, 0.0, 3.0, 2.4]
height_m = 1.0
color = "#d9d4c8"
"""


@pytest.mark.sim
async def test_a_small_room_is_explored_and_the_robot_comes_home(tmp_path: Path) -> None:
    world = tmp_path / "small-room.toml"
    world.write_text(SMALL_ROOM)
    config = load_config(
        ROOT / "config.toml",
        runtime={"autostart": True, "log_level": "warning"},
        sim={"world_file": str(world)},
        steering={"explored_after_s": 3.0},
    )
    map_path = tmp_path / "explored.npz"
    saved = asyncio.Event()
    with open_devices(config) as devices:
        runtime = Runtime(config, devices)

        async def save() -> None:
            snapshot = await runtime.saved_map_while_running()
            assert snapshot is not None
            from app.mapping.map_files import save_map

            await asyncio.to_thread(save_map, map_path, snapshot)
            saved.set()
            runtime.request_shutdown("explored")

        runtime.on_explored = save
        await runtime.run(duration_s=120.0, install_signals=False)
        report = runtime.report()
        states = [t.new for t in runtime.transitions]
        assert devices.sim is not None
        truly, start = devices.sim.robot.pose, devices.sim.world.start_pose
        true_home_m = math.hypot(truly.x_m - start.x_m, truly.y_m - start.y_m)
    print(
        f"\nsmall room: {report['exploration']}, {report['time_to_coverage_s']}, "
        f"coverage {report['coverage_reachable']}, {report['distance_m']} m"
    )
    assert saved.is_set(), f"not explored in 120 s: {report['exploration']}"
    assert State.RETURNING in states and states[-1] is State.EXPLORED
    exploration = report["exploration"]
    assert exploration["phase"] == "explored" and "back at the start" in exploration["reason"]
    assert exploration["home_distance_m"] <= 0.3
    assert true_home_m <= 0.45, true_home_m  # the truth: 0.3 m and the odometry error
    assert report["collisions"] == 0
    assert report["final_motor_pwm"] == [0, 0]
    assert report["coverage_reachable"] >= 0.6
    assert report["time_to_coverage_s"]["50"] is not None
    restored = load_map(map_path)
    assert math.hypot(restored.T_world_robot.x_m, restored.T_world_robot.y_m) <= 0.3
