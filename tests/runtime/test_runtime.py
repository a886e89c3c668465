"""The daemon's runtime on the simulator: states, stop layers, faults, shutdown."""

from __future__ import annotations

import asyncio
import itertools
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TypeVar

import numpy as np
import pytest

from app.config import FloornavConfig, PerceptionConfig
from app.devices import Devices, open_devices
from app.hardware.interfaces import CameraFrame, DeviceState, DeviceStatus
from app.hardware.protocol import MsgType
from app.messages import State
from app.perception.pipeline import FloorResult, FloorSegmenter
from app.runtime import (
    STRAGGLER_RECANCEL_S,
    WORKER_CLOSE_TIMEOUT_S,
    WORKER_STUCK_S,
    CommandRefusedError,
    Runtime,
)

from .conftest import running, sim_config, wait_for

S = TypeVar("S")


def recording_factory(
    make: Callable[[PerceptionConfig], S],
) -> tuple[list[S], Callable[[PerceptionConfig], S]]:
    """A segmenter factory for the runtime, and the list of what it made (the test
    reaches the running segmenter through it)."""
    made: list[S] = []

    def factory(config: PerceptionConfig) -> S:
        made.append(make(config))
        return made[-1]

    return made, factory


async def teleop_until(
    rt: Runtime,
    v_m_s: float,
    omega_rad_s: float,
    ok: Callable[[], bool],
    what: str,
    timeout_s: float = 5.0,
) -> None:
    """Send teleop ``(v_m_s, omega_rad_s)`` at 20 Hz, as a held key does, until ``ok``."""
    deadline = time.monotonic() + timeout_s
    while not ok():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        rt.teleop("t", v_m_s, omega_rad_s)
        await asyncio.sleep(0.05)


def moved_m(devices: Devices, start: tuple[float, float]) -> float:
    assert devices.sim is not None
    pose = devices.sim.robot.pose
    return float(np.hypot(pose.x_m - start[0], pose.y_m - start[1]))


async def test_autonomy_drives_and_shutdown_stops_the_motors() -> None:
    async with running() as (rt, task):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        start = (sim.robot.pose.x_m, sim.robot.pose.y_m, sim.robot.pose.theta_rad)
        await rt.start()
        assert rt.state is State.RUNNING
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
        await asyncio.sleep(2.0)
        pose = sim.robot.pose
        assert (pose.x_m, pose.y_m, pose.theta_rad) != start
        assert rt.latencies, "autonomy commands carry their capture-to-command latency"
        # From the frame's arrival (after the simulator's render) is the host's part.
        from_arrival = rt.drive.host_latencies.values()
        assert len(from_arrival) == len(rt.latencies)
        assert (from_arrival < rt.latencies.values()).all()
        uno = sim.uno
    await asyncio.sleep(0)
    assert task.done() and task.exception() is None
    assert uno.pwm == (0, 0)
    assert uno.count(MsgType.STOP) >= 1
    assert rt.link is not None and rt.link.state is DeviceState.DISCONNECTED
    assert sim.robot.collisions == 0


async def test_the_running_daemon_follows_the_floors_motion_and_reports_it() -> None:
    async with running() as (rt, _):
        await rt.start()
        # The robot looks around first: a key frame every 0.1 rad of its turn.
        await wait_for(
            lambda: rt.mapper is not None and rt.mapper.floor_odometry_applied >= 3,
            10.0,
            "three floor-odometry steps",
        )
        report = rt.report()
        steps = report["floor_odometry"]
        assert steps["applied"] >= 3 and steps["steps"] >= steps["applied"]
        assert report["stage_ms"]["floor_odometry"]["p50"] > 0
        # The building's axis rides along (learning it takes 20 m of wall lines).
        assert set(report["heading_axis"]) == {"axis_deg", "corrections", "recoveries"}


