"""`floornav eval-video` and the contact sheets: metrics on tiny synthetic videos (exact
where they can be), skipped files, the CLI's JSON, and the shared robot videos (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.cli import main
from app.config import PerceptionConfig
from app.perception.pipeline import METHODS, FloorSegmenter
from app.video_eval import (
    bottom_half_floor_fraction,
    contact_sheet,
    count_frames,
    evaluate_videos,
    evenly_spaced,
    mask_iou,
    read_frames,
)

from ..conftest import DATASETS

WIDTH, HEIGHT, FRAMES = 64, 48, 20
HORIZON = 12  # rows 0..11 wall, 12..47 floor: the bottom half is all floor
METRICS = {
    "consecutive_iou_mean",
    "consecutive_iou_p05",
    "bottom_half_floor_fraction_mean",
    "ms_per_frame_median",
    "ms_per_frame_p95",
    "frames",
}
CARPET = DATASETS / "robot-video-carpet"


def room_frame(horizon: int = HORIZON) -> NDArray[np.uint8]:
    """A flat grey-blue wall above a flat brown floor (no noise: codec-friendly)."""
    frame = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    frame[:horizon] = (170, 160, 150)
    frame[horizon:] = (60, 100, 140)
    return frame


def write_video(path: Path, frames: list[NDArray[np.uint8]]) -> Path:
    """Write an MJPG .avi; skip the test if this OpenCV build cannot write or read it."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 24.0, (WIDTH, HEIGHT))
    if not writer.isOpened():
        pytest.skip("this OpenCV build has no MJPG .avi writer (cv2.VideoWriter did not open)")
    for frame in frames:
        writer.write(frame)
    writer.release()
    capture = cv2.VideoCapture(str(path))
    readable = capture.isOpened() and capture.read()[0]
    capture.release()
    if not readable:
        pytest.skip("this OpenCV build cannot read back the MJPG .avi it wrote")
    return path


@pytest.fixture
def static_video(tmp_path: Path) -> Path:
    return write_video(tmp_path / "static.avi", [room_frame()] * FRAMES)


def test_mask_iou_and_bottom_half_fraction_are_exact() -> None:
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert mask_iou(a, b) == 1.0  # two empty masks agree
    a[2:, :] = True  # 8 pixels
    b[3:, :] = True  # 4 pixels, inside a
    assert mask_iou(a, b) == 0.5
    assert mask_iou(a, ~a) == 0.0
    assert bottom_half_floor_fraction(a) == 1.0
    assert bottom_half_floor_fraction(b) == 0.5
    odd = np.zeros((5, 2), bool)
    odd[3:] = True  # rows >= 2.5 are rows 3 and 4
    assert bottom_half_floor_fraction(odd) == 1.0
    with pytest.raises(ValueError, match="shapes differ"):
        mask_iou(a, np.zeros((2, 2), bool))


def test_read_frames_stride_and_max_frames(static_video: Path) -> None:
    assert count_frames(static_video) == FRAMES
    assert [i for i, _ in read_frames(static_video)] == list(range(FRAMES))
    assert [i for i, _ in read_frames(static_video, stride=3)] == list(range(0, FRAMES, 3))
    assert [i for i, _ in read_frames(static_video, stride=3, max_frames=4)] == [0, 3, 6, 9]
    _, frame = next(read_frames(static_video))
    assert frame.shape == (HEIGHT, WIDTH, 3) and frame.dtype == np.uint8
    with pytest.raises(ValueError, match="stride"):
        next(read_frames(static_video, stride=0))


def test_evenly_spaced_includes_both_ends() -> None:
    assert evenly_spaced(1631, 12)[0] == 0 and evenly_spaced(1631, 12)[-1] == 1630
    assert len(evenly_spaced(1631, 12)) == 12
    assert evenly_spaced(5, 12) == [0, 1, 2, 3, 4]
    assert evenly_spaced(0, 12) == []


