"""Floor confirmed by motion parallax: exact geometry, the column walk on tiny arrays,
and the whole test on simulated frames scored against the renderer's ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.config import load_config
from app.mapping.frames import Pose2D
from app.perception import planar
from app.perception.pipeline import FloorSegmenter
from app.sim.setup import (
    camera_model,
    project_floor_points,
    renderer_from_config,
    sim_floor_calibration,
)

CONFIG = load_config(Path(__file__).resolve().parents[2] / "config.toml")
MODEL = camera_model(CONFIG)
G = sim_floor_calibration(MODEL).H_ground_from_image
CAMERA_XY = (CONFIG.camera.x_m, CONFIG.camera.y_m)


def to_robot(pose: tuple[float, float, float], world_xy: np.ndarray) -> np.ndarray:
    x, y, t = pose
    d = world_xy - np.array([x, y])
    c, s = math.cos(t), math.sin(t)
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def test_view_homography_maps_floor_points_between_the_views() -> None:
    ref, cur = (1.0, 2.0, 0.1), (1.15, 2.03, 0.16)
    floor_world = np.array([[2.0, 2.0], [2.5, 1.7], [3.0, 2.4], [1.8, 2.2]])
    px_ref = project_floor_points(MODEL, to_robot(ref, floor_world))
    px_cur = project_floor_points(MODEL, to_robot(cur, floor_world))
    H = planar.view_homography(G, ref, cur)
    mapped = cv2.perspectiveTransform(px_ref.reshape(-1, 1, 2), H).reshape(-1, 2)
    np.testing.assert_allclose(mapped, px_cur, atol=0.05)


def test_the_epipole_is_where_the_camera_is_heading() -> None:
    ref, cur = (0.0, 0.0, 0.3), (0.2 * math.cos(0.3), 0.2 * math.sin(0.3), 0.3)
    epipole = planar.epipole_px(G, ref, cur, CAMERA_XY)
    assert epipole is not None
    far_ahead = project_floor_points(MODEL, np.array([[1e5, 0.0]]))[0]
    np.testing.assert_allclose(epipole, far_ahead, atol=0.05)
    assert planar.epipole_px(G, cur, cur, CAMERA_XY) is None  # no translation


def test_row_ground_distance_grows_towards_the_horizon() -> None:
    dist = planar.row_ground_distance_m(G, MODEL.width_px, MODEL.height_px)
    finite = np.isfinite(dist)
    assert finite[-1] and not finite[0]  # the top rows look above the horizon
    below = dist[finite]
    assert np.all(np.diff(below) < 0)  # nearer with every row down
    bottom = project_floor_points(MODEL, np.array([[below[-1], 0.0]]))[0]
    assert bottom[1] == pytest.approx(MODEL.height_px - 1, abs=0.05)


def walk(
    mask_rows: list[str], evidence_rows: list[str], dist: list[float], **kw: float
) -> list[str]:
    """Columns of tiny arrays: mask '#' floor; evidence 'f' on floor, 's' standing."""
    mask = np.array([[c == "#" for c in row] for row in mask_rows])
    on = np.array([[c == "f" for c in row] for row in evidence_rows])
    standing = np.array([[c == "s" for c in row] for row in evidence_rows])
    params = planar.PlanarParams(**kw)  # type: ignore[arg-type]
    out = planar.extend_floor(mask, on, standing, np.array(dist), params)
    return ["".join("#" if v else "." for v in row) for row in out]


def test_the_column_walk_extends_through_confirmed_floor_and_stops_at_what_stands() -> None:
    dist = [5.0, 4.0, 3.0, 2.0, 1.5, 1.2, 1.0, 0.8]
    mask = ["....", "....", "....", "....", "....", "....", "####", "###."]
    evid = ["ff..", "..s.", "f.f.", ".ff.", "f.ff", "fff.", "....", "...."]
    out = walk(mask, evid, dist, max_gap_m=0.6, min_support_px=2, max_range_m=3.5, foot_margin_px=0)
    # Exact expectations, column by column (top row first).
    cols = ["".join(row[i] for row in out) for i in range(4)]
    assert cols[0] == "..######"
    assert cols[1] == "...#####"
    assert cols[2] == "..######"
    assert cols[3] == "......#."


def test_the_walk_needs_support_and_gives_up_after_a_gap() -> None:
    dist = [3.0, 2.5, 2.0, 1.5, 1.0]
    mask = [".", ".", ".", ".", "#"]
    one = walk(mask, [".", ".", ".", "f", "."], dist, min_support_px=2, foot_margin_px=0)
    assert one == [".", ".", ".", ".", "#"]  # a single confirmed pixel is not enough
    gap = walk(mask, ["f", ".", ".", "f", "."], dist, min_support_px=1, max_gap_m=0.4)
    assert gap == [".", ".", ".", "#", "#"]  # 1.5 m of nothing after row 3: stop there
    near = walk(
        mask, ["f", ".", ".", "f", "."], dist, min_support_px=1, max_gap_m=2.0, max_range_m=5.0
    )
    assert near == ["#", "#", "#", "#", "#"]


def test_a_walk_that_ends_under_something_standing_gives_its_foot_back() -> None:
    dist = [3.0, 2.5, 2.0, 1.5, 1.2, 1.0]
    mask = [".", ".", ".", ".", ".", "#"]
    evid = [".", "s", "f", "f", "f", "."]
    kept = walk(mask, evid, dist, min_support_px=1, foot_margin_px=0)
    assert kept == [".", ".", "#", "#", "#", "#"]
    trimmed = walk(mask, evid, dist, min_support_px=1, foot_margin_px=2)
    assert trimmed == [".", ".", ".", ".", "#", "#"]


def test_extend_floor_never_removes_floor_and_checks_shapes() -> None:
    mask = np.zeros((4, 3), bool)
    mask[1, 1] = True  # an island the walk does not reach: kept as it is
    mask[3] = True
    nothing = np.zeros_like(mask)
    out = planar.extend_floor(mask, nothing, nothing, np.linspace(3, 1, 4))
    assert np.array_equal(out, mask) and out is not mask
    with pytest.raises(ValueError, match="one shape"):
        planar.extend_floor(mask, nothing[:2], nothing, np.linspace(3, 1, 4))
    with pytest.raises(ValueError, match="row_distance_m"):
        planar.extend_floor(mask, nothing, nothing, np.linspace(3, 1, 5))


def confirm_in_sim(
    pose: tuple[float, float, float], baseline_m: float = 0.12
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(colour floor mask, confirmed floor mask, true floor) for a view and a reference
    ``baseline_m`` behind it."""
    renderer = renderer_from_config(CONFIG)
    x, y, t = pose
    ref = (x - baseline_m * math.cos(t), y - baseline_m * math.sin(t), t)
    cur_frame = renderer.render(Pose2D(*pose))
    ref_frame = renderer.render(Pose2D(*ref))
    colour = FloorSegmenter(CONFIG.perception).segment(cur_frame.image).floor_mask
    gray = [cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) for f in (cur_frame, ref_frame)]
    confirmed = planar.confirm_floor(colour, gray[0], gray[1], G, ref, pose, CAMERA_XY)
    return colour, confirmed, cur_frame.floor_mask


def test_the_kitchen_tiles_beyond_the_threshold_are_confirmed_as_floor() -> None:
    colour, confirmed, truth = confirm_in_sim((3.95, 3.05, 0.0))
    added = confirmed & ~colour
    assert not (colour & ~confirmed).any(), "only ever adds floor"
    assert added.sum() > 20000, "the tiles past the doorway's threshold"
    assert (added & ~truth).sum() <= 0.01 * added.sum()


def test_a_box_in_front_is_not_confirmed_as_floor() -> None:
    # Facing the low blue tray from 0.35 m: its plain faces give no evidence, its top
    # edge stands up, so nothing of it may become floor.
    colour, confirmed, truth = confirm_in_sim((3.0, 2.8, 0.05))
    assert ((confirmed & ~colour) & ~truth).sum() < 100


def test_parallax_evidence_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        planar.parallax_evidence(
            np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.uint8), np.eye(3), (2.0, -50.0)
        )
