"""Frame sources implementing `app.hardware.interfaces.Camera`.

`OpenCVCamera`
    A V4L2 webcam read by OpenCV on a daemon thread that keeps only the newest frame.
    When the device is missing or stops delivering, the state turns ``FAILED`` (with
    the reason) and the thread reopens it with exponential backoff.
`ReplayCamera`
    A video file, a folder of images, or a recording (an MCAP file of
    `app.recording.mcap_writer`, or a folder of the former ``frames/`` + ``log.jsonl``
    format), paced at the source's rate (or a given fps; a recording always at its
    recorded timing), optionally looping; ``ENDED`` at the end, ``FAILED`` on an
    unreadable source. Never raises from its thread.

Both, and the simulator's camera (`app.sim.camera.SimCamera`), build on
`ThreadedCamera` and share its contract: `open` starts the thread and returns at once,
``latest(max_age_s)`` never blocks and refuses frames older than ``max_age_s``
(``time.monotonic`` seconds), `close` stops the thread. They are context managers.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path
from types import TracebackType
from typing import Self

import cv2
import numpy as np
from numpy.typing import NDArray

from app.hardware.interfaces import CameraFrame, DeviceState, DeviceStatus
from app.imageio import ImageFileError, decode_bgr_bytes, read_bgr

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".bmp"})
DRIVER_STAMP_MAX_AGE_S = 1.0
"""A driver's frame stamp older than this when read() returns is not on
``time.monotonic``'s clock (a driver stamping wall time) and is not used."""


def capture_time_s(driver_stamp_ms: float, read_returned_s: float) -> float:
    """When a webcam frame was captured, on ``time.monotonic``'s clock.

    A V4L2 driver stamps every buffer with CLOCK_MONOTONIC (``uvcvideo``: when the
    frame's first packet arrived), and OpenCV hands that stamp out as
    ``CAP_PROP_POS_MSEC``. It is earlier than read()'s return by the USB transfer, the
    decode and the wait for this thread, which at 1.5 rad/s of spin is a degree or
    more of heading for the pose the frame is fused at. A stamp that is not before the
    return, or is older than `DRIVER_STAMP_MAX_AGE_S`, is from another clock (or none:
    0); the return time is used then.
    """
    driver_s = driver_stamp_ms / 1000.0
    if 0.0 <= read_returned_s - driver_s <= DRIVER_STAMP_MAX_AGE_S:
        return driver_s
    return read_returned_s


class ThreadedCamera(ABC):
    """The shared part: a worker thread, the newest frame, the status."""

    _thread_name = "camera"

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frame: CameraFrame | None = None
        self._status = DeviceStatus(DeviceState.DISCONNECTED)
        self._seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._set_status(DeviceState.CONNECTING)
        self._thread = threading.Thread(target=self._guarded_run, name=self._thread_name)
        self._thread.daemon = True
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._set_status(DeviceState.DISCONNECTED)

    def latest(self, max_age_s: float) -> CameraFrame | None:
        with self._lock:
            frame = self._frame
        if frame is None or time.monotonic() - frame.timestamp_s > max_age_s:
            return None
        return frame

    def status(self) -> DeviceStatus:
        with self._lock:
            return self._status

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _set_status(self, state: DeviceState, detail: str = "") -> None:
        with self._lock:
            changed = self._status.state != state or self._status.detail != detail
            self._status = DeviceStatus(state, detail)
        if changed and state in (DeviceState.FAILED, DeviceState.ENDED):
            log.info("%s: %s %s", self._thread_name, state, detail)

    def _publish(
        self, image: NDArray[np.uint8], timestamp_s: float, arrived_s: float | None = None
    ) -> CameraFrame:
        with self._lock:
            frame = CameraFrame(
                image=image, timestamp_s=timestamp_s, seq=self._seq, arrived_s=arrived_s
            )
            self._seq += 1
            self._frame = frame
        return frame

    def _guarded_run(self) -> None:
        try:
            self._run()
        except Exception as exc:  # the thread must end in a state, never silently
            log.exception("%s thread failed", self._thread_name)
            self._set_status(DeviceState.FAILED, f"internal error: {exc!r}")

    @abstractmethod
    def _run(self) -> None:
        """The source's loop, run on the camera thread until ``_stop`` is set."""


