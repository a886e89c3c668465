"""Benchmarks behind ``floornav bench``: each module times one subsystem on one CPU and
returns a JSON-ready dict."""

from __future__ import annotations

import os

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
