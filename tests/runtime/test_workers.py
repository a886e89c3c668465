"""StageWorker: one job at a time on a daemon thread; shutdown never waits unbounded."""

from __future__ import annotations

import asyncio
import os
import threading
import time

import pytest

from app.workers import StageWorker, WorkerClosedError


async def test_jobs_run_in_order_with_results_and_exceptions() -> None:
    worker = StageWorker("test")
    order: list[int] = []

    def job(n: int) -> int:
        order.append(n)
        return n * n

    results = await asyncio.gather(*(worker.run(job, n) for n in range(5)))
    assert results == [0, 1, 4, 9, 16]
    assert order == [0, 1, 2, 3, 4]

    def broken() -> None:
        raise ValueError("bad frame")

    with pytest.raises(ValueError, match="bad frame"):
        await worker.run(broken)
    assert await worker.run(job, 7) == 49  # a failed job does not end the worker
    worker.shutdown()
    assert await worker.wait_closed(1.0)
    assert not worker.alive


async def test_shutdown_cancels_queued_jobs_and_refuses_new_ones() -> None:
    worker = StageWorker("test")
    release = threading.Event()
    running = worker.submit(release.wait, 5.0)
    queued = worker.submit(lambda: "never")
    while not running.running():
        await asyncio.sleep(0.001)
    worker.shutdown()
    assert queued.cancelled()
    with pytest.raises(WorkerClosedError, match="test"):
        worker.submit(lambda: None)
    release.set()
    assert await worker.wait_closed(1.0)
    assert running.result() is True


def stuck_in_native_code(release: threading.Event) -> None:
    release.wait(30.0)


async def test_a_stuck_job_is_reported_and_left_behind_without_blocking_the_loop() -> None:
    worker = StageWorker("mapping")
    release = threading.Event()
    worker.submit(stuck_in_native_code, release)
    await asyncio.sleep(0.05)
    assert worker.busy_s() >= 0.04
    assert "stuck_in_native_code" in worker.stack()
    worker.shutdown()

    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0.01)

    tick_task = asyncio.create_task(ticker())
    started = time.monotonic()
    assert not await worker.wait_closed(0.3)
    assert 0.3 <= time.monotonic() - started < 1.0
    assert ticks >= 10, "the event loop kept running while waiting"
    tick_task.cancel()
    assert worker.alive
    assert worker._thread.daemon, "a stuck worker must not keep the process alive"
    release.set()
    assert await worker.wait_closed(1.0)
    assert worker.busy_s() == 0.0
    assert worker.stack() == ""


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="thread priorities are Linux's")
def test_a_worker_can_run_nicer_than_the_process_and_the_bounds_are_checked() -> None:
    def own_nice() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    process_nice = os.getpriority(os.PRIO_PROCESS, 0)
    nicer, plain = StageWorker("nicer", nicer_by=5), StageWorker("plain")
    try:
        assert nicer.submit(own_nice).result(timeout=5) == min(19, process_nice + 5)
        assert plain.submit(own_nice).result(timeout=5) == process_nice
    finally:
        nicer.shutdown()
        plain.shutdown()
    with pytest.raises(ValueError, match="nicer_by"):
        StageWorker("negative", nicer_by=-1)
