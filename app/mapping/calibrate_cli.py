"""``floornav calibrate intrinsics|floor``: the calibration commands.

Errors (a board not found, too few usable photos, a missing or mismatched intrinsics
file, a bad ``--pattern`` or ``--square-m``) print one line on stderr naming the file or
parameter and exit with code 1.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

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


def _pattern(text: str) -> tuple[int, int]:
    try:
        return parse_pattern(text)
    except CalibrationError as exc:
        raise CalibrationError(f"--pattern: {exc}") from exc


def _check_square(square_m: float) -> None:
    if not (square_m > 0 and math.isfinite(square_m)):
        raise CalibrationError(f"--square-m must be a positive size in metres, got {square_m}")


def cmd_intrinsics(args: argparse.Namespace) -> int:
    pattern = _pattern(args.pattern)
    _check_square(args.square_m)
    images = []
    unreadable = []
    for path in args.images:
        try:
            images.append((str(path), read_bgr(path)))
        except ImageError as exc:
            unreadable.append((str(path), str(exc)))
    try:
        result = calibrate_intrinsics(images, pattern, args.square_m)
    except CalibrationError as exc:
        if not unreadable:
            raise
        skipped = "; ".join(f"{name}: {reason}" for name, reason in unreadable)
        raise CalibrationError(f"{exc}; also unreadable: {skipped}") from exc
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


def board_outline_m(
    pattern: tuple[int, int], square_m: float, placement: BoardPlacement
) -> NDArray[np.float64]:
    """Robot-frame corners of the rectangle the board's inner corners can span, in both
    of its orientations (which side runs away from the camera is found by the fit)."""
    cols, rows = pattern
    extents = [(cols - 1, rows - 1), (rows - 1, cols - 1)]
    board = np.array(
        [[a * i, b * j] for a, b in extents for i in (0, 1) for j in (0, 1)], dtype=np.float64
    )
    return placement.to_robot(board * square_m)


def birdseye_grid_around_board(
    calibration: FloorCalibration, board_ground: NDArray[np.float64]
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


def draw_board_frame(
    view: NDArray[np.uint8], grid: GroundGrid, placement: BoardPlacement, square_m: float
) -> None:
    """Mark the board origin (red ring) and its +x (red) and +y (green) axes, one square
    long, on a bird's-eye view: what the calibration assumed, for a person to check."""
    c, s = math.cos(placement.yaw_rad), math.sin(placement.yaw_rad)
    origin = np.array([placement.x_m, placement.y_m])
    points = np.array(
        [origin, origin + square_m * np.array([c, s]), origin + square_m * np.array([-s, c])]
    )
    cells = grid.cell_of(points)
    pixel = [(int(col), int(row)) for row, col in cells]  # cv2 wants (x = col, y = row)
    radius = max(3, round(0.25 * square_m / grid.cell_m))
    cv2.circle(view, pixel[0], radius, (0, 0, 255), 2)
    cv2.line(view, pixel[0], pixel[1], (0, 0, 255), 2)
    cv2.line(view, pixel[0], pixel[2], (0, 200, 0), 2)


def cmd_floor(args: argparse.Namespace) -> int:
    pattern = _pattern(args.pattern)
    _check_square(args.square_m)
    image = read_bgr(args.image)
    height, width = image.shape[:2]
    intrinsics = load_intrinsics(args.intrinsics, (width, height)) if args.intrinsics else None
    placement = BoardPlacement(args.board_x_m, args.board_y_m, args.board_yaw_rad)
    try:
        calibration = floor_homography_from_chessboard(
            image, pattern, args.square_m, intrinsics=intrinsics, placement=placement
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{args.image}: {exc}") from exc
    birdseye_path = None
    if args.out:
        save_floor_calibration(args.out, calibration)
        board_ground = board_outline_m(pattern, args.square_m, placement)
        grid = birdseye_grid_around_board(calibration, board_ground)
        view = birdseye_image(image, build_birdseye_map(calibration, grid, max_range_m=1e6))
        draw_board_frame(view, grid, placement, args.square_m)
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
        "board_origin_px": list(calibration.board_origin_px or ()) or None,
        "board_origin_m": [placement.x_m, placement.y_m],
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
        if calibration.board_origin_px is not None:
            u, v = calibration.board_origin_px
            print(
                f"board origin (inner corner nearest the camera, on its right) at pixel "
                f"({u:.1f}, {v:.1f}) = robot ({placement.x_m:.3f}, {placement.y_m:.3f}) m"
            )
        if intrinsics is not None:
            print("H applies to undistorted pixels (the intrinsics are stored with it)")
        if args.out:
            print(f"written to {args.out} and {birdseye_path}")
    return 0


def _run(func: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """Turn the errors a user can cause (bad input, unreadable or missing files) into
    one line on stderr and exit code 1."""

    def wrapped(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except (ValueError, OSError) as exc:  # CalibrationError and ImageError included
            print(f"floornav calibrate {args.calibrate_kind}: {exc}", file=sys.stderr)
            return 1

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
    p.add_argument(
        "--board-x-m",
        type=float,
        default=0.0,
        help="robot x of the board origin: the inner corner nearest the camera, on its right",
    )
    p.add_argument("--board-y-m", type=float, default=0.0, help="robot y of the board origin")
    p.add_argument(
        "--board-yaw-rad",
        type=float,
        default=0.0,
        help="angle from the robot's x to the board's x (its rows away from the camera)",
    )
    p.add_argument("--out", type=Path, help="write the floor calibration JSON (+ .birdseye.png)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run(cmd_floor))