async def test_the_geometric_tests_run_beside_the_mapping_thread_and_their_results_arrive() -> None:
    """The parallax and walls tests run on the geometry worker, not on the way to the
    motors; the next frames adopt them (their floor and standing reach the map), and
    the report says how long a job took and how long floors and maps waited."""
    async with running() as (rt, _):
        await rt.start()
        await wait_for(
            lambda: rt.mapper is not None and rt.mapper.memory.standing.any(),
            10.0,
            "something seen standing (walls or parallax) in the floor memory",
        )
        await wait_for(lambda: len(rt.steering_stage.map_waits) > 0, 10.0, "a steering decision")
        report = rt.report()
        assert report["stage_ms"]["geometry"]["n"] >= 1
        assert report["stage_ms"]["geometry"]["p50"] > 0
        for wait in ("floor_wait_for_mapping_ms", "map_wait_for_steering_ms"):
            assert report[wait]["n"] >= 1 and report[wait]["p50"] >= 0


async def test_estop_latches_and_refuses_until_reset() -> None:
    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        await rt.start()
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
        rt.estop("test")
        await wait_for(lambda: sim.uno.pwm == (0, 0), 0.5, "e-stop to zero the motors")
        assert rt.state is State.ESTOPPED
        with pytest.raises(CommandRefusedError, match="e-stop"):
            await rt.start()
        with pytest.raises(CommandRefusedError, match="e-stop"):
            rt.teleop("alice", 0.2, 0.0)
        await asyncio.sleep(0.3)
        assert sim.uno.pwm == (0, 0)
        assert rt.reset_estop() is True
        assert rt.state is State.IDLE  # autonomy does not resume by itself
        assert rt.mux.estops == 1


async def test_estop_reaches_the_uno_while_the_drive_stage_waits_on_a_command() -> None:
    """The drive stage can be inside ``link.drive()`` waiting for an ACK (up to the ACK
    timeout, longer on a loaded machine); the e-stop's STOP must not wait its turn."""
    async with running() as (rt, _):
        sim = rt.devices.sim
        link = rt.link
        assert sim is not None and sim.uno is not None and link is not None
        real_drive = link.drive
        stuck = asyncio.Event()

        async def drive_then_hang(left_pwm: int, right_pwm: int) -> None:
            await real_drive(left_pwm, right_pwm)
            if (left_pwm, right_pwm) != (0, 0):
                stuck.set()
                await asyncio.Event().wait()  # as if its ACK never came

        link.drive = drive_then_hang  # type: ignore[method-assign]
        await rt.start()
        await wait_for(stuck.is_set, 5.0, "a drive command")
        await wait_for(lambda: sim.uno.pwm != (0, 0), 2.0, "the motors to turn")
        rt.estop("test")
        # The heartbeat keeps re-sending the last DRIVE: only the e-stop's STOP zeroes it.
        await wait_for(lambda: sim.uno.pwm == (0, 0), 1.0, "the e-stop's STOP")
        assert rt.state is State.ESTOPPED


async def test_teleop_overrides_then_times_out_to_an_explicit_zero() -> None:
    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        commanded = time.monotonic()
        rt.teleop("alice", 0.2, 0.0)
        assert rt.state is State.TELEOP
        await wait_for(lambda: sim.uno.pwm[0] > 0 and sim.uno.pwm[1] > 0, 1.0, "teleop forward")
        with pytest.raises(CommandRefusedError, match="alice"):
            rt.teleop("bob", 0.0, 1.0)

        def timed_out() -> bool:
            drive = rt.drives.peek()
            return drive is not None and drive.source == "timeout"

        await wait_for(timed_out, 1.5, "the teleop timeout's zero")
        drive = rt.drives.peek()
        assert drive is not None and (drive.left_pwm, drive.right_pwm) == (0, 0)
        # 0.5 s teleop timeout, then the next control tick sends the zero (the Uno's
        # own deadman may zero the motors first on a loaded machine: not what we test).
        assert 0.4 < drive.sent_s - commanded < 0.9
        await wait_for(lambda: sim.uno.pwm == (0, 0), 0.5, "the Uno to apply the zero")


class StallingSegmenter:
    """Segments normally until ``stall`` is set, then takes 2 s per frame (a hung stage)."""

    def __init__(self, config: PerceptionConfig) -> None:
        self.inner = FloorSegmenter(config)
        self.stall = threading.Event()

    def segment(self, image: np.ndarray) -> FloorResult:
        if self.stall.is_set():
            time.sleep(2.0)
        return self.inner.segment(image)