def test_static_video_is_perfectly_stable_and_its_bottom_half_is_floor(
    static_video: Path,
) -> None:
    summary = evaluate_videos([static_video], ["flood_fill"], PerceptionConfig())
    assert summary["skipped"] == []
    videos = summary["videos"]
    assert isinstance(videos, dict) and list(videos) == [str(static_video)]
    video = videos[str(static_video)]
    assert (video["width"], video["height"], video["frame_count"]) == (WIDTH, HEIGHT, FRAMES)
    m = video["methods"]["flood_fill"]
    assert set(m) == METRICS
    assert m["frames"] == FRAMES
    # Identical frames through a pure method: identical masks.
    assert m["consecutive_iou_mean"] == 1.0 and m["consecutive_iou_p05"] == 1.0
    # Rows 24..47 are all floor colour; the flood fill from the safe zone takes them all.
    assert m["bottom_half_floor_fraction_mean"] == pytest.approx(1.0, abs=0.02)
    assert 0.0 < m["ms_per_frame_median"] <= m["ms_per_frame_p95"]


def test_every_method_gives_metrics_in_range(static_video: Path) -> None:
    methods = sorted(METHODS)
    summary = evaluate_videos([static_video], methods, PerceptionConfig(), stride=2, max_frames=6)
    videos = summary["videos"]
    assert isinstance(videos, dict)
    by_method = videos[str(static_video)]["methods"]
    unavailable = summary["unavailable_methods"]
    assert isinstance(unavailable, dict)
    # A method may be unavailable here (a model file not shipped): named with the reason.
    assert sorted([*by_method, *unavailable]) == methods
    assert "flood_fill" in by_method and all(unavailable.values())
    for method, m in by_method.items():
        assert m["frames"] == 6, method
        for key in ("consecutive_iou_mean", "consecutive_iou_p05"):
            assert 0.0 <= m[key] <= 1.0, (method, key)
        assert m["consecutive_iou_p05"] <= m["consecutive_iou_mean"] + 1e-12
        assert 0.0 <= m["bottom_half_floor_fraction_mean"] <= 1.0, method
        assert 0.0 < m["ms_per_frame_median"] <= m["ms_per_frame_p95"], method


def test_a_moving_floor_edge_lowers_stability_exactly_as_the_masks_do(tmp_path: Path) -> None:
    """The horizon jumps between two rows every frame; the metric equals the IoU of the
    two masks the method gives for the two frames on their own."""
    frames = [room_frame(12 if i % 2 == 0 else 20) for i in range(10)]
    video = write_video(tmp_path / "moving.avi", frames)
    summary = evaluate_videos([video], ["flood_fill"], PerceptionConfig())
    videos = summary["videos"]
    assert isinstance(videos, dict)
    m = videos[str(video)]["methods"]["flood_fill"]
    decoded = [f for _, f in read_frames(video, max_frames=2)]
    segmenter = FloorSegmenter(PerceptionConfig(), method="flood_fill")
    a, b = (segmenter.segment(f).floor_mask for f in decoded)
    expected = mask_iou(a, b)
    assert expected < 0.95
    assert m["consecutive_iou_mean"] == pytest.approx(expected, abs=1e-9)
    assert m["consecutive_iou_p05"] == pytest.approx(expected, abs=1e-9)


