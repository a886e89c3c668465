"""The daemon: the one place that wires the stages together.

::

    camera ─► capture ─[frames]─► perception ─[floors]─► mapping ─[maps]─► steering
                                  (thread)               (thread)            │
    Uno ◄── drive ◄── mux (e-stop > teleop > autonomy) ◄─────────────────────┘
     └── telemetry ─► odometry (pose for mapping, steering)

Stages are tasks in one `asyncio.TaskGroup`, joined by `LatestSlot` s: each stage takes
the newest message, so a slow one skips frames instead of queueing them. Perception and
mapping run in their own single-thread executors (OpenCV, numpy and numba release the
GIL; each owns its non-thread-safe object). The drive stage evaluates the mux every
``drive.control_period_ms`` and at once on every new command, applies the host's stop
layers (stale perception or map, camera gone, a safe zone that is not floor, minimum
clearance ahead, latched e-stop) and sends wheel PWM to the Uno; the firmware's deadman
is the last layer.

Whatever ends the run (duration, SIGTERM/SIGINT, `Runtime.request_shutdown`, a stage
crashing) ends with the motors commanded to zero and the port closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import os
import signal
import statistics
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from app import systemd
from app.channels import LatestSlot, SlotReader, wait_event
from app.config import FloornavConfig, PerceptionConfig
from app.control.kinematics import RateLimiter, WheelOdometry, twist_to_pwm
from app.control.mux import CommandMux, MuxOutput, TeleopRefusedError, Twist
from app.control.steering import Steering, SteeringDecision
from app.devices import Devices
from app.hardware.interfaces import DeviceState
from app.hardware.serial_link import LinkError, NotConnectedError, UnoLink
from app.mapping.calibration import FloorCalibration
from app.mapping.frames import FLOOR, GroundGrid, Pose2D
from app.mapping.frontiers import FrontierSearch
from app.mapping.ground_map import GroundMapper
from app.mapping.occupancy import classify_log_odds
from app.messages import DriveMsg, FloorMsg, FrameMsg, MapMsg, State, Transition
from app.perception.image_checks import ImageError
from app.perception.pipeline import FloorResult, FloorSegmenter
from app.perception.safe_zone import SafeZoneError
from app.workers import StageWorker

log = logging.getLogger("floornav.runtime")


CAMERA_START_GRACE_S = 5.0
WORKER_CLOSE_TIMEOUT_S = 5.0
"""How long shutdown waits for a perception or mapping job still running."""
STRAGGLER_RECANCEL_S = 2.0
"""After the run ends, tasks still running this long are cancelled again (and named)."""
WORKER_STUCK_S = 2.0
"""A perception or mapping job running this long is logged with its stack (once)."""
"""How long a camera may take to deliver its first frame before it counts as a fault."""

CAPTURE_POLL_S = 0.002
"""How often capture looks for a new frame (the cameras publish from their threads)."""


class Segmenter(Protocol):
    """What perception needs (`FloorSegmenter`; tests pass slow or failing ones)."""

    def segment(self, image: NDArray[np.uint8]) -> FloorResult: ...


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


def rss_mb() -> float | None:
    """Resident memory of this process (Linux), or None."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def percentiles_ms(values_s: Any) -> dict[str, float | None]:
    data = sorted(values_s)
    if not data:
        return {"p50": None, "p95": None, "max": None, "n": 0}

    def pick(q: float) -> float:
        return round(float(data[min(len(data) - 1, round(q * (len(data) - 1)))]) * 1000, 2)

    return {"p50": pick(0.5), "p95": pick(0.95), "max": round(data[-1] * 1000, 2), "n": len(data)}


def newest(values: deque[float], n: int) -> list[float]:
    """The last ``n`` values without copying the whole (100k-long) window."""
    return list(itertools.islice(reversed(values), n))


class StageClock:
    """Per-stage durations (seconds), newest last, bounded."""

    def __init__(self, maxlen: int = 100_000) -> None:
        self.maxlen = maxlen
        self.samples: dict[str, deque[float]] = {}
        self.totals: dict[str, int] = {}
        """Samples ever added per stage (the windows drop old ones; metrics need counts)."""

    def add(self, stage: str, seconds: float) -> None:
        self.samples.setdefault(stage, deque(maxlen=self.maxlen)).append(seconds)
        self.totals[stage] = self.totals.get(stage, 0) + 1

    def summary_ms(self) -> dict[str, dict[str, float | None]]:
        return {name: percentiles_ms(values) for name, values in self.samples.items()}

    def recent_ms(self, n: int = 30) -> dict[str, float]:
        out = {}
        for name, values in self.samples.items():
            tail = newest(values, n)
            if tail:
                out[name] = round(statistics.median(tail) * 1000, 2)
        return out


@dataclass
class Counters:
    frames_captured: int = 0
    frames_perceived: int = 0
    frames_mapped: int = 0
    frames_skipped: int = 0
    bad_frames: int = 0
    commands_sent: int = 0
    send_errors: int = 0
    watchdog_stops: int = 0
    clearance_stops: int = 0
    premise_stops: int = 0
    """Times the safe zone ahead stopped being floor while driving (rising edges)."""
    faults: int = 0


