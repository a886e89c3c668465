"""`floornav eval`, `segment` and `bench` end to end, including bad input files."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main

from .conftest import FLOOR_DATASETS, PROJECT_ROOT, dataset_dir, room_scene


def make_dataset(folder: Path) -> None:
    """Two good labelled images (one grayscale, one RGBA) and one of each kind of bad file."""
    folder.mkdir()
    image, truth = room_scene(160, 120, seed=1)
    mask = (truth * 255).astype(np.uint8)
    cv2.imwrite(str(folder / "good.png"), image)
    cv2.imwrite(str(folder / "good_floor.png"), mask)
    cv2.imwrite(str(folder / "gray.png"), image.mean(axis=2).astype(np.uint8))
    cv2.imwrite(str(folder / "gray_floor.png"), mask)
    cv2.imwrite(str(folder / "rgba.png"), np.dstack([image, np.full(mask.shape, 255, np.uint8)]))
    cv2.imwrite(str(folder / "rgba_floor.png"), mask)
    (folder / "corrupt.jpg").write_bytes(b"\xff\xd8 this is not a jpeg")
    cv2.imwrite(str(folder / "corrupt_floor.png"), mask)
    cv2.imwrite(str(folder / "nomask.jpg"), image)
    cv2.imwrite(str(folder / "wrongsize.jpg"), image)
    cv2.imwrite(str(folder / "wrongsize_floor.png"), mask[:60])
    cv2.imwrite(str(folder / "empty.jpg"), image)
    (folder / "empty_floor.png").write_bytes(b"")
    cv2.imwrite(str(folder / "tiny.png"), image[:5, :5])
    cv2.imwrite(str(folder / "tiny_floor.png"), mask[:5, :5])


def test_eval_json_scores_good_files_and_skips_bad_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    make_dataset(tmp_path / "toy")
    assert main(["eval", str(tmp_path / "toy"), "--method", "all", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary) >= {"default_method", "methods", "datasets"}
    for method, scores in summary["methods"].items():
        assert scores["images"] == 3, method
        assert set(scores) == {
            "iou",
            "floor_recall",
            "floor_precision",
            "near_false_floor",
            "images",
        }
        assert 0.0 <= scores["iou"] <= 1.0
    assert set(summary["datasets"]) == {"toy"}
    reasons = {Path(s["file"]).name: s["reason"] for s in summary["skipped"]}
    assert set(reasons) == {"corrupt.jpg", "nomask.jpg", "wrongsize.jpg", "empty.jpg", "tiny.png"}
    assert "not a readable image" in reasons["corrupt.jpg"]
    assert "no mask" in reasons["nomask.jpg"]
    assert "160x60" in reasons["wrongsize.jpg"] or "mask is" in reasons["wrongsize.jpg"]
    assert "too small" in reasons["tiny.png"]


def test_eval_table_names_skipped_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_dataset(tmp_path / "toy")
    assert main(["eval", str(tmp_path / "toy"), "--method", "flood_fill"]) == 0
    out = capsys.readouterr().out
    assert "== toy" in out and "flood_fill" in out
    assert "corrupt.jpg" in out


def test_eval_of_a_missing_folder_fails_clearly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["eval", str(tmp_path / "nowhere"), "--json"]) == 1
    summary = json.loads(capsys.readouterr().out)
    assert summary["skipped"][0]["reason"] == "not a folder"


def test_eval_unknown_method(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_dataset(tmp_path / "toy")
    assert main(["eval", str(tmp_path / "toy"), "--method", "magic"]) == 1
    assert "unknown method" in capsys.readouterr().err


def test_segment_writes_overlay(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "overlay.png"
    assert main(["segment", str(PROJECT_ROOT / "docs" / "sample-room.jpg"), "--out", str(out)]) == 0
    overlay = cv2.imread(str(out))
    assert overlay is not None and overlay.shape == (480, 640, 3)
    assert "floor" in capsys.readouterr().out


def test_segment_of_a_non_image_names_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bogus = tmp_path / "notes.txt"
    bogus.write_text("hello")
    assert main(["segment", str(bogus)]) == 1
    assert "notes.txt: not a readable image" in capsys.readouterr().err
    assert main(["segment", str(tmp_path / "missing.jpg")]) == 1
    assert "no such file" in capsys.readouterr().err


def test_bad_config_stops_a_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[perception]\nn_superpixels = 'many'\n")
    code = main(["segment", str(PROJECT_ROOT / "docs" / "sample-room.jpg"), "--config", str(bad)])
    assert code == 2
    assert "perception.n_superpixels" in capsys.readouterr().err


def test_eval_superpixels_compares_backends(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    make_dataset(tmp_path / "toy")
    assert main(["eval-superpixels", str(tmp_path / "toy"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    for backend in ("numba", "skimage"):
        entry = summary["all"][backend]
        assert entry["images"] == 3
        assert 0.0 <= entry["undersegmentation_error"] <= 0.5
        assert 0.0 <= entry["boundary_recall"] <= 1.0


@pytest.mark.slow
def test_eval_on_the_real_datasets_reports_every_folder(capsys: pytest.CaptureFixture[str]) -> None:
    folders = [str(dataset_dir(name)) for name in FLOOR_DATASETS]
    assert main(["eval", *folders, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["datasets"]) == set(FLOOR_DATASETS)
    default = summary["methods"][summary["default_method"]]
    assert default["images"] == 121
    assert summary["skipped"] == []


@pytest.mark.slow
def test_bench_json_has_the_promised_shape(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--json", "--repeats", "1"]) == 0
    result = json.loads(capsys.readouterr().out)
    for resolution in ("640x480", "320x240"):
        entry = result["resolutions"][resolution]
        assert entry["total_ms"] > 0
        assert {"input", "network"} <= set(entry["stages_ms"])  # floornet, the default
        assert all(s["min"] <= s["median"] <= s["max"] for s in entry["stages_ms"].values())
    assert result["method"] == "floornet"
    assert result["reference"]["640x480"]["total_ms"] > 0
    assert result["reference"]["640x480"]["method"] == "floornav"
    assert result["grid_update"]["median"] > 0
    assert result["sim_render"]["fps"] > 0
    assert result["speedup_vs_reference_640x480"] > 1.0


def test_sim_eval_scores_methods_against_ground_truth(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim-eval", "--frames", "3", "--method", "all", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 3
    for scores in summary["methods"].values():
        assert scores["images"] == 3 and 0.0 <= scores["iou"] <= 1.0
    # Every method finds a good part of the simulated floor and calls little else floor.
    assert summary["methods"]["thesis"]["iou"] > 0.5
    assert min(s["floor_precision"] for s in summary["methods"].values()) > 0.9


def test_bench_leaves_the_process_on_all_its_cpus() -> None:
    import os

    from app.benchmarks import pin_to_one_cpu, restored_affinity

    before = os.sched_getaffinity(0)
    with restored_affinity():
        pin_to_one_cpu()
        assert len(os.sched_getaffinity(0)) == 1
    assert os.sched_getaffinity(0) == before


def _mask_values_ok(path: Path, width: int, height: int) -> np.ndarray:
    """The mask at ``path``: 8-bit, one channel, the input's size, only 0 and 255."""
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert mask is not None, path
    assert mask.dtype == np.uint8 and mask.shape == (height, width)
    assert set(np.unique(mask).tolist()) <= {0, 255}
    return mask


