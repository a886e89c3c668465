"""A real Runtime on the simulator (simulated camera and Uno), with hooks for faults."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from app.config import FloornavConfig, load_config
from app.devices import Devices, open_devices
from app.runtime import Runtime


def sim_config(**sections: Any) -> FloornavConfig:
    base: dict[str, Any] = {
        "perception": {"method": "flood_fill", "flood_fill_tolerance": 18.0, "fill_gaps_px": 15},
        "runtime": {"autostart": False},
        "camera": {"fps_hz": 30.0},
    }
    for key, value in sections.items():
        base[key] = {**base.get(key, {}), **value}
    return load_config(None, **base)


async def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def running(
    config: FloornavConfig | None = None,
    *,
    prepare: Callable[[Devices], None] | None = None,
    **runtime_kwargs: Any,
) -> AsyncIterator[tuple[Runtime, asyncio.Task[None]]]:
    """Open the sim devices, run a Runtime in a task; on exit ask it to shut down and
    wait (re-raising nothing: tests inspect the task themselves when they expect a crash)."""
    config = config or sim_config()
    with open_devices(config) as devices:
        if prepare is not None:
            prepare(devices)
        runtime = Runtime(config, devices, **runtime_kwargs)
        task = asyncio.create_task(runtime.run(install_signals=False))
        try:
            await wait_for(
                lambda: runtime.maps.peek() is not None or task.done(), 20.0, "the first map"
            )
            yield runtime, task
        finally:
            runtime.request_shutdown("test over")
            with contextlib.suppress(Exception):
                await asyncio.wait_for(task, 10.0)


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"
