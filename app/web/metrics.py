"""Prometheus metrics for ``/metrics``, read from the service at scrape time.

A custom collector reads the daemon's own counters and timing windows when scraped, so
the per-frame cost of metrics is zero. Histograms are cumulative, as Prometheus expects:
each scrape adds the samples that arrived since the previous one (found through the
windows' ever-growing totals). Every app has its own `CollectorRegistry`, never the
process-global one, so two apps (tests) do not collide.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
    StateSetMetricFamily,
)
from prometheus_client.registry import Collector

from app.messages import State
from app.runtime.service_status import service_status
from app.runtime.telemetry import FloatWindow
from app.web.service import RobotService

STAGE_BUCKETS_S = (
    0.001,
    0.0025,
    0.005,
    0.01,
    0.02,
    0.03,
    0.05,
    0.075,
    0.1,
    0.15,
    0.2,
    0.3,
    0.5,
    1.0,
    2.5,
)
LATENCY_BUCKETS_S = (0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0)
ENCODE_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)
FPS_MIN_INTERVAL_S = 0.5
"""Scrapes closer together than this reuse the previous fps (too few frames between)."""


@dataclass
class CumulativeHistogram:
    """Bucket counts that only grow, fed with new samples from a bounded window."""

    bounds: Sequence[float]
    counts: np.ndarray = field(init=False)
    total: float = 0.0
    seen: int = 0
    """Samples of the window's total already counted."""

    def __post_init__(self) -> None:
        self.counts = np.zeros(len(self.bounds) + 1, dtype=np.int64)

    def catch_up(self, window: FloatWindow, window_total: int) -> None:
        """Count the window's samples added since the last call. If more arrived than
        the window holds, the ones that dropped out are lost (not invented)."""
        new = min(window_total - self.seen, len(window))
        self.seen = window_total
        if new <= 0:
            return
        values = window.tail(new)
        # side="left": a value equal to a bound belongs to that bucket (le semantics).
        index = np.searchsorted(np.asarray(self.bounds), values, side="left")
        self.counts += np.bincount(index, minlength=len(self.counts))
        self.total += float(values.sum())

    def family_buckets(self) -> list[tuple[str, float]]:
        cumulative = np.cumsum(self.counts)
        labels = [*(f"{b:g}" for b in self.bounds), "+Inf"]
        return [(label, float(count)) for label, count in zip(labels, cumulative, strict=True)]


