"""Cameras: replay of videos and image folders, a missing webcam."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.hardware.cameras import OpenCVCamera, ReplayCamera, capture_time_s
from app.hardware.interfaces import DeviceState


def _wait(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def _images(n: int) -> list[np.ndarray]:
    return [np.full((48, 64, 3), 20 * k + 10, np.uint8) for k in range(n)]


@pytest.fixture
def video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 50.0, (64, 48))
    assert writer.isOpened()
    for image in _images(5):
        writer.write(image)
    writer.release()
    return path


def _play(camera: ReplayCamera) -> list[int]:
    """Grey levels of the frames seen until the camera ends or fails."""
    seen: list[int] = []
    last_seq = -1
    with camera:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            frame = camera.latest(max_age_s=1.0)
            if frame is not None and frame.seq != last_seq:
                last_seq = frame.seq
                seen.append(int(frame.image.mean()))
            if camera.status().state in (DeviceState.ENDED, DeviceState.FAILED):
                break
            time.sleep(0.002)
        assert camera.status().state == DeviceState.ENDED
    return seen


def test_replay_video_paced_then_ended(video: Path) -> None:
    start = time.monotonic()
    seen = _play(ReplayCamera(video))
    assert time.monotonic() - start >= 4 / 50  # paced at the file's 50 fps
    assert seen[-1] == pytest.approx(90, abs=3)
    assert len(seen) >= 3


def test_replay_image_folder(tmp_path: Path) -> None:
    for k, image in enumerate(_images(4)):
        cv2.imwrite(str(tmp_path / f"{k:03d}.png"), image)
    # 25 fps: slow enough that a loaded CI machine still sees every frame.
    seen = _play(ReplayCamera(tmp_path, fps=25.0))
    assert seen == [10, 30, 50, 70]


def test_replay_loops(tmp_path: Path) -> None:
    for k, image in enumerate(_images(2)):
        cv2.imwrite(str(tmp_path / f"{k}.png"), image)
    with ReplayCamera(tmp_path, fps=200.0, loop=True) as camera:
        assert _wait(lambda: (f := camera.latest(1.0)) is not None and f.seq >= 5)
        assert camera.status().state == DeviceState.CONNECTED


@pytest.mark.parametrize("name", ["broken.avi", "folder"])
def test_replay_corrupt_fails_without_raising(tmp_path: Path, name: str) -> None:
    if name == "folder":
        (tmp_path / name).mkdir()
        (tmp_path / name / "000.jpg").write_bytes(b"not a jpeg at all")
    else:
        (tmp_path / name).write_bytes(b"\x00garbage" * 100)
    with ReplayCamera(tmp_path / name, fps=100.0) as camera:
        assert _wait(lambda: camera.status().state == DeviceState.FAILED)
        assert camera.status().detail
        assert camera.latest(1.0) is None


def test_replay_missing_source_fails(tmp_path: Path) -> None:
    with ReplayCamera(tmp_path / "nope.mp4") as camera:
        assert _wait(lambda: camera.status().state == DeviceState.FAILED)
        assert "no such" in camera.status().detail


def test_capture_time_is_the_drivers_monotonic_stamp_when_it_is_one() -> None:
    returned_s = 5000.0
    assert capture_time_s(4999.955 * 1000, returned_s) == pytest.approx(4999.955)
    assert capture_time_s(0.0, returned_s) == returned_s  # no stamp (a first frame)
    assert capture_time_s(1.79e12, returned_s) == returned_s  # wall-clock milliseconds
    assert capture_time_s(5000.2 * 1000, returned_s) == returned_s  # after the return
    assert capture_time_s(3000.0 * 1000, returned_s) == returned_s  # far too old


class _StampingCapture:
    """A V4L2 capture as OpenCV shows it: frames with a monotonic driver stamp taken
    40 ms before read() returns (the USB transfer)."""

    def __init__(self) -> None:
        self.stamp_ms = 0.0
        self.stamps_s: list[float] = []

    def read(self) -> tuple[bool, np.ndarray]:
        time.sleep(0.01)
        self.stamp_ms = (time.monotonic() - 0.040) * 1000
        self.stamps_s.append(self.stamp_ms / 1000)
        return True, np.zeros((48, 64, 3), np.uint8)

    def get(self, prop: int) -> float:
        return self.stamp_ms if prop == cv2.CAP_PROP_POS_MSEC else 0.0

    def release(self) -> None:
        pass


def test_opencv_camera_stamps_frames_with_the_drivers_capture_time() -> None:
    capture = _StampingCapture()

    class StampedCamera(OpenCVCamera):
        def _connect(self) -> cv2.VideoCapture | None:
            return capture  # type: ignore[return-value]

    with StampedCamera(0) as camera:
        assert _wait(lambda: camera.latest(1.0) is not None)
        frame = camera.latest(1.0)
        assert frame is not None
        assert frame.timestamp_s in capture.stamps_s  # the driver's, not read()'s return
        assert camera.driver_stamped
        assert time.monotonic() - frame.timestamp_s >= 0.040
        # The host had it when read() returned, the transfer after the exposure.
        assert frame.arrived_s is not None
        assert frame.arrived_s - frame.timestamp_s == pytest.approx(0.040, abs=0.005)


def test_opencv_camera_missing_device_fails_and_retries() -> None:
    camera = OpenCVCamera("/dev/video-floornav-missing", retry_initial_s=0.01, retry_max_s=0.02)
    camera.open()
    try:
        assert _wait(lambda: camera.status().state == DeviceState.FAILED)
        assert "no such device" in camera.status().detail
        assert camera.latest(10.0) is None
    finally:
        camera.close()
    assert camera.status().state == DeviceState.DISCONNECTED


def test_real_robot_video_replays_through_the_floor_pipeline() -> None:
    """The replay source on a real robot's video (MPEG-4, 320x240, 24 fps), frames fed
    to the default segmenter: the carpet just ahead of the robot is floor."""
    from app.config import PerceptionConfig
    from app.perception.pipeline import FloorSegmenter

    from ..conftest import dataset_dir

    video = dataset_dir("robot-video-carpet") / "video2.avi"
    segmenter = FloorSegmenter(PerceptionConfig())
    # Compile the numba kernels first (seconds on a cold cache), or playback runs ahead.
    segmenter.segment(np.full((240, 320, 3), 120, np.uint8))
    seqs: list[int] = []
    floor_ahead: list[float] = []
    with ReplayCamera(video) as camera:
        deadline = time.monotonic() + 10.0
        while len(seqs) < 8 and time.monotonic() < deadline:
            frame = camera.latest(max_age_s=0.5)
            if frame is None or (seqs and frame.seq == seqs[-1]):
                time.sleep(0.01)
                continue
            seqs.append(frame.seq)
            assert frame.image.shape == (240, 320, 3)
            mask = segmenter.segment(frame.image).floor_mask
            floor_ahead.append(float(mask[-24:, 100:220].mean()))
        assert camera.status().state is DeviceState.CONNECTED
    assert len(seqs) == 8 and seqs == sorted(seqs)
    assert float(np.median(floor_ahead)) > 0.5
