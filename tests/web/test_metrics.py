"""``/metrics``: names, cumulative histograms fed from bounded windows, scrape cost."""

from __future__ import annotations

import time

import numpy as np
from fastapi.testclient import TestClient
from prometheus_client import REGISTRY, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from app.messages import State
from app.runtime.telemetry import FloatWindow
from app.web import create_app
from app.web.metrics import CumulativeHistogram, build_registry

from .conftest import TOKEN
from .fakes import FakeService, floor_msg


def scrape(client: TestClient) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    samples: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(response.text):
        for sample in family.samples:
            key = tuple(sorted(sample.labels.items()))
            samples.setdefault(sample.name, {})[key] = sample.value
    return samples


def test_metrics_report_the_service(client: TestClient, service: FakeService) -> None:
    for seconds in (0.004, 0.02, 0.02, 0.3):
        service.stages.add("perception", seconds)
    service.stages.add("mapping", 0.01)
    service.add_latency(0.08)
    service.counters.watchdog_stops = 2
    service.counters.premise_stops = 3
    service.counters.frames_perceived = 40
    service.counters.learned_floor_passes = 7
    service.estop("test")
    assert service.link is not None
    service.link.stats.crc_errors = 3
    service.link.stats.timeouts = 4
    service.link.stats.reconnects = 5
    service.floors.publish(floor_msg(1, zone_floor_confidence=0.25))
    for t in (0.0, 5.0, 10.0):  # three link blips in a minute, each resumed from, latch
        service.policy.observe("link", "Uno reconnecting", t)
        service.policy.observe("link", None, t + 0.5)

    metrics = scrape(client)
    assert metrics["floornav_stops_total"][(("cause", "link"),)] == 3
    assert metrics["floornav_stops_total"][(("cause", "clearance"),)] == 0
    assert metrics["floornav_fault_latched"][()] == 1
    perception = (("stage", "perception"),)
    assert metrics["floornav_stage_latency_seconds_count"][perception] == 4
    buckets = metrics["floornav_stage_latency_seconds_bucket"]
    assert buckets[(("le", "0.005"), ("stage", "perception"))] == 1
    assert buckets[(("le", "0.02"), ("stage", "perception"))] == 3  # le: 0.02 included
    assert buckets[(("le", "+Inf"), ("stage", "perception"))] == 4
    assert np.isclose(metrics["floornav_stage_latency_seconds_sum"][perception], 0.344)
    assert metrics["floornav_capture_to_command_seconds_count"][()] == 1
    assert metrics["floornav_serial_errors_total"][(("kind", "crc"),)] == 3
    assert metrics["floornav_serial_errors_total"][(("kind", "timeout"),)] == 4
    assert metrics["floornav_serial_reconnects_total"][()] == 5
    assert metrics["floornav_watchdog_stops_total"][()] == 2
    assert metrics["floornav_premise_stops_total"][()] == 3
    assert metrics["floornav_learned_floor_passes_total"][()] == 7
    assert metrics["floornav_zone_floor_confidence"][()] == 0.25
    assert metrics["floornav_estops_total"][()] == 1
    assert 0 <= metrics["floornav_frame_age_seconds"][()] < 5
    assert metrics["floornav_fps"][()] > 0
    assert metrics["floornav_state"][(("floornav_state", "estopped"),)] == 1
    assert metrics["floornav_state"][(("floornav_state", State.IDLE.value),)] == 0

    # A second scrape adds only what is new.
    service.stages.add("perception", 0.001)
    again = scrape(client)
    assert again["floornav_stage_latency_seconds_count"][perception] == 5
    assert again["floornav_capture_to_command_seconds_count"][()] == 1


def test_web_metrics_and_no_global_registry(client: TestClient, service: FakeService) -> None:
    metrics = scrape(client)
    assert metrics["floornav_web_video_clients"][()] == 0
    assert b"floornav_" not in generate_latest(REGISTRY)
    # Two apps over one service keep separate registries (no duplicate-name errors).
    create_app(service, token=TOKEN, static_dir=None)


def test_histogram_survives_a_window_that_dropped_samples() -> None:
    window = FloatWindow(maxlen=4)
    histogram = CumulativeHistogram((0.01, 0.1))
    total = 0
    for value in (0.005, 0.05, 0.5):
        window.append(value)
        total += 1
    histogram.catch_up(window, total)
    for value in (0.005,) * 6:  # more than the window holds: two are lost, not invented
        window.append(value)
        total += 1
    histogram.catch_up(window, total)
    assert histogram.counts.tolist() == [1 + 4, 1, 1]
    histogram.catch_up(window, total)  # nothing new
    assert histogram.counts.sum() == 7


def test_scrape_time_with_full_windows() -> None:
    """Prints the scrape cost with 100k samples in each of four stage windows and the
    latency window (first scrape reads them all; later ones only what is new). Timing is
    reported, not asserted."""
    service = FakeService()
    rng = np.random.default_rng(0)
    for stage in ("perception", "mapping", "steering", "drive"):
        for value in rng.uniform(0.001, 0.2, 100_000):
            service.stages.add(stage, float(value))
    for value in rng.uniform(0.02, 0.3, 100_000):
        service.add_latency(float(value))
    registry, _ = build_registry(service)
    start = time.perf_counter()
    generate_latest(registry)
    first_ms = (time.perf_counter() - start) * 1000
    steady = []
    for _ in range(20):
        for stage in ("perception", "mapping", "steering", "drive"):
            for _ in range(450):  # 15 s at 30 fps between scrapes
                service.stages.add(stage, 0.02)
        start = time.perf_counter()
        generate_latest(registry)
        steady.append((time.perf_counter() - start) * 1000)
    print(
        f"\nmetrics scrape: first (5 x 100k samples) {first_ms:.2f} ms, "
        f"steady (4 x 450 new samples) median {float(np.median(steady)):.2f} ms, "
        f"max {max(steady):.2f} ms"
    )


def test_event_loop_lag_histogram(client: TestClient, service: FakeService) -> None:
    """``floornav_event_loop_lag_seconds`` is a well-formed cumulative histogram of the
    service's loop lags: every bucket the monitor has, non-decreasing counts, +Inf equal
    to _count, and counts that only grow from scrape to scrape."""
    for lag_s in (0.0005, 0.003, 0.02, 0.07, 2.0):
        service.loop_lag.record(lag_s)
    metrics = scrape(client)
    buckets = {
        dict(key)["le"]: count
        for key, count in metrics["floornav_event_loop_lag_seconds_bucket"].items()
    }
    expected_bounds = [f"{b:g}" for b in service.loop_lag.buckets_s] + ["+Inf"]
    assert list(buckets) == expected_bounds
    counts = list(buckets.values())
    assert counts == sorted(counts)
    assert buckets["0.001"] == 1
    assert buckets["0.02"] == 3  # le: a lag equal to the bound is in its bucket
    assert buckets["0.1"] == 4
    assert buckets["1"] == 4
    assert buckets["+Inf"] == metrics["floornav_event_loop_lag_seconds_count"][()] == 5
    assert np.isclose(metrics["floornav_event_loop_lag_seconds_sum"][()], 2.0935)

    service.loop_lag.record(0.004)
    again = scrape(client)
    assert again["floornav_event_loop_lag_seconds_count"][()] == 6
    assert again["floornav_event_loop_lag_seconds_bucket"][(("le", "0.005"),)] == 3
