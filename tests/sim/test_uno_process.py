"""The simulated Uno in its own process: a host link drives the plant through it, a
killed child is restarted on the same port, nothing is left behind, and the Uno keeps
its timing while the host's interpreter is stalled."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from app.hardware.interfaces import DeviceState
from app.hardware.protocol import MsgType, Telemetry, drive_payload, telemetry_period_payload
from app.hardware.serial_link import UnoLink, UnoLinkConfig
from app.sim.sim_uno import SimulatedUno
from app.sim.uno_process import PROJECT_ROOT, SimulatedUnoProcess

from .test_sim_uno import RawHost

FAST_RECONNECT = UnoLinkConfig(backoff_initial_s=0.05, backoff_max_s=0.1)


class RecordingPlant:
    """A `MotorPlant` that remembers every PWM it got; the test sets its encoders."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.applied: list[tuple[int, int]] = []
        self.encoders = (0, 0)

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
        with self._lock:
            self.applied.append((left_pwm, right_pwm))

    def read_encoders(self) -> tuple[int, int]:
        with self._lock:
            return self.encoders

    @property
    def pwm(self) -> tuple[int, int]:
        with self._lock:
            return self.applied[-1] if self.applied else (0, 0)


async def eventually(predicate: Callable[[], object], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.005)


def process_is_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.fixture
def plant() -> RecordingPlant:
    return RecordingPlant()


@pytest.fixture
def uno(plant: RecordingPlant) -> Iterator[SimulatedUnoProcess]:
    with SimulatedUnoProcess(plant) as process_uno:
        yield process_uno


async def test_a_link_drives_the_plant_and_reads_its_encoders(
    uno: SimulatedUnoProcess, plant: RecordingPlant
) -> None:
    assert uno.pid is not None and uno.pid != os.getpid()
    assert Path(uno.port).is_symlink() and os.path.realpath(uno.port) == uno.pty_path
    async with UnoLink(uno.port) as link:
        await link.wait_connected(5.0)
        assert link.banner is not None and link.banner.firmware.startswith("floornav-sim")
        sent_s = time.monotonic()
        await link.drive(120, -80)
        await eventually(lambda: plant.pwm == (120, -80), 1.0, "the plant to get the PWM")
        assert uno.pwm == (120, -80)
        # When the child set it, on the clock every process shares.
        assert sent_s < uno.pwm_changed_s <= time.monotonic()

        plant.encoders = (500, -300)

        def encoders_reported() -> bool:
            telemetry = link.latest_telemetry(0.5)
            return telemetry is not None and (
                telemetry.data.encoder_left,
                telemetry.data.encoder_right,
            ) == (500, -300)

        await eventually(encoders_reported, 1.0, "telemetry to carry the plant's encoders")
        await link.stop_motors()
        await eventually(lambda: plant.pwm == (0, 0), 1.0, "the stop to reach the plant")
    assert uno.count(MsgType.HELLO) >= 1 and uno.count(MsgType.DRIVE) >= 1
    assert uno.count(MsgType.STOP) >= 2  # the handshake's and ours
    assert uno.restarts == 0


def test_the_host_hears_when_the_childs_deadman_trips(
    uno: SimulatedUnoProcess, plant: RecordingPlant
) -> None:
    # Tests tell a stop the host sent from one the firmware made because the host went
    # quiet (tests/browser/test_operator_stop.py); both show as PWM 0/0.
    host = RawHost(uno.port)
    try:
        # Read the clock before sending: the child arms its deadman when the DRIVE
        # arrives, which can be before command() returns with the ACK.
        sent_s = time.monotonic()
        host.command(MsgType.DRIVE, drive_payload(90, 90))
        deadline = time.monotonic() + 2.0
        while not uno.deadman_trips_s and time.monotonic() < deadline:
            time.sleep(0.01)
        assert uno.pwm == (0, 0) and plant.pwm == (0, 0)
        assert len(uno.deadman_trips_s) == 1
        trip_s = uno.deadman_trips_s[0]
        assert 0.25 <= trip_s - sent_s < 1.0
        assert uno.pwm_changed_s == pytest.approx(trip_s, abs=0.01)
        host.command(MsgType.DRIVE, drive_payload(90, 90))
        host.command(MsgType.STOP)  # a stop the host sent is no trip
        time.sleep(0.35)
        assert len(uno.deadman_trips_s) == 1
    finally:
        host.close()


