"""The upright view: image columns along the world's verticals (app.perception.upright)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.perception.planar import row_ground_distance_m, standing_feet
from app.perception.upright import (
    camera_matrix,
    focal_from_floor_homography,
    upright_standing_feet,
    upright_view,
)

WIDTH, HEIGHT = 640, 480
CENTRE = ((WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)


def camera(
    pitch_rad: float, roll_rad: float = 0.0, focal_px: float = 500.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(P_image_from_robot 3x4, H_ground_from_image) of a camera 0.22 m above the floor,
    0.1 m ahead of the robot's centre, pitched down and rolled."""
    level = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # x fwd -> z
    c, s = math.cos(pitch_rad), math.sin(pitch_rad)
    pitch = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R_camera_from_robot = roll @ pitch @ level
    t = -R_camera_from_robot @ np.array([0.1, 0.0, 0.22])
    K = camera_matrix(focal_px, CENTRE)
    P = K @ np.column_stack([R_camera_from_robot, t])
    H_image_from_ground = P[:, [0, 1, 3]]
    return P, np.linalg.inv(H_image_from_ground)


def project(P: NDArray[np.float64], points_m: NDArray[np.float64]) -> NDArray[np.float64]:
    homogeneous = np.column_stack([points_m, np.ones(len(points_m))]) @ P.T
    return np.asarray(homogeneous[:, :2] / homogeneous[:, 2:])


@pytest.mark.parametrize(("pitch", "roll", "focal"), [(0.4, 0.0, 500.0), (0.25, 0.08, 420.0)])
def test_the_focal_length_is_the_one_the_floor_homography_implies(
    pitch: float, roll: float, focal: float
) -> None:
    _, H = camera(pitch, roll, focal)
    found = focal_from_floor_homography(H, CENTRE)
    assert found == pytest.approx(focal, rel=1e-6)


@pytest.mark.parametrize(("pitch", "roll"), [(0.4, 0.0), (0.3, 0.1)])
def test_verticals_are_columns_of_the_upright_view(pitch: float, roll: float) -> None:
    P, H = camera(pitch, roll)
    view = upright_view(H, (WIDTH, HEIGHT))
    assert view is not None
    assert view.tilt_rad == pytest.approx(math.hypot(pitch, roll), abs=0.02)
    for x, y in [(1.0, 0.5), (1.5, -0.6), (0.8, 0.0)]:
        upright = cv2.perspectiveTransform(
            project(P, np.array([[x, y, 0.0], [x, y, 0.15]]))[None], view.H_upright_from_image
        )[0]
        assert upright[0, 0] == pytest.approx(upright[1, 0], abs=1e-6)  # one column
        assert upright[0, 1] > upright[1, 1]  # the foot below
        # The foot's row has the floor point's forward distance (between its two rows).
        rows = view.row_distance_m[[math.floor(upright[0, 1]), math.ceil(upright[0, 1])]]
        assert rows.min() * 0.98 <= x <= rows.max() * 1.02
    # The whole image is inside the view.
    corners = np.array([[[0, 0], [WIDTH - 1, 0], [0, HEIGHT - 1], [WIDTH - 1, HEIGHT - 1]]])
    moved = cv2.perspectiveTransform(corners.astype(np.float64), view.H_upright_from_image)[0]
    assert (moved >= -0.5).all() and (moved[:, 0] <= view.size[0] - 0.5).all()
    assert (moved[:, 1] <= view.size[1] - 0.5).all()


def test_a_level_camera_needs_no_upright_view() -> None:
    level = np.array(
        [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    )  # camera axes in the robot frame: right, down, forward
    K = camera_matrix(500.0, CENTRE)
    R = level.T
    t = -R @ np.array([0.1, 0.0, 0.22])
    H_image_from_ground = (K @ np.column_stack([R, t]))[:, [0, 1, 3]]
    assert upright_view(np.linalg.inv(H_image_from_ground), (WIDTH, HEIGHT), K) is None


def leaning_leg(
    pitch: float, roll: float = 0.0
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.float64], tuple[float, float]]:
    """A 4 cm table leg 0.4 m tall, 1 m ahead and 0.45 m to the left (where the image
    shows it leaning), as the standing mask, the floor around it and the homography."""
    P, H = camera(pitch, roll)
    base = (1.0, 0.45)
    half = (-0.02, 0.02)
    corners = [(base[0] + dx, base[1] + dy, z) for z in (0.0, 0.4) for dx in half for dy in half]
    pixels = project(P, np.array(corners, dtype=np.float64))
    standing = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.fillConvexPoly(standing, cv2.convexHull(pixels.astype(np.float32)).astype(np.int32), 1)
    standing_mask = standing.astype(bool)
    below_horizon = np.isfinite(row_ground_distance_m(H, WIDTH, HEIGHT))[:, None]
    floor = ~standing_mask & below_horizon
    return standing_mask, floor, H, base


def far_share(feet: NDArray[np.bool_], H: NDArray[np.float64], base: tuple[float, float]) -> float:
    """Share of the feet pixels the floor homography puts over 10 cm from the leg."""
    rows, cols = np.nonzero(feet)
    ground = H @ np.vstack([cols, rows, np.ones_like(rows)]).astype(np.float64)
    x, y = ground[:2] / ground[2]
    return float((np.hypot(x - base[0], y - base[1]) > 0.1).mean())


@pytest.mark.parametrize("roll", [0.0, 0.06])
def test_a_leaning_legs_feet_are_where_it_stands_not_along_its_edge(roll: float) -> None:
    standing, floor, H, base = leaning_leg(0.4, roll)
    view = upright_view(H, (WIDTH, HEIGHT))
    assert view is not None
    column_feet = standing_feet(standing, floor, row_ground_distance_m(H, WIDTH, HEIGHT))
    feet = upright_standing_feet(standing, floor, view)
    # Walking image columns, every column across the leaning edge makes a foot, each
    # farther away: a fifth of the feet lie far behind the leg.
    assert far_share(column_feet, H, base) > 0.1
    assert far_share(feet, H, base) <= 0.01
    assert feet.sum() >= 0.5 * column_feet.sum()  # the leg's real foot is all there
    assert not (feet & floor & ~standing).any()
