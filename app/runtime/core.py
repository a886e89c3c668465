"""The daemon: assembly, the API's verbs and the state machine.

::

    camera ─► capture ─[frames]─► perception ─[floors]─► mapping ─[maps]─► steering
                                  (thread)               (thread)  │          │
                                                 [world_maps] ◄─┘          │
    Uno ◄── drive ◄── gate ◄── mux (e-stop > teleop > autonomy) ◄─────────────┘
     └── telemetry ─► odometry (pose for mapping, steering)       health ─► stop policy

Stages (`app.runtime.stages`, `app.runtime.drive`, `app.runtime.health`) are tasks in one
`asyncio.TaskGroup`, joined by `LatestSlot` s: each stage takes the newest message, so a
slow one skips frames instead of queueing them. Readers outside the pipeline (the web,
the 3D view) read those frozen messages and the 2 Hz whole-map snapshot, never the
mapper's arrays. Stops: `app.runtime.stops`; figures for people: `app.runtime.reports`.

Whatever ends the run (duration, SIGTERM/SIGINT, `Runtime.request_shutdown`, a stage
crashing) ends with the motors commanded to zero and the port closed, and the map saved
when a map file is configured.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import time
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from app.channels import LatestSlot, wait_event
from app.config import FloornavConfig, PerceptionConfig
from app.control.kinematics import RateLimiter, WheelOdometry
from app.control.mux import CommandMux, TeleopRefusedError, Twist
from app.control.steering import Steering, SteeringDecision
from app.devices import Devices
from app.hardware.interfaces import DeviceState
from app.hardware.serial_link import LinkError, UnoLink
from app.loop_lag import LoopLagMonitor
from app.mapping.calibration import FloorCalibration
from app.mapping.frontiers import FrontierSearch
from app.mapping.ground_map import GroundMapper
from app.mapping.occupancy import SavedMap
from app.messages import DriveMsg, FloorMsg, FrameMsg, MapMsg, State, Transition, WorldMapMsg
from app.perception.pipeline import FloorSegmenter
from app.runtime.context import Shared
from app.runtime.drive import DriveStage
from app.runtime.exploration import Phase, PhaseChange
from app.runtime.health import HealthStage
from app.runtime.stages import (
    CaptureStage,
    CollisionStage,
    CoverageStage,
    MappingStage,
    OdometryStage,
    PerceptionStage,
    Segmenter,
    SteeringStage,
)
from app.runtime.stops import STOP_RULES, ProtectiveStop, StopEvent, StopPolicy
from app.runtime.telemetry import Counters, FloatWindow, RssWatch, StageClock

log = logging.getLogger("floornav.runtime")

WORKER_CLOSE_TIMEOUT_S = 5.0
"""How long shutdown waits for a perception or mapping job still running."""
STRAGGLER_RECANCEL_S = 2.0
"""After the run ends, tasks still running this long are cancelled again (and named)."""


class Service(Protocol):
    """Something that runs beside the stages for the whole run (the web server)."""

    name: str

    async def serve(self) -> None: ...

    def request_stop(self) -> None: ...


class CommandRefusedError(Exception):
    """A start/teleop/calibrate request that the current state does not allow; the
    message says why (the API turns it into a 409)."""


class _ShutdownRequested(Exception):  # noqa: N818 (a signal, not an error)
    """Raised inside the task group to end the run."""


class Runtime:
    """The running daemon. Build with the configuration and opened `Devices`, then
    ``await run()``. The public methods are what the API calls; they are meant for the
    event loop's thread."""

    def __init__(
        self,
        config: FloornavConfig,
        devices: Devices,
        *,
        clock: Callable[[], float] = time.monotonic,
        segmenter_factory: Callable[[PerceptionConfig], Segmenter] = FloorSegmenter,
    ) -> None:
        self.devices = devices
        self.clock = clock
        self.intrinsics = devices.intrinsics
        self.calibration: FloorCalibration | None = devices.calibration
        self.calibration_problem = devices.calibration_problem
        self.shared = Shared(
            config=config,
            devices=devices,
            clock=clock,
            mux=CommandMux(
                teleop_timeout_s=config.safety.teleop_timeout_s,
                autonomy_timeout_s=config.safety.autonomy_timeout_s,
            ),
            odometry=WheelOdometry(config.drive),
            policy=StopPolicy(config.safety),
            on_stop=self._on_stop,
        )
        if self.calibration is not None:
            self.shared.mapper = GroundMapper(self.calibration, config.mapping, config.camera)
        self.steering = Steering(
            config.steering, config.safety, robot_radius_m=config.mapping.robot_radius_m
        )
        self.capture = CaptureStage(self.shared)
        self.perception = PerceptionStage(self.shared, segmenter_factory)
        self.mapping = MappingStage(self.shared)
        self.mapping.on_phase = self._on_phase
        self.coverage = CoverageStage(self.shared)
        self.collisions = CollisionStage(self.shared)
        self.on_explored: Callable[[], Awaitable[object]] | None = None
        """Awaited when exploration finishes (the daemon saves the map)."""
        self._explored_task: asyncio.Task[None] | None = None
        self.steering_stage = SteeringStage(self.shared, self.steering)
        self.drive = DriveStage(self.shared, RateLimiter(config.drive))
        self.workers = (
            self.perception.worker,
            self.mapping.worker,
            self.mapping.background,
            self.steering_stage.worker,
        )
        self.health = HealthStage(self.shared, self.workers, self._tick)
        self.loop_lag = LoopLagMonitor()
        self.state = State.IDLE
        self.transitions: list[Transition] = []
        self.ended_s: float | None = None
        self.rss = RssWatch()
        self.crash: str | None = None
        self._shutdown = asyncio.Event()
        self._shutdown_reason = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._services: list[Service] = []
        self._service_tasks: list[asyncio.Task[None]] = []
        self._group_tasks: list[asyncio.Task[None]] = []
        self._recanceller: asyncio.Task[None] | None = None
        self._estop_sends: set[asyncio.Task[None]] = set()

    # -- what readers see (the web's `RobotService`) ---------------------------------------

    @property
    def config(self) -> FloornavConfig:
        return self.shared.config

    @property
    def mux(self) -> CommandMux:
        return self.shared.mux

    @property
    def odometry(self) -> WheelOdometry:
        return self.shared.odometry

    @property
    def policy(self) -> StopPolicy:
        return self.shared.policy

    @property
    def link(self) -> UnoLink | None:
        return self.shared.link

    @property
    def mapper(self) -> GroundMapper | None:
        """The mapper (for the run report and map files; readers use `world_maps`)."""
        return self.shared.mapper

    @property
    def counters(self) -> Counters:
        return self.shared.counters

    @property
    def stages(self) -> StageClock:
        return self.shared.stages

    @property
    def frames(self) -> LatestSlot[FrameMsg]:
        return self.shared.frames

    @property
    def floors(self) -> LatestSlot[FloorMsg]:
        return self.shared.floors

    @property
    def maps(self) -> LatestSlot[MapMsg]:
        return self.shared.maps

    @property
    def world_maps(self) -> LatestSlot[WorldMapMsg]:
        return self.shared.world_maps

    @property
    def decisions(self) -> LatestSlot[SteeringDecision]:
        return self.shared.decisions

    @property
    def drives(self) -> LatestSlot[DriveMsg]:
        return self.shared.drives

    @property
    def latencies(self) -> FloatWindow:
        return self.drive.latencies

    @property
    def latencies_total(self) -> int:
        return self.drive.latencies_total

    @property
    def protective_stop(self) -> ProtectiveStop | None:
        return self.shared.protective_stop

    @property
    def autonomous(self) -> bool:
        return self.shared.autonomous

    @property
    def frontier(self) -> FrontierSearch | None:
        return self.mapping.frontier

    @property
    def shutdown_reason(self) -> str:
        return self._shutdown_reason

    # -- the API's verbs ------------------------------------------------------------------

    def _refuse_unless_ready(self) -> None:
        shared = self.shared
        if shared.mux.estopped:
            raise CommandRefusedError("e-stop is latched: reset it first")
        if shared.calibrating:
            raise CommandRefusedError("calibration in progress")

    async def start(self) -> None:
        """Start exploring. Raises CommandRefusedError saying why it cannot. Accepted
        while a protective stop holds the robot: it moves once the cause has cleared."""
        shared = self.shared
        self._refuse_unless_ready()
        if shared.mapper is None:
            raise CommandRefusedError(
                f"autonomy needs a floor calibration: {self.calibration_problem}"
            )
        if shared.policy.latched is not None:
            raise CommandRefusedError(
                f"fault latched: {shared.policy.latched.reason}; reset it first"
            )
        if not shared.autonomous:
            exploration = self.mapping.exploration
            exploration.set_home(shared.odometry.pose)
            if exploration.phase is Phase.EXPLORED:
                exploration.restart()
            shared.autonomous = True
            self.steering.reset()
            log.info("autonomy started", extra={"event": "start"})
        self._update_state("start requested")

    async def stop(self) -> None:
        """Stop exploring (teleop stays possible); the motors go to zero at once."""
        shared = self.shared
        if shared.autonomous:
            log.info("autonomy stopped", extra={"event": "stop"})
        shared.autonomous = False
        shared.mux.clear_autonomy()
        self._update_state("stop requested")
        shared.wake_drive.set()

    def estop(self, source: str = "api") -> None:
        """Latch the e-stop: zero now, and until `reset_estop`."""
        shared = self.shared
        if not shared.mux.estopped:
            log.warning("E-STOP latched", extra={"event": "estop", "source": source})
        shared.mux.estop(f"e-stop from {source}")
        shared.autonomous = False
        self._update_state(f"e-stop from {source}")
        shared.wake_drive.set()
        self._send_stop_now()

    def _send_stop_now(self) -> None:
        """STOP to the Uno from here, not on the drive stage's next turn: that stage may
        be waiting up to an ACK timeout for the previous command's ACK (under load the
        e-stop reached the wire 40-50 ms after `estop()`). The link writes the STOP
        beside any command in flight and drops a DRIVE queued before it."""
        link = self.shared.link
        if link is None or link.state is not DeviceState.CONNECTED:
            return  # nothing to send to (the firmware deadman has the motors)
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return  # not on the loop: the drive stage sends it on its next turn
        task = loop.create_task(self._stop_motors_logged(link), name="estop-stop")
        self._estop_sends.add(task)
        task.add_done_callback(self._estop_sends.discard)

    @staticmethod
    async def _stop_motors_logged(link: UnoLink) -> None:
        try:
            await link.stop_motors()
        except (LinkError, OSError) as exc:
            # The drive stage repeats the zero command; the deadman is below both.
            log.warning("e-stop STOP not acknowledged: %s", exc, extra={"event": "send_error"})

    def reset_estop(self) -> bool:
        was = self.shared.mux.reset_estop()
        if was:
            log.info("e-stop reset", extra={"event": "estop_reset"})
        self._update_state("e-stop reset")
        return was

    def reset_fault(self) -> StopEvent | None:
        """Clear a latched fault (autonomy stays stopped: start it again); returns the
        fault, or None when none was latched."""
        fault = self.shared.policy.reset()
        if fault is not None:
            log.info(
                "fault reset: %s",
                fault.reason,
                extra={"event": "fault_reset", "cause": fault.cause},
            )
        self._update_state("fault reset")
        return fault

    def teleop(
        self, driver: str, v_m_s: float, omega_rad_s: float, *, take_over: bool = False
    ) -> None:
        """Drive by hand for ``safety.teleop_timeout_s`` (send again to keep going).

        Raises CommandRefusedError (e-stopped, calibrating, no Uno, or another driver holds
        teleop and this one does not take over)."""
        shared = self.shared
        self._refuse_unless_ready()
        if shared.link is None or shared.link.state is not DeviceState.CONNECTED:
            raise CommandRefusedError("the Uno is not connected")
        try:
            shared.mux.teleop(driver, Twist(v_m_s, omega_rad_s), self.clock(), take_over=take_over)
        except TeleopRefusedError as exc:
            raise CommandRefusedError(str(exc)) from exc
        self._update_state(f"teleop by {driver}")
        shared.wake_drive.set()

    def release_teleop(self, driver: str | None = None) -> None:
        self.shared.mux.release(driver)
        self._update_state("teleop released")
        self.shared.wake_drive.set()

    async def calibrate_with(
        self,
        fit: Callable[[NDArray[np.uint8]], FloorCalibration],
        save: Callable[[FloorCalibration], None] | None = None,
        *,
        apply: bool = True,
    ) -> FloorCalibration:
        """Fit a new floor calibration on the newest camera frame with ``fit`` (run in a
        thread; it raises CalibrationError with the reason), save it with ``save``, and
        rebuild the mapper (the map starts afresh). Autonomy stops while calibrating; if
        the calibration then fails, that stop is recorded (cause ``calibration``: the
        status's ``last_stop`` says why autonomy is off).

        With ``apply`` false it is a preview: only ``fit`` runs (``save`` must be None)
        and its result comes back; the live calibration, the map and autonomy stay as
        they are, so it is allowed while e-stopped or calibrating too."""
        shared = self.shared
        if not apply:
            if save is not None:
                raise ValueError("a preview (apply=False) saves nothing")
            return await asyncio.to_thread(fit, self._calibration_frame().image)
        if shared.mux.estopped:
            raise CommandRefusedError("e-stop is latched: reset it first")
        frame = self._calibration_frame()
        was_autonomous = shared.autonomous
        shared.autonomous = False
        shared.mux.clear_autonomy()
        shared.calibrating = True
        self._update_state("calibrating")
        shared.wake_drive.set()
        try:
            calibration = await asyncio.to_thread(fit, frame.image)
            if save is not None:
                await asyncio.to_thread(save, calibration)
            mapper = await self.mapping.worker.run(
                GroundMapper,
                calibration,
                shared.config.mapping,
                shared.config.camera,
            )
            self.calibration, self.calibration_problem = calibration, ""
            shared.mapper = mapper
            self.mapping.forget_frontier()
            log.info(
                "floor calibration updated",
                extra={
                    "event": "calibrated",
                    "reprojection_rms_px": round(calibration.reprojection_rms_px, 3),
                },
            )
            if was_autonomous:
                log.info(
                    "autonomy stays stopped after calibration; start again", extra={"event": "stop"}
                )
            return calibration
        except Exception as exc:
            if was_autonomous:
                event = shared.policy.record(
                    "calibration",
                    f"calibration failed: {exc}; autonomy stays off until started",
                    self.clock(),
                )
                log.warning("%s", event.reason, extra={"event": "stop", "cause": event.cause})
            raise
        finally:
            shared.calibrating = False
            self._update_state("calibration finished")

    def _calibration_frame(self) -> FrameMsg:
        frame = self.shared.frames.peek()
        if frame is None or frame.age_s(self.clock()) > self.shared.config.safety.camera_max_age_s:
            raise CommandRefusedError("no recent camera frame to calibrate on")
        return frame

    def update_config(self, config: FloornavConfig) -> None:
        """Apply a new configuration live. Only steering, drive limits, safety numbers and
        perception settings take effect (perception rebuilds its segmenter before the next
        frame); devices, mapping geometry and ports need a restart, and the API allows
        changing only the live keys."""
        shared = self.shared
        shared.config = config
        self.steering.config = config.steering
        self.steering.safety = config.safety
        self.drive.limiter.drive = config.drive
        shared.mux.teleop_timeout_s = config.safety.teleop_timeout_s
        shared.mux.autonomy_timeout_s = config.safety.autonomy_timeout_s
        shared.policy.safety = config.safety
        self.perception.rebuild_segmenter()
        log.info("configuration updated", extra={"event": "config"})

    def restore_map(self, saved: SavedMap) -> None:
        """Continue from a saved map (before `run`): the mapper takes its evidence and
        odometry starts at the pose the robot had when it was saved (it has not moved
        while the daemon was off). Raises CommandRefusedError without a floor
        calibration, ValueError for a map of another grid (nothing changes then)."""
        mapper = self.shared.mapper
        if mapper is None:
            raise CommandRefusedError(
                f"no map without a floor calibration: {self.calibration_problem}"
            )
        mapper.restore(saved)
        self.shared.odometry.start_at(saved.T_world_robot)
        log.info(
            "map restored: robot at (%.2f, %.2f), %.1f m travelled into it",
            saved.T_world_robot.x_m,
            saved.T_world_robot.y_m,
            saved.travelled_m,
            extra={"event": "map_restored"},
        )

    def saved_map(self) -> SavedMap | None:
        """The map as it stands, for saving (after `run` returned: the mapping thread is
        gone then), or None without a floor calibration."""
        mapper = self.shared.mapper
        return mapper.snapshot() if mapper is not None else None

    async def saved_map_while_running(self) -> SavedMap | None:
        """`saved_map` while the stages run: the copy is taken in the mapping thread,
        between two updates."""
        mapper = self.shared.mapper
        return await self.mapping.worker.run(mapper.snapshot) if mapper is not None else None

    def request_shutdown(self, reason: str = "requested") -> None:
        if not self._shutdown.is_set():
            self._shutdown_reason = reason
            log.info("shutting down", extra={"event": "shutdown", "reason": reason})
            self._shutdown.set()

    # -- stops and state ----------------------------------------------------------------

    def _on_stop(self, event: StopEvent) -> None:
        """A stage started a stop or latched a fault."""
        shared = self.shared
        if event.latched:
            shared.counters.faults += 1
            log.error(
                "fault latched: %s; the robot stays stopped until the fault is reset",
                event.reason,
                extra={"event": "fault", "cause": event.cause},
            )
            if shared.autonomous:
                shared.autonomous = False
                shared.mux.clear_autonomy()
        elif (
            STOP_RULES[event.cause].zeroes_motors
            and not shared.config.safety.auto_resume
            and shared.autonomous
        ):
            shared.autonomous = False
            shared.mux.clear_autonomy()
            log.warning(
                "autonomy stopped by %s (safety.auto_resume is off): start again",
                event.cause,
                extra={"event": "stop"},
            )
        shared.wake_drive.set()
        self._update_state(event.reason)

    def _on_phase(self, change: PhaseChange) -> None:
        """The mapping stage saw exploration's phase change (in the loop's thread)."""
        shared = self.shared
        log.info(
            "exploration %s: %s",
            change.phase.value,
            change.reason,
            extra={"event": "exploration", "phase": change.phase.value},
        )
        if change.phase is Phase.EXPLORED:
            shared.autonomous = False
            shared.mux.clear_autonomy()
            shared.wake_drive.set()
            if self.on_explored is not None and self._explored_task is None:
                self._explored_task = asyncio.create_task(self._finish_exploration())
        self._update_state(change.reason)

    async def _finish_exploration(self) -> None:
        assert self.on_explored is not None
        try:
            await self.on_explored()
        except Exception:  # saving is not driving: say so and go on
            log.exception("after exploring: saving the map failed", extra={"event": "explored"})
        finally:
            self._explored_task = None

    def _tick(self, reason: str) -> str:
        self._update_state(reason)
        self.rss.sample(self.elapsed_s())
        return self.state.value

    def _derive_state(self) -> State:
        shared = self.shared
        if shared.mux.estopped:
            return State.ESTOPPED
        if shared.calibrating:
            return State.CALIBRATING
        if shared.policy.latched is not None:
            return State.FAULT
        now = self.clock()
        if shared.mux.teleop_driver(now) is not None:
            return State.TELEOP
        hold = shared.policy.holding(now)
        if hold is not None and (shared.autonomous or STOP_RULES[hold.cause].device):
            return State.PROTECTIVE_STOP
        phase = self.mapping.exploration.phase
        if shared.autonomous:
            return State.RETURNING if phase is Phase.RETURNING else State.RUNNING
        return State.EXPLORED if phase is Phase.EXPLORED else State.IDLE

    def _update_state(self, reason: str) -> None:
        new = self._derive_state()
        if new is self.state:
            return
        hold = self.shared.policy.holding(self.clock())
        if new is State.PROTECTIVE_STOP and hold is not None:
            reason = hold.reason
        elif new is State.FAULT and self.shared.policy.latched is not None:
            reason = self.shared.policy.latched.reason
        transition = Transition(self.clock(), time.time(), self.state, new, reason)
        self.transitions.append(transition)
        del self.transitions[:-200]
        log.info(
            "state %s -> %s (%s)",
            self.state.value,
            new.value,
            reason,
            extra={"event": "state", "old": self.state.value, "new": new.value, "reason": reason},
        )
        self.state = new

    # -- the run --------------------------------------------------------------------------

    async def run(
        self,
        *,
        duration_s: float | None = None,
        install_signals: bool = True,
        services: Sequence[Service] = (),
    ) -> None:
        """Run until `request_shutdown`, a signal, ``duration_s`` or a stage crash (which
        is re-raised after the motors are stopped). ``services`` run beside the stages
        (a crash of one ends the run like a stage's) and are asked to stop first."""
        shared = self.shared
        self._services = list(services)
        self._service_tasks, self._group_tasks, self._recanceller = [], [], None
        self._loop = asyncio.get_running_loop()
        shared.link = self.devices.make_link()
        shared.started_s = self.clock()
        self.rss.sample(0.0, force=True)
        signals = self._install_signals() if install_signals else []
        try:
            await shared.link.start()
            self.devices.camera.open()
            try:
                async with asyncio.TaskGroup() as group:
                    stages: dict[str, Coroutine[Any, Any, None]] = {
                        "capture": self.capture.run(),
                        "perception": self.perception.run(),
                        "mapping": self.mapping.run(),
                        "steering": self.steering_stage.run(),
                        "drive": self.drive.run(),
                        "odometry": OdometryStage(shared).run(),
                        "coverage": self.coverage.run(),
                        "collisions": self.collisions.run(),
                        "health": self.health.run(),
                        "loop_lag": self.loop_lag.run(),
                    }
                    for name, coro in stages.items():
                        self._group_tasks.append(
                            group.create_task(self._guard(name, coro), name=name)
                        )
                    for service in self._services:
                        task = group.create_task(
                            self._guard(service.name, service.serve()), name=service.name
                        )
                        self._service_tasks.append(task)
                        self._group_tasks.append(task)
                    if shared.config.autostarts():
                        self._group_tasks.append(
                            group.create_task(
                                self._guard("autostart", self._autostart()), name="autostart"
                            )
                        )
                    group.create_task(self._until_shutdown(duration_s), name="shutdown")
            except* _ShutdownRequested:
                pass
            finally:
                if self._recanceller is not None:
                    self._recanceller.cancel()
        except BaseException as exc:
            if self.crash is None and not isinstance(exc, asyncio.CancelledError):
                self.crash = f"{type(exc).__name__}: {exc}"
            raise
        finally:
            self.ended_s = self.clock()
            await self._stop_everything()
            self.rss.sample(self.elapsed_s(), force=True)
            for sig in signals:
                self._loop.remove_signal_handler(sig)

    def _install_signals(self) -> list[int]:
        assert self._loop is not None
        installed: list[int] = []
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                self._loop.add_signal_handler(sig, self.request_shutdown, signal.Signals(sig).name)
                installed.append(sig)
            except (NotImplementedError, RuntimeError, ValueError):
                pass  # not the main thread (tests): the caller stops us
        return installed

    async def _until_shutdown(self, duration_s: float | None) -> None:
        if not await wait_event(self._shutdown, duration_s):
            self._shutdown_reason = f"duration {duration_s:g} s reached"
            log.info("run duration reached", extra={"event": "shutdown", "duration_s": duration_s})
        # Let services close their sockets and connections before the group cancels.
        for service in self._services:
            service.request_stop()
        if self._service_tasks:
            await asyncio.wait(self._service_tasks, timeout=3.0)
        self._start_recanceller()
        raise _ShutdownRequested(self._shutdown_reason)

    def _start_recanceller(self) -> None:
        if self._recanceller is None:
            self._recanceller = asyncio.create_task(self._recancel_stragglers(), name="recancel")

    async def _recancel_stragglers(self) -> None:
        """The task group cancels every task once when the run ends, and waits for all.
        A task that loses that cancellation (a library swallowing it, or wait_for on
        3.11: see `wait_event`) would keep the daemon from ever stopping, and a second
        cancel of the run does not reach the group's tasks. So cancel them again."""
        while True:
            await asyncio.sleep(STRAGGLER_RECANCEL_S)
            stragglers = [task for task in self._group_tasks if not task.done()]
            if not stragglers:
                return
            log.error(
                "still running %.0f s after the run ended (lost a cancellation): %s; "
                "cancelling again",
                STRAGGLER_RECANCEL_S,
                ", ".join(task.get_name() for task in stragglers),
                extra={"event": "straggler"},
            )
            for task in stragglers:
                task.cancel()

    async def _guard(self, name: str, coro: Awaitable[None]) -> None:
        try:
            await coro
        except (_ShutdownRequested, asyncio.CancelledError):
            raise
        except Exception as exc:
            self.crash = f"stage {name}: {type(exc).__name__}: {exc}"
            log.exception(
                "stage %s crashed; stopping", name, extra={"event": "crash", "stage": name}
            )
            # Zero the motors before the task group unwinds the other stages.
            self.shared.autonomous = False
            self.shared.mux.estop(f"stage {name} crashed")
            self._start_recanceller()
            raise

    async def _stop_everything(self) -> None:
        self.shared.autonomous = False
        link = self.shared.link
        if link is not None:
            # Bounded: shutdown must finish even if the device hangs (the firmware's
            # deadman stops the motors 250 ms after the last command anyway).
            with contextlib.suppress(LinkError, OSError, TimeoutError):
                await asyncio.wait_for(link.stop_motors(), timeout=1.0)
            try:
                await asyncio.wait_for(link.stop(), timeout=3.0)  # STOP, then close
                log.info("motors stopped, port closed", extra={"event": "motors_zero"})
            except TimeoutError:
                log.error(
                    "the Uno link did not close in 3 s; the firmware deadman stops the motors",
                    extra={"event": "motors_zero_timeout"},
                )
        self.devices.camera.close()
        workers = self.workers
        for worker in workers:
            worker.shutdown()
        for worker in workers:
            # Bounded, and without blocking the loop: a job stuck in native code must
            # not keep the daemon from exiting (its thread is a daemon thread).
            if not await worker.wait_closed(WORKER_CLOSE_TIMEOUT_S):
                log.error(
                    "the %s thread is still busy after %.0f s; leaving it behind. It is at:\n%s",
                    worker.name,
                    WORKER_CLOSE_TIMEOUT_S,
                    worker.stack(),
                    extra={"event": "worker_stuck", "stage": worker.name},
                )

    async def _autostart(self) -> None:
        shared = self.shared
        deadline = self.clock() + shared.config.serial.handshake_timeout_s + 10.0
        while self.clock() < deadline:
            if shared.mapper is None:
                log.warning(
                    "autostart: autonomy refused, teleop allowed: %s",
                    self.calibration_problem,
                    extra={"event": "autonomy_refused"},
                )
                return
            devices_up = shared.policy.holding(self.clock()) is None
            if devices_up and shared.maps.peek() is not None:
                await self.start()
                return
            await asyncio.sleep(0.05)
        hold = shared.policy.holding(self.clock())
        log.warning(
            "autostart gave up: %s",
            hold.reason if hold is not None else "no map yet",
            extra={"event": "autostart_failed"},
        )

    # -- reports --------------------------------------------------------------------------

    def elapsed_s(self) -> float:
        started = self.shared.started_s
        if started is None:
            return 1e-9  # never started: rates come out as 0, not a division by zero
        end = self.ended_s if self.ended_s is not None else self.clock()
        return max(1e-9, end - started)

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot for the API and the dashboard."""
        from app.runtime.reports import status

        return status(self)

    def report(self) -> dict[str, Any]:
        """The run report ``floornav run --report`` writes (sim-only fields null on
        hardware)."""
        from app.runtime.reports import report

        return report(self)