async def test_teleop_forward_needs_a_fresh_map_turning_and_reversing_do_not() -> None:
    made, factory = recording_factory(StallingSegmenter)

    # No clearance threshold: what holds the robot back here is the map's age alone.
    config = sim_config(safety={"min_clearance_m": 0.0, "min_clearance_floor_m": 0.0})
    async with running(config, segmenter_factory=factory) as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        uno = sim.uno

        assert rt.state is State.IDLE, "an operator driving, not autonomy"
        await teleop_until(rt, 0.2, 0.0, lambda: uno.pwm[0] > 0 and uno.pwm[1] > 0, "forward")
        made[0].stall.set()
        await teleop_until(rt, 0.2, 0.0, lambda: uno.pwm == (0, 0), "the blind forward stop")
        status = rt.status()
        assert status["stop_cause"] == "clearance"
        reason = re.fullmatch(
            r"clearance unknown: map (\d+) ms old \(> 500 ms\): no forward motion",
            status["stop_reason"],
        )
        assert reason is not None, status["stop_reason"]
        assert int(reason[1]) > 500  # never "500 ms old (> 500 ms)"
        for _ in range(5):  # held as long as the map stays old
            rt.teleop("t", 0.2, 0.0)
            await asyncio.sleep(0.05)
            assert uno.pwm == (0, 0)
        # Turning in place and backing away stay possible on a stalled perception.
        await teleop_until(rt, 0.0, 1.0, lambda: uno.pwm[0] * uno.pwm[1] < 0, "turning")
        await teleop_until(rt, -0.1, 0.0, lambda: uno.pwm[0] < 0 and uno.pwm[1] < 0, "reversing")

        made[0].stall.clear()
        await teleop_until(rt, 0.2, 0.0, lambda: uno.pwm[0] > 0 and uno.pwm[1] > 0, "forward again")
        assert rt.status()["stop_reason"] is None
        rt.release_teleop("t")


async def test_stale_perception_stops_the_robot_and_resumes_once_fresh_for_a_second() -> None:
    made, factory = recording_factory(StallingSegmenter)

    async with running(segmenter_factory=factory) as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        await rt.start()
        rt.teleop("t", 0.0, 1.0)  # make sure the motors turn, then hand back to autonomy
        rt.release_teleop("t")
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
        made[0].stall.set()
        stalled = time.monotonic()
        await wait_for(lambda: sim.uno.pwm == (0, 0), 1.5, "the stale-perception stop")
        # perception_max_age_s = 0.5 plus at most a frame and a control tick.
        assert time.monotonic() - stalled < 0.8
        assert rt.counters.watchdog_stops >= 1
        assert rt.state is State.PROTECTIVE_STOP
        assert rt.status()["stop_cause"] == "stale"
        made[0].stall.clear()
        # A protective stop: once perception is fresh again for 1 s, autonomy goes on.
        await wait_for(lambda: rt.state is State.RUNNING, 6.0, "autonomy to resume")
        await wait_for(lambda: sim.uno.pwm != (0, 0), 3.0, "the motors to turn again")
        assert rt.status()["last_stop"]["cause"] == "stale"
        assert rt.policy.latched is None


class ZoneConfidenceSegmenter:
    """Segments normally but reports ``confidence`` as its zone floor confidence (as if
    an obstacle stood in the safe zone while the mask still said floor)."""

    def __init__(self, config: PerceptionConfig) -> None:
        self.inner = FloorSegmenter(config)
        self.confidence = 1.0

    def segment(self, image: np.ndarray) -> FloorResult:
        return replace(self.inner.segment(image), zone_floor_confidence=self.confidence)


class SecondPassSegmenter:
    """Segments normally and says it ran the learned-floor second pass on every frame,
    adding floor on every other one."""

    def __init__(self, config: PerceptionConfig) -> None:
        self.inner = FloorSegmenter(config)
        self.frames = 0

    def segment(self, image: np.ndarray) -> FloorResult:
        self.frames += 1
        added = 0.01 if self.frames % 2 else 0.0
        return replace(
            self.inner.segment(image),
            learned_floor_reference=(0.1, 0.0, 0.0),
            learned_floor_added_share=added,
        )