@dataclass(frozen=True)
class ProtectiveStop:
    """A transient stop layer holding the robot back now (it clears by itself).

    ``cause``: "watchdog" (stale perception or map: motors zero), "not_floor" (the safe
    zone is not floor: no forward motion, autonomy turns to look elsewhere) or
    "clearance" (too little free floor ahead: no forward motion). ``reason`` says it in
    a sentence for people."""

    cause: str
    reason: str


def clearance_ahead_m(
    patch: NDArray[np.uint8],
    patch_grid: GroundGrid,
    robot_radius_m: float,
    max_range_m: float,
    *,
    blocked_fraction: float = 0.25,
) -> float:
    """Free floor ahead of the robot's front edge in a bird's-eye patch: the distance to
    the nearest row of the robot-wide corridor in which at least ``blocked_fraction`` of
    the cells are not floor (unseen counts as not floor). The fraction keeps a few
    misclassified cells (a plank seam, a reflection) from stopping the robot; anything
    a quarter of the robot's width wide does."""
    x, y = patch_grid.cell_centers()
    corridor = np.abs(y[0]) <= robot_radius_m
    rows_x = x[:, 0]
    ahead = rows_x > 0
    not_floor = patch[:, corridor] != FLOOR
    blocked_rows = ahead & (not_floor.mean(axis=1) >= blocked_fraction)
    nearest = float(rows_x[blocked_rows].min()) if blocked_rows.any() else max_range_m
    return max(0.0, nearest - patch_grid.cell_m / 2 - robot_radius_m)


def map_window(
    log_odds: NDArray[np.float32],
    grid: GroundGrid,
    center_xy: tuple[float, float],
    side_m: float,
    *,
    free_threshold: float,
    occupied_threshold: float,
) -> tuple[NDArray[np.int8], GroundGrid]:
    """Classes of the square of ``side_m`` around ``center_xy`` (clipped to the grid)."""
    half = math.ceil(side_m / 2 / grid.cell_m)
    row, col = (int(v) for v in grid.cell_of(np.array([center_xy]))[0])
    r0, r1 = max(0, row - half), min(grid.rows, row + half + 1)
    c0, c1 = max(0, col - half), min(grid.cols, col + half + 1)
    if r0 >= r1 or c0 >= c1:
        r0, r1, c0, c1 = 0, 1, 0, 1
    cells = classify_log_odds(
        log_odds[r0:r1, c0:c1], free_threshold=free_threshold, occupied_threshold=occupied_threshold
    )
    window = GroundGrid(
        grid.x_max_m - r0 * grid.cell_m,
        grid.y_max_m - c0 * grid.cell_m,
        grid.cell_m,
        r1 - r0,
        c1 - c0,
    )
    return cells, window


