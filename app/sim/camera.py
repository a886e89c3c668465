"""The simulated camera: the simulator's renderer at the robot's current pose, at a
fixed fps on a thread or on demand, with the ground truth of each frame kept beside it
(`SimCamera.latest_with_truth`). Same contract as the cameras of `app.hardware.cameras`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from app.hardware.cameras import ThreadedCamera
from app.hardware.interfaces import CameraFrame, DeviceState
from app.mapping.frames import Pose2D
from app.sim.render import RenderedFrame, Renderer


class SimCamera(ThreadedCamera):
    """The simulated camera: renders at ``pose_source()`` (plan frame).

    With ``fps`` set it renders that many frames a second on its own thread (the
    renderer is then used by that thread only); with ``fps=None`` it renders on demand,
    in the caller's thread, at each `latest` / `latest_with_truth` call (serialised by a
    lock), so a test or an offline loop gets exactly the pose it just set.

    `latest_with_truth` returns the frame together with its `RenderedFrame` (floor
    mask and the exact pose it was rendered at).
    """

    _thread_name = "sim-camera"

    def __init__(
        self,
        renderer: Renderer,
        pose_source: Callable[[], Pose2D],
        *,
        fps: float | None = 15.0,
    ) -> None:
        super().__init__()
        if fps is not None and not 0 < fps <= 1000:
            raise ValueError(f"fps must be in (0, 1000] or None, got {fps}")
        self.renderer = renderer
        self.pose_source = pose_source
        self.fps = fps
        self._truth: tuple[CameraFrame, RenderedFrame] | None = None
        self._render_lock = threading.Lock()
        self._open = False

    def open(self) -> None:
        self._open = True
        if self.fps is None:
            self._set_status(DeviceState.CONNECTED)
        else:
            super().open()

    def close(self) -> None:
        self._open = False
        super().close()

    def latest(self, max_age_s: float) -> CameraFrame | None:
        pair = self.latest_with_truth(max_age_s)
        return None if pair is None else pair[0]

    def latest_with_truth(self, max_age_s: float) -> tuple[CameraFrame, RenderedFrame] | None:
        if self.fps is None:
            return self._render_now() if self._open else None
        with self._lock:
            pair = self._truth
        if pair is None or time.monotonic() - pair[0].timestamp_s > max_age_s:
            return None
        return pair

    def _render_now(self) -> tuple[CameraFrame, RenderedFrame]:
        with self._render_lock:
            # Stamped when the pose is taken, as a camera stamps its exposure: the render
            # takes 10-20 ms in a running daemon, and a frame stamped after it was placed
            # a degree or more behind in a spin turn (1.5 rad/s).
            exposure_s = time.monotonic()
            rendered = self.renderer.render(self.pose_source())
            frame = self._publish(rendered.image, exposure_s, time.monotonic())
            pair = (frame, rendered)
            with self._lock:
                self._truth = pair
        return pair

    def _run(self) -> None:
        assert self.fps is not None
        period = 1.0 / self.fps
        next_s = time.monotonic()
        while not self._stop.is_set():
            self._render_now()
            self._set_status(DeviceState.CONNECTED)
            next_s = max(next_s + period, time.monotonic() - period)
            self._stop.wait(max(0.0, next_s - time.monotonic()))
