"""MCAP recordings: the file as mcap's own reader sees it, the Foxglove messages, the
replay camera's pacing, files cut short, and ``floornav run --record`` end to end."""

from __future__ import annotations

import ast
import base64
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from numpy.typing import NDArray

from app.hardware.cameras import ReplayCamera
from app.hardware.interfaces import CameraFrame, DeviceState, DeviceStatus
from app.mapping.frames import GroundGrid, Pose2D
from app.recording.mcap_reader import (
    RecordingError,
    TruncatedRecordingError,
    iter_images,
    iter_messages,
    summarize,
)
from app.recording.mcap_writer import (
    CAMERA_TOPIC,
    CLOCK_METADATA,
    MASK_TOPIC,
    TOPICS,
    McapLogHandler,
    McapRecorder,
)
from app.recording.schemas import SCHEMAS

from ..conftest import free_port

PROJECT = Path(__file__).resolve().parents[2]
OFFSET_S = 1_700_000_000.0 - 1000.0
"""Unix minus monotonic seconds of the fake clocks below."""


def _recorder(path: Path, **kwargs: object) -> McapRecorder:
    return McapRecorder(
        path,
        clock=lambda: 1000.0,
        wall_clock=lambda: 1_700_000_000.0,
        **kwargs,  # type: ignore[arg-type]
    )


def _image(k: int) -> NDArray[np.uint8]:
    return np.full((48, 64, 3), 30 * k + 20, np.uint8)


def _mask(k: int) -> NDArray[np.bool_]:
    mask = np.zeros((48, 64), bool)
    mask[20 + k :, 5 * k :] = True
    return mask


def _write_run(path: Path, n: int = 5, spacing_s: float = 0.05) -> list[float]:
    """A short recording on every topic; the frames' capture times."""
    times = [1001.0 + spacing_s * k for k in range(n)]
    grid = GroundGrid(x_max_m=1.0, y_max_m=0.5, cell_m=0.1, rows=20, cols=10)
    cells = np.full(grid.shape, -1, np.int8)
    cells[:5] = 0
    with _recorder(path, metadata={"world": "test"}) as recorder:
        for k, t in enumerate(times):
            assert recorder.record_image(t, _image(k))
            assert recorder.record_pose(t + 0.001, Pose2D(0.1 * k, 0.0, 0.2 * k))
            assert recorder.record_mask(t, _mask(k))
            assert recorder.record_drive(
                t + 0.01,
                source="autonomy",
                linear_m_s=0.2,
                angular_rad_s=0.1 * k,
                left_wheel_m_s=0.19,
                right_wheel_m_s=0.21,
                left_pwm=100 + k,
                right_pwm=110 + k,
                heading_rad=0.05,
            )
        assert recorder.record_stop(
            times[2], cause="clearance", reason="too close", latched=False, zeroes_motors=False
        )
        assert recorder.record_map(times[-1], cells, grid)
        assert recorder.record_log(times[-1], levelno=30, message="careful", name="floornav")
    stats = recorder.stats()
    assert stats["errors"] == 0 and sum(stats["dropped"].values()) == 0, stats
    return times


def _decode(data: bytes) -> dict[str, object]:
    value = json.loads(data)
    assert isinstance(value, dict)
    return value


