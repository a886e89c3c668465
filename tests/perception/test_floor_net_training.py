"""Training and export of the floornet network (needs the ``train`` extra)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from app.config import PerceptionConfig
from app.perception.floor_net import INPUT_HEIGHT_PX, INPUT_WIDTH_PX, FloorNet, network_input
from app.perception.pipeline import trapezoid_from_config

torch = pytest.importorskip("torch", reason="the train extra (PyTorch) is not installed")
pytest.importorskip("onnx", reason="the train extra (onnx) is not installed")

from app.training.floor_net import (  # noqa: E402
    augment,
    export_onnx,
    input_zone_mask,
    paste_obstacle,
    predict_probability,
    prepare,
    recolour_far_floor,
    train,
    training_input,
)

ZONE = trapezoid_from_config(PerceptionConfig().safe_zone)


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    image = np.empty((120, 160, 3), np.uint8)
    image[:60] = rng.integers(100, 255, 3)
    image[60:] = rng.integers(0, 100, 3)
    truth = np.zeros((120, 160), bool)
    truth[60:] = True
    return image, truth


def test_augmented_views_keep_the_bottom_edge_and_the_labels_aligned() -> None:
    image, truth = _scene(0)
    prepared = prepare(image, truth)
    rng = np.random.default_rng(0)
    for _ in range(10):
        bgr, floor = augment(prepared, rng)
        assert bgr.shape == (INPUT_HEIGHT_PX, INPUT_WIDTH_PX, 3)
        assert floor.shape == (INPUT_HEIGHT_PX, INPUT_WIDTH_PX)
        assert floor[-1].all()  # the crop keeps the robot's own floor
        assert set(np.unique(floor)) <= {0, 1}


def test_a_pasted_obstacle_is_the_donors_non_floor_and_is_labelled_not_floor() -> None:
    height, width = INPUT_HEIGHT_PX, INPUT_WIDTH_PX
    floor_view = np.full((height, width, 3), 10, np.uint8)
    floor_label = np.ones((height, width), np.uint8)
    donor = np.empty((height, width, 3), np.uint8)
    donor[..., 0] = np.arange(width, dtype=np.uint8)[None, :]  # where each pixel came from
    donor[..., 1] = np.arange(height, dtype=np.uint8)[:, None]
    donor[..., 2] = 200
    donor_floor = np.zeros((height, width), np.uint8)
    donor_floor[:, : width // 2] = 1  # the donor's left half is floor: never pasted
    pasted_any = False
    for seed in range(40):
        bgr, floor = paste_obstacle(
            floor_view, floor_label, donor, donor_floor, np.random.default_rng(seed)
        )
        changed = (bgr != floor_view).any(axis=2)
        # Exactly the pasted pixels lose their floor label, and every one of them is a
        # donor pixel from the donor's not-floor half.
        np.testing.assert_array_equal(floor == 0, changed)
        assert (bgr[changed][:, 2] == 200).all()
        assert (bgr[changed][:, 0] >= width // 2).all()
        if changed.any():
            pasted_any = True
            rows = np.nonzero(changed.any(axis=1))[0]
            assert rows.max() >= 0.6 * height - 1  # it stands in the lower part of the view
    assert pasted_any
    # The inputs are unchanged.
    assert (floor_view == 10).all() and floor_label.all()


def test_recolouring_changes_only_far_floor_into_another_material() -> None:
    height, width = INPUT_HEIGHT_PX, INPUT_WIDTH_PX
    rng = np.random.default_rng(3)
    view = rng.integers(90, 110, (height, width, 3)).astype(np.uint8)  # a textured floor
    floor = np.zeros((height, width), np.uint8)
    floor[height // 3 :] = 1  # wall above, floor below
    view[: height // 3] = (30, 160, 200)
    recoloured_any = False
    for seed in range(20):
        out, recoloured = recolour_far_floor(view, floor, np.random.default_rng(seed))
        changed = (out != view).any(axis=2)
        assert not (changed & ~recoloured).any()  # nothing else moves
        assert not (recoloured & (floor == 0)).any()  # only floor is recoloured
        assert not recoloured[round(0.75 * height) :].any()  # never the safe zone
        if recoloured.any():
            recoloured_any = True
            lab_before = cv2.cvtColor(view, cv2.COLOR_BGR2Lab).astype(float)[recoloured]
            lab_after = cv2.cvtColor(out, cv2.COLOR_BGR2Lab).astype(float)[recoloured]
            assert np.linalg.norm(lab_after.mean(axis=0) - lab_before.mean(axis=0)) >= 8
    assert recoloured_any
    assert (view[: height // 3] == (30, 160, 200)).all()  # the input is unchanged


def test_no_floor_or_too_little_far_floor_is_left_as_it_is() -> None:
    view = np.full((INPUT_HEIGHT_PX, INPUT_WIDTH_PX, 3), 50, np.uint8)
    for floor in (np.zeros(view.shape[:2], np.uint8), np.ones(view.shape[:2], np.uint8)):
        floor[:-4] = 0  # at most the bottom rows: under 5 % beyond any line
        out, recoloured = recolour_far_floor(view, floor, np.random.default_rng(0))
        np.testing.assert_array_equal(out, view)
        assert not recoloured.any()


def test_a_training_view_can_take_its_colours_relative_to_another_floor() -> None:
    view = np.zeros((INPUT_HEIGHT_PX, INPUT_WIDTH_PX, 3), np.uint8)
    view[: INPUT_HEIGHT_PX // 2] = (40, 120, 200)  # the far material
    view[INPUT_HEIGHT_PX // 2 :] = (90, 90, 90)  # the near one, under the safe zone
    far = np.zeros(view.shape[:2], bool)
    far[: INPUT_HEIGHT_PX // 2] = True
    zone = input_zone_mask(ZONE)
    np.testing.assert_array_equal(training_input(view, zone, None), network_input(view, zone))
    relative = training_input(view, zone, far)
    np.testing.assert_array_equal(relative[0, :3], network_input(view, zone)[0, :3])
    np.testing.assert_allclose(relative[0, 3:, far], 0.0, atol=1e-6)  # the reference's own colour
    assert np.abs(relative[0, 3:, ~far]).max() > 0.1


def test_nothing_is_pasted_from_a_window_that_is_mostly_floor() -> None:
    view = np.zeros((INPUT_HEIGHT_PX, INPUT_WIDTH_PX, 3), np.uint8)
    label = np.ones(view.shape[:2], np.uint8)
    bgr, floor = paste_obstacle(
        view, label, np.full_like(view, 99), np.ones_like(label), np.random.default_rng(0)
    )
    np.testing.assert_array_equal(bgr, view)
    np.testing.assert_array_equal(floor, label)


def test_the_exported_onnx_model_gives_what_torch_gives(tmp_path: Path) -> None:
    images = [prepare(*_scene(seed)) for seed in range(4)]
    model = train(images, ZONE, epochs=1)
    path = tmp_path / "net.onnx"
    export_onnx(model, path)
    image, _ = _scene(7)
    expected = predict_probability(model, image, ZONE)
    blob = network_input(image, input_zone_mask(ZONE))
    zone_out = np.zeros(expected.shape, bool)
    zone_out[-8:, 30:50] = True
    output = FloorNet(path).run(blob, zone_out)
    assert output.probability.shape == expected.shape
    assert np.abs(output.probability - expected).max() < 1e-4
    assert output.zone_floor_probability == pytest.approx(float(expected[zone_out].mean()))
