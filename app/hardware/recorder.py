"""Recording of a run: camera frames, poses, commands and telemetry, to a folder.

Layout::

    FOLDER/frames/000000.jpg ...
    FOLDER/log.jsonl          one JSON object a line, in arrival order:
        {"kind": "frame", "t": 12.345, "seq": 0, "file": "frames/000000.jpg",
         "pose": [x_m, y_m, theta_rad]}            (pose only when given)
        {"kind": "command", "t": ..., ...fields}   any other kind: `Recorder.log`

``t`` is ``time.monotonic()`` seconds. `app.hardware.cameras.ReplayCamera` plays a
recording back at its recorded pace; `read_log` reads the log.

Recording never blocks the caller: entries go through a bounded queue to a writer
thread (JPEG encoding included); when the queue is full the entry is dropped and
counted (`Recorder.dropped`).
"""

from __future__ import annotations

import json
import queue
import threading
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import cv2

from app.hardware.interfaces import CameraFrame
from app.mapping.frames import Pose2D

LOG_NAME = "log.jsonl"
FRAMES_DIR = "frames"


class Recorder:
    """Writes a recording folder (see the module docstring).

    Parameters
    ----------
    folder : created if missing; must not already hold a recording
    queue_size : entries waiting for the writer before new ones are dropped
    jpeg_quality : 0..100
    """

    def __init__(self, folder: str | Path, *, queue_size: int = 64, jpeg_quality: int = 90) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        if not 0 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 0..100, got {jpeg_quality}")
        self.folder = Path(folder)
        self.jpeg_quality = jpeg_quality
        self._queue: queue.Queue[tuple[dict[str, Any], CameraFrame | None] | None] = queue.Queue(
            maxsize=queue_size
        )
        self._lock = threading.Lock()
        self._dropped = 0
        self._written_frames = 0
        self._errors: list[str] = []
        self._next_index = 0
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        """Create the folder and start the writer thread."""
        if self._thread is not None:
            return
        if (self.folder / LOG_NAME).exists():
            raise FileExistsError(f"{self.folder} already holds a recording")
        (self.folder / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Write everything queued, then stop."""
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join()
        self._thread = None

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

    @property
    def dropped(self) -> int:
        with self._lock:
            return self._dropped

    @property
    def written_frames(self) -> int:
        with self._lock:
            return self._written_frames

    @property
    def errors(self) -> list[str]:
        """Write errors (disk full, ...); recording goes on with the next entry."""
        with self._lock:
            return list(self._errors)

    def record_frame(self, frame: CameraFrame, pose: Pose2D | None = None) -> bool:
        """Queue a frame (and the robot's pose then); False when it was dropped."""
        with self._lock:
            index = self._next_index
        entry: dict[str, Any] = {
            "kind": "frame",
            "t": frame.timestamp_s,
            "seq": frame.seq,
            "file": f"{FRAMES_DIR}/{index:06d}.jpg",
        }
        if pose is not None:
            entry["pose"] = [pose.x_m, pose.y_m, pose.theta_rad]
        if self._offer(entry, frame):
            with self._lock:
                self._next_index += 1
            return True
        return False

    def log(self, kind: str, t: float, **fields: Any) -> bool:
        """Queue one log entry (a command, telemetry, ...); False when dropped.
        ``fields`` must be JSON-serialisable."""
        if kind == "frame":
            raise ValueError("use record_frame for frames")
        return self._offer({"kind": kind, "t": t, **fields}, None)

    def _offer(self, entry: dict[str, Any], frame: CameraFrame | None) -> bool:
        if self._thread is None:
            raise RuntimeError("Recorder is not open")
        try:
            self._queue.put_nowait((entry, frame))
        except queue.Full:
            with self._lock:
                self._dropped += 1
            return False
        return True

    def _run(self) -> None:
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality]
        with (self.folder / LOG_NAME).open("a", encoding="utf-8") as out:
            while True:
                item = self._queue.get()
                if item is None:
                    return
                entry, frame = item
                try:
                    if frame is not None:
                        ok, data = cv2.imencode(".jpg", frame.image, params)
                        if not ok:
                            raise OSError("JPEG encoding failed")
                        (self.folder / entry["file"]).write_bytes(data.tobytes())
                        with self._lock:
                            self._written_frames += 1
                    out.write(json.dumps(entry) + "\n")
                    out.flush()
                except (OSError, TypeError, ValueError, cv2.error) as exc:
                    with self._lock:
                        self._errors.append(f"{entry.get('kind')} at {entry.get('t')}: {exc}")


def read_log(folder: str | Path) -> list[dict[str, Any]]:
    """Every entry of a recording's log, in order."""
    path = Path(folder) / LOG_NAME
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]