async def test_a_killed_child_is_restarted_and_the_link_reconnects_on_the_same_port(
    uno: SimulatedUnoProcess, plant: RecordingPlant, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="app.sim.uno_process")
    port, first_pid = uno.port, uno.pid
    assert first_pid is not None
    async with UnoLink(port, config=FAST_RECONNECT) as link:
        await link.wait_connected(5.0)
        await link.drive(100, 100)
        await eventually(lambda: plant.pwm == (100, 100), 1.0, "the plant to get the PWM")

        uno.kill()
        await eventually(lambda: link.state is not DeviceState.CONNECTED, 1.0, "the link fault")
        # A dead Uno drives nothing: the plant's motors stop at once.
        await eventually(lambda: plant.pwm == (0, 0), 1.0, "the motors to stop")
        assert uno.pwm == (0, 0)
        await eventually(lambda: link.state is DeviceState.CONNECTED, 3.0, "the reconnection")
        assert uno.restarts == 1 and uno.port == port
        assert uno.pid not in (None, first_pid) and process_is_gone(first_pid)
        assert link.stats.reconnects >= 1

        await link.drive(60, 60)
        await eventually(lambda: plant.pwm == (60, 60), 1.0, "the restarted Uno to drive")
    assert "exited with code -9" in caplog.text


async def test_unplug_and_replug_reach_the_child(
    uno: SimulatedUnoProcess, plant: RecordingPlant
) -> None:
    async with UnoLink(uno.port, config=FAST_RECONNECT) as link:
        await link.wait_connected(5.0)
        first_pty = uno.pty_path
        uno.unplug()
        assert not os.path.lexists(uno.port)
        await eventually(lambda: link.state is not DeviceState.CONNECTED, 1.0, "the link fault")
        uno.replug()
        assert os.path.realpath(uno.port) == uno.pty_path != ""
        await eventually(lambda: link.state is DeviceState.CONNECTED, 3.0, "the reconnection")
        assert uno.restarts == 0 and first_pty
    assert plant.pwm == (0, 0)


def test_close_leaves_no_child_and_no_symlink(plant: RecordingPlant) -> None:
    uno = SimulatedUnoProcess(plant).start()
    pid, port = uno.pid, Path(uno.port)
    assert pid is not None and port.is_symlink()
    uno.close()
    assert process_is_gone(pid)
    assert not port.parent.exists()
    uno.close()  # a second close is harmless


def test_close_while_a_restart_is_pending_leaves_nothing(plant: RecordingPlant) -> None:
    uno = SimulatedUnoProcess(plant, restart_initial_s=1.0).start()
    pid, port = uno.pid, Path(uno.port)
    assert pid is not None
    uno.kill()
    deadline = time.monotonic() + 2.0
    while uno.restarts == 0:
        assert time.monotonic() < deadline, "the watcher did not see the death"
        time.sleep(0.005)
    closing = time.monotonic()
    uno.close()
    assert time.monotonic() - closing < 1.0, "close waits for no backoff"
    assert uno.pid is None and process_is_gone(pid) and not port.parent.exists()


