"""The stop policy alone: protective stops that recover, faults that latch."""

from __future__ import annotations

from app.config import SafetyConfig
from app.runtime.stops import StopPolicy


def policy(**safety: float) -> StopPolicy:
    return StopPolicy(SafetyConfig.model_validate(safety), wall_clock=lambda: 1000.0)


def test_a_link_blip_holds_then_resumes_after_being_clear_for_the_resume_time() -> None:
    stops = policy(resume_after_clear_s=1.0)
    event = stops.observe("link", "Uno reconnecting: port closed", 10.0)
    assert event is not None and event.cause == "link" and not event.latched
    hold = stops.holding(10.2)
    assert hold is not None and hold.cause == "link" and "port closed" in hold.reason
    assert stops.observe("link", None, 10.5) is None  # clear from here on
    hold = stops.holding(11.4)
    assert hold is not None and "resuming after 1 s" in hold.reason
    assert stops.holding(11.5) is None
    assert stops.latched is None
    assert stops.last_stop is not None and stops.last_stop.cause == "link"
    assert stops.stops_by_cause["link"] == 1


def test_a_cause_that_comes_back_before_the_resume_time_keeps_holding() -> None:
    stops = policy(resume_after_clear_s=1.0)
    stops.observe("stale", "perception 700 ms old", 0.0)
    stops.observe("stale", None, 0.1)
    stops.observe("stale", "perception 650 ms old", 0.6)
    stops.observe("stale", None, 0.7)
    assert stops.holding(1.6) is not None
    assert stops.holding(1.71) is None


def test_three_link_faults_within_a_minute_latch_until_reset() -> None:
    stops = policy(fault_latch_repeats=3, fault_latch_window_s=60.0)
    for t in (0.0, 20.0):
        assert not stops.observe("link", "Uno gone", t).latched  # type: ignore[union-attr]
        stops.observe("link", None, t + 0.5)
    event = stops.observe("link", "Uno gone", 40.0)
    assert event is not None and event.latched
    assert "3 times within 60 s" in event.reason
    stops.observe("link", None, 40.5)
    hold = stops.holding(500.0)  # latched: time alone never clears it
    assert hold is not None and hold.cause == "fault"
    assert stops.reset() is event
    assert stops.holding(500.0) is None
    # The repeat history went with the reset: one more blip is a protective stop again.
    again = stops.observe("link", "Uno gone", 501.0)
    assert again is not None and not again.latched


def test_repeats_spread_wider_than_the_window_do_not_latch() -> None:
    stops = policy(fault_latch_repeats=3, fault_latch_window_s=60.0)
    for t in (0.0, 35.0, 70.0, 105.0):
        event = stops.observe("camera", "camera failed: no frame", t)
        assert event is not None and not event.latched
        stops.observe("camera", None, t + 1.0)
    assert stops.latched is None


def test_a_device_gone_longer_than_the_limit_latches() -> None:
    stops = policy(device_lost_latch_s=5.0)
    stops.observe("camera", "camera failed: unplugged", 0.0)
    assert stops.observe("camera", "camera failed: unplugged", 4.9) is None
    event = stops.observe("camera", "camera failed: unplugged", 5.1)
    assert event is not None and event.latched and "more than 5 s" in event.reason
    assert stops.faults_latched == 1


def test_stale_perception_never_latches_by_duration_and_forward_layers_never_hold() -> None:
    stops = policy(fault_latch_repeats=3)
    stops.observe("stale", "no perception", 0.0)
    assert stops.observe("stale", "no perception", 100.0) is None
    assert stops.latched is None
    for t in range(10):
        stops.observe("clearance", "clearance 0.10 m ahead < 0.20 m", float(t))
        stops.observe("clearance", None, t + 0.5)
    assert stops.latched is None
    stops.observe("stale", None, 101.0)
    stops.observe("not_floor", "safe zone is not floor", 200.0)
    assert stops.holding(200.0) is None  # only takes forward motion away (the gate does)
    assert stops.active("not_floor") == "safe zone is not floor"
    assert stops.last_stop is not None and stops.last_stop.cause == "not_floor"


def test_a_cause_back_before_the_robot_went_on_continues_its_stop_and_is_no_repeat() -> None:
    # A mapping stall: the map arrives just late three times in half a second. The robot
    # never went on in between: one protective stop, not a latched fault.
    stops = policy(resume_after_clear_s=1.0, fault_latch_repeats=3, fault_latch_window_s=60.0)
    first = stops.observe("stale", "map 504 ms old (> 500 ms)", 10.0)
    assert first is not None and not first.latched
    for t in (10.1, 10.3):
        stops.observe("stale", None, t)
        assert stops.observe("stale", "map 510 ms old (> 500 ms)", t + 0.05) is None
    stops.observe("stale", None, 10.5)
    assert stops.latched is None and stops.stops_by_cause["stale"] == 1
    assert stops.holding(11.4) is not None and stops.holding(11.5) is None
    # Once it went on, each return is a stop of its own, and the third latches.
    assert not stops.observe("stale", "map 600 ms old", 12.0).latched  # type: ignore[union-attr]
    stops.observe("stale", None, 12.2)
    event = stops.observe("stale", "map 700 ms old", 14.0)
    assert event is not None and event.latched and "3 times within 60 s" in event.reason


def test_a_flapping_device_counts_its_time_gone_from_the_stops_start() -> None:
    # The Uno's link drops and comes back every half second: the robot never goes on,
    # and after 5 s of that the stop latches as a device gone.
    stops = policy(resume_after_clear_s=1.0, device_lost_latch_s=5.0)
    latched = None
    t = 0.0
    while latched is None and t < 10.0:
        event = stops.observe("link", "Uno reconnecting", t)
        if event is not None and event.latched:
            latched = event
        stops.observe("link", None, t + 0.25)
        t += 0.5
    assert latched is not None and "more than 5 s" in latched.reason
    assert 5.0 < latched.monotonic_s <= 5.5
