"""The daemon's runtime: `Runtime` (assembly, verbs, state machine) in `core`, the
stages in `stages`, `drive` and `health`, stop decisions in `stops`, measurements in
`telemetry`, status and report in `reports`."""

from app.runtime.core import (
    STRAGGLER_RECANCEL_S,
    WORKER_CLOSE_TIMEOUT_S,
    CommandRefusedError,
    Runtime,
    Service,
)
from app.runtime.health import WORKER_STUCK_S
from app.runtime.stages import (
    Segmenter,
    clearance_ahead_m,
    crop_window,
    map_window,
    path_to_xy,
)
from app.runtime.stops import ProtectiveStop, StopEvent, StopPolicy
from app.runtime.telemetry import Counters, StageClock, percentiles_ms, rss_mb

__all__ = [
    "STRAGGLER_RECANCEL_S",
    "WORKER_CLOSE_TIMEOUT_S",
    "WORKER_STUCK_S",
    "CommandRefusedError",
    "Counters",
    "ProtectiveStop",
    "Runtime",
    "Segmenter",
    "Service",
    "StageClock",
    "StopEvent",
    "StopPolicy",
    "clearance_ahead_m",
    "crop_window",
    "map_window",
    "path_to_xy",
    "percentiles_ms",
    "rss_mb",
]
