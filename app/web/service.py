"""What the web layer needs from the daemon, as a `typing.Protocol`.

`app.runtime.Runtime` is the real implementation; tests pass a fake. Attributes are
declared as read-only properties so that a class with plain attributes of narrower
types (``UnoLink`` for `LinkView`) still satisfies the protocol. Every member is meant
for the event loop's thread: route handlers are ``async def`` for that reason.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from app.channels import LatestSlot
from app.config import FloornavConfig
from app.control.kinematics import WheelOdometry
from app.control.steering import SteeringDecision
from app.hardware.serial_link import LinkStats
from app.mapping.calibration import FloorCalibration, Intrinsics
from app.messages import DriveMsg, FloorMsg, FrameMsg, MapMsg, State, WorldMapMsg
from app.runtime import Counters
from app.runtime.stops import StopEvent
from app.runtime.telemetry import FloatWindow

CalibrationFit = Callable[[NDArray[np.uint8]], FloorCalibration]
CalibrationSave = Callable[[FloorCalibration], None]


class StageTimings(Protocol):
    """`app.runtime.StageClock` as the metrics read it."""

    @property
    def samples(self) -> Mapping[str, FloatWindow]:
        """Per-stage durations in seconds, newest last (bounded: old ones drop out)."""

    @property
    def totals(self) -> Mapping[str, int]:
        """Samples ever added per stage, so a scrape knows how many of the deque's
        newest entries it has not seen yet even after old ones dropped out."""


class LinkView(Protocol):
    """The Uno link as the metrics read it (`app.hardware.serial_link.UnoLink`)."""

    @property
    def stats(self) -> LinkStats: ...


class LoopLagView(Protocol):
    """The event loop's lag as the metrics read it (`app.loop_lag.LoopLagMonitor`)."""

    @property
    def count(self) -> int:
        """Lags ever recorded."""

    @property
    def sum_s(self) -> float:
        """Their sum in seconds."""

    def cumulative_buckets(self) -> list[tuple[float, int]]:
        """``(upper bound in seconds, lags <= it)`` per bucket, ``inf`` last."""


class MuxView(Protocol):
    """The command mux as the metrics read it (`app.control.mux.CommandMux`)."""

    @property
    def estops(self) -> int:
        """E-stops latched since start."""


class StopView(Protocol):
    """The stop policy as the metrics read it (`app.runtime.stops.StopPolicy`)."""

    @property
    def stops_by_cause(self) -> Mapping[str, int]: ...

    @property
    def latched(self) -> StopEvent | None: ...


class RobotService(Protocol):
    """The daemon's verbs and state used by `app.web.create_app`."""

    @property
    def config(self) -> FloornavConfig: ...

    @property
    def state(self) -> State: ...

    @property
    def frames(self) -> LatestSlot[FrameMsg]:
        """Raw camera frames (the calibration preview draws on the newest)."""

    @property
    def floors(self) -> LatestSlot[FloorMsg]: ...

    @property
    def drives(self) -> LatestSlot[DriveMsg]: ...

    @property
    def decisions(self) -> LatestSlot[SteeringDecision]: ...

    @property
    def maps(self) -> LatestSlot[MapMsg]: ...

    @property
    def counters(self) -> Counters: ...

    @property
    def stages(self) -> StageTimings: ...

    @property
    def latencies(self) -> FloatWindow:
        """Capture-to-command latencies of autonomy commands (seconds), newest last."""

    @property
    def latencies_total(self) -> int:
        """Latencies ever appended to `latencies` (see `StageTimings.totals`)."""

    @property
    def loop_lag(self) -> LoopLagView:
        """How late the event loop wakes (`app.loop_lag`)."""

    @property
    def mux(self) -> MuxView: ...

    @property
    def policy(self) -> StopView:
        """Stops by cause and the latched fault."""

    @property
    def link(self) -> LinkView | None: ...

    @property
    def intrinsics(self) -> Intrinsics | None:
        """The lens model the floor calibration applies after (None: raw pixels)."""

    @property
    def calibration(self) -> FloorCalibration | None: ...

    @property
    def world_maps(self) -> LatestSlot[WorldMapMsg]:
        """The whole map, the pose and the frontier path, at most 2 Hz (read-only copies:
        readers never touch the mapper's arrays). Nothing published without a floor
        calibration."""

    @property
    def odometry(self) -> WheelOdometry: ...

    def elapsed_s(self) -> float:
        """Seconds since the run started (0 before)."""

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot (see `Runtime.status`)."""

    async def start(self) -> None:
        """Start exploring; raises `app.runtime.CommandRefusedError` saying why not."""

    async def stop(self) -> None: ...

    def estop(self, source: str) -> None: ...

    def reset_estop(self) -> bool:
        """Clear a latched e-stop; True if one was latched."""

    def reset_fault(self) -> StopEvent | None:
        """Clear a latched fault; returns it (None when none was latched)."""

    def teleop(
        self, driver: str, v_m_s: float, omega_rad_s: float, *, take_over: bool = False
    ) -> None:
        """Drive by hand for ``safety.teleop_timeout_s``; raises CommandRefusedError."""

    def release_teleop(self, driver: str | None) -> None: ...

    async def calibrate_with(
        self, fit: CalibrationFit, save: CalibrationSave | None, *, apply: bool = True
    ) -> FloorCalibration:
        """Fit on the newest frame (raises CalibrationError or CommandRefusedError), save
        and apply it; with ``apply`` false only fit (a preview: nothing live changes)."""

    def update_config(self, config: FloornavConfig) -> None:
        """Apply a configuration whose only changes are live keys."""
