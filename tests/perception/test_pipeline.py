"""The assembled pipeline on synthetic scenes (exact structure) and real images."""

from __future__ import annotations

import numpy as np
import pytest

from app.config import PerceptionConfig, SafeZoneConfig
from app.imageio import read_bgr
from app.perception.image_checks import ImageError
from app.perception.metrics import floor_scores
from app.perception.pipeline import METHODS, FloorSegmenter
from app.perception.safe_zone import SafeZoneError

from ..conftest import dataset_dir, room_scene

ALL_METHODS = sorted(METHODS)
MIN_SYNTHETIC_RECALL = {
    "thesis": 0.4,
    "thesis_junction": 0.4,
    "floornav": 0.65,
    "flood_fill": 0.85,
    "floornet": 0.9,
}


FLAT_BOX_MISSED = pytest.mark.xfail(
    strict=True,
    reason="floornet calls the flat, unshaded red box of this cartoon scene floor (it learned "
    "obstacles from real photos, where they have shading and edges; the simulator's "
    "shaded boxes it gets right)",
)


@pytest.mark.parametrize(
    "method",
    [pytest.param(m, marks=FLAT_BOX_MISSED) if m == "floornet" else m for m in ALL_METHODS],
)
def test_every_method_finds_floor_and_never_the_wall(method: str) -> None:
    image, truth = room_scene(320, 240)
    result = FloorSegmenter(PerceptionConfig(), method=method).segment(image)
    assert result.floor_mask.shape == truth.shape and result.floor_mask.dtype == bool
    assert result.method == method
    scores = floor_scores(result.floor_mask, truth)
    # The thesis's shape features (width, height, area) reject floor superpixels cut by
    # the image border, and floornav's fitted position cues doubt floor near the horizon
    # (a known limit, see the README), so recall is partial; what they keep is floor.
    assert scores.floor_precision > 0.97, scores
    assert scores.floor_recall > MIN_SYNTHETIC_RECALL[method], scores
    assert scores.near_false_floor < 0.05, scores
    assert not result.floor_mask[:40].any()
    assert result.timings_ms["total"] >= max(
        v for k, v in result.timings_ms.items() if k != "total"
    )


@pytest.mark.parametrize("method", ["thesis", "thesis_junction"])
def test_superpixel_methods_return_labels(method: str) -> None:
    image, _ = room_scene(320, 240)
    result = FloorSegmenter(PerceptionConfig(), method=method).segment(image)
    assert result.labels is not None and result.superpixel_floor is not None
    assert result.labels.shape == image.shape[:2]
    n = int(result.labels.max()) + 1
    assert result.superpixel_floor.shape == (n,)
    # The floor mask is the union of the floor superpixels (before junction masking).
    union = result.superpixel_floor[result.labels]
    assert np.all(result.floor_mask <= union)


def test_rgb_colour_space_and_skimage_backend_are_selectable() -> None:
    image, truth = room_scene(160, 120)
    config = PerceptionConfig(color_space="rgb", slic_backend="skimage")
    result = FloorSegmenter(config, method="thesis").segment(image)
    scores = floor_scores(result.floor_mask, truth)
    assert scores.floor_precision > 0.97 and scores.floor_recall > 0.3, scores


def test_grayscale_and_bgra_frames_are_accepted() -> None:
    image, truth = room_scene(160, 120)
    segmenter = FloorSegmenter(PerceptionConfig(), method="thesis")
    gray = image.mean(axis=2).astype(np.uint8)
    assert segmenter.segment(gray).floor_mask.shape == truth.shape
    bgra = np.dstack([image, np.full(truth.shape, 255, np.uint8)])
    np.testing.assert_array_equal(
        segmenter.segment(bgra).floor_mask, segmenter.segment(image).floor_mask
    )


def test_bad_frames_and_zones_give_clear_errors() -> None:
    segmenter = FloorSegmenter(PerceptionConfig())
    with pytest.raises(ImageError, match="too small"):
        segmenter.segment(np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(ImageError, match="uint8"):
        segmenter.segment(np.zeros((50, 50, 3), np.float64))  # type: ignore[arg-type]
    tiny_zone = SafeZoneConfig(
        bottom_left_x_frac=0.49,
        bottom_right_x_frac=0.5,
        top_left_x_frac=0.49,
        top_right_x_frac=0.5,
        top_y_frac=0.99,
    )
    with pytest.raises(SafeZoneError, match="safe zone covers"):
        FloorSegmenter(PerceptionConfig(safe_zone=tiny_zone)).segment(
            np.zeros((20, 20, 3), np.uint8)
        )
    with pytest.raises(ValueError, match="unknown method"):
        FloorSegmenter(PerceptionConfig(), method="magic")


def test_segment_is_deterministic() -> None:
    image, _ = room_scene(200, 150, seed=3)
    segmenter = FloorSegmenter(PerceptionConfig())
    np.testing.assert_array_equal(
        segmenter.segment(image).floor_mask, segmenter.segment(image.copy()).floor_mask
    )


def test_real_robot_frame_has_floor_in_front() -> None:
    frame = read_bgr(dataset_dir("robot-video-carpet") / "roboview.jpg")
    result = FloorSegmenter(PerceptionConfig()).segment(frame)
    height = frame.shape[0]
    # The carpet right in front of the robot is floor; the top rows (furniture) are not.
    assert result.floor_mask[int(0.9 * height) :].mean() > 0.7
    assert result.floor_mask[: int(0.1 * height)].mean() < 0.1


def test_floornet_finds_the_floor_and_never_the_wall_of_the_cartoon_room() -> None:
    """What floornet does get right in the synthetic room (see FLAT_BOX_MISSED)."""
    image, truth = room_scene(320, 240)
    result = FloorSegmenter(PerceptionConfig(), method="floornet").segment(image)
    scores = floor_scores(result.floor_mask, truth)
    assert scores.floor_recall > 0.95, scores
    assert not result.floor_mask[:80].any()  # wall only above row 84 (the box top)
