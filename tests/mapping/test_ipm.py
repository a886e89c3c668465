"""Inverse perspective mapping: the per-pixel look-up table, bird's-eye views of frames and
floor masks, lens distortion inside the tables, and the cost of mapping a mask."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.mapping.calibration import (
    FloorCalibration,
    Intrinsics,
    apply_homography,
    homography_from_point_pairs,
)
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid
from app.mapping.ipm import (
    birdseye_floor_patch,
    birdseye_image,
    build_birdseye_map,
    build_ground_lookup,
    lookup_error_m,
)

from .test_calibration import GROUND, HEIGHT, WIDTH, camera_homography

LENS = Intrinsics(
    np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
    np.array([-0.3, 0.1, 0.001, -0.001, 0.0]),
    (WIDTH, HEIGHT),
)
ROBOT_GRID = GroundGrid.covering(x_min_m=0.1, x_max_m=3.0, y_min_m=-1.5, y_max_m=1.5, cell_m=0.01)


def pinhole_calibration() -> FloorCalibration:
    H_true = camera_homography()
    return homography_from_point_pairs(apply_homography(H_true, GROUND), GROUND, (WIDTH, HEIGHT))


def lens_calibration(intrinsics: Intrinsics = LENS) -> FloorCalibration:
    """The same camera as `camera_homography`, with lens distortion."""
    raw = intrinsics.distort_points(apply_homography(camera_homography(), GROUND))
    return homography_from_point_pairs(raw, GROUND, (WIDTH, HEIGHT), intrinsics=intrinsics)


def test_ground_lookup_and_birdseye_patch() -> None:
    calibration = pinhole_calibration()
    lookup = build_ground_lookup(calibration, max_range_m=3.0)
    assert not lookup.valid[0].any()  # the top row sees the floor 3.9 m away: beyond 3 m
    assert lookup.valid[-1].all()
    assert np.isnan(lookup.x_m[0]).all() and np.isfinite(lookup.x_m[-1]).all()
    assert lookup.x_m.dtype == lookup.y_m.dtype == np.float32
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
    np.testing.assert_array_equal(patch == UNSEEN, ~bmap.visible)
    view = birdseye_image(np.full((HEIGHT, WIDTH, 3), 200, np.uint8), bmap)
    assert view.shape == (*grid.shape, 3)
    assert (view[bmap.visible] == 200).all() and (view[~bmap.visible] == 0).all()
    with pytest.raises(ValueError, match="built for"):
        birdseye_floor_patch(np.zeros((10, 10), bool), bmap)
    with pytest.raises(ValueError, match="built for"):
        birdseye_image(np.zeros((HEIGHT, WIDTH // 2, 3), np.uint8), bmap)
    with pytest.raises(ValueError, match="max_range_m"):
        build_ground_lookup(calibration, max_range_m=0.0)


def test_lookup_round_trip_through_the_lens() -> None:
    """Pixel -> table ground point -> pixel again (through the homography and the lens
    distortion) lands on the same pixel."""
    calibration = lens_calibration()
    lookup = build_ground_lookup(calibration, max_range_m=5.0)
    rows, cols = np.nonzero(lookup.valid)
    pick = np.random.default_rng(0).choice(rows.size, 500, replace=False)
    pixels = np.column_stack([cols[pick], rows[pick]]).astype(np.float64)
    ground = np.column_stack(
        [lookup.x_m[rows[pick], cols[pick]], lookup.y_m[rows[pick], cols[pick]]]
    )
    np.testing.assert_allclose(calibration.ground_to_image(ground), pixels, atol=2e-3)
    # ... and the table agrees with the true camera: undistorted pixels through the truth.
    ideal = LENS.undistort_points(pixels)
    truth = apply_homography(np.linalg.inv(camera_homography()), ideal)
    np.testing.assert_allclose(ground, truth, atol=1e-5)
    # The range limit holds, and the lens-corrected floor reaches the image's bottom row.
    assert np.nanmax(np.hypot(lookup.x_m, lookup.y_m)) <= 5.0
    assert lookup.valid[-1].all()


def test_birdseye_view_of_a_known_floor_pattern() -> None:
    """A floor painted with 10 cm squares, seen through a distorting lens: the bird's-eye
    view shows the squares where they are on the floor."""
    calibration = lens_calibration()
    square_m = 0.1

    def floor_colour(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.uint8]:
        dark = (np.floor(x / square_m) + np.floor(y / square_m)) % 2 == 0
        return np.where(dark, 40, 220).astype(np.uint8)

    lookup = build_ground_lookup(calibration, max_range_m=10.0)
    frame = np.where(lookup.valid, floor_colour(lookup.x_m, lookup.y_m), 0).astype(np.uint8)
    grid = GroundGrid.covering(x_min_m=0.3, x_max_m=1.5, y_min_m=-0.6, y_max_m=0.6, cell_m=0.01)
    bmap = build_birdseye_map(calibration, grid, max_range_m=10.0)
    view = birdseye_image(np.dstack([frame] * 3), bmap)[:, :, 0]
    x, y = grid.cell_centers()
    expected = floor_colour(x, y)
    # Away from the squares' edges (where a pixel straddles two squares) the view is exact.
    inner = (
        (np.abs(x / square_m - np.round(x / square_m)) > 0.15)
        & (np.abs(y / square_m - np.round(y / square_m)) > 0.15)
        & bmap.visible
    )
    assert inner.sum() > 0.3 * inner.size
    assert (np.abs(view[inner].astype(int) - expected[inner]) <= 2).mean() > 0.995


def test_floor_patch_of_a_known_floor_region() -> None:
    calibration = lens_calibration()
    lookup = build_ground_lookup(calibration, max_range_m=10.0)
    with np.errstate(invalid="ignore"):
        mask = lookup.valid & (lookup.x_m < 1.2) & (np.abs(lookup.y_m) < 0.4)
    bmap = build_birdseye_map(calibration, ROBOT_GRID, max_range_m=3.0)
    patch = birdseye_floor_patch(mask, bmap)
    x, y = ROBOT_GRID.cell_centers()
    truth = np.where((x < 1.2) & (np.abs(y) < 0.4), FLOOR, NOT_FLOOR)
    near_edge = (np.abs(x - 1.2) < 0.03) | (np.abs(np.abs(y) - 0.4) < 0.03)
    seen = bmap.visible & ~near_edge
    assert seen.sum() > 10_000
    np.testing.assert_array_equal(patch[seen], truth[seen])
    assert set(np.unique(patch)) == {FLOOR, NOT_FLOOR, UNSEEN}
    np.testing.assert_array_equal(patch == UNSEEN, ~bmap.visible)
    # The one remap is exactly a nearest-neighbour remap of the float maps.
    reference = cv2.remap(
        mask.astype(np.uint8),
        bmap.map_u,
        bmap.map_v,
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=UNSEEN,
    )
    np.testing.assert_array_equal(patch, reference)
    # A 0/255 uint8 mask means the same; a colour image is not a mask.
    np.testing.assert_array_equal(birdseye_floor_patch(mask.astype(np.uint8) * 255, bmap), patch)
    with pytest.raises(ValueError):
        birdseye_floor_patch(np.zeros((HEIGHT, WIDTH, 3), bool), bmap)


def test_cells_beyond_the_lens_fold_are_not_seen() -> None:
    """A strong barrel lens (k1 = -0.45) folds back: a ray 1.2 rad-units off axis lands
    inside the image again. Such cells must be UNSEEN, not mapped to a wrong pixel."""
    strong = Intrinsics(LENS.camera_matrix, np.array([-0.45, 0.0, 0.0, 0.0, 0.0]), (WIDTH, HEIGHT))
    calibration = lens_calibration(strong)
    grid = GroundGrid.covering(x_min_m=0.05, x_max_m=3.0, y_min_m=-3.0, y_max_m=3.0, cell_m=0.02)
    bmap = build_birdseye_map(calibration, grid, max_range_m=10.0)
    x, y = grid.cell_centers()
    ideal = apply_homography(camera_homography(), np.column_stack([x.ravel(), y.ravel()]))
    radius = np.hypot(*((ideal - (320.0, 240.0)) / 500.0).T).reshape(grid.shape)
    fold = 1.0 / np.sqrt(3 * 0.45)  # where r (1 + k1 r^2) stops growing
    assert bmap.visible.any()
    assert not bmap.visible[radius > fold].any()
    # Without the round-trip check some of those cells would have landed in the image.
    distorted = strong.distort_points(ideal[radius.ravel() > 1.1])
    inside = (distorted >= 0).all(axis=1) & (distorted <= (WIDTH - 1, HEIGHT - 1)).all(axis=1)
    assert inside.any()
    # Visible cells map to the pixel of their own floor point.
    visible = bmap.visible.ravel()
    pixels = np.column_stack([bmap.map_u.ravel(), bmap.map_v.ravel()])[visible]
    np.testing.assert_allclose(strong.distort_points(ideal[visible]), pixels, atol=1e-3)


def test_mapping_a_mask_costs_one_fast_remap() -> None:
    calibration = pinhole_calibration()
    bmap = build_birdseye_map(calibration, ROBOT_GRID, max_range_m=3.0)
    assert ROBOT_GRID.shape == (290, 300)
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[250:] = True
    for _ in range(20):
        birdseye_floor_patch(mask, bmap)
    times = []
    for _ in range(200):
        start = time.perf_counter()
        birdseye_floor_patch(mask, bmap)
        times.append(time.perf_counter() - start)
    median_ms = 1000.0 * float(np.median(times))
    assert median_ms < 1.0, f"640x480 -> 290x300 cells took {median_ms:.3f} ms"
