"""An upright view: image columns along the world's verticals.

A camera pitched down at the floor sees vertical edges lean: they meet at the vertical
vanishing point far below the image, so a table leg near the image's side edge leans by
ten degrees or more. A column walk that looks for where something standing meets the
floor (`app.perception.planar.standing_feet`) then finds a "foot" in every column that
crosses the leaning edge, higher and higher up it, and each of those projects through
the floor homography to floor far behind the leg: a ray of false obstacles.

The upright view turns a virtual camera at the real one's centre so that the world's
up is its image's up (a pure rotation, `K R K^-1`): verticals are columns there, and a
column is still a ray along the ground (a level camera's rows are lines of constant
forward distance). The column walk runs in that view and its result is warped back.

The focal length comes from the floor homography itself when the camera's intrinsics are
not known: with the principal point at the image centre and square pixels, the two floor
axes must map to orthogonal camera rays of equal length (Zhang's constraints on one
homography).

Pure functions on numpy arrays. Frames: ``H_ground_from_image`` maps undistorted pixels
(u, v, 1) to the robot frame's floor (x forward, y left, z up, metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from app.perception.planar import FOOT_DEPTH_M, row_ground_distance_m, standing_feet

MAX_UPRIGHT_SCALE = 2.5
"""The upright view is at most this many times the image's width and height (a camera
looking almost straight down would need an unbounded one: then there is none)."""

BRIDGE_ROWS = 7
"""Vertical gaps in a standing column shorter than this are bridged in the upright view."""

_VERTICAL_BRIDGE = np.ones((BRIDGE_ROWS, 1), np.uint8)

MIN_LEAN_RAD = math.radians(0.5)
"""Below this tilt of the world's up from the image's up, columns are verticals already."""


@dataclass(frozen=True)
class UprightView:
    """The upright virtual camera of one calibration (`upright_view`).

    Attributes
    ----------
    H_upright_from_image : (3, 3) float64; maps (u, v, 1) of the image to the upright
        view's pixels.
    size : (width, height) of the upright view, which holds the whole image.
    row_distance_m : (height,) forward ground distance of each upright row (NaN at and
        above the horizon), as `app.perception.planar.row_ground_distance_m` gives for
        the image.
    tilt_rad : angle between the world's up and the image's up (the camera's pitch and
        roll together).
    """

    H_upright_from_image: NDArray[np.float64]
    size: tuple[int, int]
    row_distance_m: NDArray[np.float64]
    tilt_rad: float


def focal_from_floor_homography(
    H_ground_from_image: NDArray[np.float64], principal_point_px: tuple[float, float]
) -> float | None:
    """The focal length (pixels) that makes the floor's x and y axes orthogonal camera
    rays of equal length, for square pixels and the given principal point; None when
    the homography does not decide it (a camera looking straight down or level).

    Examples
    --------
    >>> f, pitch = 500.0, 0.4
    >>> K = np.array([[f, 0, 319.5], [0, f, 239.5], [0, 0, 1]])
    >>> r1 = [0.0, math.sin(pitch), math.cos(pitch)]  # floor x (forward), camera frame
    >>> r2 = [-1.0, 0.0, 0.0]  # floor y (left)
    >>> t = [0.0, 0.22 * math.cos(pitch), -0.22 * math.sin(pitch)]
    >>> H_image_from_ground = K @ np.column_stack([r1, r2, t])
    >>> round(focal_from_floor_homography(np.linalg.inv(H_image_from_ground), (319.5, 239.5)), 6)
    500.0
    """
    cx, cy = principal_point_px
    B = np.linalg.inv(np.asarray(H_ground_from_image, dtype=np.float64))
    B = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]]) @ B
    (p1, q1, s1), (p2, q2, s2) = B[:, 0], B[:, 1]
    # In w = 1 / f^2: w (p1 p2 + q1 q2) + s1 s2 = 0 and w (|pq1|^2 - |pq2|^2) + s1^2 - s2^2
    # = 0, solved together in the least-squares sense.
    a = np.array([p1 * p2 + q1 * q2, p1 * p1 + q1 * q1 - p2 * p2 - q2 * q2])
    b = -np.array([s1 * s2, s1 * s1 - s2 * s2])
    scale = float(a @ a)
    if scale <= 1e-12 * max(float(b @ b), 1e-300):
        return None
    w = float(a @ b) / scale
    if not (w > 0 and math.isfinite(w)):
        return None
    return 1.0 / math.sqrt(w)


def camera_matrix(focal_px: float, principal_point_px: tuple[float, float]) -> NDArray[np.float64]:
    """The pinhole camera matrix of square pixels."""
    cx, cy = principal_point_px
    return np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])


def upright_view(
    H_ground_from_image: NDArray[np.float64],
    image_size: tuple[int, int],
    K: NDArray[np.float64] | None = None,
) -> UprightView | None:
    """The upright virtual camera for a floor homography and image size (width, height).

    ``K`` is the camera matrix of the pixels the homography takes (undistorted); without
    it, square pixels, the principal point at the image centre and the focal length the
    homography implies (`focal_from_floor_homography`). None when the camera's up is
    already the image's up (within `MIN_LEAN_RAD`), when the focal length cannot be
    found, or when the view would exceed `MAX_UPRIGHT_SCALE` times the image."""
    width, height = image_size
    H = np.asarray(H_ground_from_image, dtype=np.float64)
    if K is None:
        principal = ((width - 1) / 2.0, (height - 1) / 2.0)
        focal = focal_from_floor_homography(H, principal)
        if focal is None:
            return None
        K = camera_matrix(focal, principal)
    K = np.asarray(K, dtype=np.float64)
    K_inv = np.linalg.inv(K)
    # The floor's axes in the camera frame: K^-1 H_image_from_ground = s [r1 r2 t].
    rays = K_inv @ np.linalg.inv(H)
    r1 = rays[:, 0] / np.linalg.norm(rays[:, 0])
    r2 = rays[:, 1] / np.linalg.norm(rays[:, 1])
    up_camera = np.cross(r1, r2)  # the floor's z (up); the scale's sign cancels
    up_camera /= np.linalg.norm(up_camera)
    image_up = np.array([0.0, -1.0, 0.0])  # camera y points down
    tilt = math.acos(float(np.clip(up_camera @ image_up, -1.0, 1.0)))
    if tilt < MIN_LEAN_RAD:
        return None
    axis = np.cross(up_camera, image_up)
    axis *= tilt / np.linalg.norm(axis)
    R_upright_from_camera, _ = cv2.Rodrigues(axis)
    H_rotate = K @ R_upright_from_camera @ K_inv
    corners = np.array(
        [[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]],
        dtype=np.float64,
    ).T
    moved = H_rotate @ corners
    if not (moved[2] > 0).all():
        return None  # a corner behind the virtual camera
    uv = moved[:2] / moved[2]
    lo = np.floor(uv.min(axis=1))
    hi = np.ceil(uv.max(axis=1))
    out_w, out_h = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    if out_w > MAX_UPRIGHT_SCALE * width or out_h > MAX_UPRIGHT_SCALE * height:
        return None
    shift = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    H_upright_from_image = shift @ H_rotate
    # Forward distance per upright row, on the column the image's centre goes to.
    centre = H_upright_from_image @ np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
    rows_m = row_ground_distance_m(
        H @ np.linalg.inv(H_upright_from_image), out_w, out_h, column_px=centre[0] / centre[2]
    )
    return UprightView(H_upright_from_image, (out_w, out_h), rows_m, tilt)


def to_upright(mask: NDArray[np.bool_], view: UprightView) -> NDArray[np.bool_]:
    """``mask`` (H, W) seen in the upright view (nearest pixel; False outside the image)."""
    warped = cv2.warpPerspective(
        mask.view(np.uint8) if mask.dtype == np.bool_ else mask.astype(np.uint8),
        view.H_upright_from_image,
        view.size,
        flags=cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return np.asarray(warped, dtype=np.bool_)


def from_upright(
    mask: NDArray[np.bool_], view: UprightView, image_size: tuple[int, int]
) -> NDArray[np.bool_]:
    """An upright view's ``mask`` back in the image of ``image_size`` (width, height): every
    pixel that touches it (bilinear weight above zero), so that a line one pixel thin
    stays unbroken."""
    warped = cv2.warpPerspective(
        mask.view(np.uint8) * np.uint8(255),
        view.H_upright_from_image,
        image_size,
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return np.asarray(warped > 0, dtype=np.bool_)


def upright_standing_feet(
    standing: NDArray[np.bool_],
    floor: NDArray[np.bool_],
    view: UprightView,
    foot_depth_m: float = FOOT_DEPTH_M,
) -> NDArray[np.bool_]:
    """`app.perception.planar.standing_feet` walked along the world's verticals: in the
    upright view, then back in the image. A leaning edge then has its foot where the
    thing meets the floor, not wherever a column crosses it. Returns a new (H, W) bool
    mask."""
    if standing.shape != floor.shape:
        raise ValueError(f"standing {standing.shape} and floor {floor.shape} must agree")
    standing_up = to_upright(np.ascontiguousarray(standing, dtype=np.bool_), view)
    # An edge that leant in the image is a column in the upright view, but a jagged one
    # (nearest pixels of a slanted line): bridging short vertical gaps keeps every
    # sliver of floor in that column from making a foot of the standing run above it.
    standing_up = np.asarray(
        cv2.morphologyEx(standing_up.view(np.uint8), cv2.MORPH_CLOSE, _VERTICAL_BRIDGE),
        dtype=np.bool_,
    )
    floor_up = to_upright(np.ascontiguousarray(floor, dtype=np.bool_), view) & ~standing_up
    feet = standing_feet(standing_up, floor_up, view.row_distance_m, foot_depth_m)
    height, width = standing.shape
    back = from_upright(feet, view, (width, height))
    # Only pixels the column walk may keep: the back-warp's nearest pixel can stray.
    return back & (standing | ~floor)
