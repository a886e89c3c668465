"""What the stages and the `Runtime` share: the configuration, the devices, the slots
that join the stages, the clocks and counters, and the few flags the verbs set.

One instance per run, used from the event loop's thread only (the stages' CPU work runs
in executors and gets its inputs as arguments, never this object)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field

from app.channels import LatestSlot
from app.config import FloornavConfig
from app.control.kinematics import WheelOdometry
from app.control.mux import CommandMux
from app.control.steering import SteeringDecision
from app.devices import Devices
from app.hardware.serial_link import UnoLink
from app.mapping.ground_map import GroundMapper
from app.messages import DriveMsg, FloorMsg, FrameMsg, MapMsg, WorldMapMsg
from app.runtime.pose_error import PoseErrorTracker
from app.runtime.stops import ProtectiveStop, StopEvent, StopPolicy
from app.runtime.telemetry import Counters, StageClock


@dataclass
class Shared:
    config: FloornavConfig
    devices: Devices
    clock: Callable[[], float]
    mux: CommandMux
    odometry: WheelOdometry
    policy: StopPolicy
    on_stop: Callable[[StopEvent], None]
    """Called with every stop a stage starts or latches (the Runtime reacts to it)."""
    mapper: GroundMapper | None = None
    link: UnoLink | None = None
    autonomous: bool = False
    calibrating: bool = False
    camera_ok: bool = False
    floor_appearances: tuple[tuple[float, float, float], ...] = ()
    """Floor colours the map has learned (an immutable tuple the mapping stage replaces;
    perception reads it before each frame)."""
    protective_stop: ProtectiveStop | None = None
    """The stop layer the drive stage applied last (None: none holds the robot)."""
    counters: Counters = field(default_factory=Counters)
    stages: StageClock = field(default_factory=StageClock)
    frames: LatestSlot[FrameMsg] = field(default_factory=lambda: LatestSlot("frames"))
    floors: LatestSlot[FloorMsg] = field(default_factory=lambda: LatestSlot("floors"))
    maps: LatestSlot[MapMsg] = field(default_factory=lambda: LatestSlot("maps"))
    world_maps: LatestSlot[WorldMapMsg] = field(default_factory=lambda: LatestSlot("world_maps"))
    decisions: LatestSlot[SteeringDecision] = field(default_factory=lambda: LatestSlot("decisions"))
    drives: LatestSlot[DriveMsg] = field(default_factory=lambda: LatestSlot("drives"))
    wake_drive: asyncio.Event = field(default_factory=asyncio.Event)
    started_s: float | None = None
    pose_error: PoseErrorTracker | None = field(init=False, default=None)
    """The pose estimate against the simulator's truth (None on hardware)."""

    def __post_init__(self) -> None:
        if self.devices.sim is not None:
            self.pose_error = PoseErrorTracker(self.devices.sim)