class OpenCVCamera(ThreadedCamera):
    """A webcam through OpenCV (V4L2 on Linux).

    Parameters
    ----------
    device : int index (``/dev/videoN``) or a device path
    width_px, height_px, fps : requested capture mode (the driver may pick another)
    retry_initial_s, retry_max_s : reopen backoff after a failure, doubling each time
    """

    _thread_name = "opencv-camera"

    def __init__(
        self,
        device: int | str = 0,
        *,
        width_px: int = 640,
        height_px: int = 480,
        fps: float = 30.0,
        retry_initial_s: float = 0.5,
        retry_max_s: float = 10.0,
    ) -> None:
        super().__init__()
        if not 0 < retry_initial_s <= retry_max_s:
            raise ValueError("need 0 < retry_initial_s <= retry_max_s")
        self.device = device
        self.width_px = width_px
        self.height_px = height_px
        self.fps = fps
        self.retry_initial_s = retry_initial_s
        self.retry_max_s = retry_max_s
        self.driver_stamped = False
        """The last frame carries the driver's capture stamp (else read()'s return)."""

    def _connect(self) -> cv2.VideoCapture | None:
        if isinstance(self.device, str) and not Path(self.device).exists():
            self._set_status(DeviceState.FAILED, f"{self.device}: no such device")
            return None
        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            self._set_status(DeviceState.FAILED, f"{self.device}: cannot open")
            return None
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*"MJPG"))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width_px)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height_px)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        return cap

    def _run(self) -> None:
        backoff = self.retry_initial_s
        while not self._stop.is_set():
            self._set_status(DeviceState.CONNECTING)
            cap = self._connect()
            if cap is not None:
                try:
                    while not self._stop.is_set():
                        ok, image = cap.read()
                        if not ok or image is None:
                            self._set_status(DeviceState.FAILED, f"{self.device}: read failed")
                            break
                        returned_s = time.monotonic()
                        stamp_s = capture_time_s(cap.get(cv2.CAP_PROP_POS_MSEC), returned_s)
                        self.driver_stamped = stamp_s != returned_s
                        self._publish(np.ascontiguousarray(image), stamp_s, returned_s)
                        self._set_status(DeviceState.CONNECTED)
                        backoff = self.retry_initial_s
                finally:
                    cap.release()
            self._stop.wait(backoff)
            backoff = min(self.retry_max_s, backoff * 2)


