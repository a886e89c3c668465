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

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

MIN_CALIBRATION_IMAGES = 3
_FULL_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
_FIND_FLAGS = _FULL_FLAGS | cv2.CALIB_CB_FAST_CHECK
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


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
    if image.ndim == 2:
        return image
    return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)


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
    the board is not found.
    """
    gray = _gray(image)
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=_FIND_FLAGS)
    if not found:
        # FAST_CHECK quickly rejects images without a board but misses some small,
        # steeply viewed boards: look once more without it.
        found, corners = cv2.findChessboardCorners(gray, pattern, flags=_FULL_FLAGS)
    if not found or corners is None:
        return None
    # The refinement window scales with the board's square size in the image.
    spacing = float(np.median(np.linalg.norm(np.diff(corners.reshape(-1, 2), axis=0), axis=1)))
    half = int(np.clip(spacing / 4.0, 3, 11))
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
        out = cv2.undistortPoints(pts, self.camera_matrix, self.dist, P=self.camera_matrix)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def distort_points(self, points_px: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 2) undistorted pixels -> (N, 2) pixels as the lens images them."""
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
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
    """Where the floor board's frame lies in the robot frame: its first inner corner at
    (x_m, y_m), its +x axis turned by yaw_rad from the robot's +x."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0

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
        with ``intrinsics`` first when they are given) to (x, y, 1) in the robot frame
    image_size : (width, height)
    intrinsics : Intrinsics or None
    reprojection_rms_px : float, ground points projected into the image vs measured
    ground_rms_m : float, measured image points mapped to the ground vs true positions
    points : int, point pairs given; inliers : int, pairs kept
    """

    H_ground_from_image: NDArray[np.float64]
    image_size: tuple[int, int]
    intrinsics: Intrinsics | None
    reprojection_rms_px: float
    ground_rms_m: float
    points: int
    inliers: int

    @property
    def H_image_from_ground(self) -> NDArray[np.float64]:
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


def apply_homography(
    H: NDArray[np.float64], points: NDArray[np.floating], *, require_positive_w: bool = False
) -> NDArray[np.float64]:
    """(N, 2) points through a 3x3 homography; with ``require_positive_w`` the points on
    the far side of the horizon (w <= 0, normalised so w > 0 means in front) are NaN."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    homogeneous = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    w = homogeneous[:, 2]
    out = homogeneous[:, :2] / np.where(np.abs(w) < 1e-12, np.nan, w)[:, None]
    if require_positive_w:
        out[w <= 0] = np.nan
    return out


def _normalise_sign(
    H: NDArray[np.float64], image_points: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Scale H so that w > 0 for the measured floor points (they are in front)."""
    w = np.column_stack([image_points, np.ones(len(image_points))]) @ H[2]
    scale = 1.0 / H[2, 2] if abs(H[2, 2]) > 1e-12 else 1.0
    if np.median(w) * scale < 0:
        scale = -scale
    return H * scale


def _check_spread(points: NDArray[np.float64], name: str) -> None:
    if len(points) < 4:
        raise CalibrationError(f"{name}: at least 4 points are needed, got {len(points)}")
    if not np.isfinite(points).all():
        raise CalibrationError(f"{name}: points contain NaN or infinity")
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if singular[0] <= 0 or singular[1] / singular[0] < 1e-3:
        raise CalibrationError(f"{name}: points are (nearly) collinear")


def _check_horizon(H: NDArray[np.float64], image_size: tuple[int, int]) -> None:
    """The image's bottom corners must see the floor in front of the camera."""
    width, height = image_size
    bottom = np.array([[0.0, height - 1.0], [width - 1.0, height - 1.0]])
    w = np.column_stack([bottom, np.ones(2)]) @ H[2]
    if not (w > 0).all():
        raise CalibrationError(
            "the homography puts the horizon below the image bottom (the bottom row would "
            "not be floor in front of the camera): check the point pairs"
        )


def _fit_report(
    H_ground_from_image: NDArray[np.float64],
    image_pts: NDArray[np.float64],
    ground_pts: NDArray[np.float64],
) -> tuple[float, float]:
    mapped = apply_homography(H_ground_from_image, image_pts)
    ground_rms = float(np.sqrt(((mapped - ground_pts) ** 2).sum(axis=1).mean()))
    projected = apply_homography(
        np.asarray(np.linalg.inv(H_ground_from_image), dtype=np.float64), ground_pts
    )
    reprojection_rms = float(np.sqrt(((projected - image_pts) ** 2).sum(axis=1).mean()))
    return reprojection_rms, ground_rms