async def test_learned_floor_second_passes_are_counted_in_the_report() -> None:
    async with running(segmenter_factory=SecondPassSegmenter) as (rt, _):
        await wait_for(lambda: rt.counters.frames_perceived >= 6, 5.0, "six frames")
        report = rt.report()
        memory = report["floor_memory"]
        assert memory["second_passes"] == rt.counters.learned_floor_passes >= 6
        adding = memory["second_passes_adding_floor"]
        assert adding == rt.counters.learned_floor_passes_adding
        assert abs(adding - memory["second_passes"] / 2) <= 1
        assert memory["second_pass_share"] == pytest.approx(1.0, abs=0.2)


class BudgetedPassSegmenter:
    """Runs (says it ran) a learned-floor pass, adding floor, whenever the daemon lets it.

    ``due`` records when the perception stage decided (it sets ``learned_pass_due`` on its
    loop right after reading its clock), not when ``segment`` ran: the worker thread may
    start a frame late, by a different delay each time, on a loaded machine."""

    def __init__(self, config: PerceptionConfig) -> None:
        self.inner = FloorSegmenter(config)
        self.learned_floor: tuple[tuple[float, float, float], ...] = ()
        self._due = True
        self.due: list[tuple[float, bool]] = []

    @property
    def learned_pass_due(self) -> bool:
        return self._due

    @learned_pass_due.setter
    def learned_pass_due(self, due: bool) -> None:
        self._due = due
        self.due.append((time.monotonic(), due))

    def segment(self, image: np.ndarray) -> FloorResult:
        result = self.inner.segment(image)
        if not self.learned_pass_due:
            return result
        return replace(
            result, learned_floor_reference=(0.1, 0.0, 0.0), learned_floor_added_share=0.1
        )


async def test_learned_floor_passes_run_at_most_once_per_period() -> None:
    made, factory = recording_factory(BudgetedPassSegmenter)

    config = sim_config(perception={"learned_floor_pass_period_s": 0.25})
    async with running(config, segmenter_factory=factory) as (rt, _):
        await wait_for(lambda: rt.counters.frames_perceived >= 40, 10.0, "40 frames")
    due = made[-1].due
    passes = [t for t, d in due if d]
    span_s = due[-1][0] - due[0][0]
    assert 2 <= len(passes) <= span_s / 0.25 + 1
    # A pass per frame would be 33 ms apart, half the period 125 ms; 20 ms of slack is
    # for the loop thread losing the GIL between the stage's clock read and the setter.
    assert all(b - a >= 0.25 - 0.02 for a, b in itertools.pairwise(passes))
    assert len(due) - len(passes) >= 20  # the frames between: the first pass only
    assert rt.counters.learned_floor_passes == len(passes)


def premise_only_config() -> FloornavConfig:
    """No clearance stop: what holds the robot back is the premise alone. No parallax: the
    map knows no floor ahead but what a test puts there."""
    return sim_config(
        safety={"min_clearance_m": 0.0, "min_clearance_floor_m": 0.0},
        mapping={"parallax_floor": False},
    )