def test_segment_writes_a_mask_per_image(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    big, truth = room_scene(640, 480, seed=2)
    odd, _ = room_scene(333, 251, seed=4)
    cv2.imwrite(str(tmp_path / "room.png"), big)
    cv2.imwrite(str(tmp_path / "odd.jpg"), odd)
    masks = tmp_path / "out" / "masks"  # created, parents too
    code = main(
        ["segment", str(tmp_path / "room.png"), str(tmp_path / "odd.jpg"), "--mask-out", str(masks)]
    )
    assert code == 0
    assert sorted(p.name for p in masks.iterdir()) == ["odd_floor.png", "room_floor.png"]
    room = _mask_values_ok(masks / "room_floor.png", 640, 480)
    _mask_values_ok(masks / "odd_floor.png", 333, 251)
    # 255 is floor: most of the true floor is marked, little of the wall.
    assert (room[truth] == 255).mean() > 0.5
    assert (room[:100] == 255).mean() < 0.2
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    assert all("method" in line and "floor" in line and " ms" in line for line in lines)
    assert not list(tmp_path.glob("*.overlay.png"))  # masks only, no overlays


def test_segment_overlays_beside_masks_on_request(tmp_path: Path) -> None:
    image, _ = room_scene(96, 72)
    cv2.imwrite(str(tmp_path / "a.png"), image)
    masks = tmp_path / "masks"
    assert main(["segment", str(tmp_path / "a.png"), "--mask-out", str(masks), "--overlay"]) == 0
    assert sorted(p.name for p in masks.iterdir()) == ["a_floor.overlay.png", "a_floor.png"]
    overlay = cv2.imread(str(masks / "a_floor.overlay.png"))
    assert overlay is not None and overlay.shape == (72, 96, 3)


def test_segment_goes_on_past_a_bad_file_and_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name, seed in (("a.png", 1), ("c.png", 3)):
        cv2.imwrite(str(tmp_path / name), room_scene(120, 90, seed=seed)[0])
    (tmp_path / "b.jpg").write_bytes(b"\xff\xd8 this is not a jpeg")
    masks = tmp_path / "masks"
    images = [str(tmp_path / n) for n in ("a.png", "b.jpg", "missing.png", "c.png")]
    assert main(["segment", *images, "--mask-out", str(masks)]) == 1
    assert sorted(p.name for p in masks.iterdir()) == ["a_floor.png", "c_floor.png"]
    for name in ("a_floor.png", "c_floor.png"):
        _mask_values_ok(masks / name, 120, 90)
    captured = capsys.readouterr()
    assert "b.jpg: not a readable image" in captured.err
    assert "missing.png: no such file" in captured.err
    assert len(captured.out.splitlines()) == 2


def test_segment_out_is_for_one_image_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    image, _ = room_scene(64, 48)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), image)
    two = [str(tmp_path / "a.png"), str(tmp_path / "b.png")]
    assert main(["segment", *two, "--out", str(tmp_path / "o.png")]) == 1
    assert "--out names one overlay file but 2 images" in capsys.readouterr().err
    assert not (tmp_path / "o.png").exists()
    (tmp_path / "x").mkdir()
    cv2.imwrite(str(tmp_path / "x" / "a.jpg"), image)
    clash = [str(tmp_path / "a.png"), str(tmp_path / "x" / "a.jpg")]
    assert main(["segment", *clash, "--mask-out", str(tmp_path / "m")]) == 1
    assert "would both write a_floor" in capsys.readouterr().err
