"""Calibration and IPM: exact answers on synthetic views, the real chessboard photos,
and every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.cli import main
from app.mapping.calibration import (
    BoardPlacement,
    CalibrationError,
    Intrinsics,
    apply_homography,
    calibrate_intrinsics,
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
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid
from app.mapping.ipm import (
    birdseye_floor_patch,
    birdseye_image,
    build_birdseye_map,
    build_ground_lookup,
    lookup_error_m,
)

from ..conftest import dataset_dir

WIDTH, HEIGHT = 640, 480
SQUARE_M = 0.04
PATTERN = (7, 5)  # inner corners: a board of 8 x 6 squares
TEXEL_M = 0.002  # 2 mm per texel of the top-down board texture


def camera_homography() -> NDArray[np.float64]:
    """H_image_from_ground of a pinhole camera 0.3 m above the floor, pitched 30 deg
    down, looking along +x (robot frame: x forward, y left)."""
    f, cx, cy = 500.0, WIDTH / 2, HEIGHT / 2
    pitch = np.deg2rad(30.0)
    # Camera axes (x right, y down, z forward) expressed in the robot frame.
    forward = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    R_cam_from_robot = np.vstack([right, down, forward])
    t = -R_cam_from_robot @ np.array([0.0, 0.0, 0.3])
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    # Floor points (x, y, 0): columns x, y and the translation.
    return K @ np.column_stack([R_cam_from_robot[:, 0], R_cam_from_robot[:, 1], t])


def render_floor_board(
    H_image_from_ground: NDArray[np.float64], origin_m: tuple[float, float]
) -> NDArray[np.uint8]:
    """A grey floor with a chessboard whose first inner corner lies at ``origin_m``,
    squares along +x (away) and +y (left), rendered through the homography."""
    squares_x, squares_y = PATTERN[1] + 1, PATTERN[0] + 1
    size = (int(squares_x * SQUARE_M / TEXEL_M) + 80, int(squares_y * SQUARE_M / TEXEL_M) + 80)
    texture = np.full((size[1], size[0]), 150, np.uint8)  # rows: +y, cols: +x
    px = int(SQUARE_M / TEXEL_M)
    for i in range(squares_x):
        for j in range(squares_y):
            value = 20 if (i + j) % 2 == 0 else 235
            texture[40 + j * px : 40 + (j + 1) * px, 40 + i * px : 40 + (i + 1) * px] = value
    # Texture pixel (c, r) -> ground (x, y): first inner corner at texel (40 + px, 40 + px).
    x0, y0 = origin_m
    ground_from_texture = np.array(
        [[TEXEL_M, 0, x0 - (40 + px) * TEXEL_M], [0, TEXEL_M, y0 - (40 + px) * TEXEL_M], [0, 0, 1]]
    )
    image = cv2.warpPerspective(
        texture, H_image_from_ground @ ground_from_texture, (WIDTH, HEIGHT), borderValue=150
    )
    return np.dstack([image] * 3).astype(np.uint8)


def test_parse_pattern() -> None:
    assert parse_pattern("9x6") == (9, 6)
    for bad in ("9", "ax6", "1x6"):
        with pytest.raises(CalibrationError):
            parse_pattern(bad)


def test_floor_homography_recovers_a_known_view() -> None:
    H_true = camera_homography()
    image = render_floor_board(H_true, (0.45, -0.12))
    calibration = floor_homography_from_chessboard(
        image, PATTERN, SQUARE_M, placement=BoardPlacement(0.45, -0.12, 0.0)
    )
    assert calibration.inliers == calibration.points == 35
    assert calibration.reprojection_rms_px < 0.3
    assert calibration.ground_rms_m < 0.001
    # Points far from the board map where the true homography says, to about 1 cm at 2 m.
    probes_m = np.array([[1.0, 0.0], [2.0, 0.3], [0.5, -0.2]])
    pixels = apply_homography(H_true, probes_m)
    mapped = apply_homography(calibration.H_ground_from_image, pixels)
    errors = np.linalg.norm(mapped - probes_m, axis=1)
    assert errors[0] < 0.01 and errors[1] < 0.03 and errors[2] < 0.01


def test_manual_point_pairs_are_exact() -> None:
    H_true = camera_homography()
    ground = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])
    image_pts = apply_homography(H_true, ground)
    calibration = homography_from_point_pairs(image_pts, ground, (WIDTH, HEIGHT))
    assert calibration.ground_rms_m < 1e-6
    np.testing.assert_allclose(
        calibration.H_ground_from_image / calibration.H_ground_from_image[2, 2],
        np.linalg.inv(H_true) / np.linalg.inv(H_true)[2, 2],
        atol=1e-6,
    )


@pytest.mark.parametrize(
    ("image_pts", "ground_pts", "message"),
    [
        ([[0, 0], [1, 1], [2, 2]], [[0, 0], [1, 0], [0, 1]], "at least 4"),
        ([[0, 0], [10, 10], [20, 20], [30, 30]], [[0, 0], [1, 0], [0, 1], [1, 1]], "collinear"),
        ([[0, 0], [1, 0], [0, 1], [np.nan, 1]], [[0, 0], [1, 0], [0, 1], [1, 1]], "NaN"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 0], [1, 0], [0, 1], [1, 1]], "3 image points"),
    ],
)
def test_degenerate_point_pairs(
    image_pts: list[list[float]], ground_pts: list[list[float]], message: str
) -> None:
    with pytest.raises(CalibrationError, match=message):
        homography_from_point_pairs(
            np.array(image_pts, float), np.array(ground_pts, float), (WIDTH, HEIGHT)
        )


def test_horizon_below_the_image_bottom_is_refused() -> None:
    # Ground points that lie *behind* the camera for the bottom of the image: flip v.
    H_true = camera_homography()
    ground = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])
    image_pts = apply_homography(H_true, ground)
    # Mirror rows about v = 200: the horizon moves from above the image to row ~449.
    image_pts[:, 1] = 400.0 - image_pts[:, 1]
    with pytest.raises(CalibrationError, match="horizon"):
        homography_from_point_pairs(image_pts, ground, (WIDTH, HEIGHT))


def test_board_not_found_and_bad_square() -> None:
    blank = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match="not found"):
        floor_homography_from_chessboard(blank, PATTERN, SQUARE_M)
    with pytest.raises(CalibrationError, match="square size"):
        floor_homography_from_chessboard(blank, PATTERN, 0.0)


def test_too_few_calibration_images() -> None:
    H_true = camera_homography()
    image = render_floor_board(H_true, (0.45, -0.12))
    blank = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match="only 1 usable"):
        calibrate_intrinsics([("a", image), ("b", blank)], PATTERN, SQUARE_M)


def test_ground_lookup_and_birdseye_patch() -> None:
    H_true = camera_homography()
    calibration = homography_from_point_pairs(
        apply_homography(H_true, np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])),
        np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]]),
        (WIDTH, HEIGHT),
    )
    lookup = build_ground_lookup(calibration, max_range_m=3.0)
    assert not lookup.valid[0].any()  # the top row sees the floor 3.9 m away: beyond 3 m
    assert lookup.valid[-1].all()
    assert lookup_error_m(calibration, lookup, np.array([[320, 400], [10, 470]])) < 1e-6
    grid = GroundGrid.covering(x_min_m=0.2, x_max_m=2.0, y_min_m=-1.0, y_max_m=1.0, cell_m=0.01)
    bmap = build_birdseye_map(calibration, grid, max_range_m=4.0)
    # Floor everywhere below image row 300, nothing above: the patch is FLOOR up to the
    # ground distance of row 300 straight ahead, NOT_FLOOR beyond, UNSEEN outside the view.
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[300:] = True
    patch = birdseye_floor_patch(mask, bmap)
    x_300 = calibration.image_to_ground(np.array([[WIDTH / 2, 300.0]]))[0, 0]
    centre_col = grid.cell_of(np.array([[1.0, 0.0]]))[0, 1]
    column = patch[:, centre_col]
    x_cells, _ = grid.cell_centers()
    seen_floor = x_cells[:, centre_col][column == FLOOR]
    seen_other = x_cells[:, centre_col][column == NOT_FLOOR]
    assert seen_floor.max() <= x_300 + 0.02 and seen_other.min() >= x_300 - 0.02
    assert (patch[:, 0] == UNSEEN).any()  # far left at short range is outside the image
    view = birdseye_image(np.full((HEIGHT, WIDTH, 3), 200, np.uint8), bmap)
    assert view.shape == (*grid.shape, 3)
    with pytest.raises(ValueError, match="built for"):
        birdseye_floor_patch(np.zeros((10, 10), bool), bmap)


def test_calibration_files_round_trip_and_errors(tmp_path: Path) -> None:
    H_true = camera_homography()
    ground = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])
    intrinsics = Intrinsics(
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5), (WIDTH, HEIGHT), 0.2
    )
    calibration = homography_from_point_pairs(
        apply_homography(H_true, ground), ground, (WIDTH, HEIGHT), intrinsics=intrinsics
    )
    save_floor_calibration(tmp_path / "floor.json", calibration)
    save_intrinsics(tmp_path / "intrinsics.json", intrinsics)
    loaded = load_floor_calibration(tmp_path / "floor.json", (WIDTH, HEIGHT))
    np.testing.assert_allclose(loaded.H_ground_from_image, calibration.H_ground_from_image)
    assert loaded.intrinsics is not None and loaded.intrinsics.fx_px == 500.0
    assert load_intrinsics(tmp_path / "intrinsics.json").image_size == (WIDTH, HEIGHT)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporaries
    with pytest.raises(CalibrationError, match="not found"):
        load_floor_calibration(tmp_path / "missing.json")
    with pytest.raises(CalibrationError, match="1280x720"):
        load_floor_calibration(tmp_path / "floor.json", (1280, 720))
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="unreadable"):
        load_floor_calibration(tmp_path / "broken.json")
    (tmp_path / "other.json").write_text(json.dumps({"camera_matrix": 3}))
    with pytest.raises(CalibrationError, match="not a floornav"):
        load_intrinsics(tmp_path / "other.json")


# -- real chessboard photos --------------------------------------------------------------


def test_intrinsics_on_the_opencv_stereo_left_images(capsys: pytest.CaptureFixture[str]) -> None:
    folder = dataset_dir("chessboard") / "opencv-stereo-9x6"
    images = sorted(str(p) for p in folder.glob("left*.jpg"))
    assert (
        main(
            [
                "calibrate",
                "intrinsics",
                *images,
                "--pattern",
                "9x6",
                "--square-m",
                "0.025",
                "--json",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["rms_px"] <= 0.5
    assert abs(report["fx_px"] - 536.0) / 536.0 <= 0.05
    assert report["images_used"] == len(images) and report["images_rejected"] == []


@pytest.mark.slow
def test_intrinsics_reject_portrait_phone_photos(capsys: pytest.CaptureFixture[str]) -> None:
    folder = dataset_dir("chessboard") / "locv3-calibration-12x12"
    images = sorted(str(p) for p in folder.glob("*.jpg"))
    assert (
        main(
            [
                "calibrate",
                "intrinsics",
                *images,
                "--pattern",
                "12x12",
                "--square-m",
                "0.02",
                "--json",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    rejected = {Path(r["file"]).name for r in report["images_rejected"]}
    assert rejected == {"IMG_0200.jpg", "IMG_0204.jpg", "IMG_0207.jpg"}
    assert report["rms_px"] <= 0.5 and report["images_used"] == 20


def test_floor_homography_on_the_real_floor_photo(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image = dataset_dir("chessboard") / "locv3-floor-birdseye-12x12" / "IMG_0215.jpg"
    out = tmp_path / "floor.json"
    args = ["calibrate", "floor", str(image), "--pattern", "12x12", "--square-m", "0.025"]
    assert main([*args, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["reprojection_rms_px"] <= 1.0
    assert report["inliers"] == 144
    assert out.is_file() and Path(report["birdseye_png"]).is_file()
    assert load_floor_calibration(out, (1200, 1600)).points == 144


def test_calibrate_command_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((HEIGHT, WIDTH, 3), 128, np.uint8))
    assert main(["calibrate", "floor", str(blank), "--pattern", "7x5", "--square-m", "0.04"]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["calibrate", "floor", str(blank), "--pattern", "7by5", "--square-m", "0.04"]) == 1
    assert "COLSxROWS" in capsys.readouterr().err
    assert (
        main(["calibrate", "intrinsics", str(blank), "--pattern", "7x5", "--square-m", "0.04"]) == 1
    )
    assert "usable" in capsys.readouterr().err
