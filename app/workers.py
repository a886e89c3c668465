"""A single-thread worker for one CPU-heavy stage, which never holds up shutdown.

`concurrent.futures.ThreadPoolExecutor` joins its threads when it shuts down and again
when the interpreter exits; one job stuck in native code (a numba kernel, an OpenCV
call) would then hang the daemon's shutdown, and with it the command that stops the
motors. A `StageWorker` runs jobs one at a time on a daemon thread, tells how long
the current job has been running and where it is (for the health stage's log), and
lets the runtime wait for it with a bound.
"""

from __future__ import annotations

import asyncio
import os
import queue
import sys
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

T = TypeVar("T")

_Job = tuple[Future[Any], Callable[..., Any], tuple[Any, ...]]


class WorkerClosedError(RuntimeError):
    """A job was submitted to a worker that is shutting down."""


class StageWorker:
    """Runs submitted callables one at a time, in order, on one daemon thread.

    Parameters
    ----------
    name : names the thread (``floornav-<name>``) and the log lines about it.
    nicer_by : how much nicer than the process the thread runs (Linux: a thread may
        lower its own priority without privileges), so that work off the motors' path
        gives way to the stages on it when the cores are busy.
    """

    def __init__(self, name: str, *, nicer_by: int = 0) -> None:
        if not 0 <= nicer_by <= 19:
            raise ValueError(f"nicer_by must be in [0, 19], got {nicer_by}")
        self.name = name
        self.nicer_by = nicer_by
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._closed = False
        self._busy_since_s: float | None = None
        self._thread = threading.Thread(target=self._run, name=f"floornav-{name}", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Queue ``fn(*args)``; its result (or exception) arrives in the future."""
        if self._closed:
            raise WorkerClosedError(f"the {self.name} worker is shut down")
        future: Future[T] = Future()
        self._jobs.put((future, fn, args))
        return future

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` on the worker and await it. Cancelling the await does not
        stop a job already running (threads cannot be interrupted); its result is
        dropped."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    def busy_s(self, now_s: float | None = None) -> float:
        """How long the current job has been running (0 when idle)."""
        since = self._busy_since_s
        if since is None:
            return 0.0
        return (time.monotonic() if now_s is None else now_s) - since

    def stack(self) -> str:
        """Where the worker thread is right now (empty once it has ended)."""
        frame = sys._current_frames().get(self._thread.ident or -1)
        return "".join(traceback.format_stack(frame)) if frame is not None else ""

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def shutdown(self) -> None:
        """Refuse new jobs, cancel queued ones, let the thread end after its current
        job. Returns at once."""
        if self._closed:
            return
        self._closed = True
        while True:
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                job[0].cancel()
        self._jobs.put(None)

    async def wait_closed(self, timeout_s: float) -> bool:
        """After `shutdown`: wait up to ``timeout_s`` for the thread to end, without
        blocking the event loop. False if it is still busy (it is left behind: a daemon
        thread does not keep the process alive)."""
        deadline = time.monotonic() + timeout_s
        while self._thread.is_alive():
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(0.01)
        return True

    def _run(self) -> None:
        if self.nicer_by and hasattr(os, "setpriority"):
            thread_id = threading.get_native_id()
            try:
                nice = os.getpriority(os.PRIO_PROCESS, thread_id)
                os.setpriority(os.PRIO_PROCESS, thread_id, min(19, nice + self.nicer_by))
            except OSError:  # a sandbox without the call: the thread runs at the process's
                pass
        while True:
            job = self._jobs.get()
            if job is None:
                return
            future, fn, args = job
            if not future.set_running_or_notify_cancel():
                continue
            self._busy_since_s = time.monotonic()
            try:
                result = fn(*args)
            except BaseException as exc:  # delivered to the awaiting stage
                future.set_exception(exc)
            else:
                future.set_result(result)
            finally:
                self._busy_since_s = None
