"""Calibration: exact answers on synthetic views from known cameras, the real chessboard
photos, calibration files, and every bad input. (IPM: test_ipm.py; commands:
test_calibrate_cli.py.)"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.imageio import read_bgr
from app.mapping.calibration import (
    DETECT_MAX_SIDE_PX,
    BoardPlacement,
    CalibrationError,
    FloorCalibration,
    Intrinsics,
    apply_homography,
    calibrate_intrinsics,
    canonical_board_corners,
    find_chessboard,
    floor_homography_from_chessboard,
    homography_from_point_pairs,
    parse_pattern,
)
from app.mapping.calibration_files import (
    load_floor_calibration,
    load_intrinsics,
    save_floor_calibration,
    save_intrinsics,
)

from ..conftest import dataset_dir

WIDTH, HEIGHT = 640, 480
SQUARE_M = 0.04
PATTERN = (7, 5)  # inner corners: a board of 8 x 6 squares
TEXEL_M = 0.002  # 2 mm per texel of the top-down board texture
GROUND = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])


def camera_homography(
    *, pitch_deg: float = 30.0, roll_deg: float = 0.0, height_m: float = 0.3
) -> NDArray[np.float64]:
    """H_image_from_ground of a pinhole camera (f 500 px, 640x480) ``height_m`` above the
    floor at the robot origin, pitched down and rolled about its optical axis, looking
    along +x (robot frame: x forward, y left)."""
    f, cx, cy = 500.0, WIDTH / 2, HEIGHT / 2
    pitch = np.deg2rad(pitch_deg)
    # Camera axes (x right, y down, z forward) expressed in the robot frame.
    forward = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    roll = np.deg2rad(roll_deg)
    right, down = (
        np.cos(roll) * right + np.sin(roll) * down,
        -np.sin(roll) * right + np.cos(roll) * down,
    )
    R_cam_from_robot = np.vstack([right, down, forward])
    t = -R_cam_from_robot @ np.array([0.0, 0.0, height_m])
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    # Floor points (x, y, 0): columns x, y and the translation.
    return K @ np.column_stack([R_cam_from_robot[:, 0], R_cam_from_robot[:, 1], t])


def render_floor_board(
    H_image_from_ground: NDArray[np.float64],
    origin_m: tuple[float, float],
    yaw_rad: float = 0.0,
) -> NDArray[np.uint8]:
    """A grey floor with a chessboard whose near-right inner corner lies at ``origin_m``,
    its rows of squares along +x (turned by ``yaw_rad``) and columns along +y, rendered
    through the homography."""
    squares_x, squares_y = PATTERN[1] + 1, PATTERN[0] + 1
    size = (int(squares_x * SQUARE_M / TEXEL_M) + 80, int(squares_y * SQUARE_M / TEXEL_M) + 80)
    texture = np.full((size[1], size[0]), 150, np.uint8)  # rows: +y, cols: +x
    px = int(SQUARE_M / TEXEL_M)
    texture[40 - px // 2 : -40 + px // 2, 40 - px // 2 : -40 + px // 2] = 235  # white margin
    for i in range(squares_x):
        for j in range(squares_y):
            value = 20 if (i + j) % 2 == 0 else 235
            texture[40 + j * px : 40 + (j + 1) * px, 40 + i * px : 40 + (i + 1) * px] = value
    # Texel (c, r) -> board (x, y). Texel centres are at integer coordinates, so the
    # edge between texels 40 + px - 1 and 40 + px (the first inner corner) is at 39.5 + px.
    corner = (39.5 + px) * TEXEL_M
    board_from_texture = np.array([[TEXEL_M, 0, -corner], [0, TEXEL_M, -corner], [0, 0, 1]])
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    ground_from_board = np.array([[c, -s, origin_m[0]], [s, c, origin_m[1]], [0, 0, 1]])
    image = cv2.warpPerspective(
        texture,
        H_image_from_ground @ ground_from_board @ board_from_texture,
        (WIDTH, HEIGHT),
        borderValue=150,
    )
    return np.dstack([image] * 3).astype(np.uint8)


def ground_error_m(
    calibration: FloorCalibration, H_true: NDArray[np.float64], ground: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance between ``ground`` points and where the calibration maps their pixels."""
    pixels = apply_homography(H_true, ground)
    mapped = calibration.image_to_ground(pixels)
    return np.asarray(np.linalg.norm(mapped - ground, axis=1), dtype=np.float64)