async def test_a_safe_zone_that_is_not_floor_stops_forward_motion_until_it_is_again() -> None:
    made, factory = recording_factory(ZoneConfidenceSegmenter)
    async with running(premise_only_config(), segmenter_factory=factory) as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        uno = sim.uno
        assert rt.status()["zone_floor_confidence"] == 1.0
        await rt.start()
        await wait_for(lambda: uno.pwm != (0, 0), 5.0, "the motors to turn")
        assert rt.counters.premise_stops == 0

        made[0].confidence = 0.1
        await wait_for(lambda: rt.counters.premise_stops == 1, 1.0, "the premise stop")
        status = rt.status()
        assert status["zone_floor_confidence"] == 0.1
        assert status["stop_cause"] == "not_floor"
        # The reason says what perception and the map each make of the zone.
        assert re.fullmatch(
            r"safe zone is not floor \(confidence 0\.10 < 0\.50; the map knows \d+% of it "
            r"\(< 60%\)\): turning to look elsewhere",
            status["stop_reason"],
        ), status["stop_reason"]

        # Autonomy turns in place to look elsewhere: no forward motion, but turning.
        def turning_in_place() -> bool:
            decision, drive = rt.decisions.peek(), rt.drives.peek()
            return (
                decision is not None
                and decision.reason == "not_floor"
                and drive is not None
                and drive.source == "autonomy"
                and drive.twist.v_m_s == 0.0
                and abs(drive.twist.omega_rad_s) > 0.3
            )

        await wait_for(turning_in_place, 2.0, "autonomy to turn in place")
        start_xy = (sim.robot.pose.x_m, sim.robot.pose.y_m)
        start_theta = sim.robot.pose.theta_rad
        for _ in range(10):
            await asyncio.sleep(0.05)
            drive = rt.drives.peek()
            assert drive is not None and drive.twist.v_m_s <= 0.0
            assert uno.pwm[0] * uno.pwm[1] <= 0, "wheels turning the opposite ways"
        assert moved_m(rt.devices, start_xy) < 0.02
        assert abs(sim.robot.pose.theta_rad - start_theta) > 0.05

        # The gate refuses forward motion to anyone: teleop forward stands still.
        await teleop_until(
            rt,
            0.2,
            0.0,
            lambda: (drive := rt.drives.peek()) is not None and drive.source == "teleop",
            "teleop to drive",
            2.0,
        )
        for _ in range(5):
            rt.teleop("t", 0.2, 0.0)
            await asyncio.sleep(0.05)
            assert uno.pwm == (0, 0)
        assert rt.status()["stop_reason"].endswith("(< 60%)): no forward motion")
        assert rt.counters.premise_stops == 1, "one stop, counted once"

        # The zone is floor again: the stop clears by itself and forward motion resumes.
        made[0].confidence = 0.9
        await teleop_until(
            rt, 0.2, 0.0, lambda: uno.pwm[0] > 0 and uno.pwm[1] > 0, "forward motion", 2.0
        )
        status = rt.status()
        assert status["zone_floor_confidence"] == 0.9
        assert status["stop_cause"] is None and status["stop_reason"] is None
        rt.release_teleop("t")
        await wait_for(
            lambda: (d := rt.decisions.peek()) is not None and d.reason != "not_floor",
            2.0,
            "steering to stop turning away",
        )
        assert rt.counters.premise_stops == 1
        assert rt.report()["premise_stops"] == 1


async def test_a_safe_zone_the_map_knows_is_floor_is_driven_on_whatever_perception_doubts() -> None:
    made, factory = recording_factory(ZoneConfidenceSegmenter)
    async with running(premise_only_config(), segmenter_factory=factory) as (rt, _):
        sim, mapper = rt.devices.sim, rt.shared.mapper
        assert sim is not None and sim.uno is not None and mapper is not None
        uno = sim.uno
        made[0].confidence = 0.1
        # As if the robot had driven over all of it: geometry knows the floor.
        await rt.mapping.worker.run(mapper.memory.confirmed.fill, 1)
        await wait_for(
            lambda: rt.status()["zone_known_floor"] == 1.0, 2.0, "the map to know the zone"
        )
        await rt.start()
        await wait_for(lambda: uno.pwm[0] > 0 and uno.pwm[1] > 0, 5.0, "forward motion")
        status = rt.status()
        assert status["zone_floor_confidence"] == 0.1
        assert status["stop_cause"] != "not_floor"
        assert rt.counters.premise_stops == 0
        assert rt.counters.zone_known_floor_frames > 0
        # The map forgets (as if all of it had been seen standing): perception's doubt
        # stops the robot again.
        await rt.mapping.worker.run(mapper.memory.confirmed.fill, 0)
        await wait_for(lambda: rt.counters.premise_stops == 1, 2.0, "the premise stop")
        status = rt.status()
        assert status["zone_known_floor"] < 0.6
        assert "the map knows" in status["stop_reason"]
        assert rt.report()["zone_known_floor_frames"] == rt.counters.zone_known_floor_frames


