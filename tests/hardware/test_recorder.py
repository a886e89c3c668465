"""Recorder round trip, playback, and dropping instead of blocking."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from app.hardware.cameras import ReplayCamera
from app.hardware.interfaces import CameraFrame, DeviceState
from app.hardware.recorder import Recorder, read_log
from app.mapping.frames import Pose2D


def _frame(k: int) -> CameraFrame:
    image = np.full((48, 64, 3), 40 * k + 20, np.uint8)
    return CameraFrame(image=image, timestamp_s=100.0 + 0.02 * k, seq=k)


def test_round_trip_and_replay(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    with Recorder(folder) as recorder:
        for k in range(3):
            assert recorder.record_frame(_frame(k), Pose2D(0.1 * k, 0.0, 0.5))
            assert recorder.log("command", 100.0 + 0.02 * k + 0.01, left_pwm=k, right_pwm=-k)
    assert recorder.dropped == 0 and recorder.written_frames == 3 and not recorder.errors
    entries = read_log(folder)
    frames = [e for e in entries if e["kind"] == "frame"]
    commands = [e for e in entries if e["kind"] == "command"]
    assert [f["file"] for f in frames] == [f"frames/{k:06d}.jpg" for k in range(3)]
    assert frames[2]["pose"] == pytest.approx([0.2, 0.0, 0.5])
    assert commands[1] == {
        "kind": "command",
        "t": pytest.approx(100.03),
        "left_pwm": 1,
        "right_pwm": -1,
    }
    seen: list[int] = []
    with ReplayCamera(folder) as camera:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            ended = camera.status().state == DeviceState.ENDED
            frame = camera.latest(1.0)
            if frame is not None and frame.seq >= len(seen):
                seen.append(round(float(frame.image.mean())))
            if ended:
                break
            time.sleep(0.002)
        assert camera.status().state == DeviceState.ENDED
    assert seen == pytest.approx([20, 60, 100], abs=3)


def test_full_queue_drops_and_counts(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path / "run", queue_size=1)
    recorder.open()
    big = CameraFrame(np.zeros((960, 1280, 3), np.uint8), 0.0, 0)
    accepted = sum(recorder.record_frame(big) for _ in range(50))
    recorder.close()
    assert recorder.dropped == 50 - accepted > 0
    assert recorder.written_frames == accepted
    assert len(read_log(tmp_path / "run")) == accepted


def test_refuses_existing_recording(tmp_path: Path) -> None:
    with Recorder(tmp_path / "run") as recorder:
        recorder.log("note", 0.0, text="hi")
    with pytest.raises(FileExistsError):
        Recorder(tmp_path / "run").open()