def test_parse_pattern() -> None:
    assert parse_pattern("9x6") == (9, 6)
    assert parse_pattern("12X12") == (12, 12)
    for bad in ("9", "ax6", "1x6", "9x6x2", ""):
        with pytest.raises(CalibrationError):
            parse_pattern(bad)


# -- floor homography from a board: synthetic views ----------------------------------------


def test_floor_homography_recovers_a_known_view() -> None:
    H_true = camera_homography()
    image = render_floor_board(H_true, (0.45, -0.12))
    calibration = floor_homography_from_chessboard(
        image, PATTERN, SQUARE_M, placement=BoardPlacement(0.45, -0.12, 0.0)
    )
    assert calibration.inliers == calibration.points == 35
    assert calibration.reprojection_rms_px < 0.3
    assert calibration.ground_rms_m < 0.001
    # On the board and around it the map is right to well under 1 mm.
    xs, ys = np.meshgrid(np.linspace(0.4, 0.75, 8), np.linspace(-0.2, 0.2, 8))
    near = np.column_stack([xs.ravel(), ys.ravel()])
    assert ground_error_m(calibration, H_true, near).max() < 0.001
    # Points far from the board map where the true homography says, to about 1 cm at 2 m.
    errors = ground_error_m(calibration, H_true, np.array([[1.0, 0.0], [2.0, 0.3], [0.5, -0.2]]))
    assert errors[0] < 0.01 and errors[1] < 0.03 and errors[2] < 0.01
    # The board origin is the inner corner nearest to the camera on its right.
    assert calibration.board_origin_px is not None
    expected = apply_homography(H_true, np.array([[0.45, -0.12]]))[0]
    np.testing.assert_allclose(calibration.board_origin_px, expected, atol=0.2)


@pytest.mark.parametrize(
    ("roll_deg", "origin_m", "yaw_rad"),
    [
        (0.0, (0.40, -0.05), 0.3),  # board turned 17 deg on the floor
        (0.0, (0.35, -0.1), -0.6),
        (90.0, (0.42, -0.1), 0.0),  # camera rolled like the book's ...L.jpg photos
        (-20.0, (0.42, -0.1), 0.2),
    ],
)
def test_board_frame_is_geometric_for_turned_boards_and_rolled_cameras(
    roll_deg: float, origin_m: tuple[float, float], yaw_rad: float
) -> None:
    H_true = camera_homography(roll_deg=roll_deg)
    image = render_floor_board(H_true, origin_m, yaw_rad)
    calibration = floor_homography_from_chessboard(
        image, PATTERN, SQUARE_M, placement=BoardPlacement(*origin_m, yaw_rad)
    )
    xs, ys = np.meshgrid(np.linspace(0.35, 0.7, 6), np.linspace(-0.15, 0.2, 6))
    board_area = np.column_stack([xs.ravel(), ys.ravel()])
    assert ground_error_m(calibration, H_true, board_area).max() < 0.001


def test_canonical_corners_do_not_depend_on_the_detection_order() -> None:
    H_true = camera_homography()
    image = render_floor_board(H_true, (0.45, -0.12))
    corners = find_chessboard(image, PATTERN)
    assert corners is not None
    grid = corners.reshape(PATTERN[1], PATTERN[0], 2)
    reference = canonical_board_corners(corners, PATTERN)
    assert reference.shape == (PATTERN[1], PATTERN[0], 2)  # 5 rows run away, 7 to the left
    for variant, pattern in [
        (grid[::-1], PATTERN),
        (grid[:, ::-1], PATTERN),
        (grid[::-1, ::-1], PATTERN),
        (grid.transpose(1, 0, 2), (PATTERN[1], PATTERN[0])),
        (grid.transpose(1, 0, 2)[::-1], (PATTERN[1], PATTERN[0])),
    ]:
        np.testing.assert_array_equal(
            canonical_board_corners(variant.reshape(-1, 2), pattern), reference
        )
    # First index: away from the camera (up this upright image); second: to the left.
    assert reference[1, 0, 1] < reference[0, 0, 1]
    assert reference[0, 1, 0] < reference[0, 0, 0]


