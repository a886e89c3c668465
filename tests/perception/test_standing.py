"""Standing surfaces found by the horizon (`app.perception.standing`): exact answers on
synthetic frames, then a rendered floor-coloured box."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.perception.standing import (
    HorizonParams,
    horizon_rows,
    standing_across_horizon,
    wall_surfaces,
)

H, W = 240, 320
HORIZON = 40
BOX_ROWS = (10, 150)  # the box's face: its top above the horizon, its base at row 150
BOX_COLS = (100, 220)
FLOOR_BGR = (82, 122, 164)  # wood
BOX_BGR = (94, 138, 176)  # about 6 CIELAB units lighter: "floor-coloured"
PARAMS = HorizonParams(search_rows=H)  # full resolution: exact rows


def _lab_distance(bgr_a: tuple[int, int, int], bgr_b: tuple[int, int, int]) -> float:
    lab = cv2.cvtColor(np.array([[bgr_a, bgr_b]], np.uint8), cv2.COLOR_BGR2LAB).astype(float)
    lab[..., 0] *= 100 / 255
    return float(np.linalg.norm(lab[0, 0] - lab[0, 1]))


def _scene(
    box_bgr: tuple[int, int, int] = BOX_BGR, box_cols: tuple[int, int] = BOX_COLS
) -> np.ndarray:
    """Grey wall above row 50 (the far wall's foot, below the horizon), a textured
    wood floor below, a flat box on it."""
    rng = np.random.default_rng(0)
    image = np.empty((H, W, 3), np.uint8)
    image[:] = (150, 150, 150)
    floor = np.array(FLOOR_BGR, float) + rng.normal(0, 3, (H - 50, W, 1))
    image[50:] = np.clip(floor, 0, 255).astype(np.uint8)
    image[BOX_ROWS[0] : BOX_ROWS[1], box_cols[0] : box_cols[1]] = box_bgr
    return image


def _box_mask() -> np.ndarray:
    box = np.zeros((H, W), bool)
    box[BOX_ROWS[0] : BOX_ROWS[1], BOX_COLS[0] : BOX_COLS[1]] = True
    return box


def _assert_outline_within(standing: np.ndarray, expected: np.ndarray, px: int) -> None:
    """``standing`` is ``expected`` up to ``px`` pixels at its outline (the 5x5 median
    that keeps sensor noise from joining a surface moves its corners by up to 2 px)."""
    kernel = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    grown = cv2.dilate(expected.view(np.uint8), kernel).astype(bool)
    shrunk = cv2.erode(expected.view(np.uint8), kernel).astype(bool)
    assert not (standing & ~grown).any(), f"standing beyond {px} px of the surface"
    assert standing[shrunk].all(), f"surface missed more than {px} px inside its outline"


def _mask_calling_the_box_floor() -> np.ndarray:
    """What a colour segmenter does with a floor-coloured box: floor from row 50 down,
    and up the box's face past the horizon."""
    mask = np.zeros((H, W), bool)
    mask[50:] = True
    mask |= _box_mask()
    return mask


def test_the_box_is_standing_down_to_its_base_and_the_floor_is_kept() -> None:
    assert _lab_distance(FLOOR_BGR, BOX_BGR) < 8  # the premise: colour alone is close
    mask = _mask_calling_the_box_floor()
    standing = standing_across_horizon(mask, _scene(), np.full(W, HORIZON), PARAMS)
    _assert_outline_within(standing, _box_mask(), 2)
    # The base is found to the row (sensor noise may give one floor row to the box).
    assert not standing[BOX_ROWS[1] + 1 :].any()
    assert standing[BOX_ROWS[1] - 1, BOX_COLS[0] + 2 : BOX_COLS[1] - 2].all()


def test_a_rug_under_the_box_stays_floor() -> None:
    """Two floors under the surface (a dark rug in front of the box, grey tiles nearer):
    the strongest change is rug to tiles, but the surface ends at the rug."""
    image = _scene()
    image[BOX_ROWS[1] :] = (140, 140, 140)
    image[BOX_ROWS[1] : BOX_ROWS[1] + 40] = (60, 60, 120)
    mask = np.zeros((H, W), bool)
    mask[BOX_ROWS[1] :] = True
    mask |= _box_mask()
    standing = standing_across_horizon(mask, image, np.full(W, HORIZON), PARAMS)
    _assert_outline_within(standing, _box_mask(), 2)
    assert not standing[BOX_ROWS[1] + 1 :].any()


def test_floor_of_the_surface_colour_is_taken_only_beside_it() -> None:
    """Wood of nearly the box's colour far to its side is never a part of it."""
    image = _scene()
    image[BOX_ROWS[1] : BOX_ROWS[1] + 40] = (60, 60, 120)  # the box stands on a rug
    standing = standing_across_horizon(
        _mask_calling_the_box_floor(), image, np.full(W, HORIZON), PARAMS
    )
    reach = round(HorizonParams().grow_reach_frac * W)
    assert standing[:, BOX_COLS[0] : BOX_COLS[1]][_box_mask()[:, BOX_COLS[0] : BOX_COLS[1]]].all()
    assert not standing[:, : BOX_COLS[0] - reach].any()
    assert not standing[:, BOX_COLS[1] + reach :].any()
    assert not standing[BOX_ROWS[1] + 1 :].any()


def test_no_floor_above_the_horizon_finds_nothing() -> None:
    mask = np.zeros((H, W), bool)
    mask[HORIZON - 3 :] = True  # within the margin of a calibration's error
    standing = standing_across_horizon(mask, _scene(), np.full(W, HORIZON), PARAMS)
    assert not standing.any()


def test_a_surface_filling_the_view_below_the_horizon_is_all_standing() -> None:
    image = np.full((H, W, 3), BOX_BGR, np.uint8)
    mask = np.ones((H, W), bool)
    standing = standing_across_horizon(mask, image, np.full(W, HORIZON), PARAMS)
    assert standing.all()


def test_the_columns_beside_that_stay_below_the_horizon_join_the_surface() -> None:
    """The box's right part is cut off by the wall above row 60 in the mask (the
    segmenter stopped there): still the same surface, down to the same base."""
    mask = _mask_calling_the_box_floor()
    mask[:60, 180:] = False
    standing = standing_across_horizon(mask, _scene(), np.full(W, HORIZON), PARAMS)
    _assert_outline_within(standing, _box_mask() & mask, 2)
    assert standing[60 : BOX_ROWS[1] - 2, 182 : BOX_COLS[1] - 2].all()  # the short columns
    assert not standing[BOX_ROWS[1] + 1 :].any()


def test_floor_apart_from_a_blob_above_the_horizon_is_kept() -> None:
    mask = np.zeros((H, W), bool)
    mask[100:] = True
    mask[5:20, 40:60] = True  # a stray blob up in the wall
    standing = standing_across_horizon(mask, _scene(), np.full(W, HORIZON), PARAMS)
    expected = np.zeros((H, W), bool)
    expected[5:20, 40:60] = True
    np.testing.assert_array_equal(standing, expected)


def test_the_coarse_search_finds_the_base_within_its_factor() -> None:
    mask = _mask_calling_the_box_floor()
    standing = standing_across_horizon(
        mask, _scene(), np.full(W, HORIZON), HorizonParams(search_rows=60)
    )
    # Rows and columns are 4 px apart; the median's 2 search pixels are 8 here.
    _assert_outline_within(standing, _box_mask(), 4 * (2 + 1))
    assert not standing[BOX_ROWS[1] + 4 :].any()


def test_horizon_rows_are_the_first_valid_row_per_column() -> None:
    valid = np.zeros((6, 3), bool)
    valid[2:, 0] = True
    valid[4:, 1] = True
    np.testing.assert_array_equal(horizon_rows(valid), [2, 4, 6])


def test_shapes_must_agree() -> None:
    with pytest.raises(ValueError, match="must agree"):
        standing_across_horizon(np.ones((H, W), bool), _scene(), np.full(W - 1, HORIZON))


def test_a_rendered_floor_coloured_box_is_found_standing() -> None:
    """The shipped world's cardboard box, 0.6 m ahead, under a mask that calls all of it
    floor (floornet does: the box is 0.35 m tall, the camera 0.22 m)."""
    from app.config import load_config
    from app.mapping.frames import Pose2D
    from app.mapping.ground_map import image_horizon_rows
    from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

    root = Path(__file__).resolve().parents[2]
    config = load_config(root / "config.toml", sim={"world_file": "two-rooms"})
    renderer = renderer_from_config(config)
    box_xy, heading, distance = (2.4, 3.7), 2.982, 0.6
    frame = renderer.render(
        Pose2D(
            box_xy[0] - distance * math.cos(heading),
            box_xy[1] - distance * math.sin(heading),
            heading,
        )
    )
    horizon = image_horizon_rows(sim_floor_calibration(camera_model(config)))
    red, blue = frame.image[..., 2].astype(int), frame.image[..., 0].astype(int)
    box = ~frame.floor_mask & (red - blue > 30)  # brown; the walls are grey
    assert box[: horizon.min()].any(), "the box reaches above the horizon"
    mask = frame.floor_mask | box
    standing = standing_across_horizon(mask, frame.image, horizon)
    assert (standing & box).sum() >= 0.95 * box.sum()
    # The floor lost is the base line's width times the coarse search's 4 px rows.
    assert (standing & frame.floor_mask).sum() <= 0.02 * frame.floor_mask.sum()


# -- wall_surfaces: walls -----------------------------------------------------------------


def _floor_from(row: int) -> np.ndarray:
    mask = np.zeros((H, W), bool)
    mask[row:] = True
    return mask


def test_a_plain_wall_from_the_floors_end_past_the_horizon_stands() -> None:
    # The scene's grey wall meets the floor at row 50, 10 rows below the horizon; the
    # mask's floor ends there. Standing: the wall below the horizon, every column.
    walls = wall_surfaces(_floor_from(50), _scene(), np.full(W, HORIZON), PARAMS).walls
    expected = np.zeros((H, W), bool)
    expected[HORIZON:50] = True
    np.testing.assert_array_equal(walls, expected)


def test_a_rug_between_the_floor_and_the_wall_is_not_taken_for_the_wall() -> None:
    # A dark rug (rows 50-89) the mask leaves out, under the same wall: the run above the
    # floor changes colour below the horizon, so nothing in it is proven standing.
    image = _scene()
    image[50:90] = (40, 40, 90)
    assert _lab_distance((40, 40, 90), (150, 150, 150)) > 10
    walls = wall_surfaces(_floor_from(90), image, np.full(W, HORIZON), PARAMS).walls
    assert not walls.any()


def test_what_ends_below_the_horizon_or_has_no_floor_under_it_is_not_a_wall() -> None:
    image = _scene(box_bgr=(30, 30, 200))
    # The box left out of the floor, its top below the horizon: floor again above it.
    mask = _floor_from(50) & ~_box_mask()
    low_box = mask.copy()
    low_box[: BOX_ROWS[1] - 60] |= _box_mask()[: BOX_ROWS[1] - 60]  # the box's top is floor
    walls = wall_surfaces(low_box, image, np.full(W, HORIZON), PARAMS).walls
    assert not walls[:, BOX_COLS[0] : BOX_COLS[1]].any()
    # Columns whose bottom row is no floor (a wall right ahead): nothing to stand on.
    no_bottom = _floor_from(50)
    no_bottom[-1, :50] = False
    walls = wall_surfaces(no_bottom, _scene(), np.full(W, HORIZON), PARAMS).walls
    assert not walls[:, :50].any() and walls[HORIZON:50, 50:].all()
    with pytest.raises(ValueError, match="must agree"):
        wall_surfaces(_floor_from(50), _scene(), np.full(W - 1, HORIZON))


# -- wall_surfaces: a surface's lower part the mask took for floor ------------------------

LOWER_PART_FROM = 100  # the mask calls the box's face floor from this row down


def _half_box_floor() -> np.ndarray:
    """The scene's floor, with the box's face floor from `LOWER_PART_FROM` down to its
    base (a segmenter whose floor model reached halfway up a floor-coloured box)."""
    mask = _floor_from(50)
    mask[:LOWER_PART_FROM, BOX_COLS[0] : BOX_COLS[1]] = False
    return mask


def test_the_lower_part_of_a_surface_the_mask_took_for_floor_stands_down_to_its_foot() -> None:
    # The box's face (rows 10-149) runs from above the horizon down past where the mask's
    # floor ends (row 100) in one colour; its foot is the column's one real step, at
    # its base. Standing: the mask's floor from row 100 to the base, in the box's columns.
    surfaces = wall_surfaces(_half_box_floor(), _scene(), np.full(W, HORIZON), PARAMS)
    expected = np.zeros((H, W), bool)
    expected[LOWER_PART_FROM : BOX_ROWS[1], BOX_COLS[0] : BOX_COLS[1]] = True
    # To the row, but for the floor's sensor noise at the base line.
    _assert_outline_within(surfaces.floor_part, expected, 1)
    assert (surfaces.floor_part != expected).sum() <= 0.02 * (BOX_COLS[1] - BOX_COLS[0])
    # The face above the mask's floor is a wall as before; the wall beside it too.
    assert surfaces.walls[HORIZON:LOWER_PART_FROM, BOX_COLS[0] : BOX_COLS[1]].all()
    assert surfaces.walls[HORIZON:50, : BOX_COLS[0]].all()
    assert not (surfaces.walls & _half_box_floor()).any()


def test_a_wall_on_its_floor_a_fading_reflection_and_a_lone_streak_move_no_foot() -> None:
    horizon = np.full(W, HORIZON)
    # The mask ends where the box meets the floor: an edge there, nothing below stands.
    mask = _floor_from(50) & ~_box_mask()
    assert not wall_surfaces(mask, _scene(), horizon, PARAMS).floor_part.any()
    # Below the half-box, the face's colour fades into the floor's over 60 rows (its
    # reflection in a glossy floor): the step is real but no edge.
    image = _scene()
    face, floor = np.array(BOX_BGR, float), np.array(FLOOR_BGR, float)
    for k, row in enumerate(range(BOX_ROWS[1], BOX_ROWS[1] + 60)):
        image[row, BOX_COLS[0] : BOX_COLS[1]] = np.round(face + (floor - face) * k / 60)
    assert not wall_surfaces(_half_box_floor(), image, horizon, PARAMS).floor_part.any()
    # Two columns of the face alone: a streak, not a surface.
    narrow = _floor_from(50)
    narrow[:LOWER_PART_FROM, 150:152] = False
    narrow_box = _scene(box_cols=(150, 152))
    assert not wall_surfaces(narrow, narrow_box, horizon, PARAMS).floor_part.any()
    # Three columns are a surface (the search's resolution is the image's here).
    narrow[:LOWER_PART_FROM, 150:153] = False
    wide_enough = _scene(box_cols=(150, 153))
    assert wall_surfaces(narrow, wide_enough, horizon, PARAMS).floor_part[:, 150:153].any()


def test_rendered_floor_coloured_ottomans_side_stands_where_the_mask_took_it_for_floor() -> None:
    """The home's ottoman (wood-coloured, 0.40 m), passed on its east side: the shipped
    segmenter calls the lower half of its lit face floor; the walls test finds that
    half standing, and hardly any true floor."""
    from app.config import load_config
    from app.mapping.frames import Pose2D
    from app.mapping.ground_map import image_horizon_rows
    from app.perception.pipeline import FloorSegmenter
    from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

    root = Path(__file__).resolve().parents[2]
    config = load_config(root / "config.toml", sim={"world_file": "home"})
    renderer = renderer_from_config(config)
    horizon = image_horizon_rows(sim_floor_calibration(camera_model(config)))
    frame = renderer.render(Pose2D(4.3, 3.85, math.pi / 2))
    mask = FloorSegmenter(config.perception).segment(frame.image).floor_mask
    face_called_floor = mask & ~frame.floor_mask
    assert face_called_floor.sum() > 20000
    part = wall_surfaces(mask, frame.image, horizon).floor_part
    # Not the columns where the face reaches the image's bottom: no foot shows there.
    assert (part & face_called_floor).sum() >= 0.3 * face_called_floor.sum()
    assert (part & frame.floor_mask).sum() <= 0.01 * part.sum()


def test_rendered_walls_stand_and_the_floor_never_does() -> None:
    """Frames of the shipped flat, as the shipped segmenter sees them: the proven walls
    lie on true obstacles, and they cover most of the walls met where the floor ends."""
    from app.config import load_config
    from app.mapping.frames import Pose2D
    from app.mapping.ground_map import image_horizon_rows
    from app.perception.pipeline import FloorSegmenter
    from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

    root = Path(__file__).resolve().parents[2]
    config = load_config(root / "config.toml", sim={"world_file": "two-rooms"})
    renderer = renderer_from_config(config)
    horizon = image_horizon_rows(sim_floor_calibration(camera_model(config)))
    segmenter = FloorSegmenter(config.perception)
    found = off_wall = 0
    # Facing the left room's walls from its middle, and the doorway.
    for pose in [(2.0, 3.0, 0.0), (2.0, 3.0, math.pi / 2), (2.0, 3.0, math.pi), (3.2, 3.0, 0.1)]:
        frame = renderer.render(Pose2D(*pose))
        walls = wall_surfaces(segmenter.segment(frame.image).floor_mask, frame.image, horizon).walls
        obstacle = ~frame.floor_mask
        # The segmenter's floor ends a few pixels short of a wall's true foot, and the
        # wall is taken from there: true floor within 8 px below an obstacle is its foot.
        near_foot = obstacle.copy()
        for k in range(1, 9):
            near_foot[k:] |= obstacle[:-k]
        found += int((walls & obstacle).sum())
        off_wall += int((walls & ~near_foot).sum())
    assert found > 20000
    assert off_wall <= 0.002 * found
