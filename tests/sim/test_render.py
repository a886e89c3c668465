"""The simulator's camera renderer: geometry against the pinhole model, ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.config import PerceptionConfig
from app.mapping.frames import Pose2D
from app.perception.pipeline import FloorSegmenter
from app.sim.render import CameraModel, Renderer
from app.sim.world import load_world, parse_world

ROOM = """
[start]
x_m = 1.0
y_m = 2.0
[floor]
pattern = "tiles"
[[rooms]]
rect_m = [0.0, 0.0, 4.0, 4.0]
height_m = 1.5
color = "#3050a0"
"""


@pytest.fixture(scope="module")
def room_renderer() -> Renderer:
    return Renderer(parse_world(ROOM), CameraModel(noise_sigma=0.0))


@pytest.mark.parametrize("distance_m", [1.0, 2.0, 3.0])
def test_wall_bottom_edge_at_expected_row(room_renderer: Renderer, distance_m: float) -> None:
    cam = room_renderer.camera
    frame = room_renderer.render(Pose2D(4.0 - distance_m, 2.0, 0.0))
    expected = cam.floor_row_px(distance_m)
    centre = cam.width_px // 2
    column = frame.floor_mask[:, centre]
    first_floor_row = int(np.argmax(column))
    assert column[first_floor_row:].all()
    assert abs(first_floor_row - expected) <= 1.0
    # The image agrees with the mask: blue wall above, tiles below.
    wall = frame.image[max(0, first_floor_row - 3), centre].astype(int)
    floor = frame.image[min(cam.height_px - 1, first_floor_row + 3), centre].astype(int)
    assert wall[0] > wall[2] and floor[2] > floor[0]


def test_analytic_row_matches_projection() -> None:
    cam = CameraModel()
    # A floor point straight ahead projects to cy + fy * tan(depression - pitch).
    d = 2.0
    depression = math.atan2(cam.height_m, d - cam.x_m)
    assert cam.floor_row_px(d) == pytest.approx(239.5 + 500 * math.tan(depression - 0.40))


def test_turning_moves_the_view_the_right_way(room_renderer: Renderer) -> None:
    # Facing the corner (4, 4) from (3, 3): the wall x = 4 is on the right half,
    # y = 4 on the left half, and the corner's bottom is the highest floor point.
    frame = room_renderer.render(Pose2D(3.0, 3.0, math.pi / 4))
    first_floor = np.argmax(frame.floor_mask, axis=0)
    highest = np.flatnonzero(first_floor == first_floor.min())
    assert abs(highest.mean() - (room_renderer.camera.width_px - 1) / 2) <= 2


def test_box_occludes_floor_and_its_top_is_not_floor() -> None:
    world = parse_world(
        ROOM + "[[boxes]]\ncenter_m = [2.0, 2.0]\nsize_m = [0.3, 0.3]\nheight_m = 0.1\n"
    )
    renderer = Renderer(world, CameraModel(noise_sigma=0.0))
    frame = renderer.render(Pose2D(1.0, 2.0, 0.0))
    cam = renderer.camera
    near_row = cam.floor_row_px(0.85)  # the box's front bottom edge, x = 1.85
    centre = cam.width_px // 2
    assert frame.floor_mask[math.ceil(near_row) + 1 :, centre].all()
    assert not frame.floor_mask[math.floor(near_row) - 3, centre]


def test_noise_changes_pixels_not_truth() -> None:
    world = parse_world(ROOM)
    quiet = Renderer(world, CameraModel(noise_sigma=0.0)).render(world.start_pose)
    noisy = Renderer(world, CameraModel(noise_sigma=3.0), seed=1).render(world.start_pose)
    diff = noisy.image.astype(int) - quiet.image.astype(int)
    assert 2.0 < diff.std() < 4.0
    assert (quiet.floor_mask == noisy.floor_mask).all()


def test_occupancy_truth_is_cached() -> None:
    renderer = Renderer(parse_world(ROOM))
    grid, occ = renderer.occupancy
    assert renderer.occupancy[1] is occ
    wall, centre = grid.cell_of(np.array([[4.0, 2.0], [2.0, 2.0]]))
    assert occ[wall[0], wall[1]] == 1 and occ[centre[0], centre[1]] == 0


def test_perception_finds_simulated_floor() -> None:
    world = load_world()
    renderer = Renderer(world)
    segmenter = FloorSegmenter(PerceptionConfig())
    ious: list[float] = []
    for k in range(3):
        pose = Pose2D(1.2 + 0.5 * k, 3.0 - 0.2 * k, -0.3 * k)
        frame = renderer.render(pose)
        mask = segmenter.segment(frame.image).floor_mask
        union = np.count_nonzero(mask | frame.floor_mask)
        ious.append(int(np.count_nonzero(mask & frame.floor_mask)) / max(int(union), 1))
    assert float(np.mean(ious)) > 0.3
