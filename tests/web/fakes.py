"""A `RobotService` for the web tests: real slots and counters, recorded calls."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.channels import LatestSlot
from app.config import FloornavConfig
from app.control.kinematics import WheelOdometry
from app.control.mux import Twist
from app.control.steering import SteeringDecision
from app.hardware.serial_link import LinkStats
from app.loop_lag import LoopLagMonitor
from app.mapping.calibration import FloorCalibration, Intrinsics
from app.messages import DriveMsg, FloorMsg, FrameMsg, MapMsg, State, WorldMapMsg
from app.runtime import CommandRefusedError, Counters, StageClock
from app.runtime.stops import StopEvent, StopPolicy
from app.runtime.telemetry import FloatWindow
from app.web.service import CalibrationFit, CalibrationSave

from ..conftest import room_scene


@dataclass
class FakeMux:
    estops: int = 0


@dataclass
class FakeLink:
    stats: LinkStats = field(default_factory=LinkStats)


def floor_msg(
    seq: int, *, width: int = 160, height: int = 120, zone_floor_confidence: float = 0.93
) -> FloorMsg:
    """A synthetic perception result captured just now (floor = bottom part)."""
    image, truth = room_scene(width, height, seed=seq)
    return FloorMsg(
        seq=seq,
        capture_s=time.monotonic(),
        done_s=time.monotonic(),
        image=image,
        floor_mask=truth,
        method="floornav",
        timings_ms={"total": 20.0},
        zone_floor_confidence=zone_floor_confidence,
    )


def drive_msg(heading_rad: float | None = 0.3) -> DriveMsg:
    now = time.monotonic()
    return DriveMsg(Twist(0.2, 0.5), 80, 120, "autonomy", now, now - 0.05, heading_rad)


class FakeService:
    """Records every verb in ``calls``; verbs named in ``refuse`` raise CommandRefusedError."""

    def __init__(self, config: FloornavConfig | None = None) -> None:
        self.config = config or FloornavConfig()
        self.state = State.IDLE
        self.calls: list[tuple[Any, ...]] = []
        self.refuse: dict[str, str] = {}
        self.frames: LatestSlot[FrameMsg] = LatestSlot("frames")
        self.floors: LatestSlot[FloorMsg] = LatestSlot("floors")
        self.drives: LatestSlot[DriveMsg] = LatestSlot("drives")
        self.decisions: LatestSlot[SteeringDecision] = LatestSlot("decisions")
        self.maps: LatestSlot[MapMsg] = LatestSlot("maps")
        self.counters = Counters()
        self.stages = StageClock()
        self.latencies = FloatWindow()
        self.latencies_total = 0
        self.loop_lag = LoopLagMonitor()
        """Not running: tests record lags into it by hand."""
        self.mux = FakeMux()
        self.policy = StopPolicy(self.config.safety)
        self.link: FakeLink | None = FakeLink()
        self.intrinsics: Intrinsics | None = None
        self.calibration: FloorCalibration | None = None
        self.world_maps: LatestSlot[WorldMapMsg] = LatestSlot("world_maps")
        self.odometry = WheelOdometry(self.config.drive)
        self.started_s = time.monotonic()
        self.estopped = False
        self.stop_cause: str | None = None
        self.stop_reason: str | None = None

    # -- feeding it --------------------------------------------------------------------

    def add_latency(self, seconds: float) -> None:
        self.latencies.append(seconds)
        self.latencies_total += 1

    def publish_frame(self, image: NDArray[np.uint8], seq: int = 1) -> None:
        self.frames.publish(FrameMsg(image, time.monotonic(), seq))

    # -- the protocol ------------------------------------------------------------------

    def _maybe_refuse(self, verb: str) -> None:
        if verb in self.refuse:
            raise CommandRefusedError(self.refuse[verb])

    def elapsed_s(self) -> float:
        return time.monotonic() - self.started_s

    def status(self) -> dict[str, Any]:
        floor = self.floors.peek()
        return {
            "state": self.state.value,
            "fps": 12.5,
            "frame_age_ms": None if floor is None else (time.monotonic() - floor.capture_s) * 1e3,
            "stage_ms": {"perception": 21.0},
            "clearance_ahead_m": float("nan"),  # NaN must reach clients as null
            "zone_floor_confidence": None if floor is None else floor.zone_floor_confidence,
            "zone_min_floor_confidence": self.config.perception.zone_min_floor_confidence,
            "stop_cause": self.stop_cause,
            "stop_reason": self.stop_reason,
            "counters": dict(self.counters.__dict__),
            "estops": self.mux.estops,
        }

    async def start(self) -> None:
        self.calls.append(("start",))
        self._maybe_refuse("start")
        self.state = State.RUNNING

    async def stop(self) -> None:
        self.calls.append(("stop",))
        self.state = State.IDLE

    def estop(self, source: str) -> None:
        self.calls.append(("estop", source))
        if not self.estopped:
            self.mux.estops += 1
        self.estopped = True
        self.state = State.ESTOPPED

    def reset_fault(self) -> StopEvent | None:
        self.calls.append(("reset_fault",))
        return None

    def reset_estop(self) -> bool:
        self.calls.append(("reset_estop",))
        was, self.estopped = self.estopped, False
        self.state = State.IDLE
        return was

    def teleop(
        self, driver: str, v_m_s: float, omega_rad_s: float, *, take_over: bool = False
    ) -> None:
        self.calls.append(("teleop", driver, v_m_s, omega_rad_s, take_over))
        self._maybe_refuse("teleop")
        self.state = State.TELEOP

    def release_teleop(self, driver: str | None) -> None:
        self.calls.append(("release_teleop", driver))

    async def calibrate_with(
        self, fit: CalibrationFit, save: CalibrationSave | None, *, apply: bool = True
    ) -> FloorCalibration:
        self.calls.append(("calibrate",) if apply else ("calibrate", "preview"))
        self._maybe_refuse("calibrate")
        frame = self.frames.peek()
        if frame is None:
            raise CommandRefusedError("no recent camera frame to calibrate on")
        calibration = fit(frame.image)
        if not apply:
            return calibration
        if save is not None:
            save(calibration)
        self.calibration = calibration
        return calibration

    def update_config(self, config: FloornavConfig) -> None:
        self.calls.append(("update_config", config))
        self.config = config
