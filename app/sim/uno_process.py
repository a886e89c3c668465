"""The simulated Uno (`app.sim.sim_uno.SimulatedUno`) in a process of its own.

As a thread of the daemon, the simulated Uno falls silent whenever the daemon's
interpreter stalls (the GIL held by a JIT compile, a GC pass, a big request), and the
host's link then faults over what a real board would never do. In its own process it
keeps its timing whatever the daemon does, like the real firmware in simavr
(`app.hardware.simavr`), and it talks to the host the same way: the pty is the serial
port, the motors and encoders travel as text lines over the child's stdin/stdout.

The child, ``python -m app.sim.uno_process --link PATH [--encoders L R]``, writes:

``PTY <path>``
    the port is up (always the first line; again after a `SimulatedUnoProcess.replug`)
``MOTOR <left> <right> <t>``
    the motor PWM changed at ``t``, the child's ``time.monotonic()`` (one clock for all
    processes on Linux), so the host knows when the Uno acted, not only when it heard
``DEADMAN <t>``
    the deadman tripped at ``t`` (no DRIVE for its period: the host went quiet); the
    MOTOR line of the zero comes first
``RX <type>``
    a valid frame of that `MsgType` arrived (written before its reply goes out)
``OK <id>``
    the fault-injection request ``<id>`` is done

and reads:

``ENC <left> <right>``
    the plant's encoder counts now (what the next telemetry reports)
``UNPLUG|REPLUG|RESET|SILENT|ANSWER <id>``
    fault injection (see `SimulatedUnoProcess`)

It exits when its stdin ends (the host is gone) or on SIGTERM, removing its symlink.
Errors go to its stderr, which it shares with the host.

`SimulatedUnoProcess` is the host side: it runs the child, drives a `MotorPlant` from
the MOTOR lines, feeds the plant's encoders back, and restarts the child when it dies,
on the same symlink, so a host `UnoLink` reconnects to the same path.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import itertools
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Self, TextIO

from app.hardware.protocol import MsgType
from app.sim.sim_uno import IntegratingPlant, ReceivedCommand, SimulatedUno

if TYPE_CHECKING:
    # Annotations only: the child process must not import numpy for nothing.
    from app.hardware.interfaces import MotorPlant

log = logging.getLogger(__name__)

PROJECT_ROOT = Path(__file__).resolve().parents[2]

LINK_NAME = "usb-floornav-sim-uno-if00"
"""The symlink's name in the private directory (a ``/dev/serial/by-id`` look-alike)."""

STABLE_RUN_S = 10.0
"""A child that lived this long before dying starts the restart backoff afresh."""

REQUEST_TIMEOUT_S = 2.0
"""How long a fault-injection request may take (the child handles it in microseconds)."""

DEADMAN_TRIPS_KEPT = 64
"""Deadman trips the host side remembers (`SimulatedUnoProcess.deadman_trips_s`)."""

_FAULT_REQUESTS = frozenset({"UNPLUG", "REPLUG", "RESET", "SILENT", "ANSWER"})


class SimulatedUnoError(RuntimeError):
    """The simulated Uno process did not start or did not answer; says why."""


# -- the child ------------------------------------------------------------------------


class _HostLines:
    """The child's stdout: whole lines, one writer at a time (the simulator thread and
    the stdin reader both write), flushed at once."""

    def __init__(self, out: TextIO, on_broken: Callable[[], None]) -> None:
        self._out = out
        self._lock = threading.Lock()
        self._on_broken = on_broken

    def write(self, line: str) -> None:
        # The host reads continuously; its pipe buffer (64 KiB, minutes of traffic)
        # absorbs a host that stalls, so this does not block in practice.
        with self._lock:
            try:
                self._out.write(line + "\n")
                self._out.flush()
            except (OSError, ValueError):
                self._on_broken()  # the host is gone: nothing left to simulate for


