"""The simulator's camera renderer: geometry against the pinhole model, ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.mapping.frames import Pose2D
from app.sim.render import CameraModel, Renderer
from app.sim.world import parse_world

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
    """The floor pipeline against the renderer's truth on the shipped world (reported
    by ``floornav sim-eval``), only loosely asserted here."""
    from app.config import FloornavConfig
    from app.evaluation import evaluate_on_simulator

    summary = evaluate_on_simulator(FloornavConfig(), ["floornav"], frames=3)
    scores = summary["methods"]["floornav"]  # type: ignore[index]
    assert scores["iou"] > 0.3


OPEN_FLOOR = """
[start]
x_m = 0.0
y_m = 0.0
[floor]
pattern = "plain"
color = "#808080"
variation = 0.0
[[floor_areas]]
rect_m = [3.0, -2.0, 3.5, 2.0]
surface = { pattern = "plain", color = "#c02020", variation = 0.0 }
[lighting]
attenuation_distance_m = 1000.0
"""


def test_floor_only_view_mask_and_world_fixed_texture() -> None:
    renderer = Renderer(parse_world(OPEN_FLOOR), CameraModel(noise_sigma=0.0))
    cam = renderer.camera
    rays = cam.rays_robot()
    centre = cam.width_px // 2
    for x in (0.0, 1.0):
        frame = renderer.render(Pose2D(x, 0.0, 0.0))
        # Nothing but floor: the mask is exactly the pixels whose ray points down.
        assert (frame.floor_mask == (rays[..., 2] < 0)).all()
        # The red strip x in [3, 3.5] stays put in the plan as the robot moves.
        red = frame.image[:, centre, 2].astype(int) - frame.image[:, centre, 0].astype(int) > 60
        rows = np.flatnonzero(red)
        near_edge, far_edge = cam.floor_row_px(3.0 - x), cam.floor_row_px(3.5 - x)
        assert abs(rows.max() - near_edge) <= 1.5
        assert abs(rows.min() - far_edge) <= 1.5


def test_render_bench_smoke() -> None:
    from app.benchmarks.sim import bench_render

    result = bench_render(1)
    assert result["frames"] == 30 and float(result["median"]) > 0


@pytest.mark.parametrize("pitch_rad", [0.0, 0.35])
def test_the_kernels_rays_are_the_cameras_rays_to_the_bit(pitch_rad: float) -> None:
    """The renderer keeps no per-pixel ray table: its kernels work each ray out from the
    column's and row's coordinates, and must get exactly `rays_robot` (and its norm), or
    the images would change with the memory layout."""
    from app.sim.render import _axes, _ray, _ray_length, _row

    cam = CameraModel(width_px=160, height_px=120, pitch_rad=pitch_rad, fx_px=151.3)
    rays = cam.rays_robot()
    lengths = np.linalg.norm(rays, axis=2)
    u, v = cam.ray_coordinates()
    axes = _axes(cam.axes_robot())
    for r in range(cam.height_px):
        row = _row(v[r], axes)
        for c in range(cam.width_px):
            ray = _ray(u[c], row, axes)
            assert ray == tuple(rays[r, c]), (r, c)
            assert _ray_length(*ray) == lengths[r, c], (r, c)
