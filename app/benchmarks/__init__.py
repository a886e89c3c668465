"""Benchmarks behind ``floornav bench``: each module times one subsystem on one CPU and
returns a JSON-ready dict."""

from __future__ import annotations

import contextlib
import os
import platform
from collections.abc import Iterator
from pathlib import Path

import cv2


def pin_to_one_cpu() -> str:
    """Run this process on one CPU with OpenCV single-threaded (the robot gives each
    pipeline stage one core); returns what was done, for the report."""
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"cpu {cpu}"
    return "unpinned"


@contextlib.contextmanager
def restored_affinity() -> Iterator[None]:
    """Undo `pin_to_one_cpu` on exit, so a benchmark run inside a longer-lived process
    (the CLI's tests, a notebook) does not leave it on one core."""
    threads = cv2.getNumThreads()
    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    try:
        yield
    finally:
        cv2.setNumThreads(threads)
        if affinity is not None:
            os.sched_setaffinity(0, affinity)


def cpu_name() -> str:
    """The CPU's model name (Linux), for the measurement pages."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "an unknown CPU"
