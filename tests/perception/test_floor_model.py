"""The floornav floor model: free-space DP, colour model, cues, logistic fit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.perception.floor_model import (
    CUE_NAMES,
    GridStats,
    boundary_to_image,
    fit_floor_color_model,
    floor_cues,
    grid_stats,
    grid_step,
    grid_to_image,
)
from app.perception.free_space import boundary_to_mask, free_space_boundary
from app.perception.logistic import fit_logistic_regression
from app.perception.preprocess import gaussian_blur, smooth, to_color_space
from app.perception.safe_zone import Trapezoid, safe_zone_mask
from app.perception.slic import slic_superpixels

from ..conftest import room_scene


def test_free_space_picks_cheapest_run_per_column() -> None:
    cost = np.array(
        [
            [1.0, 1.0, 1.0],
            [1.0, -1.0, 1.0],
            [-1.0, -1.0, 1.0],
            [-1.0, -1.0, -1.0],
        ]
    )
    # Without smoothness each column keeps exactly its floor-like run from the bottom.
    np.testing.assert_array_equal(free_space_boundary(cost, smoothness=0.0), [2, 1, 3])
    # A large smoothness forces one row for all columns (row 2 is then cheapest: -4).
    np.testing.assert_array_equal(free_space_boundary(cost, smoothness=10.0, max_jump=4), [2, 2, 2])


def test_free_space_truncation_allows_obstacle_sides() -> None:
    # Column 1 is an obstacle reaching the bottom; truncation lets the boundary jump.
    cost = np.full((10, 3), -1.0)
    cost[:, 1] = 5.0
    boundary = free_space_boundary(cost, smoothness=1.0, max_jump=2)
    np.testing.assert_array_equal(boundary, [0, 10, 0])
    mask = boundary_to_mask(boundary, 10)
    assert mask[:, 0].all() and not mask[:, 1].any()


def test_free_space_edge_reward_moves_the_boundary() -> None:
    cost = np.zeros((6, 2))
    reward = np.zeros((7, 2))
    reward[4] = 1.0
    np.testing.assert_array_equal(free_space_boundary(cost, edge_reward=reward), [4, 4])
    with pytest.raises(ValueError, match="edge_reward"):
        free_space_boundary(cost, edge_reward=np.zeros((6, 2)))


def test_boundary_upsampling_matches_grid_upsampling() -> None:
    rng = np.random.default_rng(0)
    for height, width in [(480, 640), (240, 320), (213, 450), (479, 639)]:
        step = grid_step(width)
        gh, gw = len(range(0, height, step)), len(range(0, width, step))
        for _ in range(5):
            boundary = rng.integers(0, gh + 1, gw).astype(np.int32)
            expected = grid_to_image(boundary_to_mask(boundary, gh), (height, width))
            np.testing.assert_array_equal(boundary_to_image(boundary, (height, width)), expected)


def test_multirate_smoothing_matches_direct_gaussian() -> None:
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    image = gaussian_blur(image, 1.0)  # camera-like, not white noise
    fast = smooth(image, sigma_px=5.0).astype(int)
    direct = gaussian_blur(image, 5.0).astype(int)
    interior = (slice(15, -15), slice(15, -15))
    assert np.abs(fast[interior] - direct[interior]).max() <= 2
    assert smooth(image[:10, :10], sigma_px=5.0).shape == (10, 10, 3)


def _room_stats() -> tuple[GridStats, np.ndarray]:
    image, truth = room_scene(320, 240)
    lab = to_color_space(smooth(image, sigma_px=5.0))
    labels = slic_superpixels(lab, n_segments=200)
    zone = safe_zone_mask(truth.shape, Trapezoid(0.25, 0.75, 0.4, 0.6, 0.8, 1.0))
    return grid_stats(image, lab, labels, zone), truth


def test_grid_stats_geometry() -> None:
    stats, _ = _room_stats()
    assert stats.shape == (120, 160)
    assert stats.count.sum() == stats.labels.size
    assert np.all((stats.y_top <= stats.y_center) & (stats.y_center <= stats.y_bottom))
    assert stats.zone_frac.max() == pytest.approx(1.0)
    assert stats.edge_reward.shape == (121, 160)


def test_colour_model_ignores_an_obstacle_in_the_safe_zone() -> None:
    stats, _ = _room_stats()
    floor_lab = stats.mean_lab[stats.zone_frac > 0.5].mean(axis=0)
    # Pretend a bright red obstacle covers a third of the seeds.
    seeds = np.flatnonzero(stats.zone_frac > 0.5)
    mean_lab = stats.mean_lab.copy()
    mean_lab[seeds[: len(seeds) // 3]] = (50.0, 70.0, 50.0)
    poisoned = dataclasses.replace(stats, mean_lab=mean_lab)
    model = fit_floor_color_model(poisoned, poisoned.zone_frac, poisoned.zone, dominant_mode=True)
    np.testing.assert_allclose(model.mean_lab, floor_lab, atol=2.0)
    assert not np.isin(seeds[: len(seeds) // 3], model.prototypes).any()
    naive = fit_floor_color_model(poisoned, poisoned.zone_frac, poisoned.zone, dominant_mode=False)
    assert abs(naive.mean_lab[1] - floor_lab[1]) > 10.0


def test_cues_separate_floor_from_wall() -> None:
    stats, truth = _room_stats()
    model = fit_floor_color_model(stats, stats.zone_frac, stats.zone, dominant_mode=True)
    cues = floor_cues(stats, model)
    assert cues.shape == (stats.n, len(CUE_NAMES))
    assert np.all(cues[:, -1] == 1.0)
    grid_truth = truth[::2, ::2]
    floor_frac = stats.mean_of(grid_truth.astype(np.float64))
    d_mean = cues[:, CUE_NAMES.index("d_mean_sd_over_3")]
    assert d_mean[floor_frac > 0.9].max() < d_mean[floor_frac < 0.1].min()


def test_logistic_regression_recovers_known_weights() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20000, 2))
    true_w = np.array([2.0, -1.0, 0.5])
    features = np.column_stack([x, np.ones(len(x))])
    p = 1.0 / (1.0 + np.exp(-(features @ true_w)))
    y = (rng.random(len(x)) < p).astype(np.float64)
    w = fit_logistic_regression(features, y, np.ones(len(x)), l2=0.0)
    np.testing.assert_allclose(w, true_w, atol=0.1)
    with pytest.raises(ValueError, match="constant 1"):
        fit_logistic_regression(x, y, np.ones(len(x)))
