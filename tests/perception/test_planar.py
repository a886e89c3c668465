"""Floor confirmed by motion parallax: exact geometry, the column walk on tiny arrays,
the whole test on synthetic views of known geometry (a textured floor, a textured box
face, a plain patch) and on simulated frames scored against the renderer's ground
truth."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
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


# Synthetic views: a floor with a smooth random texture, plain beyond FAR_X_M and where
# the world's y > PLAIN_Y_M, and a textured box face across the view (x = BOX[0],
# BOX[1] <= y <= BOX[2], 0 <= z <= BOX[3]). The camera moves straight ahead.
TEXEL_M = 0.03
FAR_X_M = 3.0
PLAIN_Y_M = 0.45
PLAIN_GREY = 110.0
BOX = (1.2, -0.35, 0.25, 0.18)
CUR_POSE, REF_POSE = (0.0, 0.0, 0.0), (-0.12, 0.0, 0.0)
COLOUR_TOP_ROW = 330
"""The colour method's floor: every row below this one."""


def smooth_texture(seed: int, size: int = 256) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.normal(0.0, 1.0, (size, size)).astype(np.float32), (0, 0), 1.0)
    return np.asarray(128.0 + 45.0 * noise / noise.std(), np.float32)


def sample_texture(texture: np.ndarray, a_m: np.ndarray, b_m: np.ndarray) -> np.ndarray:
    """``texture`` at (a, b) metres (tiled), bilinear."""
    to_texels = [
        np.nan_to_num(c / TEXEL_M, posinf=0.0, neginf=0.0).astype(np.float32) for c in (a_m, b_m)
    ]
    return np.asarray(
        cv2.remap(texture, *to_texels, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP), np.float32
    )


@dataclass(frozen=True)
class SyntheticView:
    gray: np.ndarray
    face: np.ndarray
    """The box face's pixels."""
    plain: np.ndarray
    """The pixels of the plain floor patch."""


