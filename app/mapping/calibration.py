"""Camera calibration from chessboard photos, and the floor homography.

Intrinsics: OpenCV's chessboard detector with sub-pixel refinement (the sector-based
``findChessboardCornersSB`` as a fallback) and ``cv2.calibrateCamera`` (Zhang's method).
Images of another size than the majority (portrait phone photos among landscape ones) are
rejected with a reason naming both sizes, not rotated: which way to rotate them back is not
known, and the wrong way moves the principal point.

Floor homography ``H_ground_from_image``: from a chessboard lying on the floor, using every
detected inner corner (RANSAC in pixels to drop outliers, then a least-squares refit on the
inliers), optionally on undistorted corners; or from four or more hand-picked point pairs
(the dashboard's calibration wizard). With intrinsics, H applies to *undistorted* pixels
(same camera matrix, no distortion); `FloorCalibration` carries the intrinsics and its
methods undistort raw pixels first. H is scaled so that w (its third row times
(u, v, 1)) is > 0 for pixels below the horizon, i.e. floor in front of the camera.

Frames follow `app.mapping.frames`: ground = robot frame, metres, x forward, y left.
The board's own frame is fixed by geometry, not by OpenCV's detection order: +x runs along
the board's grid axis closest to the camera's viewing direction (the direction in which
the corners' camera depth grows: away from the camera), +y to the left seen from above,
and the origin is the inner corner nearest to the camera on its right. Corner (a, b) lies
at (a * square, b * square). `BoardPlacement` puts that frame into the robot frame.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

MIN_CALIBRATION_IMAGES = 3
_FULL_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
_FIND_FLAGS = _FULL_FLAGS | cv2.CALIB_CB_FAST_CHECK
_SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
# Iterative undistortion to 1e-10: OpenCV's default (5 iterations) is off by up to 0.16 px
# in the corners of a strongly distorted image.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-10)
_DIST_LENGTHS = (4, 5, 8, 12, 14)


class CalibrationError(ValueError):
    """Calibration input that cannot give a trustworthy result; the message says why."""


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): inner corners per row (columns) and per column (rows)."""
    try:
        cols_text, rows_text = text.lower().split("x")
        cols, rows = int(cols_text), int(rows_text)
    except ValueError as exc:
        raise CalibrationError(
            f"pattern must look like COLSxROWS (e.g. 9x6), got {text!r}"
        ) from exc
    if cols < 2 or rows < 2:
        raise CalibrationError(f"pattern needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def _gray(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or min(image.shape[:2]) < 8:
        raise CalibrationError(
            f"image: expected (H, W) or (H, W, 3) uint8 of at least 8x8 px, got "
            f"{image.dtype} {image.shape}"
        )
    if image.ndim == 2:
        return image
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)


DETECT_MAX_SIDE_PX = 2000
"""Chessboards are searched on a copy no longer than this (a board of 4+ squares still
spans hundreds of pixels), then refined on the full image."""


def find_chessboard(
    image: NDArray[np.uint8], pattern: tuple[int, int]
) -> NDArray[np.float32] | None:
    """Inner corners of a chessboard with sub-pixel refinement.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    pattern : (cols, rows) inner corners

    Returns
    -------
    (rows * cols, 2) float32 pixel coordinates in OpenCV's row-major order, or None when
    the board is not found. Which corner comes first depends on the view; see
    `canonical_board_corners`.
    """
    gray = _gray(image)
    # The detectors' time and memory grow with the image (a 36 MP photo took 80 s and
    # 7.6 GB): search a copy of at most DETECT_MAX_SIDE_PX, refine at full resolution.
    scale = min(1.0, DETECT_MAX_SIDE_PX / max(gray.shape))
    small = (
        gray
        if scale == 1.0
        else np.asarray(
            cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA), np.uint8
        )
    )
    found, corners = cv2.findChessboardCorners(small, pattern, flags=_FIND_FLAGS)
    if not found:
        # FAST_CHECK quickly rejects images without a board but misses some small,
        # steeply viewed boards: look once more without it.
        found, corners = cv2.findChessboardCorners(small, pattern, flags=_FULL_FLAGS)
    if not found or corners is None:
        # Last resort, slower (about 1 s at 1600x1200): the sector-based detector, which
        # copes with blur and uneven light and returns sub-pixel corners itself.
        found, corners = cv2.findChessboardCornersSB(small, pattern, flags=_SB_FLAGS)
        if not found or corners is None:
            return None
        if scale == 1.0:
            return np.asarray(corners, dtype=np.float32).reshape(-1, 2)
    corners = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2) / scale
    # The refinement window scales with the board's square size in the image.
    spacing = float(np.median(np.linalg.norm(np.diff(corners.reshape(-1, 2), axis=0), axis=1)))
    half = int(np.clip(spacing / 4.0, 3, 11 / scale))
    refined = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return np.asarray(refined, dtype=np.float32).reshape(-1, 2)


