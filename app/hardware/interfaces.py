"""The small interfaces hardware (real or simulated) is used through.

Implementations: ``app.hardware.cameras`` (webcam, replay) and
``app.hardware.serial_link`` (the Uno over a serial port, real or a pty). The simulator
(``app.sim``, which builds on this package, never the reverse) provides a simulated
camera and a `MotorPlant` for the simulated Uno to drive.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

import numpy as np
from numpy.typing import NDArray


class DeviceState(StrEnum):
    """Health of a device as shown to people (status API, logs)."""

    DISCONNECTED = "disconnected"
    CONNECTING = "connecting"
    CONNECTED = "connected"
    FAILED = "failed"  # gone; retrying with backoff
    ENDED = "ended"  # a replay source reached its end


@dataclass(frozen=True)
class CameraFrame:
    """One captured frame.

    Attributes
    ----------
    image : (H, W, 3) uint8 BGR
    timestamp_s : float, ``time.monotonic()`` at capture (the exposure)
    seq : int, increasing per camera from 0
    arrived_s : float or None, ``time.monotonic()`` when the host had the image (after
        the USB transfer and the decode; after the render in the simulator); None: at
        ``timestamp_s``. From here on the latency is the host's own.
    """

    image: NDArray[np.uint8]
    timestamp_s: float
    seq: int
    arrived_s: float | None = None


@dataclass(frozen=True)
class DeviceStatus:
    state: DeviceState
    detail: str = ""


class Camera(Protocol):
    """A frame source. ``latest`` never blocks: it returns the newest frame, or None
    when there is none newer than ``max_age_s`` (so a stalled camera reads as gone)."""

    def open(self) -> None: ...

    def latest(self, max_age_s: float) -> CameraFrame | None: ...

    def status(self) -> DeviceStatus: ...

    def close(self) -> None: ...


class MotorPlant(Protocol):
    """What a (simulated) Uno drives: two motors given signed PWM, two encoders."""

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None: ...

    def read_encoders(self) -> tuple[int, int]: ...
