"""Calibration files: small JSON documents written atomically (a temporary file renamed
over the target, so a crash never leaves half a file), and OpenCV's XML/YAML intrinsics
(``cv2.FileStorage``) accepted on input.

Every loader checks what it reads (shapes, finite numbers, a physically possible floor
homography) and, when the caller says which image size it will use, that the file was
made for that size; errors name the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.fileio import write_bytes_atomic
from app.mapping.calibration import (
    CalibrationError,
    FloorCalibration,
    Intrinsics,
    check_floor_calibration,
)

FORMAT_VERSION = 1
INTRINSICS_KIND = "floornav-intrinsics"
FLOOR_KIND = "floornav-floor-calibration"
_OPENCV_SUFFIXES = (".xml", ".yml", ".yaml")


def write_json_atomic(path: Path, document: dict[str, Any]) -> None:
    """Write ``document`` as JSON to ``path`` atomically (NaN is refused, not written)."""
    text = json.dumps(document, indent=2, allow_nan=False)
    write_bytes_atomic(path, (text + "\n").encode())


def _finite_or_none(value: float) -> float | None:
    return value if np.isfinite(value) else None


def intrinsics_document(intrinsics: Intrinsics) -> dict[str, Any]:
    return {
        "kind": INTRINSICS_KIND,
        "version": FORMAT_VERSION,
        "image_size_px": list(intrinsics.image_size),
        "camera_matrix": intrinsics.camera_matrix.tolist(),
        "dist": intrinsics.dist.tolist(),
        "rms_px": _finite_or_none(intrinsics.rms_px),
    }


def _intrinsics_from_document(doc: Any, source: Path) -> Intrinsics:
    try:
        matrix = np.array(doc["camera_matrix"], dtype=np.float64)
        dist = np.array(doc["dist"], dtype=np.float64).ravel()
        width, height = (int(v) for v in doc["image_size_px"])
        rms_value = doc.get("rms_px")
        rms = float("nan") if rms_value is None else float(rms_value)
        return Intrinsics(matrix, dist, (width, height), rms)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CalibrationError(f"{source}: not a floornav intrinsics file ({exc})") from exc


def _read_opencv_intrinsics(path: Path) -> Intrinsics:
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV 5 raises SystemError on a parse error
        raise CalibrationError(f"{path}: unreadable OpenCV calibration file ({exc})") from exc
    try:
        matrix = storage.getNode("camera_matrix").mat()
        dist = storage.getNode("distortion_coefficients").mat()
        width = storage.getNode("image_width").real()
        height = storage.getNode("image_height").real()
    finally:
        storage.release()
    if matrix is None or dist is None or not width or not height:
        raise CalibrationError(
            f"{path}: OpenCV file lacks camera_matrix, distortion_coefficients, "
            "image_width or image_height"
        )
    try:
        return Intrinsics(
            np.asarray(matrix, dtype=np.float64),
            np.asarray(dist, dtype=np.float64).ravel(),
            (int(width), int(height)),
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from exc


def load_intrinsics(path: Path, expected_size: tuple[int, int] | None = None) -> Intrinsics:
    """Read intrinsics from our JSON or OpenCV XML/YAML; check the image size if given.

    OpenCV files need ``camera_matrix``, ``distortion_coefficients``, ``image_width`` and
    ``image_height`` (the names ``cv2.FileStorage`` samples and the book use).

    Raises
    ------
    CalibrationError
        Missing, unreadable or malformed file, or a calibration for another image size
        (the message names both sizes).
    """
    if not path.is_file():
        raise CalibrationError(f"{path}: intrinsics file not found")
    if path.suffix.lower() in _OPENCV_SUFFIXES:
        intrinsics = _read_opencv_intrinsics(path)
    else:
        doc = _read_json(path)
        if doc.get("kind", INTRINSICS_KIND) != INTRINSICS_KIND:
            raise CalibrationError(
                f"{path}: not a floornav intrinsics file (kind {doc.get('kind')!r})"
            )
        intrinsics = _intrinsics_from_document(doc, path)
    _check_size(path, intrinsics.image_size, expected_size)
    return intrinsics


def save_intrinsics(path: Path, intrinsics: Intrinsics) -> None:
    """Write intrinsics JSON atomically (`load_intrinsics` reads it back)."""
    write_json_atomic(path, intrinsics_document(intrinsics))


def floor_document(calibration: FloorCalibration) -> dict[str, Any]:
    origin = calibration.board_origin_px
    return {
        "kind": FLOOR_KIND,
        "version": FORMAT_VERSION,
        "frames": "H_ground_from_image maps (u, v, 1) of a floor pixel to (x, y, 1) in the "
        "robot frame (metres, x forward, y left); w > 0 below the horizon",
        "pixels": "undistorted with intrinsics" if calibration.intrinsics else "raw",
        "image_size_px": list(calibration.image_size),
        "H_ground_from_image": calibration.H_ground_from_image.tolist(),
        "intrinsics": (
            intrinsics_document(calibration.intrinsics) if calibration.intrinsics else None
        ),
        "reprojection_rms_px": _finite_or_none(calibration.reprojection_rms_px),
        "ground_rms_m": _finite_or_none(calibration.ground_rms_m),
        "points": calibration.points,
        "inliers": calibration.inliers,
        "board_origin_px": None if origin is None else list(origin),
    }


def save_floor_calibration(path: Path, calibration: FloorCalibration) -> None:
    """Write the floor calibration JSON atomically (`load_floor_calibration` reads it)."""
    write_json_atomic(path, floor_document(calibration))


def _optional_float(doc: dict[str, Any], key: str) -> float:
    value = doc.get(key)
    return float("nan") if value is None else float(value)


def load_floor_calibration(
    path: Path, expected_size: tuple[int, int] | None = None
) -> FloorCalibration:
    """Read a floor calibration written by `save_floor_calibration`.

    Raises
    ------
    CalibrationError
        Missing, unreadable or malformed file, a homography that is singular, puts the
        horizon below the image bottom or mirrors the floor, or a calibration for another
        image size (the message names both sizes).
    """
    if not path.is_file():
        raise CalibrationError(f"{path}: floor calibration file not found")
    doc = _read_json(path)
    if doc.get("kind", FLOOR_KIND) != FLOOR_KIND:
        raise CalibrationError(
            f"{path}: not a floornav floor calibration (kind {doc.get('kind')!r})"
        )
    try:
        H = np.array(doc["H_ground_from_image"], dtype=np.float64)
        width, height = (int(v) for v in doc["image_size_px"])
        intrinsics_doc = doc.get("intrinsics")
        origin = doc.get("board_origin_px")
        calibration = FloorCalibration(
            H_ground_from_image=H,
            image_size=(width, height),
            intrinsics=(
                _intrinsics_from_document(intrinsics_doc, path) if intrinsics_doc else None
            ),
            reprojection_rms_px=_optional_float(doc, "reprojection_rms_px"),
            ground_rms_m=_optional_float(doc, "ground_rms_m"),
            points=int(doc.get("points", 0)),
            inliers=int(doc.get("inliers", 0)),
            board_origin_px=None if origin is None else (float(origin[0]), float(origin[1])),
        )
        check_floor_calibration(calibration)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CalibrationError(f"{path}: not a usable floornav floor calibration ({exc})") from exc
    _check_size(path, calibration.image_size, expected_size)
    return calibration


def _read_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: unreadable calibration file ({exc})") from exc
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: calibration file must hold a JSON object")
    return doc


def _check_size(path: Path, actual: tuple[int, int], expected: tuple[int, int] | None) -> None:
    if expected is not None and tuple(actual) != tuple(expected):
        raise CalibrationError(
            f"{path}: calibration is for {actual[0]}x{actual[1]} px images but it is used with "
            f"{expected[0]}x{expected[1]} px images"
        )
