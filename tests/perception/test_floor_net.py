"""The floornet method: its input, its model file, its premise check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.config import PerceptionConfig
from app.perception.floor_net import (
    DEFAULT_MODEL_PATH,
    INPUT_HEIGHT_PX,
    INPUT_WIDTH_PX,
    FloorNet,
    FloorNetError,
    network_input,
    probability_to_mask,
)
from app.perception.pipeline import FloorSegmenter, trapezoid_from_config
from app.perception.safe_zone import safe_zone_mask

DATASETS = Path(__file__).resolve().parents[2].parent / "shared" / "datasets"
ZONE = safe_zone_mask(
    (INPUT_HEIGHT_PX, INPUT_WIDTH_PX), trapezoid_from_config(PerceptionConfig().safe_zone)
)


def test_network_input_is_lab_and_lab_relative_to_the_safe_zone() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (333, 251, 3), dtype=np.uint8)
    blob = network_input(image, ZONE)
    assert blob.shape == (1, 6, INPUT_HEIGHT_PX, INPUT_WIDTH_PX)
    assert blob.dtype == np.float32
    absolute, relative = blob[0, :3], blob[0, 3:]
    # The relative channels are the absolute ones minus the zone's median colour.
    offset = absolute - relative
    assert np.allclose(offset, offset[:, :1, :1], atol=1e-5)
    assert np.allclose(np.median(relative[:, ZONE], axis=1), 0.0, atol=1e-5)
    assert np.all(np.abs(absolute) <= 2.0)


def test_a_uniform_frame_is_all_zero_relative_colour() -> None:
    blob = network_input(np.full((48, 64, 3), 120, np.uint8), ZONE)
    assert np.allclose(blob[0, 3:], 0.0, atol=1e-5)


def test_missing_or_broken_model_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FloorNetError, match="not found"):
        FloorNet(tmp_path / "absent.onnx")
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not an onnx file")
    with pytest.raises(FloorNetError, match="not a usable ONNX model"):
        FloorNet(broken)
    config = PerceptionConfig(method="floornet", floornet_model_path=str(tmp_path / "x.onnx"))
    with pytest.raises(FloorNetError, match="not found"):
        FloorSegmenter(config)


def test_probability_to_mask_keeps_the_input_size() -> None:
    probability = np.zeros((64, 80), np.float32)
    probability[40:] = 0.9
    mask = probability_to_mask(probability, (251, 333))
    assert mask.shape == (251, 333)
    assert mask[-1].all() and not mask[0].any()


def test_the_shipped_model_segments_any_frame_size() -> None:
    assert DEFAULT_MODEL_PATH.is_file(), "the floornet model must ship with the package"
    segmenter = FloorSegmenter(PerceptionConfig(method="floornet"))
    rng = np.random.default_rng(1)
    for shape in ((480, 640, 3), (240, 320, 3), (251, 333, 3), (24, 32, 3)):
        result = segmenter.segment(rng.integers(0, 256, shape, dtype=np.uint8))
        assert result.floor_mask.shape == shape[:2]
        assert result.floor_mask.dtype == np.bool_
        assert 0.0 <= result.zone_floor_confidence <= 1.0
        assert result.method == "floornet"


def test_other_methods_report_the_share_of_the_zone_they_call_floor() -> None:
    image = np.full((120, 160, 3), 90, np.uint8)
    result = FloorSegmenter(PerceptionConfig(method="flood_fill")).segment(image)
    assert result.zone_floor_confidence == pytest.approx(1.0)


@pytest.mark.slow
def test_the_premise_confidence_separates_blocked_zones_from_floor() -> None:
    """On the shared frames whose safe zone is mostly not floor (furniture or a bed right
    ahead), the confidence falls below 0.5; where the zone is floor it stays above.

    The shipped model was trained on these frames: this checks the signal is wired
    through; out-of-scene figures come from ``floornav eval --cv``."""
    from app.crossval import load_images

    folders = [DATASETS / d for d in ("robot-hand-floor", "hospital-ground")]
    if not all(f.is_dir() for f in folders):
        pytest.skip(f"the shared datasets are not at {DATASETS}")
    images, _ = load_images(folders, PerceptionConfig())
    segmenter = FloorSegmenter(PerceptionConfig(method="floornet"))
    blocked, clear = [], []
    for item in images:
        confidence = segmenter.segment(item.image).zone_floor_confidence
        (blocked if item.zone_floor_share < 0.5 else clear).append(confidence)
    assert len(blocked) >= 6
    assert np.mean(np.array(blocked) < 0.5) >= 0.75, blocked
    assert np.mean(np.array(clear) >= 0.5) >= 0.95