class ReplayCamera(ThreadedCamera):
    """Plays back a video file, an image folder (sorted by name), an MCAP recording
    (``*.mcap``: its ``/camera/image`` frames) or a recording folder (``frames/`` +
    ``log.jsonl``). Recordings play at their recorded timing, whatever ``fps`` says; a
    recording cut short plays up to where it stops (the status's detail says so).

    Parameters
    ----------
    source : path
    fps : playback rate of a video or an image folder; None: the video's own rate, or
        ``default_fps`` for an image folder
    loop : start again at the end instead of ending
    """

    _thread_name = "replay-camera"

    def __init__(
        self,
        source: str | Path,
        *,
        fps: float | None = None,
        loop: bool = False,
        default_fps: float = 15.0,
    ) -> None:
        super().__init__()
        if fps is not None and fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.source = Path(source)
        self.fps = fps
        self.loop = loop
        self.default_fps = default_fps

    def _image_list(self) -> tuple[list[Path], list[float] | None]:
        """Image files and, for a recording, their recorded times (seconds from the first)."""
        folder = self.source
        log_path = folder / "log.jsonl"
        if (folder / "frames").is_dir() and log_path.is_file():
            files: list[Path] = []
            times: list[float] = []
            for line in log_path.read_text(encoding="utf-8").splitlines():
                entry = json.loads(line)
                if entry.get("kind") == "frame":
                    files.append(folder / str(entry["file"]))
                    times.append(float(entry["t"]))
            if times:
                times = [t - times[0] for t in times]
            return files, times
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        return files, None

    def _pace(self, start_s: float, offset_s: float) -> bool:
        """Wait until ``start_s + offset_s``; False when closed meanwhile."""
        delay = start_s + offset_s - time.monotonic()
        return not (delay > 0 and self._stop.wait(delay))

    def _run(self) -> None:
        if not self.source.exists():
            self._set_status(DeviceState.FAILED, f"{self.source}: no such file or folder")
            return
        try:
            if self.source.is_dir():
                self._run_images()
            elif self.source.suffix.lower() == ".mcap":
                self._run_mcap()
            else:
                self._run_video()
        except (OSError, ValueError, KeyError, cv2.error) as exc:
            self._set_status(DeviceState.FAILED, f"{self.source}: {exc}")

    def _run_images(self) -> None:
        files, times = self._image_list()
        if not files:
            self._set_status(DeviceState.FAILED, f"{self.source}: no images")
            return
        period = 1.0 / (self.fps or self.default_fps)
        while not self._stop.is_set():
            start = time.monotonic()
            for k, path in enumerate(files):
                offset = times[k] if times is not None else k * period
                if not self._pace(start, offset):
                    return
                # The commands' reader: an oversized or lying file is refused from its
                # header instead of being decoded into gigabytes on the camera thread.
                try:
                    image = read_bgr(path)
                except ImageFileError as exc:
                    self._set_status(DeviceState.FAILED, str(exc))
                    return
                self._publish(image, time.monotonic())
                self._set_status(DeviceState.CONNECTED)
            if not self.loop:
                self._set_status(DeviceState.ENDED, f"{self.source}: end")
                return
            self._stop.wait(period)

    def _run_mcap(self) -> None:
        """An MCAP recording's camera frames, spaced as they were captured."""
        from app.recording.mcap_reader import RecordingError, TruncatedRecordingError, iter_images

        bad_frames, problem_logged = 0, False
        while not self._stop.is_set():
            start_s, first_ns, last_ns, played, problem = 0.0, -1, 0, 0, ""
            try:
                for k, recorded in enumerate(iter_images(self.source)):
                    try:
                        image = decode_bgr_bytes(recorded.data, name=f"{self.source} frame {k}")
                    except ImageFileError as exc:
                        bad_frames += 1
                        if bad_frames == 1:
                            log.warning("%s: skipping undecodable frames: %s", self.source, exc)
                        continue
                    if first_ns < 0:
                        first_ns, start_s = recorded.log_time_ns, time.monotonic()
                    if not self._pace(start_s, (recorded.log_time_ns - first_ns) / 1e9):
                        return
                    self._publish(image, time.monotonic())
                    self._set_status(DeviceState.CONNECTED)
                    played, last_ns = played + 1, recorded.log_time_ns
            except TruncatedRecordingError as exc:
                if played and not problem_logged:
                    log.warning("%s; played the %d frames before", exc, played)
                problem, problem_logged = str(exc), True
            except RecordingError as exc:
                self._set_status(DeviceState.FAILED, str(exc))
                return
            if played == 0:
                self._set_status(
                    DeviceState.FAILED, problem or f"{self.source}: no camera frames to replay"
                )
                return
            if not self.loop:
                detail = f"{self.source}: end" + (f" (cut short: {problem})" if problem else "")
                self._set_status(DeviceState.ENDED, detail)
                return
            gap = (last_ns - first_ns) / 1e9 / (played - 1) if played > 1 else 1 / self.default_fps
            self._stop.wait(gap)

    def _run_video(self) -> None:
        while not self._stop.is_set():
            cap = cv2.VideoCapture(str(self.source))
            try:
                if not cap.isOpened():
                    self._set_status(DeviceState.FAILED, f"{self.source}: cannot open video")
                    return
                source_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
                fps = self.fps or (source_fps if 0 < source_fps < 1000 else self.default_fps)
                start = time.monotonic()
                n = 0
                while not self._stop.is_set():
                    ok, image = cap.read()
                    if not ok or image is None:
                        break
                    if not self._pace(start, n / fps):
                        return
                    self._publish(np.ascontiguousarray(image), time.monotonic())
                    self._set_status(DeviceState.CONNECTED)
                    n += 1
            finally:
                cap.release()
            if n == 0:
                self._set_status(DeviceState.FAILED, f"{self.source}: no decodable frames")
                return
            if not self.loop:
                self._set_status(DeviceState.ENDED, f"{self.source}: end")
                return
