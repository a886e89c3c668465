"""The health stage: watches the camera and the Uno link, turns their gaps into stop
causes (`app.runtime.stops.StopPolicy`), pings systemd's watchdog, and names a
perception or mapping job that got stuck."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence

from app import systemd
from app.hardware.interfaces import DeviceState
from app.runtime.context import Shared
from app.workers import StageWorker

log = logging.getLogger("floornav.runtime")

CAMERA_START_GRACE_S = 5.0
"""How long a camera may take to deliver its first frame before it counts as gone."""
WORKER_STUCK_S = 2.0
"""A perception or mapping job running this long is logged with its stack (once)."""


class HealthStage:
    """Every control period: device problems -> stop causes, then ``on_tick`` (the
    Runtime re-derives its state there and returns it for systemd's status line)."""

    def __init__(
        self, shared: Shared, workers: Sequence[StageWorker], on_tick: Callable[[str], str]
    ) -> None:
        self.shared = shared
        self.workers = workers
        self.on_tick = on_tick
        self._stuck_reported: set[str] = set()

    def device_problems(self, now: float) -> dict[str, str | None]:
        """``{"link": problem or None, "camera": problem or None}``."""
        shared = self.shared
        link = shared.link
        assert link is not None
        link_problem = None
        if link.state is not DeviceState.CONNECTED:
            link_problem = f"Uno {link.state.value}: {link.status().detail or 'no link'}"
        camera_status = shared.devices.camera.status()
        # A camera that has not delivered its first frame yet is starting, not failing
        # (a webcam takes a second to open), unless that takes too long.
        starting = (
            shared.counters.frames_captured == 0
            and camera_status.state is not DeviceState.FAILED
            and now - (shared.started_s or 0.0) < CAMERA_START_GRACE_S
        )
        camera_problem = None
        if not shared.camera_ok and not starting:
            camera_problem = f"camera {camera_status.state.value}: " + (
                camera_status.detail or "no recent frame"
            )
        return {"link": link_problem, "camera": camera_problem}

    async def run(self) -> None:
        shared = self.shared
        link = shared.link
        assert link is not None
        was_connected = False
        watchdog_s = systemd.watchdog_interval_s()
        next_ping_s = 0.0
        while True:
            now = shared.clock()
            for cause, problem in self.device_problems(now).items():
                was = shared.policy.active(cause)
                event = shared.policy.observe(cause, problem, now)
                if event is not None:
                    if not event.latched:
                        log.warning(
                            "protective stop: %s", problem, extra={"event": "protective_stop"}
                        )
                    shared.on_stop(event)
                elif was is not None and problem is None:
                    log.info(
                        "%s healthy again", cause, extra={"event": "device_ok", "cause": cause}
                    )
            connected = link.state is DeviceState.CONNECTED
            if connected and not was_connected:
                # Counters may restart with the device: take a fresh reference.
                shared.odometry.reset_reference()
            was_connected = connected
            state = self.on_tick("health check")
            if watchdog_s is not None and now >= next_ping_s:
                # systemd restarts the daemon if these stop (a hung event loop).
                systemd.notify(f"WATCHDOG=1\nSTATUS={state}")
                next_ping_s = now + watchdog_s
            self._report_stuck_workers()
            await asyncio.sleep(shared.config.drive.control_period_ms / 1000.0)

    def _report_stuck_workers(self) -> None:
        """Log where a perception or mapping job has been stuck (once per job). The
        stale-perception layer has already stopped the motors by then."""
        for worker in self.workers:
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
