"""Exact-answer tests of the pipeline stages on tiny synthetic arrays."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from app.perception.classify import ssd_classify
from app.perception.features import adjacency_graph, superpixel_features
from app.perception.image_checks import ImageError, check_bgr_image
from app.perception.junctions import floor_junction_mask, point_segment_distance
from app.perception.preprocess import smooth, to_color_space
from app.perception.region import flood_fill_floor, grow_region
from app.perception.safe_zone import (
    SafeZoneError,
    Trapezoid,
    safe_zone_histogram,
    safe_zone_mask,
    safe_zone_superpixels,
)

ZONE = Trapezoid(0.25, 0.75, 0.4, 0.6, 0.8, 1.0)


# -- preprocess ---------------------------------------------------------------------


def test_smooth_keeps_flat_image_and_blurs_step() -> None:
    flat = np.full((20, 20, 3), 77, np.uint8)
    assert np.array_equal(smooth(flat, sigma_px=5), flat)
    step = np.zeros((1, 41, 3), np.uint8)
    step[:, 21:] = 200
    out = smooth(np.repeat(step, 5, axis=0), sigma_px=2)[2, :, 0]
    assert out[0] == 0 and out[-1] == 200
    assert 0 < out[20] < 200 and np.all(np.diff(out.astype(int)) >= 0)
    assert smooth(flat, sigma_px=0) is flat
    with pytest.raises(ValueError, match="sigma_px"):
        smooth(flat, sigma_px=-1)


def test_lab_of_white_black_and_red_matches_cielab() -> None:
    image = np.array([[[255, 255, 255], [0, 0, 0], [0, 0, 255]]], np.uint8)  # BGR
    lab = to_color_space(image, space="lab")
    assert lab.dtype == np.float32
    np.testing.assert_allclose(lab[0, 0], [100, 0, 0], atol=0.5)
    np.testing.assert_allclose(lab[0, 1], [0, 0, 0], atol=0.5)
    np.testing.assert_allclose(lab[0, 2], [53.2, 80.1, 67.2], atol=1.5)  # sRGB red


def test_rgb_space_scales_to_0_100() -> None:
    image = np.array([[[0, 128, 255]]], np.uint8)
    np.testing.assert_allclose(to_color_space(image, space="rgb")[0, 0], [100, 50.2, 0], atol=0.1)
    with pytest.raises(ValueError, match="colour space"):
        to_color_space(image, space="hsv")  # type: ignore[arg-type]


# -- image checks ---------------------------------------------------------------------


def test_gray_and_rgba_are_converted() -> None:
    gray = np.arange(100, dtype=np.uint8).reshape(10, 10)
    out = check_bgr_image(gray)
    assert out.shape == (10, 10, 3) and np.array_equal(out[:, :, 2], gray)
    rgba = np.zeros((10, 10, 4), np.uint8)
    assert check_bgr_image(rgba).shape == (10, 10, 3)


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((10, 10, 3), np.float32), "uint8"),
        (np.zeros((10, 10, 2), np.uint8), "shape"),
        (np.zeros((4, 10, 3), np.uint8), "too small"),
        (np.zeros((0, 0, 3), np.uint8), "too small"),
    ],
)
def test_bad_images_are_refused(image: np.ndarray, message: str) -> None:
    with pytest.raises(ImageError, match=message):
        check_bgr_image(image, name="frame")


# -- features -----------------------------------------------------------------------


def test_features_of_two_rectangles_exact() -> None:
    labels = np.zeros((4, 6), np.int32)
    labels[:, 4:] = 1
    image = np.zeros((4, 6, 3), np.float32)
    image[:, :4] = (10, 20, 30)
    image[:, 4:, 0] = [[1, 3]] * 4
    f = superpixel_features(labels, image)
    np.testing.assert_array_equal(f.area_px, [16, 8])
    np.testing.assert_allclose(f.mean_color, [[10, 20, 30], [2, 0, 0]])
    np.testing.assert_allclose(f.std_color[1], [1, 0, 0], atol=1e-5)
    np.testing.assert_allclose(f.centroid_xy, [[1.5, 1.5], [4.5, 1.5]])
    np.testing.assert_array_equal(f.center_xy, [[2, 2], [5, 2]])  # rounded centroid
    np.testing.assert_array_equal(f.width_px, [4, 2])
    np.testing.assert_array_equal(f.height_px, [4, 4])
    # Diagonals through (2, 2): main 4 px (0,0)..(3,3); anti 3 px (3,1),(2,2),(1,3).
    np.testing.assert_array_equal(f.diagonal_px, [3.5, 2.0])
    np.testing.assert_array_equal(f.bbox_xyxy, [[0, 0, 3, 3], [4, 0, 5, 3]])
    assert f.thesis_vector().shape == (2, 7)


def test_center_of_concave_superpixel_is_inside_it() -> None:
    # An L-shaped label 0 whose centroid falls on label 1.
    labels = np.ones((5, 5), np.int32)
    labels[:, 0] = 0
    labels[4, :] = 0
    f = superpixel_features(labels, np.zeros((5, 5, 3), np.float32))
    x, y = f.center_xy[0]
    assert labels[y, x] == 0


def test_features_match_numpy_reference_on_random_labels() -> None:
    rng = np.random.default_rng(1)
    labels = ndimage.zoom(rng.integers(0, 12, (6, 8)), 8, order=0).astype(np.int32)
    image = rng.normal(50, 10, (*labels.shape, 3)).astype(np.float32)
    f = superpixel_features(labels, image)
    n = labels.max() + 1
    count = np.bincount(labels.ravel(), minlength=n)
    np.testing.assert_array_equal(f.area_px, count)
    for c in range(3):
        mean = np.bincount(labels.ravel(), image[..., c].ravel(), n) / np.maximum(count, 1)
        np.testing.assert_allclose(f.mean_color[:, c], np.where(count > 0, mean, 0), rtol=1e-4)
    _ys, xs = np.indices(labels.shape)
    cx = np.bincount(labels.ravel(), xs.ravel(), n) / np.maximum(count, 1)
    np.testing.assert_allclose(f.centroid_xy[count > 0, 0], cx[count > 0], rtol=1e-5)


def test_adjacency_graph_exact() -> None:
    labels = np.array([[0, 0, 1], [2, 2, 1], [2, 2, 3]], np.int32)
    g = adjacency_graph(labels)
    assert [g.neighbors(k).tolist() for k in range(4)] == [[1, 2], [0, 2, 3], [0, 1, 3], [1, 2]]
    # 0-1 share one horizontal pair, 0-2 two vertical pairs.
    assert g.shared_px[g.indptr[0] : g.indptr[1]].tolist() == [1, 2]
    assert g.edges().tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_feature_inputs_are_checked() -> None:
    with pytest.raises(ValueError, match="labels"):
        superpixel_features(np.zeros((0, 3), np.int32), np.zeros((0, 3, 3), np.float32))
    with pytest.raises(ValueError, match="image"):
        superpixel_features(np.zeros((3, 3), np.int32), np.zeros((3, 4, 3), np.float32))
    with pytest.raises(ValueError, match="negative"):
        adjacency_graph(np.full((3, 3), -1, np.int32))


# -- safe zone --------------------------------------------------------------------------


def test_safe_zone_mask_corners_and_seed() -> None:
    mask = safe_zone_mask((11, 21), ZONE)
    # Bottom row spans x 5..15, top row (y 8) spans x 8..12.
    assert np.flatnonzero(mask[10]).tolist() == list(range(5, 16))
    assert np.flatnonzero(mask[8]).tolist() == list(range(8, 13))
    assert not mask[:8].any()
    assert ZONE.seed_xy(21, 11) == (10, 9)


def test_safe_zone_errors() -> None:
    with pytest.raises(SafeZoneError, match="too small"):
        safe_zone_mask((4, 4), ZONE)
    with pytest.raises(SafeZoneError, match="fractions"):
        safe_zone_mask((100, 100), Trapezoid(0.25, 1.5, 0.4, 0.6, 0.8, 1.0))


def test_superpixels_intersecting_zone_and_histogram() -> None:
    labels = np.zeros((10, 10), np.int32)
    labels[5:, :] = 1
    labels[5:, 8:] = 2
    zone = np.zeros((10, 10), bool)
    zone[9, 7:9] = True  # touches labels 1 and 2
    np.testing.assert_array_equal(safe_zone_superpixels(labels, zone, 3), [False, True, True])
    # Label 2 has 10 px of which 1 in the zone: dropped by a 20 % overlap rule.
    np.testing.assert_array_equal(
        safe_zone_superpixels(labels, zone, 3, min_overlap_frac=0.2), [False, False, False]
    )
    image = np.zeros((10, 10, 3), np.uint8)
    image[5:] = (8, 16, 255)
    hist = safe_zone_histogram(image, labels, np.array([False, True, True]), bins=32)
    assert hist.shape == (3, 32)
    assert hist[0, 1] == 1.0 and hist[1, 2] == 1.0 and hist[2, 31] == 1.0


# -- classifier and region growing -------------------------------------------------------


def test_ssd_threshold_is_max_of_training() -> None:
    x = np.array([[0, 0], [1, 0], [0, 1], [5, 5], [0.5, 0.5]], np.float32)
    result = ssd_classify(x, np.array([True, True, True, False, False]))
    assert result.threshold == pytest.approx(result.ssd[:3].max())
    assert result.is_floor.tolist() == [True, True, True, False, True]
    with pytest.raises(ValueError, match="safe zone"):
        ssd_classify(x, np.zeros(5, bool))


def test_grow_region_follows_adjacency_only() -> None:
    # Chain 0-1-2-3 and an isolated accepted node 4 (adjacent only to 3).
    labels = np.array([[0, 1, 2, 3, 4]], np.int32)
    g = adjacency_graph(labels)
    accept = np.array([True, True, False, True, True])
    region = grow_region(g, np.array([True, False, False, False, False]), accept)
    assert region.tolist() == [True, True, False, False, False]


def test_flood_fill_stops_at_colour_change() -> None:
    image = np.zeros((10, 10, 3), np.uint8)
    image[:, 6:] = 100
    image[:, 3] = 5  # within tolerance of the seed colour 0
    filled = flood_fill_floor(image, (0, 9), tolerance=10)
    assert filled[:, :6].all() and not filled[:, 6:].any()
    with pytest.raises(ValueError, match="outside"):
        flood_fill_floor(image, (10, 0), tolerance=10)


# -- junctions --------------------------------------------------------------------------


def test_point_segment_distance_exact() -> None:
    d = point_segment_distance(np.array([[0.0, 1.0], [5.0, 0.0]]), np.array([[0.0, 0.0, 2.0, 0.0]]))
    np.testing.assert_allclose(d[:, 0], [1.0, 3.0])


def test_junction_masks_above_wall_floor_line() -> None:
    # A dark wall panel standing on a light floor: its vertical sides meet the
    # horizontal floor line at y = 60; everything above that line in its span is masked.
    gray = np.full((100, 120), 200, np.uint8)
    gray[10:60, 30:90] = 40
    result = floor_junction_mask(
        gray, min_line_length_px=20, junction_radius_px=6, vertical_tolerance_rad=0.2
    )
    assert result.junctions.shape[1] == 2 and len(result.junctions) >= 1
    assert result.vertical.any() and not result.vertical.all()
    assert not result.mask[30, 60]  # above the floor junction, inside the panel
    assert result.mask[80, 60]  # floor below it
    assert result.mask[80, 5]


def test_junctions_on_blank_image_mask_nothing() -> None:
    result = floor_junction_mask(np.full((50, 50), 128, np.uint8))
    assert result.mask.all() and result.lines.shape == (0, 4)