def board_points(pattern: tuple[int, int], square_m: float) -> NDArray[np.float32]:
    """(rows * cols, 3) float32 board coordinates of the inner corners in OpenCV's order
    (x along a row, y down the rows, z = 0)."""
    cols, rows = pattern
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera with OpenCV's distortion model.

    Attributes
    ----------
    camera_matrix : (3, 3) float64
    dist : (k,) float64, OpenCV order (k1, k2, p1, p2, k3, ...)
    image_size : (width, height) in pixels the calibration belongs to
    rms_px : float, RMS reprojection error of the calibration
    """

    camera_matrix: NDArray[np.float64]
    dist: NDArray[np.float64]
    image_size: tuple[int, int]
    rms_px: float = float("nan")

    def __post_init__(self) -> None:
        matrix = np.asarray(self.camera_matrix, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
            raise CalibrationError(f"camera matrix must be a finite 3x3 matrix, got {matrix}")
        if not (matrix[0, 0] > 0 and matrix[1, 1] > 0) or not np.allclose(
            matrix[2], (0.0, 0.0, 1.0)
        ):
            raise CalibrationError(
                f"camera matrix must look like [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with "
                f"fx, fy > 0, got {matrix.tolist()}"
            )
        if dist.size not in _DIST_LENGTHS or not np.isfinite(dist).all():
            raise CalibrationError(
                f"distortion must be {', '.join(map(str, _DIST_LENGTHS))} finite "
                f"coefficients, got {dist.size}: {dist.tolist()}"
            )
        size = tuple(int(v) for v in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise CalibrationError(f"image size must be (width, height) > 0, got {size}")
        object.__setattr__(self, "camera_matrix", matrix)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", size)

    @property
    def fx_px(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy_px(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx_px(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy_px(self) -> float:
        return float(self.camera_matrix[1, 2])

    def undistort_points(self, points_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) distorted pixels -> (N, 2) undistorted pixels (same camera matrix)."""
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.empty((0, 2), dtype=np.float64)
        out = cv2.undistortPoints(
            pts, self.camera_matrix, self.dist, P=self.camera_matrix, criteria=_UNDISTORT_CRITERIA
        )
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def distort_points(self, points_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) undistorted pixels -> (N, 2) pixels as the lens images them."""
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return np.empty((0, 2), dtype=np.float64)
        k_inv = np.linalg.inv(self.camera_matrix)
        rays = np.column_stack([pts, np.ones(len(pts))]) @ k_inv.T
        projected, _ = cv2.projectPoints(
            rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.camera_matrix, self.dist
        )
        return np.asarray(projected, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class IntrinsicsCalibration:
    """Result of `calibrate_intrinsics`: the model, and what each image contributed."""

    intrinsics: Intrinsics
    per_image_rms_px: dict[str, float]
    used: list[str]
    rejected: list[tuple[str, str]] = field(default_factory=list)


def calibrate_intrinsics(
    images: Sequence[tuple[str, NDArray[np.uint8]]],
    pattern: tuple[int, int],
    square_m: float,
) -> IntrinsicsCalibration:
    """Calibrate a camera from chessboard photos.

    Parameters
    ----------
    images : (name, image) pairs; image (H, W) or (H, W, 3) uint8
    pattern : (cols, rows) inner corners
    square_m : board square size in metres (scales the extrinsics only; the intrinsics
        do not depend on it)

    Returns
    -------
    IntrinsicsCalibration. Images whose size differs from the most common one (for
    example portrait phone photos among landscape ones: a rotated picture is a different
    camera model) and images where the board is not found are listed in ``rejected``
    with the reason.

    Raises
    ------
    CalibrationError
        Fewer than three usable images, or a non-positive square size.
    """
    if square_m <= 0 or not math.isfinite(square_m):
        raise CalibrationError(f"square size must be a positive number of metres, got {square_m}")
    if not images:
        raise CalibrationError("no images given")
    sizes = [(img.shape[1], img.shape[0]) for _, img in images]
    size = max(set(sizes), key=sizes.count)
    rejected: list[tuple[str, str]] = []
    object_points: list[NDArray[np.float32]] = []
    image_points: list[NDArray[np.float32]] = []
    used: list[str] = []
    board = board_points(pattern, square_m)
    for (name, image), image_size in zip(images, sizes, strict=True):
        if image_size != size:
            rejected.append(
                (
                    name,
                    f"image is {image_size[0]}x{image_size[1]} px but the calibration's size "
                    f"is {size[0]}x{size[1]} (rotated or from another camera)",
                )
            )
            continue
        corners = find_chessboard(image, pattern)
        if corners is None:
            rejected.append(
                (name, f"chessboard with {pattern[0]}x{pattern[1]} inner corners not found")
            )
            continue
        object_points.append(board)
        image_points.append(corners.reshape(-1, 1, 2))
        used.append(name)
    if len(used) < MIN_CALIBRATION_IMAGES:
        raise CalibrationError(
            f"only {len(used)} usable image(s); at least {MIN_CALIBRATION_IMAGES} are needed "
            f"(rejected: {'; '.join(f'{n}: {r}' for n, r in rejected) or 'none'})"
        )
    rms, camera_matrix, dist, rvecs, tvecs = cv2.calibrateCamera(
        object_points, image_points, size, None, None
    )
    per_image: dict[str, float] = {}
    for name, obj, img, rvec, tvec in zip(
        used, object_points, image_points, rvecs, tvecs, strict=True
    ):
        projected, _ = cv2.projectPoints(obj, rvec, tvec, camera_matrix, dist)
        err = np.asarray(projected).reshape(-1, 2) - img.reshape(-1, 2)
        per_image[name] = float(np.sqrt((err**2).sum(axis=1).mean()))
    intrinsics = Intrinsics(
        camera_matrix=np.asarray(camera_matrix, dtype=np.float64),
        dist=np.asarray(dist, dtype=np.float64).ravel(),
        image_size=(int(size[0]), int(size[1])),
        rms_px=float(rms),
    )
    return IntrinsicsCalibration(intrinsics, per_image, used, rejected)


# -- floor homography ---------------------------------------------------------------------


@dataclass(frozen=True)
class BoardPlacement:
    """Where the floor board's frame lies in the robot frame: its origin (the inner corner
    nearest to the camera on its right) at (x_m, y_m), its +x axis (the grid axis that runs
    away from the camera) turned by yaw_rad from the robot's +x. Keep |yaw| < 45 deg: +x
    is by definition the board axis closest to the viewing direction."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x_m", "y_m", "yaw_rad"):
            if not math.isfinite(getattr(self, name)):
                raise CalibrationError(f"board placement {name} must be finite")

    def to_robot(self, board_xy: NDArray[np.floating]) -> NDArray[np.float64]:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        pts = np.asarray(board_xy, dtype=np.float64)
        return np.column_stack(
            (c * pts[:, 0] - s * pts[:, 1] + self.x_m, s * pts[:, 0] + c * pts[:, 1] + self.y_m)
        )