class HangingSegmenter(FloorSegmenter):
    """Segments normally until ``hang`` is set, then blocks in its job until ``release``
    (like a kernel stuck in native code: the thread cannot be interrupted)."""

    hang = threading.Event()
    release = threading.Event()

    def segment(self, image: np.ndarray) -> FloorResult:
        if self.hang.is_set():
            self.release.wait(60.0)
        return super().segment(image)


async def test_a_hung_perception_job_stops_the_motors_and_does_not_block_shutdown(
    caplog: pytest.LogCaptureFixture,
) -> None:
    HangingSegmenter.hang.clear()
    HangingSegmenter.release.clear()
    caplog.set_level(logging.WARNING, logger="floornav.runtime")
    try:
        async with running(segmenter_factory=HangingSegmenter) as (rt, task):
            sim = rt.devices.sim
            assert sim is not None and sim.uno is not None
            uno = sim.uno
            await rt.start()
            await wait_for(lambda: uno.pwm != (0, 0), 5.0, "the motors to turn")
            HangingSegmenter.hang.set()
            await wait_for(lambda: uno.pwm == (0, 0), 1.5, "the stale-perception stop")
            await wait_for(
                lambda: "worker_stuck" in [getattr(r, "event", "") for r in caplog.records],
                WORKER_STUCK_S + 2.0,
                "the stuck job to be logged",
            )
            assert "segment" in caplog.text, "the log says where the job is stuck"
            closing = time.monotonic()
        assert task.done() and task.exception() is None
        assert time.monotonic() - closing < WORKER_CLOSE_TIMEOUT_S + 4.0
        assert uno.pwm == (0, 0)
        assert uno.count(MsgType.STOP) >= 1
    finally:
        HangingSegmenter.release.set()
        HangingSegmenter.hang.clear()


class CrashingSegmenter(FloorSegmenter):
    crash = threading.Event()

    def segment(self, image: np.ndarray) -> FloorResult:
        if self.crash.is_set():
            raise RuntimeError("injected perception bug")
        return super().segment(image)


async def test_a_crashing_stage_stops_the_motors_and_ends_the_run() -> None:
    CrashingSegmenter.crash.clear()
    async with running(segmenter_factory=CrashingSegmenter) as (rt, task):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        rt.teleop("t", 0.2, 0.0)
        await wait_for(lambda: sim.uno.pwm != (0, 0), 2.0, "teleop to drive")
        CrashingSegmenter.crash.set()
        await asyncio.wait({task}, timeout=5.0)
        assert task.done()
        with pytest.raises(ExceptionGroup) as info:
            task.result()
        assert info.group_contains(RuntimeError, match="injected")
        assert sim.uno.pwm == (0, 0)
        assert sim.uno.count(MsgType.STOP) >= 1
        assert rt.crash is not None and "injected" in rt.crash
    CrashingSegmenter.crash.clear()


async def test_missing_calibration_refuses_autonomy_but_allows_teleop() -> None:
    def no_calibration(devices: Devices) -> None:
        devices.calibration = None
        devices.calibration_problem = "no floor calibration at calibration/floor.json"

    config = sim_config()
    from app.devices import open_devices
    from app.runtime import Runtime

    with open_devices(config) as devices:
        no_calibration(devices)
        rt = Runtime(config, devices)
        task = asyncio.create_task(rt.run(install_signals=False))
        try:
            await wait_for(lambda: rt.floors.peek() is not None, 20.0, "perception")
            with pytest.raises(CommandRefusedError, match="calibration"):
                await rt.start()
            assert rt.status()["calibration_problem"].startswith("no floor calibration")
            sim = devices.sim
            assert sim is not None and sim.uno is not None
            rt.teleop("alice", 0.0, 1.0)
            await wait_for(lambda: sim.uno.pwm != (0, 0), 1.0, "teleop to drive")
        finally:
            rt.request_shutdown()
            await asyncio.wait_for(task, 10.0)