@dataclass(frozen=True)
class CameraRays:
    """The camera's rays in the world at ``supersample`` times the resolution: its
    centre (ex, ey, ez), each pixel's direction (rx, ry, rz) and the range at which the
    ray meets the floor (``t_floor``, inf above the horizon)."""

    ex: float
    ey: float
    ez: float
    rx: np.ndarray
    ry: np.ndarray
    rz: np.ndarray
    t_floor: np.ndarray

    @classmethod
    def at(cls, pose: tuple[float, float, float], supersample: int) -> CameraRays:
        big = replace(
            MODEL,
            width_px=MODEL.width_px * supersample,
            height_px=MODEL.height_px * supersample,
            fx_px=MODEL.fx_px * supersample,
            fy_px=MODEL.fy_px * supersample,
        )
        rays = big.rays_robot()
        x, y, t = pose
        c, s = math.cos(t), math.sin(t)
        rz = rays[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(rz < 0, MODEL.height_m / -rz, np.inf)
        return cls(
            x + c * MODEL.x_m - s * MODEL.y_m,
            y + s * MODEL.x_m + c * MODEL.y_m,
            MODEL.height_m,
            c * rays[..., 0] - s * rays[..., 1],
            s * rays[..., 0] + c * rays[..., 1],
            rz,
            t_floor,
        )

    def averaged_down(self, image: np.ndarray, seed: int) -> np.ndarray:
        """``image`` (at this resolution) averaged down to the camera's (against
        aliasing), with sensor noise (grey levels, sd 2), as uint8."""
        size = (MODEL.width_px, MODEL.height_px)
        noise = np.random.default_rng(seed).normal(0.0, 2.0, (MODEL.height_px, MODEL.width_px))
        small = cv2.resize(image.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        return np.clip(small + noise, 0, 255).astype(np.uint8)


def synthetic_view(pose: tuple[float, float, float], supersample: int = 2) -> SyntheticView:
    """The camera's grey frame at the robot ``pose``, ray-cast at ``supersample`` times
    the resolution and averaged down (against aliasing), with sensor noise."""
    cam = CameraRays.at(pose, supersample)
    ex, ey, ez, rx, ry, rz, t_floor = (cam.ex, cam.ey, cam.ez, cam.rx, cam.ry, cam.rz, cam.t_floor)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_face = np.where(rx > 0, (BOX[0] - ex) / rx, np.inf)
    floor = np.isfinite(t_floor)
    fx, fy = ex + t_floor * rx, ey + t_floor * ry
    image = sample_texture(smooth_texture(1), fx, fy)
    image[~floor] = 200.0  # the wall far away: plain
    image[floor & ((fx > FAR_X_M) | (fy > PLAIN_Y_M))] = PLAIN_GREY
    hy, hz = ey + t_face * ry, ez + t_face * rz
    face = np.isfinite(t_face) & (t_face < t_floor) & (hy >= BOX[1]) & (hy <= BOX[2])
    face &= (hz >= 0.0) & (hz <= BOX[3])
    image[face] = sample_texture(smooth_texture(2), hy, BOX[3] - hz)[face]
    plain = floor & ~face & (fy > PLAIN_Y_M) & (fx <= FAR_X_M)
    size = (MODEL.width_px, MODEL.height_px)

    def down(values: np.ndarray) -> np.ndarray:
        return np.asarray(cv2.resize(values, size, interpolation=cv2.INTER_AREA), np.float32)

    return SyntheticView(
        cam.averaged_down(image, seed=3),
        down(face.astype(np.float32)) > 0.5,
        down(plain.astype(np.float32)) > 0.5,
    )


Synthetic = tuple[SyntheticView, np.ndarray, planar.ParallaxResult]


@pytest.fixture(scope="module")
def synthetic() -> Synthetic:
    """(current view, colour floor mask, the parallax test's result against the view
    0.12 m behind)."""
    cur, ref = synthetic_view(CUR_POSE), synthetic_view(REF_POSE)
    colour = np.zeros(cur.gray.shape, bool)
    colour[COLOUR_TOP_ROW:] = True
    result = planar.confirm_floor(
        colour, cur.gray, ref.gray, G, REF_POSE, CUR_POSE, CAMERA_XY, return_standing=True
    )
    return cur, colour, result


def open_floor(view: SyntheticView, colour: np.ndarray) -> np.ndarray:
    """Textured floor above the colour floor and within reach of the walk, clear of the
    box by a few pixels."""
    dist = planar.row_ground_distance_m(G, MODEL.width_px, MODEL.height_px)
    reach = (np.isfinite(dist) & (dist <= 0.95 * planar.PlanarParams().max_range_m))[:, None]
    near_box = cv2.dilate(view.face.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    return np.asarray(reach & ~colour & ~view.plain & ~near_box, dtype=bool)


def test_a_textured_floor_seen_from_two_poses_is_confirmed(synthetic: Synthetic) -> None:
    view, colour, result = synthetic
    zone = open_floor(view, colour)
    assert zone.sum() > 50000
    assert (result.floor & zone).sum() >= 0.85 * zone.sum()
    assert not (colour & ~result.floor).any(), "only ever adds floor"
    # Floor is tested (it is textured) and, within reach, hardly ever stands up.
    assert (result.tested & zone).sum() >= 0.3 * zone.sum()
    assert (result.standing & zone).sum() <= 0.02 * (result.tested & zone).sum()


def test_a_textured_box_face_stands_up_and_stops_the_floor_at_its_foot(
    synthetic: Synthetic,
) -> None:
    view, colour, result = synthetic
    rows = np.flatnonzero(view.face.any(axis=1))
    upper = np.zeros_like(view.face)
    upper[rows[0] : rows[0] + 3 * len(rows) // 4] = True  # all but its foot, whose
    # parallax is below what the test resolves
    face_upper = view.face & upper
    assert (result.tested & face_upper).sum() >= 0.4 * face_upper.sum()
    assert (result.standing & face_upper).sum() >= 0.6 * (result.tested & face_upper).sum()
    assert not (result.floor & face_upper).any()
    # The floor in front of the box is confirmed up to it.
    in_front = open_floor(view, colour)[:, view.face.any(axis=0)]
    assert (result.floor[:, view.face.any(axis=0)] & in_front).sum() >= 0.85 * in_front.sum()


def test_plain_floor_gives_no_evidence(synthetic: Synthetic) -> None:
    view, _, result = synthetic
    inside = cv2.erode(view.plain.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    assert inside.sum() > 10000
    assert not (result.tested & inside).any()
    assert not (result.standing & inside).any()


def test_asking_for_what_stands_changes_nothing_of_the_floor(synthetic: Synthetic) -> None:
    view, colour, result = synthetic
    ref = synthetic_view(REF_POSE)
    floor = planar.confirm_floor(colour, view.gray, ref.gray, G, REF_POSE, CUR_POSE, CAMERA_XY)
    assert isinstance(floor, np.ndarray) and np.array_equal(floor, result.floor)
    assert result.standing.shape == result.tested.shape == colour.shape
    assert not (result.standing & ~result.tested).any()


def test_without_translation_nothing_is_tested() -> None:
    gray = synthetic_view(CUR_POSE).gray
    colour = np.zeros(gray.shape, bool)
    colour[COLOUR_TOP_ROW:] = True
    assert planar.confirm_floor(colour, gray, gray, G, CUR_POSE, CUR_POSE, CAMERA_XY) is colour
    result = planar.confirm_floor(
        colour, gray, gray, G, CUR_POSE, CUR_POSE, CAMERA_XY, return_standing=True
    )
    assert result.floor is colour and not result.standing.any() and not result.tested.any()


def test_parallax_evidence_tells_floor_from_the_box_at_full_resolution(
    synthetic: Synthetic,
) -> None:
    view, colour, _ = synthetic
    ref = synthetic_view(REF_POSE)
    H = planar.view_homography(G, REF_POSE, CUR_POSE)
    epipole = planar.epipole_px(G, REF_POSE, CUR_POSE, CAMERA_XY)
    assert epipole is not None
    on_floor, standing = planar.parallax_evidence(view.gray, ref.gray, H, epipole)
    zone = open_floor(view, colour)
    assert (on_floor & zone).sum() > 5000
    assert (standing & zone).sum() <= 0.05 * (on_floor & zone).sum()
    assert (standing & view.face).sum() > 10 * (on_floor & view.face).sum()


STRIP_M = (0.9, 1.02)
"""A dark threshold strip across a plain floor (x metres from the robot's centre)."""


def strip_view(pose: tuple[float, float, float], seed: int, supersample: int = 2) -> np.ndarray:
    """The grey frame of a plain light floor crossed by a dark strip (`STRIP_M`): two
    strong edges and nothing else, anti-aliased like `synthetic_view`."""
    cam = CameraRays.at(pose, supersample)
    fx = cam.ex + cam.t_floor * cam.rx
    floor = np.isfinite(cam.t_floor)
    image = np.where(floor, 170.0, 200.0)
    image[floor & (fx >= STRIP_M[0]) & (fx <= STRIP_M[1])] = 40.0
    return cam.averaged_down(image, seed)


def test_a_threshold_seen_sharper_than_from_the_reference_does_not_stand() -> None:
    # Approaching a flat dark strip: the reference, 0.12 m farther back, holds its edges
    # less sharply. Compared as they are, most of the edges' pixels match at no shift and
    # would stand; the second look, with the current frame as soft as the reference,
    # finds them flat.
    cur, ref = strip_view(CUR_POSE, seed=3), strip_view(REF_POSE, seed=4)
    colour = np.zeros(cur.shape, bool)
    colour[400:] = True

    def test(soft_sigma_px: float) -> planar.ParallaxResult:
        params = replace(planar.PlanarParams(), soft_sigma_px=soft_sigma_px)
        return planar.confirm_floor(
            colour, cur, ref, G, REF_POSE, CUR_POSE, CAMERA_XY, params, return_standing=True
        )

    unchecked, shipped = test(0.0), test(planar.PlanarParams().soft_sigma_px)
    assert unchecked.tested.sum() > 5000, "the strip's two edges are tested"
    assert unchecked.standing.sum() > 0.5 * unchecked.tested.sum()
    assert np.array_equal(shipped.tested, unchecked.tested)
    assert shipped.standing.sum() <= 0.01 * shipped.tested.sum()


def test_the_search_holds_no_gil() -> None:
    """The mapping thread runs it while the others go on (app/jit.py compiles it)."""
    for kernel in (
        planar._parallax_search,
        planar._shifted_differences,
        planar._covered,
        planar._judge,
        planar._extend_columns,
    ):
        assert kernel.targetoptions.get("nogil") is True


def test_the_floor_of_a_column_ends_below_what_stands_on_it() -> None:
    floor = np.ones((6, 5), bool)
    floor[0] = False  # the colour floor ends at row 1 anyway
    standing = np.zeros((6, 5), bool)
    standing[[1, 3], 0] = True  # column 0: two standing pixels, the lowest in row 3
    standing[2, 2] = True  # column 2: a stray pixel
    standing[4, 4] = True  # column 4: standing where the mask says no floor counts not
    floor[4, 4] = False
    standing[[1, 2], 4] = True
    kept = planar.floor_before_standing(floor, standing, 2)
    assert kept[:, 0].tolist() == [False] * 4 + [True] * 2
    assert np.array_equal(kept[:, 1:4], floor[:, 1:4])  # one pixel cuts nothing
    assert kept[:, 4].tolist() == [False, False, False, True, False, True]
    standing[1, 1] = True  # column 1: one pixel of its own, beside column 0's cut
    spread = planar.floor_before_standing(floor, standing, 2, spread_px=1)
    assert spread[:, 1].tolist() == [False] * 4 + [True] * 2  # column 0's cut
    assert np.array_equal(spread[:, 2], floor[:, 2])  # no cut within one column
    assert np.array_equal(spread[:, 3], floor[:, 3])  # beside column 4, but no evidence
    assert planar.floor_before_standing(floor, np.zeros_like(floor), 2) is floor
    with pytest.raises(ValueError, match="match"):
        planar.floor_before_standing(floor, standing[:, :3], 2)


def test_a_cut_leaves_floor_seen_past_a_gap_and_ignores_the_floors_own_edge() -> None:
    # One column, bottom up: floor, floor (standing), floor (standing), box, floor, floor.
    floor = np.array([[1], [1], [0], [1], [1], [1]], bool)
    standing = np.array([[0], [0], [0], [1], [1], [0]], bool)
    kept = planar.floor_before_standing(floor, standing, 2)
    assert kept[:, 0].tolist() == [True, True, False, False, False, True]
    # Only what stands on floor the test saw flat counts: none seen below, no cut.
    flat_below = np.array([[0], [0], [0], [0], [0], [1]], bool)
    flat_above = np.array([[1], [0], [0], [0], [0], [0]], bool)
    assert np.array_equal(planar.floor_before_standing(floor, standing, 2, flat=flat_below), kept)
    assert planar.floor_before_standing(floor, standing, 2, flat=flat_above) is floor
    # A box's outline: standing pixels on the floor's edge, beside what the mask leaves
    # out, are no surface the mask took for floor.
    wide = np.ones((9, 9), bool)
    wide[:4, 3:6] = False  # the box
    edge = np.zeros((9, 9), bool)
    edge[:5, 2] = edge[:5, 6] = edge[4, 2:7] = True
    assert np.array_equal(planar.floor_before_standing(wide, edge, 2, interior_px=1), wide)
    assert not np.array_equal(planar.floor_before_standing(wide, edge, 2), wide)


def standing_share(result: planar.ParallaxResult, zone: np.ndarray) -> float:
    return float((result.standing & zone).sum() / max(1, (result.tested & zone).sum()))


def test_alignment_recovers_the_reference_pose_wheel_slip_got_wrong(
    synthetic: Synthetic,
) -> None:
    # Odometry believes the reference view 1.5 degrees and 4 mm off: wheel slip in a
    # turn. Uncorrected, the textured floor stands up; aligned, it is floor again.
    view, colour, _ = synthetic
    ref = synthetic_view(REF_POSE)
    slipped = (REF_POSE[0] + 0.004, REF_POSE[1], REF_POSE[2] + math.radians(1.5))
    # The colour method's floor as it would be on this texture: all of it, up to the box.
    zone = open_floor(view, colour)
    floor = colour | zone
    aligned = planar.align_reference_pose(view.gray, ref.gray, floor, G, slipped, CUR_POSE)
    assert aligned is not None
    assert math.hypot(aligned[0] - REF_POSE[0], aligned[1] - REF_POSE[1]) < 0.002
    assert abs(aligned[2] - REF_POSE[2]) < math.radians(0.1)

    def test(ref_pose: tuple[float, float, float]) -> planar.ParallaxResult:
        result = planar.confirm_floor(
            colour, view.gray, ref.gray, G, ref_pose, CUR_POSE, CAMERA_XY, return_standing=True
        )
        assert isinstance(result, planar.ParallaxResult)
        return result

    assert standing_share(test(slipped), zone) > 0.3
    assert standing_share(test(aligned), zone) <= 0.02


def test_a_floor_without_texture_is_not_aligned_and_shapes_are_checked() -> None:
    rng = np.random.default_rng(0)
    h, w = MODEL.height_px, MODEL.width_px
    # Sensor noise alone, on a plain floor: nothing to align on.
    plain = [np.clip(120 + rng.normal(0, 2, (h, w)), 0, 255).astype(np.uint8) for _ in "ab"]
    floor = np.zeros((h, w), bool)
    floor[COLOUR_TOP_ROW:] = True
    assert planar.align_reference_pose(plain[0], plain[1], floor, G, REF_POSE, CUR_POSE) is None
    # No floor in view: nothing either.
    nothing = np.zeros((h, w), bool)
    assert planar.align_reference_pose(plain[0], plain[1], nothing, G, REF_POSE, CUR_POSE) is None
    with pytest.raises(ValueError, match="must match"):
        planar.align_reference_pose(plain[0][:-1], plain[1], floor, G, REF_POSE, CUR_POSE)


def pose_error(pose: tuple[float, float, float] | None) -> tuple[float, float]:
    """(metres, degrees) from the true reference pose."""
    assert pose is not None
    shift = math.hypot(pose[0] - REF_POSE[0], pose[1] - REF_POSE[1])
    return shift, abs(math.degrees(math.remainder(pose[2] - REF_POSE[2], math.tau)))


def test_refinement_matches_the_views_pixel_for_pixel_where_the_alignment_stops_short(
    synthetic: Synthetic,
) -> None:
    # The same slip as above: 1.5 degrees and 4 mm. The bird's-eye alignment gets
    # within a tenth of a degree; comparing the test's own pixels gets within a
    # hundredth, and then the floor stands up no more than with the true pose.
    view, colour, exact = synthetic
    ref = synthetic_view(REF_POSE)
    slipped = (REF_POSE[0] + 0.004, REF_POSE[1], REF_POSE[2] + math.radians(1.5))
    zone = open_floor(view, colour)
    floor = colour | zone
    refined = planar.refine_reference_pose(view.gray, ref.gray, floor, G, slipped, CUR_POSE)
    shift_m, turn_deg = pose_error(refined)
    assert shift_m < 0.0005 and turn_deg < 0.02
    aligned = planar.align_reference_pose(view.gray, ref.gray, floor, G, slipped, CUR_POSE)
    aligned_shift_m, aligned_turn_deg = pose_error(aligned)
    assert turn_deg < aligned_turn_deg and shift_m < aligned_shift_m
    assert planar.reference_pose_from_views(
        view.gray, ref.gray, floor, G, slipped, CUR_POSE
    ) == pytest.approx(refined)
    assert refined is not None
    result = planar.confirm_floor(
        colour, view.gray, ref.gray, G, refined, CUR_POSE, CAMERA_XY, return_standing=True
    )
    assert isinstance(result, planar.ParallaxResult)
    assert standing_share(result, zone) <= standing_share(exact, zone) + 0.005


def test_a_slip_beyond_the_refinements_reach_is_aligned_first() -> None:
    # 3 degrees, and a refinement with its fine pass only: from odometry it does not
    # converge; the wide heading search of the alignment brings it within reach.
    view, ref = synthetic_view(CUR_POSE), synthetic_view(REF_POSE)
    floor = np.zeros(view.gray.shape, bool)
    floor[COLOUR_TOP_ROW:] = True
    floor |= open_floor(view, floor)
    slipped = (REF_POSE[0], REF_POSE[1] - 0.003, REF_POSE[2] - math.radians(3.0))
    fine = planar.RefineParams(sigmas_px=(0.5,))
    assert (
        planar.refine_reference_pose(view.gray, ref.gray, floor, G, slipped, CUR_POSE, fine) is None
    )
    shift_m, turn_deg = pose_error(
        planar.reference_pose_from_views(view.gray, ref.gray, floor, G, slipped, CUR_POSE, fine)
    )
    assert shift_m < 0.0005 and turn_deg < 0.02


def test_a_floor_without_texture_is_not_refined_nor_one_that_does_not_match() -> None:
    rng = np.random.default_rng(0)
    h, w = MODEL.height_px, MODEL.width_px
    plain = [np.clip(120 + rng.normal(0, 2, (h, w)), 0, 255).astype(np.uint8) for _ in "ab"]
    floor = np.zeros((h, w), bool)
    floor[COLOUR_TOP_ROW:] = True
    assert planar.refine_reference_pose(plain[0], plain[1], floor, G, REF_POSE, CUR_POSE) is None
    assert (
        planar.reference_pose_from_views(plain[0], plain[1], floor, G, REF_POSE, CUR_POSE) is None
    )
    # Two unrelated textures (what fills the view is not the floor the pose predicts):
    # whatever the steps found, too few samples match in the end.
    view = synthetic_view(CUR_POSE)
    other = np.ascontiguousarray(view.gray[::-1, ::-1])
    assert planar.refine_reference_pose(view.gray, other, floor, G, REF_POSE, CUR_POSE) is None
    with pytest.raises(ValueError, match="must match"):
        planar.refine_reference_pose(plain[0][:-1], plain[1], floor, G, REF_POSE, CUR_POSE)


# -- standing_feet -------------------------------------------------------------------------

FEET_ROWS_M = planar.row_ground_distance_m(G, 640, 480)


def one_column(*runs: tuple[int, int, str]) -> tuple[np.ndarray, np.ndarray]:
    """A 480 x 1 column: (first row, last row, "floor" | "standing") runs; the rest is
    not floor and untested."""
    standing = np.zeros((480, 1), bool)
    floor = np.zeros((480, 1), bool)
    for first, last, kind in runs:
        (floor if kind == "floor" else standing)[first : last + 1, 0] = True
    return standing, floor


def kept_rows(feet: np.ndarray) -> list[int]:
    return np.flatnonzero(feet[:, 0]).tolist()


def test_only_the_foot_of_a_standing_thing_is_kept_not_the_ray_behind_it() -> None:
    # A table leg on the floor: standing from row 300 up to near the horizon.
    standing, floor = one_column((301, 479, "floor"), (250, 300, "standing"))
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert rows and rows[-1] == 300
    foot_m = FEET_ROWS_M[300]
    assert all(FEET_ROWS_M[r] - foot_m <= planar.FOOT_DEPTH_M for r in rows)
    assert FEET_ROWS_M[rows[0] - 1] - foot_m > planar.FOOT_DEPTH_M  # the ray is dropped


def test_a_plain_walls_foot_is_where_the_floor_below_it_ends() -> None:
    # Parallax saw only the wall's upper part standing; its plain lower part is untested.
    standing, floor = one_column((301, 479, "floor"), (150, 240, "standing"))
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert rows and rows[-1] == 300  # the first not-floor pixel above the floor
    assert min(rows) > 240  # nothing of the run itself, far behind


def test_flat_floor_between_an_edge_and_a_far_wall_keeps_the_edge_unproven() -> None:
    # Tiles past a threshold: not floor by colour at rows 280-300 (untested), then flat by
    # parallax (rows 230-279), then untested tiles and the far wall standing at 180-200.
    standing, floor = one_column((301, 479, "floor"), (230, 279, "floor"), (180, 200, "standing"))
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert rows and rows[-1] == 229  # the wall's foot is past the flat tiles...
    assert not any(r >= 280 for r in rows)  # ...not at the threshold


def test_a_run_with_no_floor_seen_below_it_has_no_foot() -> None:
    """A wall whose plain lower part rises from ground the mask does not call floor
    (another room's floor, seen through a door): its lowest standing pixel projects
    behind the wall, and each frame's lands elsewhere along the ray (the home's runs
    drew streaks of such marks through the walls). No foot is better than that one."""
    standing, floor = one_column((200, 260, "standing"))
    assert kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M)) == []
    # Above a nearer thing (a wall over a box, not-floor between): the box keeps its
    # foot, the wall none.
    standing, floor = one_column(
        (401, 479, "floor"), (330, 400, "standing"), (200, 300, "standing")
    )
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert rows and rows[-1] == 400 and min(rows) > 300
    # Floor seen between them gives the wall its foot again: where that floor ends.
    floor[320:330, 0] = True
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert 400 in rows and 319 in rows and max(r for r in rows if r < 330) == 319


def test_a_run_at_the_bottom_of_the_image_stands_there() -> None:
    standing, floor = one_column((420, 479, "standing"))
    rows = kept_rows(planar.standing_feet(standing, floor, FEET_ROWS_M))
    assert rows and rows[-1] == 479


def test_standing_feet_checks_its_shapes() -> None:
    with pytest.raises(ValueError, match="must agree"):
        planar.standing_feet(np.zeros((4, 3), bool), np.zeros((4, 3), bool), np.zeros(3))