class RelayPlant:
    """The `MotorPlant` the child's Uno drives: motor changes go to the host as MOTOR
    lines, encoder counts are the last ones the host sent (ENC lines)."""

    def __init__(self, lines: _HostLines, encoders: tuple[int, int] = (0, 0)) -> None:
        self._lines = lines
        self._lock = threading.Lock()
        self._encoders = encoders
        self._pwm = (0, 0)  # what the host last heard; the host starts at zero too

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
        with self._lock:
            if (left_pwm, right_pwm) == self._pwm:
                return
            self._pwm = (left_pwm, right_pwm)
        self._lines.write(f"MOTOR {left_pwm} {right_pwm} {time.monotonic():.6f}")

    def read_encoders(self) -> tuple[int, int]:
        with self._lock:
            return self._encoders

    def set_encoders(self, left: int, right: int) -> None:
        with self._lock:
            self._encoders = (left, right)


def _follow_host(
    stdin: TextIO, uno: SimulatedUno, plant: RelayPlant, lines: _HostLines, end: Callable[[], None]
) -> None:
    """The child's stdin reader: encoder counts and fault-injection requests, until the
    host closes the pipe."""
    for line in stdin:
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "ENC":
                plant.set_encoders(int(words[1]), int(words[2]))
                continue
            request, request_id = words[0], words[1]
            if request not in _FAULT_REQUESTS:
                raise ValueError(f"unknown request {request!r}")
            if request == "UNPLUG":
                uno.unplug()
            elif request == "REPLUG":
                uno.replug()
                lines.write(f"PTY {uno.pty_path}")
            elif request == "RESET":
                uno.reset()
            else:
                uno.go_silent(request == "SILENT")
            lines.write(f"OK {request_id}")
        except (IndexError, ValueError) as exc:
            print(f"uno_process: ignoring host line {line!r}: {exc}", file=sys.stderr, flush=True)
    end()


