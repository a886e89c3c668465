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
        assert {"smooth", "color", "slic", "floor_model"} <= set(entry["stages_ms"])
        assert all(s["min"] <= s["median"] <= s["max"] for s in entry["stages_ms"].values())
    assert result["reference"]["640x480"]["total_ms"] > 0
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