def path_to_xy(search: FrontierSearch, grid: GroundGrid) -> NDArray[np.float64] | None:
    if search.goal is None:
        return None
    rc = search.goal.path_cells
    xs = grid.x_max_m - (rc[:, 0] + 0.5) * grid.cell_m
    ys = grid.y_max_m - (rc[:, 1] + 0.5) * grid.cell_m
    return np.column_stack((xs, ys))


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
        self.config = config
        self.devices = devices
        self.clock = clock
        self.segmenter_factory = segmenter_factory
        self.intrinsics = devices.intrinsics
        self.mux = CommandMux(
            teleop_timeout_s=config.safety.teleop_timeout_s,
            autonomy_timeout_s=config.safety.autonomy_timeout_s,
        )
        self.odometry = WheelOdometry(config.drive)
        self.steering = Steering(
            config.steering, config.safety, robot_radius_m=config.mapping.robot_radius_m
        )
        self.limiter = RateLimiter(config.drive)
        self.stages = StageClock()
        self.frame_ages: deque[float] = deque(maxlen=100_000)
        self.latencies: deque[float] = deque(maxlen=100_000)
        self.latencies_total = 0
        self.counters = Counters()
        self.steering_reasons: dict[str, int] = {}
        self.transitions: deque[Transition] = deque(maxlen=200)
        self.frames: LatestSlot[FrameMsg] = LatestSlot("frames")
        self.floors: LatestSlot[FloorMsg] = LatestSlot("floors")
        self.maps: LatestSlot[MapMsg] = LatestSlot("maps")
        self.decisions: LatestSlot[SteeringDecision] = LatestSlot("decisions")
        self.drives: LatestSlot[DriveMsg] = LatestSlot("drives")
        self.frontier: FrontierSearch | None = None
        self.given_up_goals: list[tuple[float, float]] = []
        self._goal_since: tuple[tuple[float, float], float] | None = None
        self.link: UnoLink | None = None
        self.mapper: GroundMapper | None = None
        self.calibration: FloorCalibration | None = devices.calibration
        self.calibration_problem = devices.calibration_problem
        self.state = State.IDLE
        self.started_s: float | None = None
        self.ended_s: float | None = None
        self.rss_start_mb: float | None = None
        self.rss_end_mb: float | None = None
        self.crash: str | None = None
        self._autonomous = False
        self._calibrating = False
        self._fault_reason = ""
        self._camera_ok = False
        self._wake_drive = asyncio.Event()
        self._shutdown = asyncio.Event()
        self._shutdown_reason = ""
        self._perception_worker = StageWorker("perception")
        self._mapping_worker = StageWorker("mapping")
        self._stuck_reported: set[str] = set()
        self._frontier_due_s = 0.0
        self._last_latency_origin = -1.0
        self._last_pwm: tuple[int, int] | None = None
        self._stale_active = False
        self._clearance_active = False
        self._premise_active = False
        self.protective_stop: ProtectiveStop | None = None
        """The stop layer the drive stage applied last (None: none holds the robot)."""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._perception_config_changed = False
        self._services: list[Service] = []
        self._service_tasks: list[asyncio.Task[None]] = []
        self._group_tasks: list[asyncio.Task[None]] = []
        self._recanceller: asyncio.Task[None] | None = None
        if self.calibration is not None:
            self.mapper = GroundMapper(self.calibration, config.mapping, config.camera)

    # -- the API's verbs ------------------------------------------------------------------

    async def start(self) -> None:
        """Start exploring. Raises CommandRefusedError saying why it cannot."""
        if self.mux.estopped:
            raise CommandRefusedError("e-stop is latched: reset it first")
        if self._calibrating:
            raise CommandRefusedError("calibration in progress")
        if self.mapper is None:
            raise CommandRefusedError(
                f"autonomy needs a floor calibration: {self.calibration_problem}"
            )
        if self._fault_reason:
            raise CommandRefusedError(f"devices not ready: {self._fault_reason}")
        if not self._autonomous:
            self._autonomous = True
            self.steering.reset()
            log.info("autonomy started", extra={"event": "start"})
        self._update_state("start requested")

    async def stop(self) -> None:
        """Stop exploring (teleop stays possible); the motors go to zero at once."""
        if self._autonomous:
            log.info("autonomy stopped", extra={"event": "stop"})
        self._autonomous = False
        self.mux.clear_autonomy()
        self._update_state("stop requested")
        self._wake_drive.set()

    def estop(self, source: str = "api") -> None:
        """Latch the e-stop: zero now, and until `reset_estop`."""
        if not self.mux.estopped:
            log.warning("E-STOP latched", extra={"event": "estop", "source": source})
        self.mux.estop(f"e-stop from {source}")
        self._autonomous = False
        self._update_state(f"e-stop from {source}")
        self._wake_drive.set()

    def reset_estop(self) -> bool:
        was = self.mux.reset_estop()
        if was:
            log.info("e-stop reset", extra={"event": "estop_reset"})
        self._update_state("e-stop reset")
        return was

    def teleop(
        self, driver: str, v_m_s: float, omega_rad_s: float, *, take_over: bool = False
    ) -> None:
        """Drive by hand for ``safety.teleop_timeout_s`` (send again to keep going).

        Raises CommandRefusedError (e-stopped, calibrating, no Uno, or another driver holds
        teleop and this one does not take over)."""
        if self.mux.estopped:
            raise CommandRefusedError("e-stop is latched: reset it first")
        if self._calibrating:
            raise CommandRefusedError("calibration in progress")
        if self.link is None or self.link.state is not DeviceState.CONNECTED:
            raise CommandRefusedError("the Uno is not connected")
        try:
            self.mux.teleop(driver, Twist(v_m_s, omega_rad_s), self.clock(), take_over=take_over)
        except TeleopRefusedError as exc:
            raise CommandRefusedError(str(exc)) from exc
        self._update_state(f"teleop by {driver}")
        self._wake_drive.set()

    def release_teleop(self, driver: str | None = None) -> None:
        self.mux.release(driver)
        self._update_state("teleop released")
        self._wake_drive.set()

    async def calibrate_with(
        self,
        fit: Callable[[NDArray[np.uint8]], FloorCalibration],
        save: Callable[[FloorCalibration], None] | None = None,
    ) -> FloorCalibration:
        """Fit a new floor calibration on the newest camera frame with ``fit`` (run in a
        thread; it raises CalibrationError with the reason), save it with ``save``, and
        rebuild the mapper (the map starts afresh). Autonomy stops while calibrating."""
        if self.mux.estopped:
            raise CommandRefusedError("e-stop is latched: reset it first")
        frame = self.frames.peek()
        if frame is None or frame.age_s(self.clock()) > self.config.safety.camera_max_age_s:
            raise CommandRefusedError("no recent camera frame to calibrate on")
        was_autonomous = self._autonomous
        self._autonomous = False
        self.mux.clear_autonomy()
        self._calibrating = True
        self._update_state("calibrating")
        self._wake_drive.set()
        try:
            calibration = await asyncio.to_thread(fit, frame.image)
            if save is not None:
                await asyncio.to_thread(save, calibration)
            mapper = await self._mapping_worker.run(
                GroundMapper,
                calibration,
                self.config.mapping,
                self.config.camera,
            )
            self.calibration, self.mapper, self.calibration_problem = calibration, mapper, ""
            self.frontier = None
            log.info(
                "floor calibration updated",
                extra={
                    "event": "calibrated",
                    "reprojection_rms_px": round(calibration.reprojection_rms_px, 3),
                },
            )
            return calibration
        finally:
            self._calibrating = False
            self._update_state("calibration finished")
            if was_autonomous and self.mapper is not None:
                log.info(
                    "autonomy stays stopped after calibration; start again", extra={"event": "stop"}
                )

    def update_config(self, config: FloornavConfig) -> None:
        """Apply a new configuration live. Only steering, drive limits, safety numbers and
        perception settings take effect (perception rebuilds its segmenter before the next
        frame); devices, mapping geometry and ports need a restart, and the API allows
        changing only the live keys."""
        self.config = config
        self.steering.config = config.steering
        self.steering.safety = config.safety
        self.limiter.drive = config.drive
        self.mux.teleop_timeout_s = config.safety.teleop_timeout_s
        self.mux.autonomy_timeout_s = config.safety.autonomy_timeout_s
        self._perception_config_changed = True
        log.info("configuration updated", extra={"event": "config"})

    def request_shutdown(self, reason: str = "requested") -> None:
        if not self._shutdown.is_set():
            self._shutdown_reason = reason
            log.info("shutting down", extra={"event": "shutdown", "reason": reason})
            self._shutdown.set()

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
        self._services = list(services)
        self._service_tasks, self._group_tasks, self._recanceller = [], [], None
        self._loop = asyncio.get_running_loop()
        self.link = self.devices.make_link()
        self.rss_start_mb = rss_mb()
        self.started_s = self.clock()
        signals = self._install_signals() if install_signals else []
        try:
            await self.link.start()
            self.devices.camera.open()
            try:
                async with asyncio.TaskGroup() as group:
                    stages: dict[str, Coroutine[Any, Any, None]] = {
                        "capture": self._capture_stage(),
                        "perception": self._perception_stage(),
                        "mapping": self._mapping_stage(),
                        "steering": self._steering_stage(),
                        "drive": self._drive_stage(),
                        "odometry": self._odometry_stage(),
                        "health": self._health_stage(),
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
                    if self.config.runtime.autostart:
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
            self.rss_end_mb = rss_mb()
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
            self._autonomous = False
            self.mux.estop(f"stage {name} crashed")
            self._start_recanceller()
            raise

    async def _stop_everything(self) -> None:
        self._autonomous = False
        link = self.link
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
        for worker in (self._perception_worker, self._mapping_worker):
            worker.shutdown()
        for worker in (self._perception_worker, self._mapping_worker):
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
        deadline = self.clock() + self.config.serial.handshake_timeout_s + 10.0
        while self.clock() < deadline:
            if self.mapper is None:
                log.warning(
                    "autostart: autonomy refused, teleop allowed: %s",
                    self.calibration_problem,
                    extra={"event": "autonomy_refused"},
                )
                return
            if not self._fault_reason and self.maps.peek() is not None:
                await self.start()
                return
            await asyncio.sleep(0.05)
        log.warning(
            "autostart gave up: %s",
            self._fault_reason or "no map yet",
            extra={"event": "autostart_failed"},
        )

    # -- stages ---------------------------------------------------------------------------

    async def _capture_stage(self) -> None:
        camera = self.devices.camera
        max_age = self.config.safety.camera_max_age_s
        last_seq = -1
        while True:
            frame = camera.latest(max_age)
            if frame is not None and frame.seq != last_seq:
                if last_seq >= 0 and frame.seq > last_seq + 1:
                    self.counters.frames_skipped += frame.seq - last_seq - 1
                last_seq = frame.seq
                self.counters.frames_captured += 1
                self.frames.publish(FrameMsg(frame.image, frame.timestamp_s, frame.seq))
            self._camera_ok = frame is not None
            await asyncio.sleep(CAPTURE_POLL_S)

    async def _perception_stage(self) -> None:
        segmenter = self.segmenter_factory(self.config.perception)
        reader = SlotReader(self.frames)
        while True:
            frame = await reader.next()
            if self._perception_config_changed:
                self._perception_config_changed = False
                segmenter = self.segmenter_factory(self.config.perception)
            start = self.clock()
            self.frame_ages.append(start - frame.capture_s)
            try:
                result = await self._perception_worker.run(segmenter.segment, frame.image)
            except (ImageError, SafeZoneError) as exc:
                self.counters.bad_frames += 1
                log.warning("frame %d rejected: %s", frame.seq, exc, extra={"event": "bad_frame"})
                continue
            done = self.clock()
            self.stages.add("perception", done - start)
            self.counters.frames_perceived += 1
            self.floors.publish(
                FloorMsg(
                    frame.seq,
                    frame.capture_s,
                    done,
                    frame.image,
                    result.floor_mask,
                    result.method,
                    result.timings_ms,
                    result.zone_floor_confidence,
                )
            )

    def _map_step(
        self,
        mapper: GroundMapper,
        floor: FloorMsg,
        pose: Pose2D,
        now_pose: Pose2D,
        frontier_due: bool,
    ) -> tuple[MapMsg, FrontierSearch | None]:
        """In the mapping thread: fuse the frame, maybe search frontiers, cut the window."""
        update = mapper.update(floor.floor_mask, pose, floor.capture_s, floor.image)
        search = (
            mapper.frontiers(now_pose, given_up_xy=self.given_up_goals) if frontier_due else None
        )
        frontier = search if search is not None else self.frontier
        params = mapper.grid.params
        cells, window = map_window(
            mapper.grid.log_odds,
            mapper.grid.world_grid,
            (now_pose.x_m, now_pose.y_m),
            self.config.steering.local_window_m,
            free_threshold=params.free_threshold,
            occupied_threshold=params.occupied_threshold,
        )
        clearance = clearance_ahead_m(
            update.patch,
            mapper.birdseye.grid,
            self.config.mapping.robot_radius_m,
            self.config.mapping.max_range_m,
        )
        goal = frontier.goal if frontier is not None else None
        msg = MapMsg(
            seq=floor.seq,
            capture_s=floor.capture_s,
            done_s=time.monotonic(),
            T_odom_robot=pose,
            window_cells=cells,
            window_grid=window,
            path_xy=path_to_xy(frontier, mapper.grid.world_grid) if frontier is not None else None,
            goal_xy=goal.xy if goal is not None else None,
            frontier_reason=frontier.reason if frontier is not None else "not searched yet",
            clearance_ahead_m=clearance,
        )
        return msg, search

    async def _mapping_stage(self) -> None:
        reader = SlotReader(self.floors)
        while True:
            floor = await reader.next()
            mapper = self.mapper
            if mapper is None or self._calibrating:
                continue
            start = self.clock()
            frontier_due = start >= self._frontier_due_s
            if frontier_due:
                self._frontier_due_s = start + self.config.steering.frontier_period_s
            pose = self.odometry.pose_at(floor.capture_s)
            msg, search = await self._mapping_worker.run(
                self._map_step,
                mapper,
                floor,
                pose,
                self.odometry.pose,
                frontier_due,
            )
            if mapper is not self.mapper:
                continue  # recalibrated meanwhile: this map is gone
            if search is not None:
                self.frontier = search
                if self._autonomous and not self.mux.estopped:
                    self._track_goal(search, start)
                else:
                    self._goal_since = None  # patience counts only while exploring
            done = self.clock()
            self.stages.add("mapping", done - start)
            self.counters.frames_mapped += 1
            self.maps.publish(msg)

    def _track_goal(self, search: FrontierSearch, now: float) -> None:
        """Give up on a goal that has stayed (within 0.3 m) the goal for
        ``steering.goal_patience_s``: it cannot be seen from where the robot can go."""
        goal = search.goal
        if goal is None:
            self._goal_since = None
            return
        if self._goal_since is None or math.dist(goal.xy, self._goal_since[0]) > 0.3:
            self._goal_since = (goal.xy, now)
            return
        if now - self._goal_since[1] > self.config.steering.goal_patience_s:
            self.given_up_goals.append(goal.xy)
            log.info(
                "frontier goal (%.2f, %.2f) given up after %.0f s",
                goal.xy[0],
                goal.xy[1],
                self.config.steering.goal_patience_s,
                extra={"event": "goal_given_up"},
            )
            self._goal_since = None

    async def _steering_stage(self) -> None:
        reader = SlotReader(self.maps)
        while True:
            msg = await reader.next()
            if not self._autonomous or self.mux.estopped:
                continue
            start = self.clock()
            decision = self.steering.decide(
                msg.window_cells,
                msg.window_grid,
                self.odometry.pose,
                msg.path_xy,
                blocked_ahead=self._zone_not_floor(start) is not None,
            )
            self.stages.add("steering", self.clock() - start)
            self.steering_reasons[decision.reason] = (
                self.steering_reasons.get(decision.reason, 0) + 1
            )
            self.decisions.publish(decision)
            self.mux.autonomy(decision.twist, self.clock(), origin_s=msg.capture_s)
            self._wake_drive.set()

    async def _odometry_stage(self) -> None:
        link = self.link
        assert link is not None
        async for telemetry in link.telemetry_updates():
            data = telemetry.data
            self.odometry.update(data.encoder_left, data.encoder_right, telemetry.received_s)

    async def _health_stage(self) -> None:
        link = self.link
        assert link is not None
        period = self.config.drive.control_period_ms / 1000.0
        was_connected = False
        watchdog_s = systemd.watchdog_interval_s()
        next_ping_s = 0.0
        while True:
            if watchdog_s is not None and self.clock() >= next_ping_s:
                # systemd restarts the daemon if these stop (a hung event loop).
                systemd.notify(f"WATCHDOG=1\nSTATUS={self.state.value}")
                next_ping_s = self.clock() + watchdog_s
            problems = []
            if link.state is not DeviceState.CONNECTED:
                problems.append(f"Uno {link.state.value}: {link.status().detail}")
            camera_status = self.devices.camera.status()
            # A camera that has not delivered its first frame yet is starting, not
            # failing (a webcam takes a second to open), unless that takes too long.
            starting = (
                self.counters.frames_captured == 0
                and camera_status.state is not DeviceState.FAILED
                and self.clock() - (self.started_s or 0.0) < CAMERA_START_GRACE_S
            )
            if not self._camera_ok and not starting:
                problems.append(
                    f"camera {camera_status.state.value}: "
                    + (camera_status.detail or "no recent frame")
                )
            reason = "; ".join(problems)
            if reason and not self._fault_reason:
                self.counters.faults += 1
                log.warning("fault: %s", reason, extra={"event": "fault"})
                if self._autonomous:
                    self._autonomous = False
                    self.mux.clear_autonomy()
                    log.warning(
                        "autonomy stopped by the fault; start again when it clears",
                        extra={"event": "stop"},
                    )
            elif not reason and self._fault_reason:
                log.info("devices healthy again", extra={"event": "fault_cleared"})
            connected = link.state is DeviceState.CONNECTED
            if connected and not was_connected:
                # Counters may restart with the device: take a fresh reference.
                self.odometry.reset_reference()
            was_connected = connected
            self._fault_reason = reason
            self._update_state(reason or "devices healthy")
            self._report_stuck_workers()
            await asyncio.sleep(period)

    def _report_stuck_workers(self) -> None:
        """Log where a perception or mapping job has been stuck (once per job). The
        stale-perception layer has already stopped the motors by then."""
        for worker in (self._perception_worker, self._mapping_worker):
            if worker.busy_s() < WORKER_STUCK_S:
                self._stuck_reported.discard(worker.name)
            elif worker.name not in self._stuck_reported:
                self._stuck_reported.add(worker.name)
                log.error(
                    "the %s job has run for %.1f s; it is at:\n%s",
                    worker.name,
                    worker.busy_s(),
                    worker.stack(),
                    extra={"event": "worker_stuck", "stage": worker.name},
                )

    async def _drive_stage(self) -> None:
        link = self.link
        assert link is not None
        period = self.config.drive.control_period_ms / 1000.0
        while True:
            await wait_event(self._wake_drive, period)
            self._wake_drive.clear()
            start = self.clock()
            out = self._gate(self.mux.output(start), start)
            twist = self.limiter(out.twist, start)
            pwm = twist_to_pwm(twist, self.config.drive)
            new_autonomy = out.source == "autonomy" and out.origin_s != self._last_latency_origin
            if pwm == self._last_pwm and not new_autonomy:
                continue  # the link's heartbeat keeps repeating it
            if link.state is not DeviceState.CONNECTED:
                self._last_pwm = None
                continue
            try:
                if pwm == (0, 0) and out.source == "estop":
                    await link.stop_motors()
                else:
                    await link.drive(*pwm)
            except NotConnectedError:
                self._last_pwm = None
                continue
            except LinkError as exc:
                self.counters.send_errors += 1
                log.warning("drive command failed: %s", exc, extra={"event": "send_error"})
                continue
            sent = self.clock()
            self._last_pwm = pwm
            self.counters.commands_sent += 1
            self.stages.add("drive", sent - start)
            if new_autonomy:
                self._last_latency_origin = out.origin_s
                self.latencies.append(sent - out.origin_s)
                self.latencies_total += 1
            decision = self.decisions.peek()
            self.drives.publish(
                DriveMsg(
                    twist,
                    pwm[0],
                    pwm[1],
                    out.source,
                    sent,
                    out.origin_s,
                    decision.heading_rad
                    if decision is not None and out.source == "autonomy"
                    else None,
                )
            )

    def _zone_not_floor(self, now: float) -> FloorMsg | None:
        """The newest floor result if it is fresh and says the safe zone is not floor
        (``zone_floor_confidence`` below ``perception.zone_min_floor_confidence``)."""
        floor = self.floors.peek()
        if floor is None or floor.age_s(now) > self.config.safety.perception_max_age_s:
            return None
        if floor.zone_floor_confidence >= self.config.perception.zone_min_floor_confidence:
            return None
        return floor

    def _gate(self, out: MuxOutput, now: float) -> MuxOutput:
        """The host's stop layers on top of the mux; `protective_stop` says which one
        holds the robot back."""
        self.protective_stop = None
        safety = self.config.safety
        if out.source == "autonomy" or (self._autonomous and out.source == "timeout"):
            # Judged on capture times, so it trips before the mux's own timeout on the
            # (later) steering time would: the stop is counted as what it is.
            floor, map_msg = self.floors.peek(), self.maps.peek()
            stale = (
                not self._autonomous
                or bool(self._fault_reason)
                or floor is None
                or map_msg is None
                or floor.age_s(now) > safety.perception_max_age_s
                or map_msg.age_s(now) > safety.perception_max_age_s
            )
            if stale:
                if not self._stale_active:
                    self._stale_active = True
                    self.counters.watchdog_stops += 1
                    log.warning(
                        "stale perception or map: motors zero", extra={"event": "watchdog_stop"}
                    )
                self.protective_stop = ProtectiveStop(
                    "watchdog",
                    "no recent perception or map"
                    + (f" ({self._fault_reason})" if self._fault_reason else "")
                    + ": motors zero",
                )
                return MuxOutput(Twist(), "watchdog", now, now)
            self._stale_active = False
        out = self._premise_gate(out, now)
        if out.twist.v_m_s > 0:
            map_msg = self.maps.peek()
            fresh = map_msg is not None and map_msg.age_s(now) <= safety.perception_max_age_s
            if fresh and map_msg is not None and map_msg.clearance_ahead_m < safety.min_clearance_m:
                if not self._clearance_active:
                    self._clearance_active = True
                    self.counters.clearance_stops += 1
                    log.debug(
                        "clearance %.2f m ahead < %.2f m: no forward motion",
                        map_msg.clearance_ahead_m,
                        safety.min_clearance_m,
                        extra={"event": "clearance_stop"},
                    )
                self.protective_stop = ProtectiveStop(
                    "clearance",
                    f"clearance {map_msg.clearance_ahead_m:.2f} m ahead < "
                    f"{safety.min_clearance_m:.2f} m: no forward motion",
                )
                return MuxOutput(
                    Twist(0.0, out.twist.omega_rad_s), out.source, out.stamp_s, out.origin_s
                )
            self._clearance_active = False
        return out

    def _premise_gate(self, out: MuxOutput, now: float) -> MuxOutput:
        """The thesis's premise: the safe zone right ahead is floor. When perception says
        it is not, the way ahead is blocked: no forward motion (turning stays allowed;
        steering turns to look elsewhere). Recovers by itself when the zone is floor
        again. It holds autonomy back, or any command that would move forward."""
        floor = self._zone_not_floor(now)
        if floor is None or not (out.source == "autonomy" or out.twist.v_m_s > 0):
            if self._premise_active:
                log.debug(
                    "premise stop over: %s",
                    "nothing drives forward" if floor is not None else "the safe zone is floor",
                    extra={"event": "premise_clear"},
                )
            self._premise_active = False
            return out
        minimum = self.config.perception.zone_min_floor_confidence
        confidence = floor.zone_floor_confidence
        if not self._premise_active:
            self._premise_active = True
            self.counters.premise_stops += 1
            log.info(
                "safe zone is not floor (confidence %.2f < %.2f): no forward motion",
                confidence,
                minimum,
                extra={
                    "event": "premise_stop",
                    "zone_floor_confidence": round(confidence, 3),
                    "source": out.source,
                },
            )
        then = "turning to look elsewhere" if out.source == "autonomy" else "no forward motion"
        self.protective_stop = ProtectiveStop(
            "not_floor",
            f"safe zone is not floor (confidence {confidence:.2f} < {minimum:.2f}): {then}",
        )
        if out.twist.v_m_s <= 0:
            return out
        return MuxOutput(Twist(0.0, out.twist.omega_rad_s), out.source, out.stamp_s, out.origin_s)

    # -- state ----------------------------------------------------------------------------

    def _derive_state(self) -> State:
        if self.mux.estopped:
            return State.ESTOPPED
        if self._calibrating:
            return State.CALIBRATING
        if self._fault_reason:
            return State.FAULT
        if self.mux.teleop_driver(self.clock()) is not None:
            return State.TELEOP
        if self._autonomous:
            return State.RUNNING
        return State.IDLE

    def _update_state(self, reason: str) -> None:
        new = self._derive_state()
        if new is self.state:
            return
        transition = Transition(self.clock(), time.time(), self.state, new, reason)
        self.transitions.append(transition)
        log.info(
            "state %s -> %s (%s)",
            self.state.value,
            new.value,
            reason,
            extra={"event": "state", "old": self.state.value, "new": new.value, "reason": reason},
        )
        self.state = new

    # -- reports --------------------------------------------------------------------------

    def elapsed_s(self) -> float:
        if self.started_s is None:
            return 1e-9  # never started: rates come out as 0, not a division by zero
        end = self.ended_s if self.ended_s is not None else self.clock()
        return max(1e-9, end - self.started_s)

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot for the API and the dashboard."""
        now = self.clock()
        floor, map_msg, drive = self.floors.peek(), self.maps.peek(), self.drives.peek()
        stop = self.protective_stop
        link = self.link
        pose = self.odometry.pose
        frontier = self.frontier
        recent = newest(self.frame_ages, 30)
        return {
            "state": self.state.value,
            "autonomous": self._autonomous,
            "estop": self.mux.estop_reason,
            "fault": self._fault_reason or None,
            "teleop_driver": self.mux.teleop_driver(now),
            "uptime_s": round(self.elapsed_s(), 2),
            "fps": round(self.counters.frames_perceived / self.elapsed_s(), 2),
            "frame_age_ms": round((now - floor.capture_s) * 1000, 1) if floor else None,
            "pickup_age_ms": round(statistics.median(recent) * 1000, 2) if recent else None,
            "stage_ms": self.stages.recent_ms(),
            "pose": {
                "x_m": round(pose.x_m, 3),
                "y_m": round(pose.y_m, 3),
                "theta_rad": round(pose.theta_rad, 3),
            },
            "distance_m": round(self.odometry.distance_m, 3),
            "camera": {
                "state": self.devices.camera.status().state.value,
                "detail": self.devices.camera.status().detail,
                "ok": self._camera_ok,
                "description": self.devices.description.get("camera", ""),
            },
            "serial": {
                "state": link.state.value if link else "disconnected",
                "detail": link.status().detail if link else "",
                "port": self.devices.port,
                "reconnects": link.stats.reconnects if link else 0,
                "crc_errors": link.stats.crc_errors if link else 0,
                "timeouts": link.stats.timeouts if link else 0,
            },
            "calibration": None
            if self.calibration is None
            else {
                "reprojection_rms_px": self.calibration.reprojection_rms_px,
            },
            "calibration_problem": self.calibration_problem or None,
            "command": None
            if drive is None
            else {
                "v_m_s": round(drive.twist.v_m_s, 3),
                "omega_rad_s": round(drive.twist.omega_rad_s, 3),
                "left_pwm": drive.left_pwm,
                "right_pwm": drive.right_pwm,
                "source": drive.source,
                "age_ms": round((now - drive.sent_s) * 1000, 1),
            },
            "frontier": None
            if frontier is None
            else {
                "goal_xy": list(frontier.goal.xy) if frontier.goal else None,
                "reason": frontier.reason,
                "clusters": len(frontier.clusters),
            },
            "clearance_ahead_m": round(map_msg.clearance_ahead_m, 3) if map_msg else None,
            "zone_floor_confidence": round(floor.zone_floor_confidence, 3) if floor else None,
            "zone_min_floor_confidence": self.config.perception.zone_min_floor_confidence,
            "stop_cause": stop.cause if stop is not None else None,
            "stop_reason": stop.reason if stop is not None else None,
            "counters": dict(self.counters.__dict__),
            "estops": self.mux.estops,
            "transitions": [
                {
                    "t": round(t.wall_time, 3),
                    "from": t.old.value,
                    "to": t.new.value,
                    "reason": t.reason,
                }
                for t in list(self.transitions)[-10:]
            ],
        }

    def report(self) -> dict[str, Any]:
        """The run report ``floornav run --report`` writes (sim-only fields null on
        hardware)."""
        from app.sim.truth import map_truth_scores

        elapsed = self.elapsed_s()
        sim = self.devices.sim
        truth: dict[str, float] | None = None
        if sim is not None and self.mapper is not None and self.devices.camera is sim.camera:
            truth = map_truth_scores(
                self.mapper.grid.classify(), self.mapper.grid.world_grid, sim.T_plan_odom, sim.world
            ).as_dict()
        link = self.link
        return {
            "duration_s": round(elapsed, 2),
            "frames": self.counters.frames_perceived,
            "fps": round(self.counters.frames_perceived / elapsed, 2),
            "camera_frames": self.counters.frames_captured,
            "frames_mapped": self.counters.frames_mapped,
            "frames_skipped_by_capture": self.counters.frames_skipped,
            "bad_frames": self.counters.bad_frames,
            "latency_ms": percentiles_ms(self.latencies),
            "frame_age_at_perception_ms": percentiles_ms(self.frame_ages),
            "stage_ms": self.stages.summary_ms(),
            "collisions": sim.robot.collisions if sim is not None else None,
            "coverage_ratio": truth["coverage_ratio"] if truth else None,
            "map_iou": truth["map_iou"] if truth else None,
            "map_truth": truth,
            "distance_m": round(self.odometry.distance_m, 3),
            "estops": self.mux.estops,
            "watchdog_stops": self.counters.watchdog_stops,
            "clearance_stops": self.counters.clearance_stops,
            "premise_stops": self.counters.premise_stops,
            "steering_decisions": dict(self.steering_reasons),
            "goals_given_up": len(self.given_up_goals),
            "faults": self.counters.faults,
            "commands_sent": self.counters.commands_sent,
            "send_errors": self.counters.send_errors,
            "serial": None
            if link is None
            else {
                "reconnects": link.stats.reconnects,
                "timeouts": link.stats.timeouts,
                "crc_errors": link.stats.crc_errors,
                "rtt_ms_p50": link.stats.rtt_median_ms(),
            },
            "rss_mb": {"start": self.rss_start_mb, "end": self.rss_end_mb},
            "method": self.config.perception.method,
            "final_state": self.state.value,
            "shutdown_reason": self._shutdown_reason or None,
            "crash": self.crash,
            "final_motor_pwm": list(sim.uno.pwm)
            if sim is not None and sim.uno is not None
            else None,
            "pid": os.getpid(),
        }