class DyingCamera:
    """Wraps a camera; while ``dead`` it has no frames and reports FAILED."""

    def __init__(self, inner: object) -> None:
        self.inner = inner
        self.dead = False

    def open(self) -> None:
        self.inner.open()  # type: ignore[attr-defined]

    def close(self) -> None:
        self.inner.close()  # type: ignore[attr-defined]

    def latest(self, max_age_s: float) -> CameraFrame | None:
        return None if self.dead else self.inner.latest(max_age_s)  # type: ignore[attr-defined]

    def status(self) -> DeviceStatus:
        if self.dead:
            return DeviceStatus(DeviceState.FAILED, "unplugged (test)")
        return self.inner.status()  # type: ignore[attr-defined,no-any-return]


def dying_camera(cameras: list[DyingCamera]) -> Callable[[Devices], None]:
    def wrap(devices: Devices) -> None:
        cameras.append(DyingCamera(devices.camera))
        devices.camera = cameras[0]  # type: ignore[assignment]

    return wrap


async def test_a_camera_gap_is_a_protective_stop_that_resumes_by_itself() -> None:
    cameras: list[DyingCamera] = []
    async with running(prepare=dying_camera(cameras)) as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        await rt.start()
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
        cameras[0].dead = True
        await wait_for(lambda: rt.state is State.PROTECTIVE_STOP, 1.5, "the protective stop")
        await wait_for(lambda: sim.uno.pwm == (0, 0), 1.0, "motors zero")
        status = rt.status()
        assert status["stop_cause"] == "camera" and "unplugged" in status["stop_reason"]
        assert status["last_stop"]["cause"] == "camera" and status["fault"] is None
        cameras[0].dead = False
        back = time.monotonic()
        await wait_for(lambda: rt.state is State.RUNNING, 3.0, "autonomy to resume")
        # Resumes only once the cause has been clear for resume_after_clear_s (1 s).
        assert time.monotonic() - back >= 0.9
        await wait_for(lambda: sim.uno.pwm != (0, 0), 3.0, "the motors to turn again")
        assert rt.report()["faults"] == 0
        assert rt.report()["protective_stops"]["camera"] == 1


async def test_a_camera_gone_too_long_latches_a_fault_until_the_operator_resets_it() -> None:
    cameras: list[DyingCamera] = []
    config = sim_config(safety={"device_lost_latch_s": 1.0})
    async with running(config, prepare=dying_camera(cameras)) as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        await rt.start()
        cameras[0].dead = True
        await wait_for(lambda: rt.state is State.FAULT, 3.0, "the latched fault")
        assert "more than 1 s" in (rt.status()["fault"] or "")
        cameras[0].dead = False
        await asyncio.sleep(1.5)
        assert rt.state is State.FAULT  # the cause is gone, the fault stays latched
        assert sim.uno.pwm == (0, 0)
        with pytest.raises(CommandRefusedError, match="fault latched"):
            await rt.start()
        fault = rt.reset_fault()
        assert fault is not None and fault.cause == "camera"
        assert rt.state is State.IDLE  # autonomy does not resume by itself after a fault
        assert rt.status()["fault"] is None
        await rt.start()
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")


async def test_a_pulled_usb_cable_is_a_protective_stop_that_resumes_after_replug() -> None:
    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        await rt.start()
        await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
        sim.uno.unplug()
        await wait_for(lambda: rt.state is State.PROTECTIVE_STOP, 2.0, "the protective stop")
        assert "Uno" in (rt.status()["stop_reason"] or "")
        assert rt.status()["fault"] is None
        sim.uno.replug()
        await wait_for(lambda: rt.state is State.RUNNING, 6.0, "reconnection and resume")
        assert rt.link is not None and rt.link.stats.reconnects >= 1
        await wait_for(lambda: sim.uno.pwm != (0, 0), 3.0, "autonomy to drive again")
        assert rt.report()["protective_stops"]["link"] == 1