def homography_from_point_pairs(
    image_points_px: NDArray[np.floating],
    ground_points_m: NDArray[np.floating],
    image_size: tuple[int, int],
    *,
    intrinsics: Intrinsics | None = None,
    ransac_threshold_px: float | None = None,
) -> FloorCalibration:
    """``H_ground_from_image`` from N >= 4 image points with known ground positions.

    Parameters
    ----------
    image_points_px : (N, 2) raw pixels (undistorted here when ``intrinsics`` are given)
    ground_points_m : (N, 2) robot-frame metres
    image_size : (width, height) of the images the homography is for
    ransac_threshold_px : reject pairs farther than this from the RANSAC model before
        the least-squares fit (None: use every pair, the manual path)

    Raises
    ------
    CalibrationError
        Fewer than 4 pairs, mismatched counts, NaNs, collinear points, or a result that
        puts the horizon below the image bottom.
    """
    image_pts = np.asarray(image_points_px, dtype=np.float64).reshape(-1, 2)
    ground_pts = np.asarray(ground_points_m, dtype=np.float64).reshape(-1, 2)
    if len(image_pts) != len(ground_pts):
        raise CalibrationError(f"{len(image_pts)} image points but {len(ground_pts)} ground points")
    _check_spread(image_pts, "image points")
    _check_spread(ground_pts, "ground points")
    if intrinsics is not None:
        image_pts = intrinsics.undistort_points(image_pts)
    inliers = np.ones(len(image_pts), dtype=bool)
    if ransac_threshold_px is not None and len(image_pts) > 4:
        # RANSAC on ground -> image so the threshold is in pixels, where the noise is.
        _, mask = cv2.findHomography(ground_pts, image_pts, cv2.RANSAC, ransac_threshold_px)
        if mask is not None and int(mask.sum()) >= 4:
            inliers = mask.ravel().astype(bool)
    H_image_from_ground, _ = cv2.findHomography(ground_pts[inliers], image_pts[inliers], 0)
    if H_image_from_ground is None:
        raise CalibrationError("no homography fits these points (degenerate configuration)")
    H = _normalise_sign(np.linalg.inv(np.asarray(H_image_from_ground, dtype=np.float64)), image_pts)
    if not np.isfinite(H).all():
        raise CalibrationError("the homography is not finite (degenerate configuration)")
    _check_horizon(H, image_size)
    reprojection_rms, ground_rms = _fit_report(H, image_pts[inliers], ground_pts[inliers])
    return FloorCalibration(
        H_ground_from_image=H,
        image_size=image_size,
        intrinsics=intrinsics,
        reprojection_rms_px=reprojection_rms,
        ground_rms_m=ground_rms,
        points=len(image_pts),
        inliers=int(inliers.sum()),
    )


def canonical_board_corners(
    corners_px: NDArray[np.floating], pattern: tuple[int, int]
) -> NDArray[np.float64]:
    """Reorder detected corners into a (rows', cols', 2) grid whose first index runs away
    from the camera (up the image) and whose second index runs to the left, whatever
    corner OpenCV started from. For a square board rows and columns may swap."""
    cols, rows = pattern
    grid = np.asarray(corners_px, dtype=np.float64).reshape(rows, cols, 2)
    step_first = (grid[1:, :, :] - grid[:-1, :, :]).mean(axis=(0, 1))
    step_second = (grid[:, 1:, :] - grid[:, :-1, :]).mean(axis=(0, 1))
    # The axis whose step is more vertical in the image becomes "away" (+x).
    if abs(step_second[1]) > abs(step_first[1]):
        grid = grid.transpose(1, 0, 2)
        step_first, step_second = step_second, step_first
    if step_first[1] > 0:  # +x must go up the image (v decreasing)
        grid = grid[::-1, :, :]
    if step_second[0] > 0:  # +y must go left in the image (u decreasing)
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

    Raises
    ------
    CalibrationError
        The board is not found, the square size is not positive, the intrinsics belong to
        another image size, or the fit is degenerate.
    """
    if square_m <= 0 or not math.isfinite(square_m):
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
            f"chessboard with {pattern[0]}x{pattern[1]} inner corners not found in the image"
        )
    grid = canonical_board_corners(corners, pattern)
    n_away, n_left = grid.shape[:2]
    board_xy = np.stack(
        np.meshgrid(np.arange(n_away) * square_m, np.arange(n_left) * square_m, indexing="ij"),
        axis=-1,
    ).reshape(-1, 2)
    ground = (placement or BoardPlacement()).to_robot(board_xy)
    return homography_from_point_pairs(
        grid.reshape(-1, 2),
        ground,
        (width, height),
        intrinsics=intrinsics,
        ransac_threshold_px=ransac_threshold_px,
    )