class RuntimeCollector(Collector):
    """Reads a `RobotService` on every scrape (call it on the event loop's thread)."""

    def __init__(self, service: RobotService) -> None:
        self.service = service
        self.stage_histograms: dict[str, CumulativeHistogram] = {}
        self.latency_histogram = CumulativeHistogram(LATENCY_BUCKETS_S)
        self._fps = 0.0
        self._fps_mark: tuple[float, int] | None = None

    def _update_fps(self, now: float, frames: int) -> float:
        if self._fps_mark is None:
            elapsed = self.service.elapsed_s()
            self._fps = frames / elapsed if elapsed > 0 else 0.0
            self._fps_mark = (now, frames)
        elif now - self._fps_mark[0] >= FPS_MIN_INTERVAL_S:
            then, frames_then = self._fps_mark
            self._fps = max(0, frames - frames_then) / (now - then)
            self._fps_mark = (now, frames)
        return self._fps

    def collect(self) -> Iterable[Metric]:
        service = self.service
        now = time.monotonic()
        counters = service.counters

        stage_family = HistogramMetricFamily(
            "floornav_stage_latency_seconds",
            "Duration of each daemon stage per frame or command",
            labels=["stage"],
        )
        stages = service.stages
        for stage, window in list(stages.samples.items()):
            histogram = self.stage_histograms.setdefault(
                stage, CumulativeHistogram(STAGE_BUCKETS_S)
            )
            histogram.catch_up(window, stages.totals.get(stage, len(window)))
            stage_family.add_metric([stage], histogram.family_buckets(), histogram.total)
        yield stage_family

        self.latency_histogram.catch_up(service.latencies, service.latencies_total)
        latency = HistogramMetricFamily(
            "floornav_capture_to_command_seconds",
            "Camera capture to the autonomy command it produced reaching the Uno",
        )
        latency.add_metric(
            [], self.latency_histogram.family_buckets(), self.latency_histogram.total
        )
        yield latency

        lag = service.loop_lag
        loop_lag = HistogramMetricFamily(
            "floornav_event_loop_lag_seconds",
            "How much later than scheduled the event loop woke a timer: the delay every "
            "callback (drive commands, Uno ACKs, requests) suffered at that moment",
        )
        loop_lag.add_metric(
            [],
            [
                (f"{bound:g}" if math.isfinite(bound) else "+Inf", float(count))
                for bound, count in lag.cumulative_buckets()
            ],
            lag.sum_s,
        )
        yield loop_lag

        yield GaugeMetricFamily(
            "floornav_fps",
            "Frames perceived per second since the previous scrape",
            value=self._update_fps(now, counters.frames_perceived),
        )
        floor = service.floors.peek()
        yield GaugeMetricFamily(
            "floornav_frame_age_seconds",
            "Age of the newest perception result's camera frame (NaN before the first)",
            value=now - floor.capture_s if floor is not None else float("nan"),
        )
        yield GaugeMetricFamily(
            "floornav_zone_floor_confidence",
            "How sure perception is that the safe zone ahead is floor, 0..1, newest frame "
            "(NaN before the first)",
            value=floor.zone_floor_confidence if floor is not None else float("nan"),
        )
        map_msg = service.maps.peek()
        yield GaugeMetricFamily(
            "floornav_zone_known_floor",
            "Share of the safe zone's ground the map knows is floor, 0..1, newest map (NaN "
            "before the first)",
            value=map_msg.zone_known_floor
            if map_msg is not None and map_msg.zone_known_floor is not None
            else float("nan"),
        )
        yield GaugeMetricFamily(
            "floornav_uptime_seconds", "Seconds since the run started", value=service.elapsed_s()
        )

        link = service.link
        serial_errors = CounterMetricFamily(
            "floornav_serial_errors",
            "Uno link errors: frames with a bad CRC and commands without an ACK in time",
            labels=["kind"],
        )
        serial_errors.add_metric(["crc"], link.stats.crc_errors if link else 0)
        serial_errors.add_metric(["timeout"], link.stats.timeouts if link else 0)
        yield serial_errors
        yield CounterMetricFamily(
            "floornav_serial_reconnects",
            "Reconnections of the Uno link after the first connect",
            value=link.stats.reconnects if link else 0,
        )

        for name, value, documentation in (
            ("watchdog_stops", counters.watchdog_stops, "Stops for stale perception or map"),
            ("clearance_stops", counters.clearance_stops, "Forward motion refused for clearance"),
            ("premise_stops", counters.premise_stops, "Stops because the safe zone is not floor"),
            (
                "zone_known_floor_frames",
                counters.zone_known_floor_frames,
                "Frames whose safe zone perception doubted but the map knew was floor",
            ),
            ("estops", service.mux.estops, "E-stops latched"),
            ("faults", counters.faults, "Faults latched (they need the operator)"),
            ("commands_sent", counters.commands_sent, "Drive commands sent to the Uno"),
            ("send_errors", counters.send_errors, "Drive commands that failed"),
        ):
            yield CounterMetricFamily(f"floornav_{name}", documentation, value=value)

        policy = service.policy
        stops = CounterMetricFamily(
            "floornav_stops",
            "Stops by cause: protective (link, camera, stale: motors zero, resume by "
            "themselves), forward-only (clearance, not_floor), and calibration (a failed "
            "calibration left autonomy off)",
            labels=["cause"],
        )
        for cause, count in policy.stops_by_cause.items():
            stops.add_metric([cause], count)
        yield stops
        yield GaugeMetricFamily(
            "floornav_fault_latched",
            "1 while a fault is latched (needs POST /api/fault/reset), else 0",
            value=1.0 if policy.latched is not None else 0.0,
        )
        mqtt = service_status(service, "mqtt")
        if mqtt is not None:  # the MQTT bridge is configured (`app.bridges.mqtt`)
            yield GaugeMetricFamily(
                "floornav_mqtt_connected",
                "1 while the MQTT bridge is connected to its broker, else 0",
                value=1.0 if mqtt.get("state") == "connected" else 0.0,
            )
            yield CounterMetricFamily(
                "floornav_mqtt_reconnects",
                "Reconnections of the MQTT bridge after its first connect",
                value=mqtt.get("reconnects", 0),
            )

        frames = CounterMetricFamily(
            "floornav_frames", "Camera frames by what happened to them", labels=["outcome"]
        )
        for outcome, value in (
            ("captured", counters.frames_captured),
            ("perceived", counters.frames_perceived),
            ("mapped", counters.frames_mapped),
            ("skipped", counters.frames_skipped),
            ("bad", counters.bad_frames),
        ):
            frames.add_metric([outcome], value)
        yield frames
        yield CounterMetricFamily(
            "floornav_learned_floor_passes",
            "Frames on which floornet ran a second pass for a floor colour learned earlier",
            value=counters.learned_floor_passes,
        )

        state = StateSetMetricFamily("floornav_state", "The daemon's state")
        current = service.state
        state.add_metric([], {s.value: s is current for s in State})
        yield state


@dataclass
class WebMetrics:
    """The web layer's own metrics (updated as things happen; cheap)."""

    registry: CollectorRegistry
    video_clients: Gauge
    telemetry_clients: Gauge
    control_clients: Gauge
    video_frames_sent: Counter
    jpeg_encode_seconds: Histogram


def build_registry(service: RobotService) -> tuple[CollectorRegistry, WebMetrics]:
    """A fresh registry holding the runtime collector and the web layer's metrics."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(RuntimeCollector(service))
    web = WebMetrics(
        registry=registry,
        video_clients=Gauge(
            "floornav_web_video_clients", "Connected /ws/video clients", registry=registry
        ),
        telemetry_clients=Gauge(
            "floornav_web_telemetry_clients", "Connected /ws/telemetry clients", registry=registry
        ),
        control_clients=Gauge(
            "floornav_web_control_clients", "Connected /ws/control clients", registry=registry
        ),
        video_frames_sent=Counter(
            "floornav_web_video_frames_sent",
            "JPEG frames sent to video clients",
            registry=registry,
        ),
        jpeg_encode_seconds=Histogram(
            "floornav_web_jpeg_encode_seconds",
            "Drawing the overlay and encoding one video frame (once per frame, all clients)",
            buckets=ENCODE_BUCKETS_S,
            registry=registry,
        ),
    )
    return registry, web