def test_board_seen_from_straight_above_runs_up_the_image() -> None:
    # A camera looking straight down (pitch 90 deg): no depth change across the board, so
    # "away" falls back to "up the image" (which is robot +x for this camera).
    H_true = camera_homography(pitch_deg=90.0, height_m=0.5)
    image = render_floor_board(H_true, (-0.08, -0.12))
    calibration = floor_homography_from_chessboard(
        image, PATTERN, SQUARE_M, placement=BoardPlacement(-0.08, -0.12)
    )
    assert ground_error_m(calibration, H_true, np.array([[0.0, 0.0], [0.05, 0.2]])).max() < 1e-3


# -- point pairs -------------------------------------------------------------------------


def test_manual_point_pairs_are_exact() -> None:
    H_true = camera_homography()
    image_pts = apply_homography(H_true, GROUND)
    calibration = homography_from_point_pairs(image_pts, GROUND, (WIDTH, HEIGHT))
    assert calibration.ground_rms_m < 1e-6 and calibration.reprojection_rms_px < 1e-4
    np.testing.assert_allclose(
        calibration.H_ground_from_image / calibration.H_ground_from_image[2, 2],
        np.linalg.inv(H_true) / np.linalg.inv(H_true)[2, 2],
        atol=1e-6,
    )
    # w > 0 below the horizon, < 0 above it; the board path has det(H) < 0 too.
    H = calibration.H_ground_from_image
    assert H[2] @ [320.0, 479.0, 1.0] > 0 > H[2] @ [320.0, -200.0, 1.0]
    assert np.linalg.det(H) < 0


def test_manual_point_pairs_with_lens_distortion_are_exact() -> None:
    intrinsics = Intrinsics(
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        np.array([-0.3, 0.1, 0.001, -0.001, 0.0]),
        (WIDTH, HEIGHT),
    )
    H_true = camera_homography()
    raw = intrinsics.distort_points(apply_homography(H_true, GROUND))
    calibration = homography_from_point_pairs(raw, GROUND, (WIDTH, HEIGHT), intrinsics=intrinsics)
    assert calibration.ground_rms_m < 1e-6
    assert calibration.reprojection_rms_px < 1e-4  # measured in raw (distorted) pixels
    probes = np.array([[0.7, 0.2], [1.2, -0.4], [2.5, 0.0]])
    pixels = intrinsics.distort_points(apply_homography(H_true, probes))
    np.testing.assert_allclose(calibration.image_to_ground(pixels), probes, atol=1e-6)
    np.testing.assert_allclose(calibration.ground_to_image(probes), pixels, atol=1e-4)


def test_least_squares_with_many_noisy_pairs() -> None:
    H_true = camera_homography()
    rng = np.random.default_rng(3)
    ground = np.column_stack([rng.uniform(0.6, 2.0, 40), rng.uniform(-0.3, 0.3, 40)])
    pixels = apply_homography(H_true, ground) + rng.normal(0, 0.3, (40, 2))
    pixels[5] += (40.0, -25.0)  # one bad click
    assert ((pixels >= 0) & (pixels <= (WIDTH - 1, HEIGHT - 1))).all()
    calibration = homography_from_point_pairs(
        pixels, ground, (WIDTH, HEIGHT), ransac_threshold_px=2.0
    )
    assert calibration.inliers == 39
    assert 0.2 < calibration.reprojection_rms_px < 0.5


def swap(points: list[list[float]], i: int, j: int) -> list[list[float]]:
    out = [list(p) for p in points]
    out[i], out[j] = out[j], out[i]
    return out


IMAGE_4 = apply_homography(camera_homography(), GROUND).tolist()
GROUND_4 = GROUND.tolist()