@pytest.mark.parametrize("ending", ["end of stdin", "SIGTERM"])
def test_the_child_ends_with_its_host_and_removes_its_link(ending: str, tmp_path: Path) -> None:
    link = tmp_path / "uno"
    child = subprocess.Popen(
        [sys.executable, "-m", "app.sim.uno_process", "--link", str(link)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=PROJECT_ROOT,
    )
    try:
        assert child.stdout is not None and child.stdin is not None
        first = child.stdout.readline()
        assert first.startswith("PTY /dev/")
        assert os.path.realpath(link) == first.split()[1]
        if ending == "SIGTERM":
            child.send_signal(signal.SIGTERM)
        else:
            child.stdin.close()
        assert child.wait(timeout=3.0) == 0
        assert not os.path.lexists(link)
    finally:
        with contextlib.suppress(ProcessLookupError):
            child.kill()
        child.wait()


def test_the_child_imports_no_heavy_modules() -> None:
    probe = (
        "import sys, app.sim.uno_process; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'cv2', 'numba'}))"
    )
    result = subprocess.run(
        [sys.executable, "-E", "-s", "-c", probe],
        capture_output=True,
        text=True,
        cwd=PROJECT_ROOT,
        check=True,
    )
    assert result.stdout.strip() == "[]"


def hold_the_gil(seconds: float) -> None:
    """Stall this interpreter as a long JIT compile or GC pass does: a pure-Python loop
    that does not hand the GIL to other threads (they would ask for it only after the
    switch interval)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(100.0)
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(interval)


def telemetry_gap_over_a_stall(port: str, stall_s: float) -> tuple[float, float]:
    """Stream telemetry every 20 ms from the Uno at ``port`` while this interpreter is
    stalled; returns (longest gap between frames, span covered), in seconds of the Uno's
    own clock."""
    host = RawHost(port)
    try:
        host.command(MsgType.SET_TELEMETRY, telemetry_period_payload(20))
        host.expect(MsgType.TELEMETRY)
        host.frames.clear()
        host.pump(0.05)
        hold_the_gil(stall_s)
        host.pump(0.05)  # what queued up in the pty meanwhile
        host.send(MsgType.SET_TELEMETRY, telemetry_period_payload(0))
        uptimes_ms = [
            Telemetry.parse(frame.payload).uptime_ms
            for frame in host.frames
            if frame.type == MsgType.TELEMETRY
        ]
    finally:
        host.close()
    assert len(uptimes_ms) >= 2
    gaps_ms = [b - a for a, b in itertools.pairwise(uptimes_ms)]
    return max(gaps_ms) / 1000.0, (uptimes_ms[-1] - uptimes_ms[0]) / 1000.0


def test_the_process_uno_keeps_its_timing_while_the_host_interpreter_stalls() -> None:
    with SimulatedUnoProcess() as uno:
        gap_s, span_s = telemetry_gap_over_a_stall(uno.port, stall_s=0.5)
    assert span_s >= 0.5
    assert gap_s < 0.25, f"telemetry paused {gap_s:.3f} s while the host was stalled"


def test_the_stall_check_catches_a_uno_that_is_a_thread_of_the_host(tmp_path: Path) -> None:
    """The check above is not vacuous: the in-process Uno falls silent during the stall."""
    with SimulatedUno(link_path=tmp_path / "uno") as uno:
        gap_s, _ = telemetry_gap_over_a_stall(uno.port, stall_s=0.5)
    assert gap_s >= 0.4


async def test_a_stall_of_the_whole_machine_is_not_a_pulled_cable(
    uno: SimulatedUnoProcess,
) -> None:
    """A VM paused or a starved CPU stops the host and the simulated Uno together; when
    both resume, the host's silence timer fires before the Uno has had a chance to speak.
    The link must count only the time it was awake to listen."""
    assert uno.pid is not None
    async with UnoLink(uno.port) as link:
        await link.wait_connected(5.0)
        await asyncio.sleep(0.1)
        os.kill(uno.pid, signal.SIGSTOP)
        try:
            time.sleep(0.5)  # this event loop stalls as long as the Uno does
        finally:
            os.kill(uno.pid, signal.SIGCONT)
        await asyncio.sleep(0.5)
        assert link.state is DeviceState.CONNECTED, link.status().detail
        assert link.stats.connects == 1


async def test_a_uno_that_stops_while_the_host_runs_still_faults_as_silent(
    uno: SimulatedUnoProcess,
) -> None:
    """The stall allowance above does not hide a Uno that stopped on its own: the link
    still fails within the silence timeout (the ACK timeouts may say it first)."""
    assert uno.pid is not None
    async with UnoLink(uno.port, config=FAST_RECONNECT) as link:
        await link.wait_connected(5.0)
        os.kill(uno.pid, signal.SIGSTOP)
        stopped_s = time.monotonic()
        try:
            fault = await link.wait_state(DeviceState.FAILED, timeout_s=1.0)
            detected_s = time.monotonic() - stopped_s
        finally:
            os.kill(uno.pid, signal.SIGCONT)
        assert "no bytes from" in fault.detail or "without ACK" in fault.detail
        assert detected_s < 0.2 + 0.1 + 0.1  # the timeout, one telemetry period, slack


def test_the_child_runs_in_a_session_and_scheduler_group_of_its_own(
    uno: SimulatedUnoProcess,
) -> None:
    """So a busy daemon cannot starve it (the kernel's autogroups follow sessions)."""
    assert uno.pid is not None
    assert os.getsid(uno.pid) == uno.pid != os.getsid(0)
    autogroup = Path(f"/proc/{uno.pid}/autogroup")
    if autogroup.exists():
        assert autogroup.read_text() != Path("/proc/self/autogroup").read_text()


def test_the_child_and_its_threads_get_the_cpu_when_they_want_it(
    uno: SimulatedUnoProcess,
) -> None:
    # A board on its own is never starved by the host's load: the child asks for the
    # lowest real-time priority (root here in CI), else a raised nice value.
    pid = uno.pid
    assert pid is not None
    threads = [int(tid) for tid in os.listdir(f"/proc/{pid}/task")]
    assert len(threads) >= 2  # the simulator's threads were started after the request
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        may_use_realtime = False
    else:
        may_use_realtime = True
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if not may_use_realtime:
        original = os.getpriority(os.PRIO_PROCESS, 0)
        try:
            os.setpriority(os.PRIO_PROCESS, 0, -10)
        except OSError:
            pytest.skip("neither real-time priority nor a raised nice value is allowed here")
        os.setpriority(os.PRIO_PROCESS, 0, original)
    for tid in threads:
        if may_use_realtime:
            assert os.sched_getscheduler(tid) == os.SCHED_FIFO
        else:
            assert os.getpriority(os.PRIO_PROCESS, tid) == -10
