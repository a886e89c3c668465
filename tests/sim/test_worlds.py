"""The shipped worlds (two-rooms, home, office) and what they need: selection by name,
the seed, light areas, a glossy floor's reflections, a two-tone rug, and the reachable
floor of a disk robot (`app.sim.truth`)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main
from app.config import ConfigError, FloornavConfig, load_config
from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import FREE, UNKNOWN
from app.sim.render import CameraModel, Renderer
from app.sim.setup import project_floor_points, renderer_from_config, world_from_config
from app.sim.truth import coverage_reachable, marks_near_truth, reachable_free_mask
from app.sim.world import (
    DEFAULT_ROBOT_RADIUS_M,
    World,
    WorldError,
    load_named_world,
    mip_levels,
    parse_world,
)
from app.sim.worlds import DEFAULT_WORLD_PATH, UnknownWorldError, resolve_world_path, world_names

ROBOT_RADIUS_M = FloornavConfig().mapping.robot_radius_m
CELL_M = 0.05

ROOMS = {
    "two-rooms": {"living room": (0.0, 0.0, 4.5, 6.0), "kitchen": (4.5, 0.0, 8.0, 6.0)},
    "home": {
        "living room": (0.0, 3.2, 5.5, 8.0),
        "kitchen": (5.5, 3.2, 10.0, 8.0),
        "hallway": (0.0, 2.0, 10.0, 3.2),
        "bedroom": (0.0, 0.0, 6.0, 2.0),
        "bathroom": (6.0, 0.0, 10.0, 2.0),
    },
    "office": {
        "corridor": (0.0, 2.5, 14.0, 4.5),
        "meeting room": (0.0, 4.5, 5.0, 7.0),
        "office A": (5.0, 4.5, 9.5, 7.0),
        "office B": (9.5, 4.5, 14.0, 7.0),
        "kitchenette": (0.0, 0.0, 4.0, 2.5),
        "open-plan office": (4.0, 0.0, 14.0, 2.5),
    },
}
"""Every room of every shipped world (rectangles in the plan): all must be reachable."""


def test_the_shipped_worlds_are_the_documented_ones() -> None:
    assert world_names() == sorted(ROOMS)
    assert resolve_world_path("") == DEFAULT_WORLD_PATH == resolve_world_path("default")
    assert resolve_world_path("two-rooms") == DEFAULT_WORLD_PATH


@pytest.fixture(scope="module", params=sorted(ROOMS))
def shipped(request: pytest.FixtureRequest) -> tuple[str, World]:
    """(name, world) of each shipped world."""
    name: str = request.param
    return name, load_named_world(name)


def test_world_loads_and_renders_a_sane_frame(shipped: tuple[str, World]) -> None:
    _, world = shipped
    # load_named_world already ran the world checks (they raise); a World can be rebuilt
    # from its spec, which runs them again without line numbers.
    assert World(world.spec).name == world.name
    renderer = Renderer(world, CameraModel(noise_sigma=0.0))
    start = world.start_pose
    for pose in (start, Pose2D(start.x_m, start.y_m, start.theta_rad + 2.0)):
        frame = renderer.render(pose)
        assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
        assert frame.floor_mask.shape == (480, 640)
        assert frame.floor_mask[-40:].mean() > 0.5  # floor just ahead of the robot
        # NaN in the shading becomes int(NaN), clamped to 0: pure black. No colour of
        # any world is that dark once lit.
        assert (frame.image.max(axis=2) > 0).all()


def test_start_pose_is_free_with_room_for_the_robot(shipped: tuple[str, World]) -> None:
    _, world = shipped
    start = world.start_pose
    assert world.clearance_m(start.x_m, start.y_m) >= DEFAULT_ROBOT_RADIUS_M >= ROBOT_RADIUS_M
    grid, occ = world.occupancy(CELL_M)
    row, col = grid.cell_of(np.array([[start.x_m, start.y_m]]))[0]
    assert occ[row, col] == 0


def test_every_room_is_reachable(shipped: tuple[str, World]) -> None:
    name, world = shipped
    grid, reachable = reachable_free_mask(world, CELL_M, ROBOT_RADIUS_M)
    _, occ = world.occupancy(CELL_M)
    x, y = grid.cell_centers()
    for room, (x0, y0, x1, y1) in ROOMS[name].items():
        inside = (x > x0) & (x < x1) & (y > y0) & (y < y1)
        free = inside & (occ == 0)
        fraction = (reachable & inside).sum() / free.sum()
        assert fraction >= 0.9, f"{name}: {room} {fraction:.3f} reachable"


def test_home_has_what_it_promises() -> None:
    spec = load_named_world("home").spec
    patterns = {spec.floor.pattern} | {a.surface.pattern for a in spec.floor_areas}
    colors = {spec.floor.color} | {a.surface.color for a in spec.floor_areas}
    assert patterns == {"wood", "tiles", "plain", "carpet"} and len(colors) >= 8
    assert any(a.end_color is not None for a in spec.floor_areas)
    legs = [b for b in spec.boxes if max(b.size_m) <= 0.05]
    assert len(legs) >= 12  # a coffee table, an armchair, a dining table, two chairs
    assert any(b.color == "#a37953" for b in spec.boxes)  # the floor-coloured ottoman
    gains = sorted(a.gain for a in spec.light_areas)
    assert gains[0] < 0.6 and gains[-1] > 1.2  # a dim hallway, a patch of sun


def test_office_is_glossy_with_lights() -> None:
    world = load_named_world("office")
    assert world.spec.floor.gloss >= 0.4 and len(world.spec.lights) >= 5
    x0, y0, x1, y1 = ROOMS["office"]["corridor"]
    assert x1 - x0 >= 12.0 and y1 - y0 == pytest.approx(2.0)


# -- selection by name, the seed ---------------------------------------------------------


def test_unknown_world_name_lists_the_names() -> None:
    with pytest.raises(UnknownWorldError) as info:
        resolve_world_path("kitchen")
    for name in ("two-rooms", "home", "office", "'default'"):
        assert name in str(info.value)


def test_config_world_file_takes_a_name_an_alias_or_a_path(tmp_path: Path) -> None:
    default = world_from_config(FloornavConfig())
    assert default.spec == world_from_config(load_config(None, sim={"world_file": "default"})).spec
    assert default.spec == load_named_world("two-rooms").spec
    home = world_from_config(load_config(None, sim={"world_file": "home"}))
    assert home.name == "home"
    path = tmp_path / "mine.toml"
    path.write_text(
        'name = "mine"\n[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 3, 2]\n'
    )
    assert world_from_config(load_config(None, sim={"world_file": str(path)})).name == "mine"
    with pytest.raises(ConfigError) as info:
        load_config(None, sim={"world_file": "hom"})
    assert info.value.issues[0].key == "sim.world_file"
    assert "home, office, two-rooms" in str(info.value)
    with pytest.raises(WorldError):  # a path is read when the world is built
        world_from_config(load_config(None, sim={"world_file": str(tmp_path / "no.toml")}))


def test_run_takes_world_and_seed(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import app.daemon

    seen: list[FloornavConfig] = []

    def fake_run(config: FloornavConfig, **_: object) -> int:
        seen.append(config)
        return 0

    monkeypatch.setattr(app.daemon, "run_daemon", fake_run)
    config_file = tmp_path / "config.toml"
    config_file.write_text("[sim]\nnoise_sigma = 3.0\nseed = 5\n")
    assert main(["run", "--world", "office", "--seed", "7", "--config", str(config_file)]) == 0
    assert seen[-1].sim.world_file == "office" and seen[-1].sim.seed == 7
    assert seen[-1].sim.noise_sigma == 3.0  # the file's other [sim] keys stay
    assert main(["run", "--config", str(config_file)]) == 0
    assert seen[-1].sim.world_file == "" and seen[-1].sim.seed == 5


def test_run_with_an_unknown_world_names_the_worlds(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import app.daemon

    def never(*_: object, **__: object) -> int:
        raise AssertionError("the daemon must not start")

    monkeypatch.setattr(app.daemon, "run_daemon", never)
    assert main(["run", "--world", "nowhere", "--config", "config.toml"]) == 2
    err = capsys.readouterr().err
    assert "unknown world 'nowhere'" in err and "home, office, two-rooms" in err


def test_seed_sets_the_sensor_noise() -> None:
    def frame(seed: int) -> np.ndarray:
        config = load_config(None, sim={"seed": seed})
        renderer = renderer_from_config(config)
        return renderer.render(renderer.world.start_pose).image

    assert np.array_equal(frame(3), frame(3))
    assert not np.array_equal(frame(3), frame(4))
    with pytest.raises(ConfigError):
        load_config(None, sim={"seed": -1})


# -- light areas, gloss, rugs -------------------------------------------------------------

PLAIN_ROOM = """
[start]
x_m = 1.0
y_m = 2.0
[floor]
pattern = "plain"
color = "#808080"
variation = 0.0
[[rooms]]
rect_m = [0.0, 0.0, 6.0, 4.0]
height_m = 1.2
color = "#c03030"
"""


def _floor_pixels(cam: CameraModel, pose: Pose2D, plan_xy: np.ndarray) -> np.ndarray:
    """(N, 2) integer (row, col) of plan-frame floor points seen from ``pose``."""
    robot = pose.inverse().apply(plan_xy)
    uv = project_floor_points(cam, robot)
    return np.rint(uv[:, ::-1]).astype(int)


def test_light_areas_scale_the_floor_inside_them_only() -> None:
    cam = CameraModel(noise_sigma=0.0)
    pose = Pose2D(1.0, 2.0, 0.0)
    dark = PLAIN_ROOM + "[[light_areas]]\nrect_m = [2.0, 1.6, 3.0, 2.4]\ngain = 0.5\n"
    dark += "softness_m = 0.0\n"
    sun = PLAIN_ROOM + "[[light_areas]]\nrect_m = [2.0, 1.6, 3.0, 2.4]\ngain = 1.5\n"
    sun += 'color = "#fff0d0"\nsoftness_m = 0.0\n'
    plain = Renderer(parse_world(PLAIN_ROOM), cam).render(pose).image.astype(float)
    dimmed = Renderer(parse_world(dark), cam).render(pose).image.astype(float)
    sunlit = Renderer(parse_world(sun), cam).render(pose).image.astype(float)
    inside = _floor_pixels(cam, pose, np.array([[2.5, 2.0], [2.3, 1.7], [2.7, 2.3]]))
    outside = _floor_pixels(cam, pose, np.array([[1.7, 2.0], [3.4, 2.0], [2.5, 1.4]]))
    for r, c in inside:
        assert dimmed[r, c] == pytest.approx(0.5 * plain[r, c], abs=1.0)
        b, g, red = sunlit[r, c] / plain[r, c]
        assert red == pytest.approx(1.5, abs=0.02) and b < g < red  # warm: less blue
    for r, c in outside:
        assert np.array_equal(dimmed[r, c], plain[r, c])
        assert np.array_equal(sunlit[r, c], plain[r, c])


def test_light_area_dims_the_walls_standing_in_it() -> None:
    cam = CameraModel(noise_sigma=0.0)
    pose = Pose2D(3.0, 2.0, 0.0)  # facing the east wall x = 6
    dark = PLAIN_ROOM + "[[light_areas]]\nrect_m = [5.5, 0.0, 6.5, 2.0]\ngain = 0.5\n"
    plain = Renderer(parse_world(PLAIN_ROOM), cam).render(pose)
    dimmed = Renderer(parse_world(dark), cam).render(pose)
    wall = ~plain.floor_mask[:100]
    right, left = wall[:, 330:], wall[:, :310]  # y < 2 is on the right of the image
    ratio_right = dimmed.image[:100, 330:][right].mean() / plain.image[:100, 330:][right].mean()
    ratio_left = dimmed.image[:100, :310][left].mean() / plain.image[:100, :310][left].mean()
    assert ratio_right == pytest.approx(0.5, abs=0.03) and ratio_left == pytest.approx(1.0)


def test_light_gain_matches_its_definition() -> None:
    world = parse_world(
        PLAIN_ROOM + "[[light_areas]]\nrect_m = [1.0, 1.0, 2.0, 2.0]\ngain = 2.0\n"
        "softness_m = 0.2\n[[light_areas]]\nrect_m = [1.5, 1.0, 3.0, 2.0]\ngain = 0.5\n"
    )
    gain = world.light_gain(np.array([0.5, 0.95, 1.0, 1.3, 1.7, 2.5]), np.full(6, 1.5))
    # Outside; on the ramp (a quarter in); at the edge (half); inside the first; in
    # both (they multiply); inside the second only (with its hard edge).
    assert gain[:, 2] == pytest.approx([1.0, 1.25, 1.5, 2.0, 1.0, 0.5])


GLOSSY = """
[start]
x_m = 1.0
y_m = 2.0
[floor]
pattern = "plain"
color = "#606060"
variation = 0.0
gloss = {gloss}
[[rooms]]
rect_m = [0.0, 0.0, 4.0, 4.0]
height_m = 2.5
color = "#30a0e0"
[lighting]
background_color = "#606060"
"""


def test_glossy_floor_mirrors_the_wall_and_keeps_the_floor_mask() -> None:
    cam = CameraModel(noise_sigma=0.0)
    pose = Pose2D(2.5, 2.0, 0.0)  # the blue wall x = 4 is 1.5 m ahead
    matte = Renderer(parse_world(GLOSSY.format(gloss=0.0)), cam).render(pose)
    glossy = Renderer(parse_world(GLOSSY.format(gloss=0.8)), cam).render(pose)
    assert np.array_equal(matte.floor_mask, glossy.floor_mask)
    col = cam.width_px // 2
    base = int(np.argmax(matte.floor_mask[:, col]))  # the wall's foot
    below = slice(base + 2, base + 30)
    m = matte.image[below, col].astype(float)
    g = glossy.image[below, col].astype(float)
    # The blue wall shows in the grey floor just below its foot: bluer (BGR), less red.
    assert (g[:, 0] - m[:, 0] > 8).all() and (m[:, 2] - g[:, 2] > 15).all()
    # The walls (not floor) are the same.
    assert np.array_equal(matte.image[~matte.floor_mask], glossy.image[~glossy.floor_mask])
    # Looking down at the floor right ahead, the reflection fades (Fresnel).
    near = slice(cam.height_px - 20, cam.height_px)
    assert (
        np.abs(glossy.image[near, col].astype(float) - matte.image[near, col]).mean()
        < np.abs(g - m).mean() / 2
    )


def test_ceiling_light_shows_as_a_spot_on_a_glossy_floor() -> None:
    cam = CameraModel(noise_sigma=0.0)
    pose = Pose2D(0.5, 2.0, 0.0)
    text = GLOSSY.format(gloss=0.6) + "[[lights]]\nposition_m = [3.0, 2.0]\nheight_m = 2.4\n"
    lit = Renderer(parse_world(text), cam).render(pose).image.astype(float)
    unlit = Renderer(parse_world(GLOSSY.format(gloss=0.6)), cam).render(pose).image.astype(float)
    # The light's mirror image (3, 2, -2.4) in the camera, from the robot.
    eye = np.array([cam.x_m, cam.y_m, cam.height_m])
    p = np.array([3.0 - pose.x_m, 0.0, -2.4]) - eye
    right, down, forward = cam.axes_robot()
    cx, cy = cam.principal_point_px
    u = cx + cam.fx_px * (p @ right) / (p @ forward)
    v = cy + cam.fy_px * (p @ down) / (p @ forward)
    spot = lit[round(v), round(u)] - unlit[round(v), round(u)]
    assert (spot > 30).all()
    far = lit[round(v), 40] - unlit[round(v), 40]
    assert np.abs(far).max() <= 1


def test_rug_fades_from_its_colour_to_its_end_colour() -> None:
    world = parse_world(
        PLAIN_ROOM + "[[floor_areas]]\nrect_m = [1.0, 1.0, 3.0, 2.0]\nend_color = '#2040c0'\n"
        "surface = { pattern = 'plain', color = '#c04020', variation = 0.0 }\n"
    )
    texture = world.floor_raster(0.01)
    points = np.array([[1.01, 1.5], [2.0, 1.5], [2.99, 1.5]])
    rows, cols = texture.grid.cell_of(points).T
    west, middle, east = texture.levels[0][rows, cols].astype(int)  # BGR
    assert np.abs(west - (0x20, 0x40, 0xC0)).max() <= 3
    assert np.abs(east - (0xC0, 0x40, 0x20)).max() <= 3
    assert np.abs(middle - (0x70, 0x40, 0x70)).max() <= 3


def test_a_floors_mip_levels_do_not_blend_it_with_the_floor_next_to_it() -> None:
    # A dark carpet beside the light floor, as behind a wall: far away (the coarser
    # levels) the light floor keeps its own colour up to the line, and the carpet its.
    world = parse_world(
        PLAIN_ROOM + "[[floor_areas]]\nrect_m = [0.0, 2.0, 6.0, 4.0]\n"
        "surface = { pattern = 'plain', color = '#202020', variation = 0.0 }\n"
    )
    texture = world.floor_raster(0.01)
    assert set(np.unique(texture.surfaces)) == {0, 1}
    for level in texture.levels[1:]:
        assert set(np.unique(level)) == {0x20, 0x80}
    # One surface: the plain pyramid.
    plain = load_named_world("two-rooms").floor_raster(0.01)
    image = plain.levels[0][:200, :200]
    levels = mip_levels(image, np.zeros(image.shape[:2], np.int16), 4)
    expected = [image]
    for _ in range(3):
        expected.append(cv2.pyrDown(expected[-1]))
    assert all(np.array_equal(a, b) for a, b in zip(levels, expected, strict=True))


def test_degenerate_light_area_is_named() -> None:
    with pytest.raises(WorldError) as info:
        parse_world(PLAIN_ROOM + "[[light_areas]]\nrect_m = [2.0, 1.0, 2.0, 3.0]\ngain = 0.5\n")
    assert info.value.issues[0].key == "light_areas[0].rect_m"


# -- the reachable floor -----------------------------------------------------------------

TWO_ROOMS = """
[start]
x_m = 1.0
y_m = 1.0
[[rooms]]
rect_m = [0.0, 0.0, 4.0, 2.0]
[[walls]]
points_m = [[2.0, 0.0], [2.0, {door_y0}]]
[[walls]]
points_m = [[2.0, {door_y1}], [2.0, 2.0]]
"""


def _two_rooms(door_m: float) -> World:
    return parse_world(TWO_ROOMS.format(door_y0=1.0 - door_m / 2, door_y1=1.0 + door_m / 2))


def test_open_room_reachable_floor_is_the_swept_square() -> None:
    radius = 0.3
    world = parse_world("[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 2, 2]\n")
    grid, mask = reachable_free_mask(world, CELL_M, radius)
    _, occ = world.occupancy(CELL_M)
    x, y = grid.cell_centers()
    # The centre may go where the walls are `radius` away: cell centres in
    # [0.325, 1.675]^2. The body sweeps what lies within `radius` of that square.
    lo, hi = 0.325, 1.675
    dx = np.maximum(np.maximum(lo - x, x - hi), 0.0)
    dy = np.maximum(np.maximum(lo - y, y - hi), 0.0)
    inside = (x > 0) & (x < 2) & (y > 0) & (y < 2) & (occ == 0)
    expected = inside & (np.hypot(dx, dy) <= radius + 1e-9)
    assert np.array_equal(mask, expected)
    assert not mask[np.hypot(x - 0.05, y - 0.05) < 0.03].any()  # corners stay unswept


def test_doorway_narrower_than_the_robot_closes_the_far_room() -> None:
    world = _two_rooms(door_m=0.2)  # < 2 * 0.12
    grid, mask = reachable_free_mask(world, CELL_M, ROBOT_RADIUS_M)
    x, _ = grid.cell_centers()
    assert not mask[x > 2.0].any()
    # The near room alone is exactly what a closed wall leaves.
    closed = parse_world(TWO_ROOMS.format(door_y0=1.0, door_y1=1.0 + 1e-2))
    _, closed_mask = reachable_free_mask(closed, CELL_M, ROBOT_RADIUS_M)
    assert np.array_equal(mask[x < 1.95], closed_mask[x < 1.95])
    # From the far room's side, the near one is out of reach instead.
    _, from_far = reachable_free_mask(world, CELL_M, ROBOT_RADIUS_M, start_xy=(3.0, 1.0))
    assert from_far.any() and not (from_far & mask).any()
    # A wide enough doorway joins them.
    _, wide = reachable_free_mask(_two_rooms(door_m=0.4), CELL_M, ROBOT_RADIUS_M)
    assert wide[x > 2.0].sum() > 0.9 * mask[x < 2.0].sum()


def test_reachable_mask_refuses_bad_arguments() -> None:
    world = _two_rooms(door_m=0.4)
    with pytest.raises(ValueError, match="sqrt"):
        reachable_free_mask(world, 0.2, 0.12)
    with pytest.raises(ValueError, match="start"):
        reachable_free_mask(world, CELL_M, ROBOT_RADIUS_M, start_xy=(2.0, 0.5))


def test_coverage_reachable_counts_reachable_floor_the_map_calls_free() -> None:
    world = _two_rooms(door_m=0.2)
    grid, reachable = reachable_free_mask(world, CELL_M, ROBOT_RADIUS_M)
    x, _ = grid.cell_centers()
    identity = Pose2D()
    west = np.where(x < 2.0, FREE, UNKNOWN).astype(np.int8)
    # The far room is unreachable: mapping just the near room is full coverage.
    assert coverage_reachable(west, grid, identity, world, ROBOT_RADIUS_M) == 1.0
    half = np.where(x < 1.0, FREE, UNKNOWN).astype(np.int8)
    expected = (reachable & (x < 1.0)).sum() / reachable.sum()
    assert coverage_reachable(half, grid, identity, world, ROBOT_RADIUS_M) == expected
    # A map in the robot's start frame, rotated by 90 degrees: the lookup follows.
    start = Pose2D(1.0, 1.0, math.pi / 2)
    map_grid = GroundGrid.covering(
        x_min_m=-3.0, x_max_m=3.0, y_min_m=-4.0, y_max_m=4.0, cell_m=CELL_M
    )
    mx, my = map_grid.cell_centers()
    plan_x = start.apply(np.column_stack((mx.ravel(), my.ravel())))[:, 0].reshape(mx.shape)
    rotated = np.where(plan_x < 1.0, FREE, UNKNOWN).astype(np.int8)
    got = coverage_reachable(rotated, map_grid, start, world, ROBOT_RADIUS_M)
    assert got == pytest.approx(expected, abs=0.02)
    assert coverage_reachable(np.full_like(west, UNKNOWN), grid, identity, world, 0.12) == 0.0


def test_marks_near_truth_is_the_share_of_marks_at_walls_and_boxes() -> None:
    world = parse_world("[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 2, 2]\n")
    grid, _ = world.occupancy(CELL_M)
    identity = Pose2D()
    marks = np.zeros(grid.shape, dtype=bool)
    assert marks_near_truth(marks, grid, identity, world) is None

    def mark(map_grid: GroundGrid, layer: np.ndarray, xy: tuple[float, float]) -> None:
        row, col = map_grid.cell_of(np.array([xy]))[0]
        layer[row, col] = True

    mark(grid, marks, (1.0, 0.03))  # on the south wall
    mark(grid, marks, (1.0, 1.0))  # the middle of the room
    assert marks_near_truth(marks, grid, identity, world) == 0.5
    # A map in the robot's start frame, turned by 90 degrees: each mark is taken to the
    # plan first; one off the plan's grid is far from everything.
    start = Pose2D(1.0, 1.0, math.pi / 2)
    map_grid = GroundGrid.covering(
        x_min_m=-4.0, x_max_m=4.0, y_min_m=-4.0, y_max_m=4.0, cell_m=CELL_M
    )
    turned = np.zeros(map_grid.shape, dtype=bool)
    on_wall = start.inverse().apply(np.array([[1.0, 0.03]]))[0]
    mark(map_grid, turned, (float(on_wall[0]), float(on_wall[1])))
    mark(map_grid, turned, (0.0, 0.0))  # the start, mid-room
    mark(map_grid, turned, (1.0, 1.0))  # the plan's corner (0, 2)
    mark(map_grid, turned, (-3.5, 0.0))  # 3.5 m behind the start: outside the plan
    assert marks_near_truth(turned, map_grid, start, world) == 0.5
    with pytest.raises(ValueError, match="shape"):
        marks_near_truth(marks[1:], grid, identity, world)


def test_every_world_renders_with_the_kernels_the_default_world_compiled() -> None:
    """`app.jit.compile_kernels` renders one frame of the configured world only: the
    glossy, lit and plain worlds must all call the same kernel signatures (the
    reflection kernels run, and return at once, for a world without gloss)."""
    from numba.core.registry import CPUDispatcher

    import app.sim.render as render

    kernels = {
        name: value
        for name, value in vars(render).items()
        if isinstance(value, CPUDispatcher) and value.py_func.__module__ == render.__name__
    }
    renderer = renderer_from_config(FloornavConfig())
    renderer.render(renderer.world.start_pose)
    before = {name: len(kernel.signatures) for name, kernel in kernels.items()}
    assert before["_render_mirror"] == 1 and before["_light_spots"] == 1
    for name in ("home", "office"):
        world = load_named_world(name)
        start = world.start_pose
        Renderer(world).render(Pose2D(start.x_m + 0.1, start.y_m, start.theta_rad + 0.5))
    assert {name: len(kernel.signatures) for name, kernel in kernels.items()} == before
