"""JPEG frames with overlays for ``/ws/video``, encoded once per perception result.

Every video client has its own sender loop, but they all ask the one `FrameEncoder`,
which keeps the JPEG of the newest `FloorMsg` by sequence number: N clients cost one
encode per frame, not N. Drawing and encoding run in a worker thread (OpenCV releases
the GIL), so the event loop stays responsive.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import SafeZoneConfig
from app.messages import DriveMsg, FloorMsg
from app.perception.overlay import draw_overlay
from app.perception.pipeline import trapezoid_from_config

HEADING_BGR = (0, 215, 255)
HEADING_MAX_AGE_S = 1.0
"""A heading older than this (relative to the frame) is not drawn: autonomy stopped."""


@dataclass(frozen=True)
class EncodedFrame:
    """One perception result as a JPEG, with the times a browser needs for latency."""

    seq: int
    capture_s: float
    """``time.monotonic()`` at capture."""
    capture_wall_s: float
    """The same instant on the wall clock (``time.time()``), comparable with Date.now()."""
    width: int
    height: int
    method: str
    jpeg: bytes
    encode_s: float


def heading_arrow_px(
    width: int, height: int, heading_rad: float
) -> tuple[tuple[int, int], tuple[int, int]]:
    """A schematic arrow for a robot-frame heading (positive = left): from the bottom
    centre of the image, a quarter of the height long, straight up for heading 0."""
    start = (width // 2, height - 1)
    length = 0.25 * height
    end = (
        round(start[0] - length * math.sin(heading_rad)),
        round(start[1] - length * math.cos(heading_rad)),
    )
    return start, end


def render_overlay(
    floor: FloorMsg, safe_zone: SafeZoneConfig, heading_rad: float | None
) -> NDArray[np.uint8]:
    """The frame with the floor tinted, the safe zone outlined and steering's heading."""
    height, width = floor.image.shape[:2]
    corners = trapezoid_from_config(safe_zone).corners_px(width, height)
    image = draw_overlay(floor.image, floor.floor_mask, safe_zone_corners_px=corners)
    if heading_rad is not None and math.isfinite(heading_rad):
        start, end = heading_arrow_px(width, height, heading_rad)
        thickness = max(2, width // 160)
        cv2.arrowedLine(image, start, end, HEADING_BGR, thickness, cv2.LINE_AA, tipLength=0.2)
    return image


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"JPEG encoding failed for an image of shape {image.shape}")
    return bytes(buffer)


def capture_wall_time(capture_s: float) -> float:
    """Wall-clock time of a ``time.monotonic()`` instant (now minus its age)."""
    return time.time() - (time.monotonic() - capture_s)


def heading_for(floor: FloorMsg, drive: DriveMsg | None) -> float | None:
    """Steering's heading if the newest command is an autonomy one near this frame."""
    if drive is None or drive.heading_rad is None or drive.source != "autonomy":
        return None
    if abs(drive.sent_s - floor.capture_s) > HEADING_MAX_AGE_S:
        return None
    return drive.heading_rad


class FrameEncoder:
    """Encodes each `FloorMsg` once and shares the result with every client."""

    def __init__(
        self,
        quality: int,
        safe_zone: Callable[[], SafeZoneConfig],
        *,
        on_encoded: Callable[[float], None] | None = None,
    ) -> None:
        self.quality = quality
        self.safe_zone = safe_zone
        self.on_encoded = on_encoded
        self.encodes = 0
        self._seq = -1
        self._pending: asyncio.Task[EncodedFrame] | None = None

    def _encode(
        self, floor: FloorMsg, heading_rad: float | None, zone: SafeZoneConfig
    ) -> EncodedFrame:
        start = time.perf_counter()
        jpeg = encode_jpeg(render_overlay(floor, zone, heading_rad), self.quality)
        height, width = floor.image.shape[:2]
        return EncodedFrame(
            seq=floor.seq,
            capture_s=floor.capture_s,
            capture_wall_s=capture_wall_time(floor.capture_s),
            width=width,
            height=height,
            method=floor.method,
            jpeg=jpeg,
            encode_s=time.perf_counter() - start,
        )

    async def frame_for(self, floor: FloorMsg, drive: DriveMsg | None) -> EncodedFrame:
        """The JPEG of ``floor``: cached if this sequence number was encoded (or is being
        encoded) already, else encoded now in a worker thread."""
        if floor.seq != self._seq or self._pending is None:
            self._seq = floor.seq
            coro = asyncio.to_thread(
                self._encode, floor, heading_for(floor, drive), self.safe_zone()
            )
            # A task, not a bare coroutine, so every client can await the same result
            # and a client that disconnects mid-encode does not cancel it for the others.
            self._pending = asyncio.ensure_future(coro)
            self._pending.add_done_callback(self._count)
        return await asyncio.shield(self._pending)

    def _count(self, task: asyncio.Task[EncodedFrame]) -> None:
        if task.cancelled() or task.exception() is not None:
            if task is self._pending:
                self._pending = None  # retry on the next request
            return
        self.encodes += 1
        if self.on_encoded is not None:
            self.on_encoded(task.result().encode_s)