def _stand_apart() -> str:
    """Ask the scheduler for what a board on its own has: the CPU whenever it wants it.

    Under a saturated machine (the daemon and chromium on two cores in the browser
    tests) this process, at normal priority, woke up to 240 ms late, and the host took
    the silence for a hung board; a real Uno's clock does not wait for the host's
    scheduler. The lowest real-time priority does it (the process sleeps between
    frames and uses ~1 % of a core); without the right to it (not root, no
    RLIMIT_RTPRIO) a raised nice value; else nothing. Called before any thread starts,
    so that the simulator's threads inherit it. Returns what it got."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        return "SCHED_FIFO 1"
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, -10)
        return "nice -10"
    return "normal"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m app.sim.uno_process",
        description="The simulated Uno for a host that drives it over stdin/stdout.",
    )
    parser.add_argument("--link", required=True, help="publish the port as a symlink here")
    parser.add_argument(
        "--encoders",
        type=int,
        nargs=2,
        default=(0, 0),
        metavar=("LEFT", "RIGHT"),
        help="the plant's encoder counts at start (so a restarted Uno counts from them)",
    )
    args = parser.parse_args(argv)
    got = _stand_apart()
    if got != "SCHED_FIFO 1":
        # Said once, in the daemon's log (stderr is shared): on a saturated machine a
        # board at normal priority can be late enough for the host to call it silent.
        print(f"uno_process: no real-time priority, running at {got}", file=sys.stderr, flush=True)

    # The host decides when this process ends: a Ctrl-C meant for the daemon reaches
    # the whole process group, and the daemon still has to stop the motors through us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # SIGTERM, the end of stdin and a broken stdout all write to the pipe the main
    # thread waits on (the signal through the wakeup fd: no code runs in its handler).
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGTERM, lambda signum, frame: None)

    def end() -> None:
        with contextlib.suppress(OSError):  # full: the main thread is waking already
            os.write(wake_w, b"\0")

    lines = _HostLines(sys.stdout, end)
    plant = RelayPlant(lines, (args.encoders[0], args.encoders[1]))

    def report_command(command: ReceivedCommand) -> None:
        lines.write(f"RX {int(command.frame.type)}")

    def report_deadman(trip_s: float) -> None:
        lines.write(f"DEADMAN {trip_s:.6f}")

    with SimulatedUno(
        plant,
        link_path=args.link,
        on_command=report_command,
        on_deadman=report_deadman,
        keep_received=False,
    ) as uno:
        lines.write(f"PTY {uno.pty_path}")
        threading.Thread(
            target=_follow_host,
            args=(sys.stdin, uno, plant, lines, end),
            name="host-lines",
            daemon=True,
        ).start()
        os.read(wake_r, 1)  # until SIGTERM or the end of stdin
    return 0


# -- the host side --------------------------------------------------------------------


@dataclass
class _Request:
    done: threading.Event = field(default_factory=threading.Event)
    carried_out: bool = False


class SimulatedUnoProcess:
    """Runs the simulated Uno in a child process and keeps it running.

    Parameters
    ----------
    plant : the `MotorPlant` the simulated motors drive (``apply_pwm`` is called from
        this object's watcher thread); its encoder counts are sent to the child every
        ``encoder_period_s``. Default: an `IntegratingPlant`.
    restart_initial_s, restart_max_s : the delay before restarting a child that died,
        doubling after each quick death up to the maximum.
    start_timeout_s : how long a child may take to announce its port.
    stop_timeout_s : how long `close` waits after SIGTERM before SIGKILL.

    Attributes
    ----------
    port : the symlink to open; stays the same across restarts and replugs.
    pty_path : the pty the symlink currently points to.
    pwm : the last motor command the child reported ((0, 0) while no child runs).
    pwm_changed_s : when the child applied it (``time.monotonic()``; the host reads the
        report a little later, when its thread gets to it).
    deadman_trips_s : when the child's deadman tripped (``time.monotonic()``, newest
        last, the latest `DEADMAN_TRIPS_KEPT`).
    restarts : how many times the child died while in use (each death is followed by
        a restart).
    """

    def __init__(
        self,
        plant: MotorPlant | None = None,
        *,
        encoder_period_s: float = 0.02,
        restart_initial_s: float = 0.2,
        restart_max_s: float = 2.0,
        start_timeout_s: float = 10.0,
        stop_timeout_s: float = 2.0,
    ) -> None:
        if not 0 < restart_initial_s <= restart_max_s:
            raise ValueError("need 0 < restart_initial_s <= restart_max_s")
        if not encoder_period_s > 0:
            raise ValueError(f"encoder_period_s must be > 0, got {encoder_period_s}")
        self.plant: MotorPlant = plant if plant is not None else IntegratingPlant()
        self.encoder_period_s = encoder_period_s
        self.restart_initial_s = restart_initial_s
        self.restart_max_s = restart_max_s
        self.start_timeout_s = start_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.pty_path = ""
        self.pwm = (0, 0)
        self.pwm_changed_s = time.monotonic()
        self.deadman_trips_s: collections.deque[float] = collections.deque(
            maxlen=DEADMAN_TRIPS_KEPT
        )
        self.restarts = 0

        self._dir: Path | None = None
        self._proc: subprocess.Popen[str] | None = None
        self._proc_lock = threading.Lock()  # guards _proc and _dir against close()
        self._stdin_lock = threading.Lock()
        self._closing = threading.Event()
        self._watcher: threading.Thread | None = None
        self._feeder: threading.Thread | None = None
        self._received: collections.Counter[int] = collections.Counter()
        self._received_lock = threading.Lock()
        self._request_ids = itertools.count(1)
        self._requests: dict[str, _Request] = {}

    # -- lifecycle ----------------------------------------------------------------------

    @property
    def port(self) -> str:
        if self._dir is None:
            raise RuntimeError("the simulated Uno process is not started (call start())")
        return str(self._dir / LINK_NAME)

    @property
    def pid(self) -> int | None:
        """The current child's process id (None while none runs)."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def start(self) -> Self:
        with self._proc_lock:
            if self._dir is not None:
                raise RuntimeError("the simulated Uno process is already started")
            self._closing.clear()
            self._dir = Path(tempfile.mkdtemp(prefix="floornav-sim-uno-"))
        try:
            proc = self._spawn()
        except BaseException:
            self.close()
            raise
        self._watcher = threading.Thread(
            target=self._watch, args=(proc,), name="sim-uno-watcher", daemon=True
        )
        self._watcher.start()
        self._feeder = threading.Thread(
            target=self._feed_encoders, name="sim-uno-encoders", daemon=True
        )
        self._feeder.start()
        return self

    def close(self) -> None:
        """End the child (SIGTERM, SIGKILL after ``stop_timeout_s``) and remove the
        port's directory. Never hangs; safe to call twice."""
        with self._proc_lock:
            if self._dir is None:
                return
            self._closing.set()
            proc = self._proc
        if proc is not None:
            self._end(proc)
        for thread in (self._watcher, self._feeder):
            if thread is not None:
                thread.join(timeout=self.stop_timeout_s + 1.0)
        self._watcher = self._feeder = None
        if proc is not None:
            self._release(proc)  # when the watcher never ran
        self._motors_off()
        with self._proc_lock:
            self._proc = None
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- fault injection ----------------------------------------------------------------

    def kill(self) -> None:
        """SIGKILL the child, as a crash would; the watcher restarts it."""
        proc = self._proc
        if proc is not None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()

    def unplug(self) -> None:
        """Pull the simulated USB cable (see `SimulatedUno.unplug`)."""
        self._request("UNPLUG")

    def replug(self) -> None:
        """Plug it back in: a new pty behind the same `port` and a fresh boot."""
        self._request("REPLUG")

    def reset(self) -> None:
        """Reboot the simulated firmware, the port staying open."""
        self._request("RESET")

    def go_silent(self, silent: bool = True) -> None:
        """Stop answering while keeping the port open; ``go_silent(False)`` comes back."""
        self._request("SILENT" if silent else "ANSWER")

    # -- observations -------------------------------------------------------------------

    def count(self, msg_type: MsgType) -> int:
        """Valid frames of this type the simulated firmware received, over all restarts."""
        with self._received_lock:
            return self._received[msg_type]

    # -- the child ----------------------------------------------------------------------

    def _spawn(self) -> subprocess.Popen[str]:
        """Start a child and wait for its PTY line; raises `SimulatedUnoError`."""
        left, right = self.plant.read_encoders()
        with self._proc_lock:
            if self._closing.is_set() or self._dir is None:
                raise SimulatedUnoError("closing")
            command = [
                sys.executable,
                # Nothing from the environment or the user's site-packages
                # (PYTHONDEVMODE, PYTHONTRACEMALLOC, PYTHONMALLOC, ... would slow it): the
                # project is found from the working directory, and the child needs only
                # the standard library besides.
                "-E",
                "-s",
                "-m",
                "app.sim.uno_process",
                "--link",
                str(self._dir / LINK_NAME),
                "--encoders",
                str(left),
                str(right),
            ]
            # stderr is shared: a crash's traceback lands in the daemon's log. A session
            # of its own puts the child in its own scheduler autogroup (where the kernel
            # has them), so the daemon's busy threads cannot starve it of CPU as one of
            # its own threads would be: a real board does not share the host's CPU at
            # all. It still ends with the host (its stdin closes), and a Ctrl-C in the
            # terminal reaches the host only, which then ends it in order.
            proc = subprocess.Popen(
                command,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                bufsize=1,
                cwd=PROJECT_ROOT,
                start_new_session=True,
            )
            self._proc = proc
        assert proc.stdout is not None
        too_slow = threading.Timer(self.start_timeout_s, proc.kill)
        too_slow.start()
        try:
            # The child publishes its port (the symlink) before it prints PTY, so a host
            # that keeps reopening the port may already talk to it: its RX and MOTOR
            # lines can come first, and count like any others.
            first = proc.stdout.readline()
            while first and not first.startswith("PTY "):
                self._on_line(first)
                first = proc.stdout.readline()
        finally:
            too_slow.cancel()
        if not first.startswith("PTY "):
            self._end(proc)
            self._release(proc)
            raise SimulatedUnoError(
                f"the simulated Uno process did not announce its port within "
                f"{self.start_timeout_s:g} s (exit code {proc.returncode}, first line "
                f"{first!r}; its stderr says why)"
            )
        self.pty_path = first.split(maxsplit=1)[1].strip()
        return proc

    def _end(self, proc: subprocess.Popen[str]) -> None:
        if proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.terminate()
        try:
            proc.wait(timeout=self.stop_timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            proc.wait(timeout=self.stop_timeout_s)

    def _release(self, proc: subprocess.Popen[str]) -> None:
        """Close our ends of a dead child's pipes."""
        with self._stdin_lock:
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    with contextlib.suppress(OSError):
                        pipe.close()

    def _watch(self, proc: subprocess.Popen[str]) -> None:
        """Follow the child until it exits, then restart it (with backoff) until closed."""
        delay_s = self.restart_initial_s
        while True:
            started = time.monotonic()
            self._follow(proc)
            try:
                proc.wait(timeout=self.stop_timeout_s)  # its stdout ended: it is exiting
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            self._release(proc)
            self._child_gone()
            if self._closing.is_set():
                return
            self.restarts += 1
            if time.monotonic() - started >= STABLE_RUN_S:
                delay_s = self.restart_initial_s
            log.warning(
                "the simulated Uno process exited with code %s; restarting it in %.1f s",
                proc.returncode,
                delay_s,
                extra={"event": "sim_uno_exited", "exit_code": proc.returncode},
            )
            while True:
                if self._closing.wait(delay_s):
                    return
                delay_s = min(self.restart_max_s, delay_s * 2)
                try:
                    proc = self._spawn()
                    break
                except SimulatedUnoError as exc:
                    if self._closing.is_set():
                        return
                    log.warning("restarting the simulated Uno process failed: %s", exc)

    def _follow(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        with contextlib.suppress(OSError, ValueError):  # our end closed by close()
            for line in proc.stdout:
                self._on_line(line)

    def _on_line(self, line: str) -> None:
        kind, _, rest = line.strip().partition(" ")
        words = rest.split()
        try:
            if kind == "MOTOR":
                left, right = int(words[0]), int(words[1])
                self.pwm_changed_s = float(words[2])
                self.pwm = (left, right)
                self.plant.apply_pwm(left, right)
            elif kind == "DEADMAN":
                self.deadman_trips_s.append(float(words[0]))
            elif kind == "RX":
                with self._received_lock:
                    self._received[int(words[0])] += 1
            elif kind == "PTY":
                self.pty_path = rest
            elif kind == "OK":
                request = self._requests.get(words[0])
                if request is not None:
                    request.carried_out = True
                    request.done.set()
            else:
                raise ValueError("unknown kind")
        except (IndexError, ValueError):
            log.warning("unexpected line from the simulated Uno process: %r", line)

    def _child_gone(self) -> None:
        """A dead Uno drives no motor, answers no pending request, and has no port: a
        killed child leaves its symlink behind, pointing at a pty number the system may
        soon give to something else."""
        with self._proc_lock:
            if self._dir is not None:
                with contextlib.suppress(FileNotFoundError):
                    (self._dir / LINK_NAME).unlink()
        self._motors_off()
        for request in list(self._requests.values()):
            request.done.set()

    def _motors_off(self) -> None:
        if self.pwm != (0, 0):
            self.pwm_changed_s = time.monotonic()
            self.pwm = (0, 0)
            self.plant.apply_pwm(0, 0)

    def _send(self, line: str) -> bool:
        """Write a line to the current child; False when there is none to write to."""
        with self._stdin_lock:
            proc = self._proc
            if proc is None or proc.stdin is None:
                return False
            try:
                proc.stdin.write(line + "\n")
                proc.stdin.flush()
            except (OSError, ValueError):
                return False  # it died: the watcher restarts it
            return True

    def _request(self, request: str) -> None:
        request_id = str(next(self._request_ids))
        pending = _Request()
        self._requests[request_id] = pending
        try:
            if not self._send(f"{request} {request_id}"):
                raise SimulatedUnoError(f"{request}: the simulated Uno process is not running")
            if not pending.done.wait(REQUEST_TIMEOUT_S) or not pending.carried_out:
                raise SimulatedUnoError(f"{request}: the simulated Uno process did not do it")
        finally:
            del self._requests[request_id]

    def _feed_encoders(self) -> None:
        while not self._closing.wait(self.encoder_period_s):
            left, right = self.plant.read_encoders()
            self._send(f"ENC {left} {right}")


if __name__ == "__main__":
    raise SystemExit(main())
