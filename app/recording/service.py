"""``floornav run --record FILE.mcap``: the daemon's recording, as a `Service` beside
the web server.

It reads what the web reads (the runtime's `LatestSlot` s of frozen messages, the
odometry pose, the stop policy's last stop, the 2 Hz whole-map snapshot) on the event
loop, hands each item to the `McapRecorder`'s queue and returns at once: the encoding
and the disk are the recorder's thread's. A recording that fails (a full disk, a bug
here) logs why and stops recording; it never stops the run.

Every camera frame the capture stage publishes, every command sent and the daemon's log
records (INFO and up) are recorded; floor masks at most every ``MASK_PERIOD_S`` (they
are for looking at, and replaying the frames computes every one again); the pose is
sampled every ``POSE_PERIOD_S`` when it changed, stops are looked for as often (a second
stop within one period is counted in the next message's ``missed``), and the map is
recorded at most every ``MAP_PERIOD_S``.

Cost, measured on the simulator (2-core development machine, 640x480 at ~29 fps, two
runs each way, CPU of the daemon's process between 12 s and 32 s into a run): 25.4 ms
of CPU per frame without recording, 26.6 ms with (+1.2 ms, +4.7 %). The writer thread
alone uses ~1.4 ms per frame at 10 masks a second, ~1.8 ms with every mask (the run
report's ``recording.writer_cpu_s`` over its ``frames``).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.channels import SlotReader
from app.recording.mcap_writer import McapLogHandler, McapRecorder

if TYPE_CHECKING:
    from app.runtime import Runtime

log = logging.getLogger("floornav.recording")

POSE_PERIOD_S = 0.05
MASK_PERIOD_S = 0.1
MAP_PERIOD_S = 2.0
LOG_LEVEL = logging.INFO


class RecordingService:
    """Records a running `Runtime` into ``recorder`` (opened and closed by the caller:
    the file is finished after the run, whatever ended it)."""

    name = "recording"

    def __init__(
        self,
        runtime: Runtime,
        recorder: McapRecorder,
        *,
        pose_period_s: float = POSE_PERIOD_S,
        mask_period_s: float = MASK_PERIOD_S,
        map_period_s: float = MAP_PERIOD_S,
        log_level: int = LOG_LEVEL,
    ) -> None:
        self.runtime = runtime
        self.recorder = recorder
        self.pose_period_s = pose_period_s
        self.mask_period_s = mask_period_s
        self.map_period_s = map_period_s
        self.log_level = log_level
        self._stop = asyncio.Event()

    def request_stop(self) -> None:
        self._stop.set()

    async def serve(self) -> None:
        handler = McapLogHandler(self.recorder, self.log_level)
        root = logging.getLogger()
        root.addHandler(handler)
        jobs: dict[str, Coroutine[Any, Any, None]] = {
            "frames": self._frames(),
            "masks": self._masks(),
            "commands": self._commands(),
            "samples": self._samples(),
        }
        tasks = [asyncio.create_task(job, name=f"recording-{n}") for n, job in jobs.items()]
        for task in tasks:
            task.add_done_callback(_report_failure)
        try:
            await self._stop.wait()
        finally:
            root.removeHandler(handler)
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _frames(self) -> None:
        reader = SlotReader(self.runtime.frames)
        while True:
            frame = await reader.next()
            self.recorder.record_image(frame.capture_s, frame.image)

    async def _masks(self) -> None:
        reader = SlotReader(self.runtime.floors)
        last_s = float("-inf")
        while True:
            floor = await reader.next()
            # 5 % slack: frames a period apart by the camera's clock are not refused
            # for a millisecond of jitter.
            if floor.capture_s - last_s >= 0.95 * self.mask_period_s:
                self.recorder.record_mask(floor.capture_s, floor.floor_mask)
                last_s = floor.capture_s

    async def _commands(self) -> None:
        half_base_m = self.runtime.config.drive.wheel_base_m / 2
        reader = SlotReader(self.runtime.drives)
        while True:
            drive = await reader.next()
            v, omega = drive.twist.v_m_s, drive.twist.omega_rad_s
            self.recorder.record_drive(
                drive.sent_s,
                source=drive.source,
                linear_m_s=v,
                angular_rad_s=omega,
                left_wheel_m_s=v - omega * half_base_m,
                right_wheel_m_s=v + omega * half_base_m,
                left_pwm=drive.left_pwm,
                right_pwm=drive.right_pwm,
                heading_rad=drive.heading_rad,
                origin_age_ms=round((drive.sent_s - drive.origin_s) * 1e3, 3),
            )

    async def _samples(self) -> None:
        """The pose, new stops and map snapshots, polled."""
        from app.runtime.stops import STOP_RULES

        runtime = self.runtime
        recorder = self.recorder
        last_pose = None
        last_stop = runtime.policy.last_stop
        stops_seen = sum(runtime.policy.stops_by_cause.values())
        last_map_seq: int | None = None
        last_map_s = float("-inf")
        while True:
            now = runtime.clock()
            pose = runtime.odometry.pose
            if pose != last_pose:
                recorder.record_pose(now, pose)
                last_pose = pose
            policy = runtime.policy
            stop = policy.last_stop
            if stop is not None and stop is not last_stop:
                # A new stop counts once in stops_by_cause (a device latching after it
                # was lost long enough does not count again).
                total = sum(policy.stops_by_cause.values())
                rule = STOP_RULES.get(stop.cause)
                recorder.record_stop(
                    stop.monotonic_s,
                    cause=stop.cause,
                    reason=stop.reason,
                    latched=stop.latched,
                    zeroes_motors=stop.latched or rule is None or rule.zeroes_motors,
                    missed=max(0, total - stops_seen - 1),
                )
                last_stop, stops_seen = stop, total
            world = runtime.world_maps.peek()
            if (
                world is not None
                and world.seq != last_map_seq
                and now - last_map_s >= self.map_period_s
            ):
                recorder.record_map(world.done_s, world.cells, world.grid)
                last_map_seq, last_map_s = world.seq, now
            await asyncio.sleep(self.pose_period_s)


def _report_failure(task: asyncio.Task[None]) -> None:
    if task.cancelled():
        return
    exc = task.exception()
    if exc is not None:
        log.error(
            "recording: %s failed, it records no more: %r",
            task.get_name(),
            exc,
            extra={"event": "recording_failed"},
        )


def start_recording(path: Path, metadata: dict[str, str] | None = None) -> McapRecorder:
    """Open the recorder for ``floornav run --record`` (FileExistsError: never
    overwrites)."""
    recorder = McapRecorder(path, metadata=metadata)
    recorder.open()
    log.info("recording to %s", path, extra={"event": "recording", "file": str(path)})
    return recorder


def finish_recording(recorder: McapRecorder) -> dict[str, Any]:
    """Close the recorder (summary and index written) and log what it holds; the stats
    for the run report."""
    recorder.close()
    stats = recorder.stats()
    log.info(
        "recording %s finished: %d messages, %d dropped, %d errors",
        recorder.path,
        sum(stats["written"].values()),
        sum(stats["dropped"].values()),
        stats["errors"],
        extra={
            "event": "recording_done",
            "written": stats["written"],
            "dropped": stats["dropped"],
        },
    )
    return stats