def test_unreadable_videos_are_skipped_with_the_reason(static_video: Path, tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(b"RIFF this is not a video at all" * 10)
    missing = tmp_path / "missing.avi"
    summary = evaluate_videos(
        [missing, garbage, static_video], ["flood_fill"], PerceptionConfig(), max_frames=3
    )
    reasons = {Path(s["file"]).name: s["reason"] for s in summary["skipped"]}  # type: ignore[attr-defined]
    assert set(reasons) == {"missing.avi", "garbage.avi"}
    assert "no such file" in reasons["missing.avi"]
    assert "not a readable video" in reasons["garbage.avi"] or "no frame" in reasons["garbage.avi"]
    videos = summary["videos"]
    assert isinstance(videos, dict) and list(videos) == [str(static_video)]


def test_unknown_method_and_bad_options_are_refused(static_video: Path) -> None:
    with pytest.raises(ValueError, match="unknown method"):
        evaluate_videos([static_video], ["nope"], PerceptionConfig())
    with pytest.raises(ValueError, match="stride"):
        evaluate_videos([static_video], ["flood_fill"], PerceptionConfig(), stride=0)
    with pytest.raises(ValueError, match="max_frames"):
        evaluate_videos([static_video], ["flood_fill"], PerceptionConfig(), max_frames=0)


def test_cli_json_parses_and_exit_codes(
    static_video: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["eval-video", str(static_video), str(tmp_path / "missing.avi")]
    assert main([*args, "--method", "flood_fill", "--stride", "2", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["stride"] == 2 and summary["max_frames"] is None
    m = summary["videos"][str(static_video)]["methods"]["flood_fill"]
    assert set(m) == METRICS and m["frames"] == FRAMES // 2
    assert [Path(s["file"]).name for s in summary["skipped"]] == ["missing.avi"]

    assert main([*args, "--method", "all", "--max-frames", "2"]) == 0
    table = capsys.readouterr().out
    assert all(method in table for method in METHODS) and "missing.avi" in table
    assert "iou_mean" in table

    assert main(["eval-video", str(tmp_path / "missing.avi"), "--json"]) == 1
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["videos"] == {} and len(summary["skipped"]) == 1
    assert "no video could be read" in captured.err
    assert main(["eval-video", str(static_video), "--method", "nope"]) == 1


def test_contact_sheet_shape_labels_and_caption() -> None:
    frames = [room_frame() for _ in range(10)]
    masks = [np.zeros((HEIGHT, WIDTH), bool) for _ in range(10)]
    masks[0][HORIZON:] = True
    labels = [f"frame {i}" for i in range(10)]
    sheet = contact_sheet(frames, masks, labels, columns=4, gap_px=2)
    rows = 3  # ceil(10 / 4)
    assert sheet.shape == (rows * HEIGHT + 4 * 2, 4 * WIDTH + 5 * 2, 3)
    assert sheet.dtype == np.uint8
    # Tile 0 is tinted where its mask is floor; tile 1 (no floor) keeps the frame's pixels.
    assert not np.array_equal(sheet[2 + HEIGHT - 1, 2], frames[0][HEIGHT - 1, 0])
    assert np.array_equal(sheet[2 + HEIGHT - 1, 2 + WIDTH + 2], frames[1][HEIGHT - 1, 0])
    # The label darkens the top-left corner of each tile.
    assert sheet[3, 3].sum() < frames[0][1, 1].sum()
    # Two empty cells at the end stay the gap colour.
    last = sheet[2 + 2 * (HEIGHT + 2) + 10, 2 + 3 * (WIDTH + 2) + 10]
    assert np.array_equal(last, sheet[0, 0])
    captioned = contact_sheet(frames, masks, labels, columns=4, gap_px=2, caption="method x")
    assert captioned.shape[1] == sheet.shape[1] and captioned.shape[0] > sheet.shape[0]
    assert np.array_equal(captioned[-sheet.shape[0] :], sheet)
    with pytest.raises(ValueError, match="must match"):
        contact_sheet(frames, masks[:3], labels)


def carpet_video(name: str) -> Path:
    path = CARPET / name
    if not path.is_file():
        pytest.skip(f"shared video {path} is absent (CI clones ../shared beside the project)")
    return path


@pytest.mark.slow
@pytest.mark.parametrize(("name", "frames"), [("recording.avi", 1631), ("video2.avi", 630)])
def test_shared_carpet_videos_decode_fully(name: str, frames: int) -> None:
    assert count_frames(carpet_video(name)) == frames


@pytest.mark.slow
def test_shared_carpet_video_metrics_are_sane() -> None:
    """Every method on 30 frames (stride 8) of the carpet recording: values in range, and
    floor found in the bottom half, which the carpet fills in nearly every frame."""
    video = carpet_video("recording.avi")
    methods = sorted(METHODS)
    summary = evaluate_videos([video], methods, PerceptionConfig(), stride=8, max_frames=30)
    videos = summary["videos"]
    assert isinstance(videos, dict)
    info = videos[str(video)]
    assert (info["width"], info["height"]) == (320, 240)
    assert sorted([*info["methods"], *summary["unavailable_methods"]]) == methods  # type: ignore[misc]
    for method, m in info["methods"].items():
        assert m["frames"] == 30, method
        assert 0.0 <= m["consecutive_iou_p05"] <= m["consecutive_iou_mean"] <= 1.0, method
        assert 0.3 < m["bottom_half_floor_fraction_mean"] <= 1.0, method