@pytest.mark.parametrize(
    ("image_pts", "ground_pts", "message"),
    [
        ([[0, 0], [1, 1], [2, 2]], [[0, 0], [1, 0], [0, 1]], "at least 4"),
        ([[0, 0], [10, 10], [20, 20], [30, 30]], [[0, 0], [1, 0], [0, 1], [1, 1]], "collinear"),
        ([[0, 0], [1, 0], [0, 1], [np.nan, 1]], [[0, 0], [1, 0], [0, 1], [1, 1]], "NaN"),
        (IMAGE_4, [[0, 0], [1, 0], [0, 1], [np.inf, 1]], "NaN or infinity"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 0], [1, 0], [0, 1], [1, 1]], "3 image points"),
        # three of four on a line: no homography, even though the set is not collinear
        ([[100, 400], [200, 400], [300, 400], [200, 300]], GROUND_4, "points 0, 1 and 2"),
        (IMAGE_4, [[0.5, 0.3], [0.5, 0.3], [1.5, 0.5], [1.5, -0.5]], "collinear"),
        # two neighbours swapped: the quadrilateral becomes a bow-tie, whose fitted horizon
        # runs between the points
        (IMAGE_4, swap(GROUND_4, 0, 1), "inconsistent"),
        # opposite corners swapped: a valid homography, but of a mirrored floor
        (IMAGE_4, swap(GROUND_4, 0, 3), "mirrored"),
        # y to the right instead of the left
        (IMAGE_4, (GROUND * [1, -1]).tolist(), "mirrored"),
        ([[10, 10], [700, 10], [10, 400], [600, 400]], GROUND_4, "outside the 640x480"),
    ],
)
def test_bad_point_pairs_are_refused(
    image_pts: list[list[float]], ground_pts: list[list[float]], message: str
) -> None:
    with pytest.raises(CalibrationError, match=message):
        homography_from_point_pairs(
            np.array(image_pts, float), np.array(ground_pts, float), (WIDTH, HEIGHT)
        )


def test_horizon_below_the_image_bottom_is_refused() -> None:
    # Ground points that lie *behind* the camera for the bottom of the image: flip v.
    image_pts = apply_homography(camera_homography(), GROUND)
    # Mirror rows about v = 200: the horizon moves from above the image to row ~449.
    image_pts[:, 1] = 400.0 - image_pts[:, 1]
    with pytest.raises(CalibrationError, match="horizon below the image bottom"):
        homography_from_point_pairs(image_pts, GROUND, (WIDTH, HEIGHT))


def test_a_horizon_crossing_the_image_bottom_is_allowed() -> None:
    # A camera rolled by 90 deg sees the horizon run down the image: one bottom corner
    # sees floor, the other sky. That is a valid view (the ...L.jpg photos), not an error.
    H_true = camera_homography(roll_deg=90.0)
    ground = np.array([[0.5, 0.1], [0.5, -0.1], [0.8, 0.15], [0.8, -0.15]])
    calibration = homography_from_point_pairs(
        apply_homography(H_true, ground), ground, (WIDTH, HEIGHT)
    )
    H = calibration.H_ground_from_image
    w_bottom = [H[2] @ [0.0, 479.0, 1.0], H[2] @ [639.0, 479.0, 1.0]]
    assert min(w_bottom) < 0 < max(w_bottom)


def test_board_not_found_bad_square_and_mismatched_intrinsics() -> None:
    blank = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match="not found in the 640x480 px image"):
        floor_homography_from_chessboard(blank, PATTERN, SQUARE_M)
    for square in (0.0, -0.04, float("nan")):
        with pytest.raises(CalibrationError, match="square size"):
            floor_homography_from_chessboard(blank, PATTERN, square)
    other = Intrinsics(
        np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]]), np.zeros(5), (1280, 720)
    )
    with pytest.raises(CalibrationError, match="1280x720 px images but this image is 640x480"):
        floor_homography_from_chessboard(blank, PATTERN, SQUARE_M, intrinsics=other)
    with pytest.raises(CalibrationError, match="uint8"):
        floor_homography_from_chessboard(blank.astype(np.float32), PATTERN, SQUARE_M)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("matrix", "dist", "message"),
    [
        ([[0.0, 0, 320], [0, 500, 240], [0, 0, 1]], [0.0] * 5, "fx, fy > 0"),
        ([[500.0, 0, 320], [0, 500, 240], [0, 0, 2]], [0.0] * 5, "fx, fy > 0"),
        ([[500.0, 0, 320], [0, 500, 240]], [0.0] * 5, "3x3"),
        ([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], [0.0] * 3, "got 3"),
        ([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], [np.nan] * 5, "finite"),
    ],
)
def test_bad_intrinsics_are_refused(
    matrix: list[list[float]], dist: list[float], message: str
) -> None:
    with pytest.raises(CalibrationError, match=message):
        Intrinsics(np.array(matrix), np.array(dist), (WIDTH, HEIGHT))