def test_round_trip_with_the_mcap_reader(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    times = _write_run(path)
    with path.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {channel.topic: channel for channel in summary.channels.values()}
        assert set(topics) == set(TOPICS)
        for topic, channel in topics.items():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json"
            assert schema.encoding == "jsonschema"
            assert schema.name == TOPICS[topic]
            assert json.loads(schema.data) == SCHEMAS[schema.name]
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
        assert counts == {
            "/camera/image": 5,
            "/floor/mask": 5,
            "/odom": 5,
            "/drive/command": 5,
            "/stops": 1,
            "/map": 1,
            "/log": 1,
        }
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
        assert float(metadata[CLOCK_METADATA]["monotonic_to_unix_offset_s"]) == OFFSET_S
        assert metadata["floornav.run"] == {"world": "test"}

        by_topic: dict[str, list[tuple[int, dict[str, object]]]] = {}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append((message.log_time, _decode(message.data)))

    for topic, messages in by_topic.items():
        log_times = [t for t, _ in messages]
        assert log_times == sorted(log_times), topic  # in time order within a topic
        for t, value in messages:  # the timestamp field is the log time
            assert value["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}
    frames = by_topic["/camera/image"]
    assert [t for t, _ in frames] == [round((c + OFFSET_S) * 1e9) for c in times]
    for k, (_, value) in enumerate(frames):
        assert value["format"] == "jpeg" and value["frame_id"] == "camera"
        image = cv2.imdecode(np.frombuffer(base64.b64decode(str(value["data"])), np.uint8), 1)
        assert image is not None and image.shape == (48, 64, 3)
        assert float(image.mean()) == pytest.approx(30 * k + 20, abs=2)
    for k, (_, value) in enumerate(by_topic["/floor/mask"]):
        assert value["format"] == "png"
        png = base64.b64decode(str(value["data"]))
        mask = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(mask, np.where(_mask(k), 255, 0).astype(np.uint8))
    pose = by_topic["/odom"][3][1]["pose"]
    assert isinstance(pose, dict)
    assert pose["position"] == {"x": pytest.approx(0.3), "y": 0.0, "z": 0.0}
    quaternion = pose["orientation"]
    assert 2 * math.atan2(quaternion["z"], quaternion["w"]) == pytest.approx(0.6)
    drive = by_topic["/drive/command"][2][1]
    assert (drive["left_pwm"], drive["right_pwm"], drive["source"]) == (102, 112, "autonomy")
    stop = by_topic["/stops"][0][1]
    assert (stop["cause"], stop["reason"], stop["latched"]) == ("clearance", "too close", False)
    log_message = by_topic["/log"][0][1]
    assert (log_message["level"], log_message["message"]) == (3, "careful")  # WARNING


def test_grid_cells_land_where_the_map_has_them() -> None:
    """A cell Foxglove draws at (x, y) is the map's cell at (x, y)."""
    from app.recording.mcap_writer import occupancy_grid

    grid = GroundGrid(x_max_m=2.0, y_max_m=1.0, cell_m=0.1, rows=30, cols=15)
    cells = np.full(grid.shape, -1, np.int8)
    points = {(1.23, 0.47): 1, (-0.62, -0.31): 0, (0.05, 0.95): 1}
    for (x, y), value in points.items():
        row, col = grid.cell_of(np.array([[x, y]]))[0]
        cells[row, col] = value
    message = occupancy_grid(0, cells, grid)
    columns = int(message["column_count"])
    data = np.frombuffer(base64.b64decode(message["data"]), np.int8).reshape(-1, columns)
    assert data.shape == (15, 30)  # rows along y, columns along x
    assert message["row_stride"] == columns and message["cell_stride"] == 1
    x0, y0 = message["pose"]["position"]["x"], message["pose"]["position"]["y"]
    cell = message["cell_size"]["x"]
    for (x, y), value in points.items():
        i, j = math.floor((x - x0) / cell), math.floor((y - y0) / cell)
        assert data[j, i] == (100 if value else 0)
    assert int(np.count_nonzero(data != -1)) == len(points)


def test_full_queue_drops_frames_but_keeps_room_for_commands(tmp_path: Path) -> None:
    recorder = _recorder(tmp_path / "run.mcap", queue_size=1)
    recorder.open()
    big = np.zeros((960, 1280, 3), np.uint8)
    accepted = sum(recorder.record_image(1000.0 + k, big) for k in range(50))
    assert recorder.record_stop(1001.0, cause="link", reason="x", latched=False, zeroes_motors=True)
    recorder.close()
    stats = recorder.stats()
    assert stats["dropped"][CAMERA_TOPIC] == 50 - accepted > 0
    assert stats["written"][CAMERA_TOPIC] == accepted
    assert summarize(tmp_path / "run.mcap").messages["/stops"] == 1


def test_never_overwrites(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        _recorder(path).open()
    assert path.read_bytes() == b"precious"


def test_log_handler_records_log_lines(tmp_path: Path) -> None:
    import logging

    path = tmp_path / "run.mcap"
    logger = logging.getLogger("floornav.test_mcap")
    logger.setLevel(logging.DEBUG)
    with McapRecorder(path) as recorder:
        handler = McapLogHandler(recorder)
        logger.addHandler(handler)
        try:
            logger.info("state %s -> %s", "idle", "running")
            logger.debug("not recorded")
        finally:
            logger.removeHandler(handler)
    logs = [m.decoded() for m in iter_messages(path, {"/log"})]
    assert [(m["message"], m["level"], m["name"]) for m in logs] == [
        ("state idle -> running", 2, "floornav.test_mcap")
    ]


class _TimedReplay(ReplayCamera):
    """Notes when each frame was published and its grey level."""

    def __init__(self, source: Path) -> None:
        super().__init__(source, fps=200.0)  # a recording keeps its own timing anyway
        self.published: list[tuple[float, int]] = []
        self.done = threading.Event()
        self.final = DeviceStatus(DeviceState.DISCONNECTED)
        """The status it ended in (ENDED or FAILED), kept past `close`."""

    def _publish(self, image: NDArray[np.uint8], timestamp_s: float) -> CameraFrame:
        self.published.append((timestamp_s, round(float(image.mean()))))
        return super()._publish(image, timestamp_s)

    def _set_status(self, state: DeviceState, detail: str = "") -> None:
        super()._set_status(state, detail)
        if state in (DeviceState.ENDED, DeviceState.FAILED) and not self.done.is_set():
            self.final = DeviceStatus(state, detail)
            self.done.set()


def _replay(path: Path) -> _TimedReplay:
    camera = _TimedReplay(path)
    with camera:
        assert camera.done.wait(10.0)
    return camera


def test_replay_keeps_the_recorded_spacing(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    spacing_s = 0.08
    _write_run(path, n=6, spacing_s=spacing_s)
    camera = _replay(path)
    assert camera.final.state == DeviceState.ENDED
    levels = [level for _, level in camera.published]
    assert levels == pytest.approx([30 * k + 20 for k in range(6)], abs=2)
    stamps = [t for t, _ in camera.published]
    # Pacing waits until each frame's recorded offset: never early (the first frame may
    # be a few ms late, hence the slack); late only by a loaded machine's scheduling.
    for k, t in enumerate(stamps):
        assert t - stamps[0] >= k * spacing_s - 0.02
    assert stamps[-1] - stamps[0] < 5 * spacing_s + 2.0


def _cut(source: Path, target: Path, fraction: float) -> None:
    data = source.read_bytes()
    target.write_bytes(data[: int(len(data) * fraction)])


def _long_run(path: Path, n: int = 40) -> None:
    rng = np.random.default_rng(1)
    with _recorder(path, chunk_size=16_384) as recorder:  # many chunks
        for k in range(n):
            image = rng.integers(0, 255, (48, 64, 3)).astype(np.uint8)
            image[:] = np.clip(image // 8 + 5 * k, 0, 255)
            assert recorder.record_image(1001.0 + 0.01 * k, image)
            time.sleep(0.001)  # let the writer keep up (no drops)


def test_a_file_cut_short_replays_what_is_readable(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    _long_run(full)
    assert summarize(full).complete and summarize(full).messages[CAMERA_TOPIC] == 40
    cut = tmp_path / "cut.mcap"
    _cut(full, cut, 0.6)

    summary = summarize(cut)
    assert not summary.complete and summary.problem
    assert 5 <= summary.messages[CAMERA_TOPIC] < 40
    readable: list[int] = []
    with pytest.raises(TruncatedRecordingError, match="cut short or damaged after"):
        for image in iter_images(cut):
            readable.append(image.log_time_ns)
    assert len(readable) == summary.messages[CAMERA_TOPIC]

    camera = _replay(cut)
    assert camera.final.state == DeviceState.ENDED
    assert "cut short" in camera.final.detail
    assert len(camera.published) == len(readable)


def test_unreadable_files_fail_with_the_reason(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    _long_run(full, n=3)
    header_only = tmp_path / "header.mcap"
    _cut(full, header_only, 0.02)
    not_mcap = tmp_path / "clip.mcap"
    not_mcap.write_bytes(b"\x00" * 100)
    for path in (header_only, not_mcap):
        with pytest.raises(RecordingError, match="not a readable MCAP file"):
            summarize(path)
    for path, reason in (
        (header_only, "not a readable MCAP file"),
        (not_mcap, "not a readable MCAP file"),
        (tmp_path / "missing.mcap", "no such file"),
    ):
        camera = _replay(path)
        assert camera.final.state is DeviceState.FAILED
        assert reason in camera.final.detail and not camera.published


def test_a_writer_that_never_finished_leaves_a_readable_file(tmp_path: Path) -> None:
    """What a crash leaves: the chunks written so far, readable, without the summary."""
    path = tmp_path / "run.mcap"
    recorder = _recorder(path, chunk_size=8_192)
    recorder.open()
    rng = np.random.default_rng(2)
    for k in range(20):
        recorder.record_image(1001.0 + 0.01 * k, rng.integers(0, 255, (48, 64, 3), np.uint8))
        time.sleep(0.002)
    time.sleep(1.5)  # the writer flushes within a second
    snapshot = tmp_path / "crashed.mcap"
    shutil.copyfile(path, snapshot)  # the file as a crash would leave it now
    recorder.close()
    summary = summarize(snapshot)
    assert not summary.complete
    assert summary.messages[CAMERA_TOPIC] >= 10
    assert summarize(path).complete


def test_old_recording_folders_still_replay(tmp_path: Path) -> None:
    """The former folder format (frames/*.jpg + log.jsonl) is still read."""
    folder = tmp_path / "run"
    (folder / "frames").mkdir(parents=True)
    lines = []
    for k in range(3):
        name = f"frames/{k:06d}.jpg"
        cv2.imwrite(str(folder / name), _image(k))
        lines.append(json.dumps({"kind": "frame", "t": 100.0 + 0.05 * k, "seq": k, "file": name}))
        lines.append(json.dumps({"kind": "command", "t": 100.0 + 0.05 * k, "left_pwm": k}))
    (folder / "log.jsonl").write_text("\n".join(lines) + "\n")
    camera = _replay(folder)
    assert camera.final.state == DeviceState.ENDED
    assert [level for _, level in camera.published] == pytest.approx([20, 50, 80], abs=3)


def test_writer_and_reader_depend_on_no_device_simulator_or_server() -> None:
    banned = ("app.sim", "app.hardware", "app.runtime", "app.web", "app.daemon", "app.devices")
    for name in ("mcap_writer", "mcap_reader", "schemas"):
        source = (PROJECT / "app" / "recording" / f"{name}.py").read_text()
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert not node.module.startswith(banned), f"{name} imports {node.module}"


# -- the daemon -----------------------------------------------------------------------


def _env(extra: dict[str, str]) -> dict[str, str]:
    return {
        **os.environ,
        "FLOORNAV_WEB__PORT": str(free_port()),
        "FLOORNAV_VISER__ENABLED": "false",
        "FLOORNAV_TOKEN": "mcap-test-token-000000000000",
        **extra,
    }


def _floornav(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app", *args],
        cwd=PROJECT,
        env=_env(env),
        capture_output=True,
        text=True,
        timeout=180,
    )


def _camera_fps(path: Path) -> float:
    times = np.array([m.log_time_ns for m in iter_messages(path, {CAMERA_TOPIC})]) / 1e9
    return float(1.0 / np.median(np.diff(times)))


@pytest.mark.sim
def test_run_records_then_replays_through_the_pipeline(tmp_path: Path) -> None:
    """``floornav run --record`` on the simulator, then that file replayed through
    ``floornav run`` (camera source "replay", itself recorded, stopped by SIGTERM): the
    replay feeds the pipeline at the recorded 15 fps, not the configured 30."""
    first = tmp_path / "sim.mcap"
    # No safe zone is ever sure enough to be floor (the network says ~0.98): the premise
    # stop holds forward motion from the first frame and the robot turns to look, so a
    # stop is recorded whatever way exploration would have gone.
    done = _floornav(
        "run",
        "--duration-s",
        "20",
        "--record",
        str(first),
        env={
            "FLOORNAV_CAMERA__FPS_HZ": "15",
            "FLOORNAV_PERCEPTION__ZONE_MIN_FLOOR_CONFIDENCE": "1.0",
        },
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = summarize(first)
    assert summary.complete, summary.problem
    counts = summary.messages
    assert counts[CAMERA_TOPIC] >= 200, counts  # 20 s at 15 fps, minus start-up
    assert counts[MASK_TOPIC] >= 30 and counts["/odom"] >= 10, counts
    assert counts["/drive/command"] >= 10 and counts["/map"] >= 1, counts
    assert counts["/log"] >= 1 and counts["/stops"] >= 1, counts
    assert summary.schemas[CAMERA_TOPIC] == "foxglove.CompressedImage"
    assert 13.0 < _camera_fps(first) < 17.0
    assert "recording" in done.stderr and "finished" in done.stderr

    # The replay ends with SIGTERM, as a service manager stops it: the file is finished.
    second = tmp_path / "replayed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "run", "--duration-s", "120", "--record", str(second)],
        cwd=PROJECT,
        env=_env({"FLOORNAV_CAMERA__SOURCE": "replay", "FLOORNAV_CAMERA__DEVICE": str(first)}),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    lines: list[str] = []
    try:
        for line in proc.stderr:
            lines.append(line)
            if "dashboard and API on" in line:
                break
        time.sleep(5.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, "".join(lines) + err[-3000:]
    replayed = summarize(second)
    assert replayed.complete, replayed.problem
    assert replayed.messages[CAMERA_TOPIC] >= 40, replayed.messages
    assert replayed.messages[MASK_TOPIC] >= 20, replayed.messages  # perception ran on them
    assert 13.0 < _camera_fps(second) < 17.0


def test_run_refuses_to_overwrite_a_recording(tmp_path: Path) -> None:
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep")
    done = _floornav("run", "--duration-s", "1", "--record", str(existing), env={})
    assert done.returncode == 1
    assert "never overwritten" in done.stderr
    assert existing.read_bytes() == b"keep"
