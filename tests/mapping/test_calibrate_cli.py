"""``floornav calibrate intrinsics|floor``: outputs, files, and errors (exit code 1 with a
message naming the file or parameter), through the sub-parser alone and through
``floornav``'s own command line."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main
from app.imageio import read_bgr
from app.mapping.calibrate_cli import add_calibrate_parser
from app.mapping.calibration import apply_homography
from app.mapping.calibration_files import load_floor_calibration, load_intrinsics

from ..conftest import dataset_dir
from .test_calibration import (
    HEIGHT,
    PATTERN,
    SQUARE_M,
    VIEW_PATTERN,
    WIDTH,
    camera_homography,
    render_board_photo,
    render_floor_board,
)

INTRINSICS_KEYS = {
    "rms_px",
    "fx_px",
    "fy_px",
    "cx_px",
    "cy_px",
    "dist",
    "images_used",
    "images_rejected",
    "per_image_rms_px",
    "image_size_px",
}
FLOOR_KEYS = {"reprojection_rms_px", "ground_rms_m", "H_ground_from_image", "inliers", "corners"}


def run(argv: Sequence[str]) -> int:
    """The calibrate commands on a parser of their own (as app/cli.py hooks them in)."""
    parser = argparse.ArgumentParser(prog="floornav")
    add_calibrate_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    code: int = args.func(args)
    return code


@pytest.fixture(scope="module")
def photo_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Five synthetic board photos, a portrait one, a corrupt file and a blank image."""
    folder = tmp_path_factory.mktemp("photos")
    rng = np.random.default_rng(5)
    centre = np.array([(VIEW_PATTERN[0] + 1) / 2, (VIEW_PATTERN[1] + 1) / 2, 0.0]) * 0.03
    for index, (dx, dy) in enumerate([(0, 0), (-0.1, -0.07), (0.1, 0.07), (0.1, -0.07), (0, 0)]):
        rvec = rng.uniform(-0.4, 0.4, 3) * np.array([1.0, 1.0, 0.4])
        R, _ = cv2.Rodrigues(rvec)
        photo = render_board_photo(rvec, np.array([dx, dy, 0.6]) - R @ centre)
        cv2.imwrite(str(folder / f"view{index}.png"), photo)
        if index == 0:
            cv2.imwrite(str(folder / "portrait.png"), np.ascontiguousarray(np.rot90(photo)))
    (folder / "corrupt.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    cv2.imwrite(str(folder / "blank.png"), np.full((HEIGHT, WIDTH), 128, np.uint8))
    return folder


@pytest.fixture(scope="module")
def floor_photo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("floor") / "floor.png"
    cv2.imwrite(str(path), render_floor_board(camera_homography(), (0.45, -0.12)))
    return path


def test_intrinsics_json_and_file(
    photo_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = sorted(str(p) for p in photo_folder.iterdir())
    out = tmp_path / "intrinsics.json"
    argv = ["calibrate", "intrinsics", *images, "--pattern", "9x6", "--square-m", "0.03"]
    assert run([*argv, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) >= INTRINSICS_KEYS
    assert report["images_used"] == 5 and report["image_size_px"] == [640, 480]
    assert len(report["dist"]) == 5 and report["rms_px"] < 0.3
    assert abs(report["fx_px"] - 520.0) < 3.0
    reasons = {Path(r["file"]).name: r["reason"] for r in report["images_rejected"]}
    assert set(reasons) == {"portrait.png", "corrupt.jpg", "blank.png"}
    assert "480x640 px" in reasons["portrait.png"]
    assert "not a readable image" in reasons["corrupt.jpg"]
    assert "not found" in reasons["blank.png"]
    assert set(report["per_image_rms_px"]) == {str(photo_folder / f"view{i}.png") for i in range(5)}
    loaded = load_intrinsics(out, (640, 480))
    assert loaded.fx_px == pytest.approx(report["fx_px"])
    # Human output: a short summary.
    assert run(argv) == 0
    text = capsys.readouterr().out
    assert "RMS" in text and "fx" in text and "rejected" in text and "portrait.png" in text


def test_floor_json_file_and_birdseye_png(
    floor_photo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "calibration" / "floor.json"
    argv = ["calibrate", "floor", str(floor_photo), "--pattern", "7x5", "--square-m", "0.04"]
    placement = ["--board-x-m", "0.45", "--board-y-m", "-0.12", "--board-yaw-rad", "0"]
    assert run([*argv, *placement, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) >= FLOOR_KEYS
    assert report["inliers"] == report["corners"] == 35
    assert report["reprojection_rms_px"] < 0.3 and report["ground_rms_m"] < 0.001
    assert report["birdseye_png"] == str(tmp_path / "calibration" / "floor.birdseye.png")
    calibration = load_floor_calibration(out, (WIDTH, HEIGHT))
    probes = np.array([[0.5, 0.0], [0.7, 0.1]])
    pixels = apply_homography(camera_homography(), probes)
    np.testing.assert_allclose(calibration.image_to_ground(pixels), probes, atol=0.001)
    birdseye = read_bgr(Path(report["birdseye_png"]))
    assert birdseye.shape[0] >= 500 and birdseye.std() > 30  # the board is in view
    assert run(argv) == 0
    text = capsys.readouterr().out
    assert "reprojection RMS" in text and "board origin" in text


def test_floor_with_intrinsics_of_another_size(
    floor_photo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lens = tmp_path / "lens.json"
    lens.write_text(
        json.dumps(
            {
                "kind": "floornav-intrinsics",
                "camera_matrix": [[900.0, 0, 640], [0, 900, 360], [0, 0, 1]],
                "dist": [0, 0, 0, 0, 0],
                "image_size_px": [1280, 720],
            }
        )
    )
    argv = ["calibrate", "floor", str(floor_photo), "--pattern", "7x5", "--square-m", "0.04"]
    assert run([*argv, "--intrinsics", str(lens)]) == 1
    err = capsys.readouterr().err
    assert "lens.json" in err and "1280x720" in err and "640x480" in err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--pattern", "7by5", "--square-m", "0.04"], "--pattern"),
        (["--pattern", "1x5", "--square-m", "0.04"], "--pattern"),
        (["--pattern", "7x5", "--square-m", "0"], "--square-m"),
        (["--pattern", "7x5", "--square-m", "-0.04"], "--square-m"),
        (["--pattern", "7x5", "--square-m", "nan"], "--square-m"),
        (["--pattern", "6x4", "--square-m", "0.04"], "not found"),
        (
            ["--pattern", "7x5", "--square-m", "0.04", "--intrinsics", "/nonexistent/k.json"],
            "k.json",
        ),
    ],
)
def test_floor_errors(
    floor_photo: Path, extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run(["calibrate", "floor", str(floor_photo), *extra]) == 1
    err = capsys.readouterr().err
    assert message in err and "floornav calibrate floor" in err


def test_missing_and_unusable_images(
    photo_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "missing.png"
    assert run(["calibrate", "floor", str(missing), "--pattern", "7x5", "--square-m", "1"]) == 1
    assert "missing.png" in capsys.readouterr().err
    blank = str(photo_folder / "blank.png")
    assert run(["calibrate", "floor", blank, "--pattern", "7x5", "--square-m", "1"]) == 1
    err = capsys.readouterr().err
    assert "blank.png" in err and "not found" in err
    few = [str(photo_folder / n) for n in ("view0.png", "view1.png", "corrupt.jpg")]
    assert run(["calibrate", "intrinsics", *few, "--pattern", "9x6", "--square-m", "1"]) == 1
    err = capsys.readouterr().err
    assert "only 2 usable" in err and "corrupt.jpg" in err


def test_floornav_command_line_has_the_calibrate_commands(
    floor_photo: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["calibrate", "floor", str(floor_photo), "--pattern", "7x5", "--square-m", "0.04"]
    assert main([*argv, "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)) >= FLOOR_KEYS
    assert main([*argv[:3], "--pattern", "7by5", "--square-m", "0.04"]) == 1
    assert "COLSxROWS" in capsys.readouterr().err
    assert PATTERN == (7, 5) and SQUARE_M == 0.04


# -- real chessboard photos --------------------------------------------------------------


def test_intrinsics_command_on_the_opencv_stereo_left_images(
    capsys: pytest.CaptureFixture[str],
) -> None:
    folder = dataset_dir("chessboard") / "opencv-stereo-9x6"
    images = sorted(str(p) for p in folder.glob("left*.jpg"))
    assert (
        run(["calibrate", "intrinsics", *images, "--pattern", "9x6", "--square-m", "1", "--json"])
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["rms_px"] <= 0.5
    assert abs(report["fx_px"] - 536.0) / 536.0 <= 0.05
    assert report["images_used"] == len(images) == 14 and report["images_rejected"] == []


@pytest.mark.slow
def test_intrinsics_command_rejects_portrait_phone_photos(
    capsys: pytest.CaptureFixture[str],
) -> None:
    folder = dataset_dir("chessboard") / "locv3-calibration-12x12"
    images = sorted(str(p) for p in folder.glob("*.jpg"))
    argv = ["calibrate", "intrinsics", *images, "--pattern", "12x12", "--square-m", "0.02"]
    assert run([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    reasons = {Path(r["file"]).name: r["reason"] for r in report["images_rejected"]}
    assert set(reasons) == {"IMG_0200.jpg", "IMG_0204.jpg", "IMG_0207.jpg"}
    assert all("1200x1600 px" in reason for reason in reasons.values())
    assert report["rms_px"] <= 0.5 and report["images_used"] == 20


def test_floor_command_on_the_books_photo_with_its_intrinsics(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The book's example: ``12 12 intrinsics.xml IMG_0215L.jpg``."""
    folder = dataset_dir("chessboard") / "locv3-floor-birdseye-12x12"
    out = tmp_path / "floor.json"
    argv = [
        "calibrate",
        "floor",
        str(folder / "IMG_0215L.jpg"),
        "--pattern",
        "12x12",
        "--square-m",
        "0.025",
        "--intrinsics",
        str(folder / "intrinsics.xml"),
        "--out",
        str(out),
        "--json",
    ]
    assert run(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["reprojection_rms_px"] <= 1.0 and report["inliers"] >= 140
    assert report["undistorted"] is True
    calibration = load_floor_calibration(out, (1600, 1200))
    assert calibration.intrinsics is not None and calibration.points == 144
    assert Path(report["birdseye_png"]).is_file()