# -- intrinsics: a known camera ------------------------------------------------------------

K_TRUE = np.array([[520.0, 0.0, 318.0], [0.0, 515.0, 243.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.25, 0.08, 0.0005, -0.0003, 0.0])
VIEW_PATTERN = (9, 6)
VIEW_SQUARE_M = 0.03


def render_board_photo(rvec: NDArray[np.float64], tvec: NDArray[np.float64]) -> NDArray[np.uint8]:
    """A 640x480 photo of a 9x6 board (3 cm squares, white margin) by the camera
    K_TRUE / DIST_TRUE with the board at pose (rvec, tvec): each raw pixel is undistorted,
    cast onto the board plane and the board texture (1 mm texels) sampled there."""
    texel = 0.001
    px = round(VIEW_SQUARE_M / texel)
    squares_x, squares_y = VIEW_PATTERN[0] + 1, VIEW_PATTERN[1] + 1
    texture = np.full((squares_y * px + 2 * px, squares_x * px + 2 * px), 255, np.uint8)
    for i in range(squares_x):
        for j in range(squares_y):
            if (i + j) % 2 == 0:
                texture[px + j * px : px + (j + 1) * px, px + i * px : px + (i + 1) * px] = 0
    R, _ = cv2.Rodrigues(rvec)
    G = K_TRUE @ np.column_stack([R[:, 0], R[:, 1], tvec])  # board plane -> pixels
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    raw = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
    ideal = np.asarray(
        cv2.undistortPoints(raw, K_TRUE, DIST_TRUE, P=K_TRUE, criteria=(3, 30, 1e-9))
    ).reshape(-1, 2)
    board = apply_homography(np.linalg.inv(G), ideal)  # metres from the outer corner
    map_x = (board[:, 0] / texel + px - 0.5).reshape(HEIGHT, WIDTH).astype(np.float32)
    map_y = (board[:, 1] / texel + px - 0.5).reshape(HEIGHT, WIDTH).astype(np.float32)
    photo = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderValue=128)
    return np.asarray(photo, dtype=np.uint8)


@pytest.fixture(scope="module")
def board_photos() -> list[tuple[str, NDArray[np.uint8]]]:
    """Seven photos of the board 0.6 m away, tilted up to 23 deg, in the middle and
    towards each corner of the image."""
    rng = np.random.default_rng(1)
    centre = np.array([(VIEW_PATTERN[0] + 1) / 2, (VIEW_PATTERN[1] + 1) / 2, 0.0])
    centre *= VIEW_SQUARE_M
    offsets = [(0, 0), (-0.1, -0.07), (0.1, -0.07), (-0.1, 0.07), (0.1, 0.07), (0, 0), (0, 0)]
    photos = []
    for index, (dx, dy) in enumerate(offsets):
        rvec = rng.uniform(-0.4, 0.4, 3) * np.array([1.0, 1.0, 0.4])
        R, _ = cv2.Rodrigues(rvec)
        tvec = np.array([dx, dy, 0.6]) - R @ centre
        photos.append((f"view{index}.png", render_board_photo(rvec, tvec)))
    return photos


