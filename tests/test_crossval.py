"""Out-of-scene cross-validation: whole scenes held out, fits never see them."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from app import crossval
from app.cli import main
from app.config import PerceptionConfig
from app.scenes import scene_folds, scene_of


def test_scene_of_groups_frames_of_one_video_and_keeps_photos_apart() -> None:
    assert scene_of("robot-hand-floor", "robot_hand_Living_room_01_f000019") == (
        "robot-hand-floor/Living_room_01"
    )
    assert scene_of("robot-hand-floor", "robot_hand_Living_room_01_f000088") == (
        "robot-hand-floor/Living_room_01"
    )
    assert scene_of("hospital-ground", "floor3") != scene_of("hospital-ground", "floor4")
    assert scene_of("umd-drivable-toy", "A00001") == scene_of("umd-drivable-toy", "A00002")
    assert scene_of("mine", "hall-0001") == scene_of("mine", "hall-0002") == "mine/hall"


def test_scene_folds_hold_out_whole_scenes() -> None:
    scenes = ["a", "a", "b", "c", "c", "d", "e"]
    assert scene_folds(scenes, None) == [["a"], ["b"], ["c"], ["d"], ["e"]]
    folds = scene_folds(scenes, 2)
    assert sorted(s for fold in folds for s in fold) == ["a", "b", "c", "d", "e"]
    assert all(len(fold) >= 2 for fold in folds)
    assert scene_folds(scenes, 9) == scene_folds(scenes, None)
    with pytest.raises(ValueError, match="at least 2 folds"):
        scene_folds(scenes, 1)


def _write_scene(folder: Path, stem: str, floor_bgr: tuple[int, int, int], seed: int) -> None:
    """A 96x72 frame: a wall above row 40, a floor below it, and a box in the safe zone
    when ``seed`` is odd (the premise broken)."""
    rng = np.random.default_rng(seed)
    image = np.empty((72, 96, 3), np.uint8)
    image[:40] = (200, 60, 40)
    image[40:] = floor_bgr
    truth = np.zeros((72, 96), np.uint8)
    truth[40:] = 255
    if seed % 2:
        image[50:, 30:66] = (20, 20, 220)
        truth[50:, 30:66] = 0
    noisy = np.clip(image.astype(int) + rng.integers(-4, 5, image.shape), 0, 255)
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / f"{stem}.png"), noisy.astype(np.uint8))
    cv2.imwrite(str(folder / f"{stem}_floor.png"), truth)


@pytest.fixture()
def datasets(tmp_path: Path) -> list[Path]:
    hand = tmp_path / "robot-hand-floor"
    for seq, colour in (("Hall_01", (90, 120, 140)), ("Lab_02", (60, 160, 90))):
        for frame in range(3):
            _write_scene(hand, f"robot_hand_{seq}_f{frame:06d}", colour, frame)
    photos = tmp_path / "hospital-ground"
    for n in range(1, 4):
        _write_scene(photos, f"floor{n}", (150, 150, 150), n)
    return [hand, photos]


def test_every_image_is_scored_once_by_a_fit_that_never_saw_its_scene(
    datasets: list[Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[tuple[set[str], set[str]]] = []

    def spy_fitter(method, config, images, progress):  # type: ignore[no-untyped-def]
        def fit(train, test):  # type: ignore[no-untyped-def]
            train_scenes, test_scenes = {i.scene for i in train}, {i.scene for i in test}
            seen.append((train_scenes, test_scenes))
            return lambda item: item.truth

        return fit

    monkeypatch.setattr(crossval, "make_fitter", spy_fitter)
    summary = crossval.cross_validate(datasets, ["thesis"], PerceptionConfig())
    assert summary["cv"] == {
        "scheme": "leave-one-scene-out",
        "folds": 5,
        "scenes": 5,
        "images": 9,
    }
    assert all(not (train & test) for train, test in seen)
    assert sorted(s for _, test in seen for s in test) == sorted(
        {s for train, test in seen for s in train | test}
    )
    per_image = summary["per_image"]["thesis"]  # type: ignore[index]
    assert len(per_image) == 9
    assert len({(r["dataset"], r["name"]) for r in per_image}) == 9
    # The spy predicts the truth: every subset scores perfectly.
    assert summary["methods"]["thesis"]["iou"] == 1.0  # type: ignore[index]
    premise = summary["premise"]
    assert premise["premise_holds"]["thesis"]["images"] == 5  # type: ignore[index]
    assert premise["premise_broken"]["thesis"]["images"] == 4  # type: ignore[index]


def test_flood_fill_tolerance_is_chosen_from_the_training_scenes_only(
    datasets: list[Path],
) -> None:
    config = PerceptionConfig(fill_gaps_px=0)
    images, _ = crossval.load_images(datasets, config)
    fit = crossval.make_fitter("flood_fill", config, images, None)
    test = [i for i in images if i.scene == "hospital-ground/floor1"]
    train = [i for i in images if i.scene != "hospital-ground/floor1"]
    predict = fit(train, test)
    mask = predict(test[0])
    assert mask.shape == test[0].truth.shape
    assert mask[-1, 48]  # the seed pixel is floor


def test_eval_cv_command_prints_tables_and_json(
    datasets: list[Path], capsys: pytest.CaptureFixture[str]
) -> None:
    folders = [str(d) for d in datasets]
    assert main(["eval", *folders, "--cv", "--folds", "2", "--method", "flood_fill"]) == 0
    text = capsys.readouterr().out
    assert "2 folds of whole scenes" in text
    assert "premise broken" in text
    assert main(["eval", *folders, "--cv", "--method", "thesis", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cv"]["scheme"] == "leave-one-scene-out"
    assert set(summary["datasets"]) == {"robot-hand-floor", "hospital-ground"}
    assert "per_image" not in summary
    assert main(["eval", *folders, "--folds", "3"]) == 1  # --folds without --cv