async def test_a_killed_uno_process_is_restarted_and_three_kills_in_a_minute_latch() -> None:
    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        uno = sim.uno
        await rt.start()
        for kill in range(1, 4):
            await wait_for(lambda: uno.pwm != (0, 0), 8.0, "the motors to turn")
            uno.kill()  # type: ignore[attr-defined]
            await wait_for(
                lambda n=kill: rt.policy.stops_by_cause["link"] == n, 2.0, f"link stop {kill}"
            )
            if kill < 3:
                # Restarted by the daemon's watcher; autonomy resumes by itself.
                await wait_for(lambda: rt.state is State.RUNNING, 8.0, f"resume after kill {kill}")
        assert uno.restarts >= 2  # type: ignore[attr-defined]
        await wait_for(lambda: rt.state is State.FAULT, 2.0, "the latched fault")
        assert "3 times within 60 s" in (rt.status()["fault"] or "")
        assert not rt.status()["autonomous"]
        await wait_for(
            lambda: rt.link is not None and rt.link.state.value == "connected", 8.0, "link"
        )
        await asyncio.sleep(1.2)
        assert rt.state is State.FAULT and uno.pwm == (0, 0)
        assert rt.report()["faults"] == 1
        rt.reset_fault()
        assert rt.state is State.IDLE


async def test_start_stop_restart() -> None:
    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None and sim.uno is not None
        for _ in range(2):
            await rt.start()
            assert rt.state is State.RUNNING
            await wait_for(lambda: sim.uno.pwm != (0, 0), 5.0, "the motors to turn")
            await rt.stop()
            assert rt.state is State.IDLE
            await wait_for(lambda: sim.uno.pwm == (0, 0), 0.5, "stop to zero the motors")
        assert [t.new for t in rt.transitions][-4:] == [
            State.RUNNING,
            State.IDLE,
            State.RUNNING,
            State.IDLE,
        ]


class CancellationSwallowingService:
    """A service with a library bug: it loses the first cancellation and carries on."""

    name = "stubborn"

    def __init__(self) -> None:
        self.cancels = 0

    async def serve(self) -> None:
        while True:
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                self.cancels += 1
                if self.cancels > 1:
                    raise

    def request_stop(self) -> None:
        pass  # ignores it too


async def test_a_task_that_loses_its_cancellation_does_not_hang_shutdown(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="floornav.runtime")
    service = CancellationSwallowingService()
    config = sim_config()
    with open_devices(config) as devices:
        runtime = Runtime(config, devices)
        started = time.monotonic()
        await asyncio.wait_for(
            runtime.run(duration_s=1.0, install_signals=False, services=[service]), 20.0
        )
        elapsed = time.monotonic() - started
        assert devices.sim is not None and devices.sim.uno is not None
        assert devices.sim.uno.pwm == (0, 0)
        assert devices.sim.uno.count(MsgType.STOP) >= 1
    # 1 s run + 3 s for services to stop + one re-cancel after 2 s.
    assert elapsed < 1.0 + 3.0 + STRAGGLER_RECANCEL_S + 3.0
    assert service.cancels == 2
    assert "stubborn" in caplog.text and "cancelling again" in caplog.text


async def test_a_collision_in_the_simulator_is_logged_and_reported_with_its_context(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from app.mapping.frames import Pose2D

    async with running() as (rt, _):
        sim = rt.devices.sim
        assert sim is not None
        await wait_for(lambda: rt.counters.frames_perceived >= 3, 5.0, "three frames")
        start = sim.robot.pose
        wall = sim.world.nearest_obstacle_xy(start.x_m, start.y_m)
        assert wall is not None
        # Face the nearest wall from 0.5 mm short of touching it, and push the motors
        # (again and again: the Uno's own commands may zero them meanwhile).
        heading = np.arctan2(wall[1] - start.y_m, wall[0] - start.x_m)
        back = sim.robot.params.radius_m + 0.0005
        sim.robot.teleport(
            Pose2D(wall[0] - back * np.cos(heading), wall[1] - back * np.sin(heading), heading)
        )
        caplog.set_level(logging.WARNING, logger="floornav.runtime")

        def push() -> bool:
            sim.robot.apply_pwm(200, 200)
            return bool(rt.collisions.events)

        await wait_for(push, 5.0, "the collision to be reported")
        (event,) = rt.collisions.events
        assert event["number"] == 1
        assert abs(event["bearing_deg"]) < 5.0
        assert {"command", "steering_reason", "map_clearance_ahead_m", "map_age_ms"} <= set(event)
        assert rt.report()["collision_events"] == [event]
        assert any("collision 1 in the simulator" in r.getMessage() for r in caplog.records)