def test_intrinsics_of_a_known_camera(board_photos: list[tuple[str, NDArray[np.uint8]]]) -> None:
    result = calibrate_intrinsics(board_photos, VIEW_PATTERN, VIEW_SQUARE_M)
    k = result.intrinsics
    assert result.rejected == [] and len(result.used) == 7
    assert k.rms_px < 0.2 and max(result.per_image_rms_px.values()) < 0.3
    assert abs(k.fx_px - 520.0) / 520.0 < 0.005 and abs(k.fy_px - 515.0) / 515.0 < 0.005
    assert abs(k.cx_px - 318.0) < 2.0 and abs(k.cy_px - 243.0) < 2.0
    # The lens model (k2 and k3 trade off) undistorts like the true one where the boards
    # were; towards the image corners, where no board was, it extrapolates.
    u, v = np.meshgrid(np.linspace(100, 540, 8), np.linspace(80, 400, 6))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    true = np.asarray(
        cv2.undistortPoints(pixels.reshape(-1, 1, 2), K_TRUE, DIST_TRUE, P=K_TRUE)
    ).reshape(-1, 2)
    assert np.abs(k.undistort_points(pixels) - true).max() < 0.5


def test_intrinsics_reject_other_sizes_and_missing_boards(
    board_photos: list[tuple[str, NDArray[np.uint8]]],
) -> None:
    portrait = ("portrait.png", np.ascontiguousarray(np.rot90(board_photos[0][1])))
    blank = ("blank.png", np.full((HEIGHT, WIDTH), 128, np.uint8))
    result = calibrate_intrinsics([*board_photos[:3], portrait, blank], VIEW_PATTERN, VIEW_SQUARE_M)
    reasons = dict(result.rejected)
    assert set(reasons) == {"portrait.png", "blank.png"}
    assert "480x640 px" in reasons["portrait.png"] and "640x480" in reasons["portrait.png"]
    assert "not found" in reasons["blank.png"]
    assert result.used == ["view0.png", "view1.png", "view2.png"]
    with pytest.raises(CalibrationError, match=r"only 2 usable.*portrait\.png: image is 480x640"):
        calibrate_intrinsics([*board_photos[:2], portrait], VIEW_PATTERN, VIEW_SQUARE_M)


def test_too_few_calibration_images() -> None:
    image = render_floor_board(camera_homography(), (0.45, -0.12))
    blank = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match="only 1 usable"):
        calibrate_intrinsics([("a", image), ("b", blank)], PATTERN, SQUARE_M)
    with pytest.raises(CalibrationError, match="no images"):
        calibrate_intrinsics([], PATTERN, SQUARE_M)
    with pytest.raises(CalibrationError, match="square size"):
        calibrate_intrinsics([("a", image)], PATTERN, 0.0)


# -- calibration files -------------------------------------------------------------------


def make_calibration() -> FloorCalibration:
    intrinsics = Intrinsics(
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5), (WIDTH, HEIGHT), 0.2
    )
    return homography_from_point_pairs(
        apply_homography(camera_homography(), GROUND),
        GROUND,
        (WIDTH, HEIGHT),
        intrinsics=intrinsics,
    )


def test_calibration_files_round_trip_and_errors(tmp_path: Path) -> None:
    calibration = make_calibration()
    assert calibration.intrinsics is not None
    save_floor_calibration(tmp_path / "floor.json", calibration)
    save_intrinsics(tmp_path / "intrinsics.json", calibration.intrinsics)
    loaded = load_floor_calibration(tmp_path / "floor.json", (WIDTH, HEIGHT))
    np.testing.assert_allclose(loaded.H_ground_from_image, calibration.H_ground_from_image)
    assert loaded.intrinsics is not None and loaded.intrinsics.fx_px == 500.0
    assert load_intrinsics(tmp_path / "intrinsics.json").image_size == (WIDTH, HEIGHT)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporaries
    with pytest.raises(CalibrationError, match="not found"):
        load_floor_calibration(tmp_path / "missing.json")
    with pytest.raises(CalibrationError, match="not found"):
        load_intrinsics(tmp_path / "missing.json")
    with pytest.raises(
        CalibrationError, match="for 640x480 px images but it is used with 1280x720"
    ):
        load_floor_calibration(tmp_path / "floor.json", (1280, 720))
    with pytest.raises(CalibrationError, match="640x480 px images but it is used with 480x640"):
        load_intrinsics(tmp_path / "intrinsics.json", (480, 640))
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="unreadable"):
        load_floor_calibration(tmp_path / "broken.json")
    (tmp_path / "other.json").write_text(json.dumps({"camera_matrix": 3}))
    with pytest.raises(CalibrationError, match="not a floornav"):
        load_intrinsics(tmp_path / "other.json")
    with pytest.raises(CalibrationError, match="not a floornav floor calibration"):
        load_floor_calibration(tmp_path / "intrinsics.json")