@dataclass(frozen=True)
class FloorCalibration:
    """The floor homography and how well it fits.

    Attributes
    ----------
    H_ground_from_image : (3, 3) float64; maps (u, v, 1) of a floor pixel (undistorted
        with ``intrinsics`` first when they are given) to (x, y, 1) in the robot frame;
        scaled so that w > 0 below the horizon
    image_size : (width, height)
    intrinsics : Intrinsics or None
    reprojection_rms_px : float, ground points projected into the raw image (through the
        inverse homography and the lens distortion) vs the measured pixels, over inliers
    ground_rms_m : float, measured image points mapped to the ground vs true positions,
        over inliers
    points : int, point pairs given; inliers : int, pairs kept
    board_origin_px : (u, v) raw pixel of the board's origin corner (chessboard path only)
    """

    H_ground_from_image: NDArray[np.float64]
    image_size: tuple[int, int]
    intrinsics: Intrinsics | None
    reprojection_rms_px: float
    ground_rms_m: float
    points: int
    inliers: int
    board_origin_px: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        H = np.asarray(self.H_ground_from_image, dtype=np.float64)
        if H.shape != (3, 3) or not np.isfinite(H).all():
            raise CalibrationError("H_ground_from_image must be a finite 3x3 matrix")
        norm = float(np.linalg.norm(H))
        if norm == 0.0 or abs(np.linalg.det(H / norm)) < 1e-15:
            raise CalibrationError("H_ground_from_image is singular")
        size = tuple(int(v) for v in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise CalibrationError(f"image size must be (width, height) > 0, got {size}")
        if self.intrinsics is not None and self.intrinsics.image_size != size:
            raise CalibrationError(
                f"the intrinsics are for {_size_text(self.intrinsics.image_size)} images but "
                f"the floor calibration for {_size_text(size)}"
            )
        object.__setattr__(self, "H_ground_from_image", H)
        object.__setattr__(self, "image_size", size)

    @property
    def H_image_from_ground(self) -> NDArray[np.float64]:
        """Ground -> undistorted pixels; w > 0 for floor points in front of the camera."""
        return np.asarray(np.linalg.inv(self.H_ground_from_image), dtype=np.float64)

    def image_to_ground(self, points_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) raw image pixels -> (N, 2) robot-frame metres (NaN above the horizon)."""
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        if self.intrinsics is not None:
            pts = self.intrinsics.undistort_points(pts)
        return apply_homography(self.H_ground_from_image, pts, require_positive_w=True)

    def ground_to_image(self, points_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) robot-frame metres -> (N, 2) raw image pixels (NaN behind the camera)."""
        pts = apply_homography(self.H_image_from_ground, points_m, require_positive_w=True)
        if self.intrinsics is not None:
            finite = np.isfinite(pts).all(axis=1)
            pts[finite] = self.intrinsics.distort_points(pts[finite])
        return pts


def _size_text(size: Sequence[int]) -> str:
    return f"{size[0]}x{size[1]} px"


def apply_homography(
    H: NDArray[np.float64], points: NDArray[np.floating], *, require_positive_w: bool = False
) -> NDArray[np.float64]:
    """(N, 2) points through a 3x3 homography; with ``require_positive_w`` the points on
    the far side of the horizon (w <= 0, normalised so w > 0 means in front) are NaN."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    homogeneous = np.column_stack([pts, np.ones(len(pts))]) @ np.asarray(H, np.float64).T
    w = homogeneous[:, 2]
    out = homogeneous[:, :2] / np.where(np.abs(w) < 1e-12, np.nan, w)[:, None]
    if require_positive_w:
        out[w <= 0] = np.nan
    return out


def homography_w(H: NDArray[np.float64], points: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N,) third homogeneous coordinate of H (p, 1): for a `FloorCalibration`'s H > 0
    below the horizon, < 0 above it, 0 on it."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return np.asarray(pts @ H[2, :2] + H[2, 2], dtype=np.float64)


def _normalise_sign(
    H: NDArray[np.float64], image_points: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Scale H so that |H[2, 2]| = 1 (if possible) and w > 0 at the measured floor points.

    Raises `CalibrationError` if the points lie on both sides of the fitted horizon:
    a camera sees every floor point in front of it, so such pairs are inconsistent.
    """
    scale = 1.0 / abs(H[2, 2]) if abs(H[2, 2]) > 1e-9 * np.abs(H).max() else 1.0
    H = H * scale
    w = homography_w(H, image_points)
    if np.median(w) < 0:
        H, w = -H, -w
    if not (w > 0).all():
        raise CalibrationError(
            f"the point pairs are inconsistent: {int((w <= 0).sum())} of {len(w)} lie beyond "
            "the horizon the others imply (is each image point paired with its own ground "
            "point?)"
        )
    return H


def _check_spread(points: NDArray[np.float64], name: str) -> None:
    if len(points) < 4:
        raise CalibrationError(f"{name}: at least 4 points are needed, got {len(points)}")
    if not np.isfinite(points).all():
        raise CalibrationError(f"{name}: points contain NaN or infinity")
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if singular[0] <= 0 or singular[1] / singular[0] < 1e-3:
        raise CalibrationError(f"{name}: points are (nearly) collinear or coincide")
    if len(points) == 4:
        # Four points fix a homography only if no three of them are on a line.
        scale = float(singular[0]) ** 2
        for a, b, c in itertools.combinations(range(4), 3):
            (u1, v1), (u2, v2) = points[b] - points[a], points[c] - points[a]
            if abs(u1 * v2 - u2 * v1) < 1e-4 * scale:
                raise CalibrationError(
                    f"{name}: points {a}, {b} and {c} are (nearly) collinear; 4 pairs need "
                    "no three on a line"
                )


def _check_horizon(
    H: NDArray[np.float64], image_size: tuple[int, int], intrinsics: Intrinsics | None
) -> None:
    """Refuse a horizon below the image bottom: both bottom corners above the horizon
    means every image row is, so no pixel would see the floor in front of the camera.
    (A rolled camera may see the horizon cross the bottom edge; that is allowed.)"""
    width, height = image_size
    bottom = np.array([[0.0, height - 1.0], [width - 1.0, height - 1.0]])
    if intrinsics is not None:
        bottom = intrinsics.undistort_points(bottom)
    if not (homography_w(H, bottom) > 0).any():
        raise CalibrationError(
            "the homography puts the horizon below the image bottom (no image row would "
            "see floor in front of the camera): are near and far points swapped?"
        )


def _check_orientation(H: NDArray[np.float64]) -> None:
    """A camera above the floor sees it from above, where the image's (u right, v down)
    is left-handed and the robot's (x forward, y left) right-handed: with w > 0 on the
    floor, det(H) < 0 (the Jacobian of a homography is det(H) / w^3)."""
    if np.linalg.det(H) > 0:
        raise CalibrationError(
            "the ground points are mirrored relative to the image: the robot frame has "
            "x forward and y to the LEFT (were left and right swapped, or is the camera "
            "image mirrored?)"
        )


def _fit_report(
    H_ground_from_image: NDArray[np.float64],
    image_pts: NDArray[np.float64],
    ground_pts: NDArray[np.float64],
    *,
    raw_pts: NDArray[np.float64],
    intrinsics: Intrinsics | None,
) -> tuple[float, float]:
    """(reprojection RMS in raw pixels, ground RMS in metres); ``image_pts`` are the
    pixels H applies to, ``raw_pts`` the measured ones."""
    mapped = apply_homography(H_ground_from_image, image_pts)
    ground_rms = float(np.sqrt(((mapped - ground_pts) ** 2).sum(axis=1).mean()))
    projected = apply_homography(
        np.asarray(np.linalg.inv(H_ground_from_image), dtype=np.float64), ground_pts
    )
    if intrinsics is not None:
        projected = intrinsics.distort_points(projected)
    reprojection_rms = float(np.sqrt(((projected - raw_pts) ** 2).sum(axis=1).mean()))
    return reprojection_rms, ground_rms


def check_floor_calibration(calibration: FloorCalibration) -> None:
    """The physical sanity checks of a fitted homography, for one loaded from a file:
    some of the image bottom sees the floor in front of the camera, and the ground is
    not mirrored. Raises `CalibrationError`."""
    _check_horizon(calibration.H_ground_from_image, calibration.image_size, calibration.intrinsics)
    _check_orientation(calibration.H_ground_from_image)


def homography_from_point_pairs(
    image_points_px: NDArray[np.floating],
    ground_points_m: NDArray[np.floating],
    image_size: tuple[int, int],
    *,
    intrinsics: Intrinsics | None = None,
    ransac_threshold_px: float | None = None,
) -> FloorCalibration:
    """``H_ground_from_image`` from N >= 4 image points with known ground positions.

    The fit minimises the image-space error (where the measurement noise is): a DLT and
    Levenberg-Marquardt refinement of H_image_from_ground (``cv2.findHomography``),
    inverted. With exactly 4 pairs it is exact.

    Parameters
    ----------
    image_points_px : (N, 2) raw pixels (undistorted here when ``intrinsics`` are given)
    ground_points_m : (N, 2) robot-frame metres (x forward, y left)
    image_size : (width, height) of the images the homography is for
    intrinsics : lens model; H then applies to undistorted pixels
    ransac_threshold_px : reject pairs farther than this from the RANSAC model before
        the least-squares fit (None: use every pair, the manual path)

    Returns
    -------
    FloorCalibration, H scaled so that w > 0 below the horizon.

    Raises
    ------
    CalibrationError
        Fewer than 4 pairs, mismatched counts, NaNs, image points outside the image,
        collinear or repeated points, pairs on both sides of the fitted horizon, a
        result that puts the horizon below the image bottom, or mirrored ground points
        (y to the right).
    """
    image_pts = np.asarray(image_points_px, dtype=np.float64).reshape(-1, 2)
    ground_pts = np.asarray(ground_points_m, dtype=np.float64).reshape(-1, 2)
    if len(image_pts) != len(ground_pts):
        raise CalibrationError(f"{len(image_pts)} image points but {len(ground_pts)} ground points")
    _check_spread(image_pts, "image points")
    _check_spread(ground_pts, "ground points")
    width, height = image_size
    if intrinsics is not None and intrinsics.image_size != (width, height):
        raise CalibrationError(
            f"intrinsics are for {_size_text(intrinsics.image_size)} images but the "
            f"homography for {_size_text(image_size)}"
        )
    outside = (
        (image_pts[:, 0] < -0.5)
        | (image_pts[:, 0] > width - 0.5)
        | (image_pts[:, 1] < -0.5)
        | (image_pts[:, 1] > height - 0.5)
    )
    if outside.any():
        u, v = image_pts[np.flatnonzero(outside)[0]]
        raise CalibrationError(
            f"image point ({u:.1f}, {v:.1f}) lies outside the {_size_text(image_size)} image"
        )
    raw_pts = image_pts
    if intrinsics is not None:
        image_pts = intrinsics.undistort_points(image_pts)
    inliers = np.ones(len(image_pts), dtype=bool)
    if ransac_threshold_px is not None and len(image_pts) > 4:
        # RANSAC on ground -> image so the threshold is in pixels, where the noise is.
        _, mask = cv2.findHomography(ground_pts, image_pts, cv2.RANSAC, ransac_threshold_px)
        if mask is not None and int(mask.sum()) >= 4:
            inliers = np.asarray(mask).ravel().astype(bool)
    H_image_from_ground, _ = cv2.findHomography(ground_pts[inliers], image_pts[inliers], 0)
    if H_image_from_ground is None:
        raise CalibrationError("no homography fits these points (degenerate configuration)")
    G = np.asarray(H_image_from_ground, dtype=np.float64)
    if not np.isfinite(G).all() or np.linalg.cond(G) > 1e12:
        raise CalibrationError("the homography is singular (degenerate configuration)")
    H = _normalise_sign(np.asarray(np.linalg.inv(G), np.float64), image_pts[inliers])
    _check_horizon(H, (width, height), intrinsics)
    _check_orientation(H)
    reprojection_rms, ground_rms = _fit_report(
        H,
        image_pts[inliers],
        ground_pts[inliers],
        raw_pts=raw_pts[inliers],
        intrinsics=intrinsics,
    )
    return FloorCalibration(
        H_ground_from_image=H,
        image_size=(width, height),
        intrinsics=intrinsics,
        reprojection_rms_px=reprojection_rms,
        ground_rms_m=ground_rms,
        points=len(image_pts),
        inliers=int(inliers.sum()),
    )


def _grid_homography(grid: NDArray[np.float64]) -> NDArray[np.float64]:
    """H_image_from_indices of an (n0, n1, 2) corner grid, scaled so w > 0 on the board
    (w is then proportional to each corner's depth along the camera axis)."""
    n0, n1 = grid.shape[:2]
    i0, i1 = np.meshgrid(np.arange(n0), np.arange(n1), indexing="ij")
    indices = np.column_stack([i0.ravel(), i1.ravel()]).astype(np.float64)
    found, _ = cv2.findHomography(indices, grid.reshape(-1, 2), 0)
    if found is None:
        raise CalibrationError("the detected corners do not form a planar grid")
    G = np.asarray(found, dtype=np.float64)
    if np.median(homography_w(G, indices)) < 0:
        G = -G
    return G


def canonical_board_corners(
    corners_px: NDArray[np.floating], pattern: tuple[int, int]
) -> NDArray[np.float64]:
    """Reorder detected corners into an (n_away, n_left, 2) grid, whatever corner OpenCV
    started from.

    The first index runs away from the camera: along the grid axis in which the corners'
    camera depth (the w of the board's homography) grows fastest; if the camera looks
    straight down (no depth change), along the axis that runs up the image. The second
    index runs to the left seen from above (chosen so the image-from-board homography
    keeps det < 0, see `_check_orientation`). Corner [0, 0] is the one nearest to the
    camera on its right. Rows and columns swap when the pattern lies the other way round.
    This holds for a rolled camera too (e.g. a landscape photo of a portrait scene).
    """
    cols, rows = pattern
    grid = np.asarray(corners_px, dtype=np.float64).reshape(rows, cols, 2)
    G = _grid_homography(grid)
    gradient = G[2, :2]  # depth change per index step along each grid axis
    mean_w = float(np.median(homography_w(G, np.array([[(rows - 1) / 2, (cols - 1) / 2]]))))
    if float(np.abs(gradient).max()) * max(rows, cols) > 1e-3 * abs(mean_w):
        away_axis = int(np.argmax(np.abs(gradient)))
        away_positive = bool(gradient[away_axis] > 0)
    else:  # looking straight down: away = up the image
        steps = [
            (grid[1:, :, :] - grid[:-1, :, :]).mean(axis=(0, 1)),
            (grid[:, 1:, :] - grid[:, :-1, :]).mean(axis=(0, 1)),
        ]
        ups = [-step[1] / (np.linalg.norm(step) + 1e-12) for step in steps]
        away_axis = int(np.argmax(np.abs(ups)))
        away_positive = bool(ups[away_axis] > 0)
    if away_axis == 1:
        grid = grid.transpose(1, 0, 2)
    if not away_positive:
        grid = grid[::-1, :, :]
    if np.linalg.det(_grid_homography(grid)) > 0:
        grid = grid[:, ::-1, :]
    return np.ascontiguousarray(grid)


def floor_homography_from_chessboard(
    image: NDArray[np.uint8],
    pattern: tuple[int, int],
    square_m: float,
    *,
    intrinsics: Intrinsics | None = None,
    placement: BoardPlacement | None = None,
    ransac_threshold_px: float = 2.0,
) -> FloorCalibration:
    """``H_ground_from_image`` from a chessboard lying on the floor (all inner corners).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    pattern : (cols, rows) inner corners; square_m : square side in metres
    intrinsics : lens model for this image size; corners are undistorted first and H
        applies to undistorted pixels
    placement : the board frame (see the module docstring) in the robot frame; default:
        the board frame itself
    ransac_threshold_px : RANSAC inlier threshold before the least-squares refit

    Returns
    -------
    FloorCalibration with ``board_origin_px`` set.

    Raises
    ------
    CalibrationError
        The board is not found, the square size is not positive, the intrinsics belong to
        another image size, or the fit is degenerate or fails a sanity check of
        `homography_from_point_pairs`.
    """
    if not (square_m > 0 and math.isfinite(square_m)):
        raise CalibrationError(f"square size must be a positive number of metres, got {square_m}")
    height, width = image.shape[:2]
    if intrinsics is not None and intrinsics.image_size != (width, height):
        raise CalibrationError(
            f"intrinsics are for {intrinsics.image_size[0]}x{intrinsics.image_size[1]} px "
            f"images but this image is {width}x{height} px"
        )
    corners = find_chessboard(image, pattern)
    if corners is None:
        raise CalibrationError(
            f"chessboard with {pattern[0]}x{pattern[1]} inner corners not found in the "
            f"{width}x{height} px image (whole board visible? --pattern counts inner corners)"
        )
    grid = canonical_board_corners(corners, pattern)
    n_away, n_left = grid.shape[:2]
    board_xy = np.stack(
        np.meshgrid(np.arange(n_away) * square_m, np.arange(n_left) * square_m, indexing="ij"),
        axis=-1,
    ).reshape(-1, 2)
    ground = (placement or BoardPlacement()).to_robot(board_xy)
    calibration = homography_from_point_pairs(
        grid.reshape(-1, 2),
        ground,
        (width, height),
        intrinsics=intrinsics,
        ransac_threshold_px=ransac_threshold_px,
    )
    origin = (float(grid[0, 0, 0]), float(grid[0, 0, 1]))
    return dataclasses.replace(calibration, board_origin_px=origin)
