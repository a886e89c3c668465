"""Calibration files: small JSON documents written atomically (a temporary file renamed
over the target, so a crash never leaves half a file), and OpenCV's XML/YAML intrinsics
(``cv2.FileStorage``) accepted on input."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.fileio import write_bytes_atomic
from app.mapping.calibration import CalibrationError, FloorCalibration, Intrinsics

FORMAT_VERSION = 1


def write_json_atomic(path: Path, document: dict[str, Any]) -> None:
    """Write ``document`` as JSON to ``path`` atomically."""
    write_bytes_atomic(path, (json.dumps(document, indent=2) + "\n").encode())


def intrinsics_document(intrinsics: Intrinsics) -> dict[str, Any]:
    return {
        "kind": "floornav-intrinsics",
        "version": FORMAT_VERSION,
        "image_size_px": list(intrinsics.image_size),
        "camera_matrix": intrinsics.camera_matrix.tolist(),
        "dist": intrinsics.dist.tolist(),
        "rms_px": intrinsics.rms_px,
    }


def _intrinsics_from_document(doc: dict[str, Any], source: Path) -> Intrinsics:
    try:
        matrix = np.array(doc["camera_matrix"], dtype=np.float64)
        dist = np.array(doc["dist"], dtype=np.float64).ravel()
        width, height = (int(v) for v in doc["image_size_px"])
        rms = float(doc.get("rms_px", float("nan")))
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{source}: not a floornav intrinsics file ({exc})") from exc
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all() or not np.isfinite(dist).all():
        raise CalibrationError(f"{source}: camera_matrix must be a finite 3x3 matrix")
    return Intrinsics(matrix, dist, (width, height), rms)


def _read_opencv_intrinsics(path: Path) -> Intrinsics:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
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
    return Intrinsics(
        np.asarray(matrix, dtype=np.float64),
        np.asarray(dist, dtype=np.float64).ravel(),
        (int(width), int(height)),
    )


def load_intrinsics(path: Path, expected_size: tuple[int, int] | None = None) -> Intrinsics:
    """Read intrinsics from our JSON or OpenCV XML/YAML; check the image size if given.

    Raises
    ------
    CalibrationError
        Missing or unreadable file, or a calibration for another image size.
    """
    if not path.is_file():
        raise CalibrationError(f"{path}: intrinsics file not found")
    if path.suffix.lower() in (".xml", ".yml", ".yaml"):
        intrinsics = _read_opencv_intrinsics(path)
    else:
        intrinsics = _intrinsics_from_document(_read_json(path), path)
    _check_size(path, intrinsics.image_size, expected_size)
    return intrinsics


def save_intrinsics(path: Path, intrinsics: Intrinsics) -> None:
    write_json_atomic(path, intrinsics_document(intrinsics))


def floor_document(calibration: FloorCalibration) -> dict[str, Any]:
    return {
        "kind": "floornav-floor-calibration",
        "version": FORMAT_VERSION,
        "image_size_px": list(calibration.image_size),
        "H_ground_from_image": calibration.H_ground_from_image.tolist(),
        "intrinsics": (
            intrinsics_document(calibration.intrinsics) if calibration.intrinsics else None
        ),
        "reprojection_rms_px": calibration.reprojection_rms_px,
        "ground_rms_m": calibration.ground_rms_m,
        "points": calibration.points,
        "inliers": calibration.inliers,
    }


def save_floor_calibration(path: Path, calibration: FloorCalibration) -> None:
    write_json_atomic(path, floor_document(calibration))


def load_floor_calibration(
    path: Path, expected_size: tuple[int, int] | None = None
) -> FloorCalibration:
    """Read a floor calibration written by `save_floor_calibration`.

    Raises
    ------
    CalibrationError
        Missing or malformed file, or a calibration for another image size.
    """
    if not path.is_file():
        raise CalibrationError(f"{path}: floor calibration file not found")
    doc = _read_json(path)
    try:
        H = np.array(doc["H_ground_from_image"], dtype=np.float64)
        width, height = (int(v) for v in doc["image_size_px"])
        intrinsics_doc = doc.get("intrinsics")
        calibration = FloorCalibration(
            H_ground_from_image=H,
            image_size=(width, height),
            intrinsics=(
                _intrinsics_from_document(intrinsics_doc, path) if intrinsics_doc else None
            ),
            reprojection_rms_px=float(doc.get("reprojection_rms_px", float("nan"))),
            ground_rms_m=float(doc.get("ground_rms_m", float("nan"))),
            points=int(doc.get("points", 0)),
            inliers=int(doc.get("inliers", 0)),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: not a floornav floor calibration ({exc})") from exc
    if H.shape != (3, 3) or not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-15:
        raise CalibrationError(f"{path}: H_ground_from_image must be a finite invertible 3x3")
    _check_size(path, calibration.image_size, expected_size)
    return calibration


def _read_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: unreadable calibration file ({exc})") from exc
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: calibration file must hold a JSON object")
    return doc


def _check_size(path: Path, actual: tuple[int, int], expected: tuple[int, int] | None) -> None:
    if expected is not None and tuple(actual) != tuple(expected):
        raise CalibrationError(
            f"{path}: calibration is for {actual[0]}x{actual[1]} px images but the camera "
            f"gives {expected[0]}x{expected[1]} px"
        )
