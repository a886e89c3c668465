"""``floornav calibrate intrinsics|floor``: the calibration commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from app.fileio import print_json
from app.imageio import read_bgr, write_image_atomic
from app.mapping.calibration import (
    BoardPlacement,
    CalibrationError,
    FloorCalibration,
    calibrate_intrinsics,
    floor_homography_from_chessboard,
    parse_pattern,
)
from app.mapping.calibration_files import (
    load_intrinsics,
    save_floor_calibration,
    save_intrinsics,
)
from app.mapping.frames import GroundGrid
from app.mapping.ipm import birdseye_image, build_birdseye_map
from app.perception.image_checks import ImageError


def cmd_intrinsics(args: argparse.Namespace) -> int:
    pattern = parse_pattern(args.pattern)
    images = []
    unreadable = []
    for path in args.images:
        try:
            images.append((str(path), read_bgr(path)))
        except ImageError as exc:
            unreadable.append((str(path), str(exc)))
    result = calibrate_intrinsics(images, pattern, args.square_m)
    intrinsics = result.intrinsics
    if args.out:
        save_intrinsics(args.out, intrinsics)
    report = {
        "rms_px": intrinsics.rms_px,
        "fx_px": intrinsics.fx_px,
        "fy_px": intrinsics.fy_px,
        "cx_px": intrinsics.cx_px,
        "cy_px": intrinsics.cy_px,
        "dist": intrinsics.dist.tolist(),
        "image_size_px": list(intrinsics.image_size),
        "images_used": len(result.used),
        "images_rejected": [
            {"file": name, "reason": reason} for name, reason in unreadable + result.rejected
        ],
        "per_image_rms_px": result.per_image_rms_px,
        "out": str(args.out) if args.out else None,
    }
    if args.json:
        print_json(report)
    else:
        w, h = intrinsics.image_size
        print(
            f"calibrated on {len(result.used)} image(s) of {w}x{h} px: "
            f"RMS {intrinsics.rms_px:.3f} px"
        )
        print(
            f"fx {intrinsics.fx_px:.1f}  fy {intrinsics.fy_px:.1f}  "
            f"cx {intrinsics.cx_px:.1f}  cy {intrinsics.cy_px:.1f} px"
        )
        print("dist " + " ".join(f"{d:.4f}" for d in intrinsics.dist))
        for item in report["images_rejected"]:
            print(f"rejected {item['file']}: {item['reason']}")
        if args.out:
            print(f"written to {args.out}")
    return 0


def birdseye_grid_around_board(
    calibration: FloorCalibration, board_ground: np.ndarray
) -> GroundGrid:
    """A bird's-eye raster centred on the board, twice its size, about 600 cells across."""
    x_min, y_min = board_ground.min(axis=0)
    x_max, y_max = board_ground.max(axis=0)
    span = max(x_max - x_min, y_max - y_min)
    margin = 0.5 * span
    cell = (span + 2 * margin) / 600.0
    return GroundGrid.covering(
        x_min_m=x_min - margin,
        x_max_m=x_max + margin,
        y_min_m=y_min - margin,
        y_max_m=y_max + margin,
        cell_m=cell,
    )


def cmd_floor(args: argparse.Namespace) -> int:
    pattern = parse_pattern(args.pattern)
    image = read_bgr(args.image)
    height, width = image.shape[:2]
    intrinsics = load_intrinsics(args.intrinsics, (width, height)) if args.intrinsics else None
    placement = BoardPlacement(args.board_x_m, args.board_y_m, args.board_yaw_rad)
    calibration = floor_homography_from_chessboard(
        image, pattern, args.square_m, intrinsics=intrinsics, placement=placement
    )
    birdseye_path = None
    if args.out:
        save_floor_calibration(args.out, calibration)
        cols, rows = pattern
        corners = np.array(
            [[0, 0], [0, cols - 1], [rows - 1, 0], [rows - 1, cols - 1], [cols - 1, rows - 1]],
            dtype=np.float64,
        )
        board_ground = placement.to_robot(corners * args.square_m)
        grid = birdseye_grid_around_board(calibration, board_ground)
        view = birdseye_image(image, build_birdseye_map(calibration, grid, max_range_m=1e6))
        birdseye_path = args.out.with_suffix(".birdseye.png")
        write_image_atomic(birdseye_path, view)
    report = {
        "reprojection_rms_px": calibration.reprojection_rms_px,
        "ground_rms_m": calibration.ground_rms_m,
        "H_ground_from_image": calibration.H_ground_from_image.tolist(),
        "corners": calibration.points,
        "inliers": calibration.inliers,
        "undistorted": intrinsics is not None,
        "image_size_px": [width, height],
        "out": str(args.out) if args.out else None,
        "birdseye_png": str(birdseye_path) if birdseye_path else None,
    }
    if args.json:
        print_json(report)
    else:
        print(
            f"floor homography from {calibration.inliers}/{calibration.points} corners: "
            f"reprojection RMS {calibration.reprojection_rms_px:.3f} px, "
            f"ground RMS {calibration.ground_rms_m * 1000:.2f} mm"
        )
        if args.out:
            print(f"written to {args.out} and {birdseye_path}")
    return 0


def _run(func: Any) -> Any:
    def wrapped(args: argparse.Namespace) -> int:
        try:
            code: int = func(args)
        except CalibrationError as exc:
            print(f"floornav calibrate: {exc}", file=sys.stderr)
            return 1
        return code

    return wrapped


def add_calibrate_parser(sub: Any) -> None:
    """Register ``calibrate intrinsics`` and ``calibrate floor`` on a subparsers object."""
    calibrate = sub.add_parser("calibrate", help="camera intrinsics and the floor homography")
    kinds = calibrate.add_subparsers(dest="calibrate_kind", required=True)

    p = kinds.add_parser("intrinsics", help="camera matrix and distortion from chessboard photos")
    p.add_argument("images", type=Path, nargs="+", metavar="IMAGE")
    p.add_argument("--pattern", required=True, help="inner corners, COLSxROWS (e.g. 9x6)")
    p.add_argument("--square-m", type=float, required=True, help="square size in metres")
    p.add_argument("--out", type=Path, help="write the intrinsics JSON here")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run(cmd_intrinsics))

    p = kinds.add_parser("floor", help="floor homography from a chessboard lying on the floor")
    p.add_argument("image", type=Path, metavar="IMAGE")
    p.add_argument("--pattern", required=True, help="inner corners, COLSxROWS (e.g. 12x12)")
    p.add_argument("--square-m", type=float, required=True, help="square size in metres")
    p.add_argument("--intrinsics", type=Path, help="intrinsics (our JSON or OpenCV XML/YAML)")
    p.add_argument("--board-x-m", type=float, default=0.0, help="first corner, robot x (m)")
    p.add_argument("--board-y-m", type=float, default=0.0, help="first corner, robot y (m)")
    p.add_argument("--board-yaw-rad", type=float, default=0.0, help="board yaw in the robot frame")
    p.add_argument("--out", type=Path, help="write the floor calibration JSON (+ .birdseye.png)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run(cmd_floor))