def test_a_loaded_homography_gets_the_same_sanity_checks(tmp_path: Path) -> None:
    calibration = make_calibration()
    save_floor_calibration(tmp_path / "floor.json", calibration)
    doc = json.loads((tmp_path / "floor.json").read_text())
    mirrored = np.diag([1.0, -1.0, 1.0]) @ np.array(doc["H_ground_from_image"])
    for H, message in [
        (mirrored, "mirrored"),
        (-np.array(doc["H_ground_from_image"]), "horizon"),
        (np.zeros((3, 3)), "singular|finite"),
        ([[1, 2], [3, 4]], "3x3"),
    ]:
        doc["H_ground_from_image"] = np.asarray(H).tolist()
        (tmp_path / "bad.json").write_text(json.dumps(doc))
        with pytest.raises(CalibrationError, match=message):
            load_floor_calibration(tmp_path / "bad.json")


def test_a_failed_write_leaves_the_old_file_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calibration = make_calibration()
    target = tmp_path / "floor.json"
    save_floor_calibration(target, calibration)
    before = target.read_bytes()

    def crash(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        save_floor_calibration(target, calibration)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["floor.json"]


def test_opencv_intrinsics_files(tmp_path: Path) -> None:
    path = tmp_path / "camera.yaml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("camera_matrix", K_TRUE)
    storage.write("distortion_coefficients", DIST_TRUE.reshape(1, 5))
    storage.release()
    intrinsics = load_intrinsics(path, (640, 480))
    np.testing.assert_allclose(intrinsics.camera_matrix, K_TRUE)
    np.testing.assert_allclose(intrinsics.dist, DIST_TRUE)
    lacking = tmp_path / "lacking.xml"
    storage = cv2.FileStorage(str(lacking), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", K_TRUE)
    storage.release()
    with pytest.raises(CalibrationError, match="lacks"):
        load_intrinsics(lacking)
    (tmp_path / "garbage.xml").write_text("<opencv_storage><camera_matrix>")
    with pytest.raises(CalibrationError, match=r"garbage\.xml"):
        load_intrinsics(tmp_path / "garbage.xml")


# -- real chessboard photos --------------------------------------------------------------


def test_intrinsics_on_the_opencv_stereo_left_images() -> None:
    folder = dataset_dir("chessboard") / "opencv-stereo-9x6"
    images = [(p.name, read_bgr(p)) for p in sorted(folder.glob("left*.jpg"))]
    result = calibrate_intrinsics(images, (9, 6), 1.0)
    assert len(result.used) == 14 and result.rejected == []
    assert result.intrinsics.rms_px <= 0.5
    assert abs(result.intrinsics.fx_px - 536.0) / 536.0 <= 0.05
    assert abs(result.intrinsics.fy_px - 536.0) / 536.0 <= 0.05
    assert set(result.per_image_rms_px) == {name for name, _ in images}


def test_intrinsics_on_phone_photos_reject_the_portrait_ones() -> None:
    folder = dataset_dir("chessboard") / "locv3-calibration-12x12"
    names = ["IMG_0191", "IMG_0194", "IMG_0197", "IMG_0200", "IMG_0201", "IMG_0204"]
    images = [(n, read_bgr(folder / f"{n}.jpg")) for n in names]
    result = calibrate_intrinsics(images, (12, 12), 1.0)
    reasons = dict(result.rejected)
    assert set(reasons) == {"IMG_0200", "IMG_0204"}
    assert "1200x1600 px" in reasons["IMG_0200"] and "1600x1200" in reasons["IMG_0200"]
    assert result.intrinsics.image_size == (1600, 1200)
    assert result.intrinsics.rms_px <= 0.5
    assert abs(result.intrinsics.fx_px - 1766.7) / 1766.7 <= 0.03


FLOOR_PHOTOS = ["IMG_0214", "IMG_0215", "IMG_0217", "IMG_0218", "IMG_0219", "IMG_0220"]


def floor_folder() -> Path:
    return dataset_dir("chessboard") / "locv3-floor-birdseye-12x12"


@pytest.mark.parametrize("name", ["IMG_0215", "IMG_0218"])
def test_floor_homography_on_real_photos_with_and_without_intrinsics(name: str) -> None:
    """The upright photo, its landscape copy, and the copy with the book's intrinsics
    (which belong to the landscape orientation) all fit to well under 1 px, and agree."""
    folder = floor_folder()
    upright = read_bgr(folder / f"{name}.jpg")
    landscape = read_bgr(folder / f"{name}L.jpg")
    intrinsics = load_intrinsics(folder / "intrinsics.xml", (1600, 1200))
    fits = {
        "upright": floor_homography_from_chessboard(upright, (12, 12), 0.025),
        "landscape": floor_homography_from_chessboard(landscape, (12, 12), 0.025),
        "landscape+lens": floor_homography_from_chessboard(
            landscape, (12, 12), 0.025, intrinsics=intrinsics
        ),
    }
    for label, fit in fits.items():
        assert fit.reprojection_rms_px <= 1.0, label
        assert fit.ground_rms_m <= 0.001, label
        assert fit.inliers >= 140, label
    # The landscape copy is the upright photo turned 90 deg counter-clockwise: the same
    # board origin, and the same ground point for the same physical pixel.
    u, v = fits["upright"].board_origin_px or (0.0, 0.0)
    np.testing.assert_allclose(fits["landscape"].board_origin_px or (), (v, 1199 - u), atol=0.5)
    upright_px = np.array([[600.0, 1300.0], [300.0, 1200.0], [900.0, 1500.0]])
    landscape_px = np.column_stack([upright_px[:, 1], 1199 - upright_px[:, 0]])
    np.testing.assert_allclose(
        fits["landscape"].image_to_ground(landscape_px),
        fits["upright"].image_to_ground(upright_px),
        atol=0.001,
    )
    with pytest.raises(CalibrationError, match="1600x1200 px images but this image is 1200x1600"):
        floor_homography_from_chessboard(upright, (12, 12), 0.025, intrinsics=intrinsics)


@pytest.mark.slow
@pytest.mark.parametrize("name", FLOOR_PHOTOS)
def test_floor_homography_on_every_real_floor_photo(name: str) -> None:
    folder = floor_folder()
    intrinsics = load_intrinsics(folder / "intrinsics.xml", (1600, 1200))
    for file, lens in [(f"{name}.jpg", None), (f"{name}L.jpg", None), (f"{name}L.jpg", intrinsics)]:
        fit = floor_homography_from_chessboard(
            read_bgr(folder / file), (12, 12), 0.025, intrinsics=lens
        )
        assert fit.reprojection_rms_px <= 1.0, (file, lens is not None)
        assert fit.inliers >= 140, (file, lens is not None)


def test_a_board_in_a_huge_photo_is_found_on_a_small_copy_and_refined_at_full_size(
    board_photos: list[tuple[str, NDArray[np.uint8]]],
) -> None:
    """Detection runs on a copy of at most DETECT_MAX_SIDE_PX (bounded time and memory);
    the corners still come from the full-resolution image."""
    _, photo = board_photos[0]
    native = find_chessboard(photo, VIEW_PATTERN)
    assert native is not None
    factor = 5  # 3200x2400 px, above the detection limit
    big = cv2.resize(photo, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
    assert max(big.shape) > DETECT_MAX_SIDE_PX
    corners = find_chessboard(big, VIEW_PATTERN)
    assert corners is not None
    # Pixel centres: x_big = factor * (x + 0.5) - 0.5.
    back = (corners + 0.5) / factor - 0.5
    assert np.abs(back - native).max() < 0.25
