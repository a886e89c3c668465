"""A simulated Arduino Uno that speaks the floornav serial protocol (``docs/protocol.md``)
over a pseudo-terminal, so the host driver (``app.hardware.serial_link``) can be run and
tested without hardware.

The simulated firmware answers ``HELLO`` with ``BANNER`` (and sends one at boot), acks
``DRIVE``/``STOP``/``PING``/``SET_TELEMETRY``/``RESET_COUNTERS``, stops the motors when no
``DRIVE`` arrived for 250 ms, counts CRC errors, garbage bytes and receive-buffer overruns,
and streams ``TELEMETRY``. It drives a `MotorPlant` when given one, else an internal
plant whose encoders integrate the PWM over time.

It runs in its own thread, waiting with ``select()`` on the pty master, so it keeps its
timing while the host's event loop is busy or frozen (but not while the host's whole
interpreter stalls: the daemon therefore runs it in a process of its own,
`app.sim.uno_process`). Fault injection for tests:
`SimulatedUno.unplug`, `~SimulatedUno.replug`, `~SimulatedUno.go_silent`,
`~SimulatedUno.send_garbage`, `~SimulatedUno.reset`, and ``banner_protocol_version=``
for a wrong firmware.

Run ``python -m app.sim.sim_uno`` to get a port a person can point the daemon at.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import queue
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Self

from app.hardware.protocol import (
    DEADMAN_MS,
    FRAME_OVERHEAD,
    PROTOCOL_VERSION,
    Ack,
    AckStatus,
    Banner,
    DecoderStats,
    Frame,
    FrameDecoder,
    MsgType,
    ProtocolError,
    Telemetry,
    encode_frame,
    parse_drive,
    parse_telemetry_period,
)

if TYPE_CHECKING:
    # Only for annotations: the interfaces module pulls in numpy, which the Uno's own
    # process (`app.sim.uno_process`) has no use for.
    from app.hardware.interfaces import MotorPlant

UNO_RX_BUFFER_BYTES = 64
"""The ATmega328P core's serial receive buffer: bytes beyond it are lost (an overrun)."""

_HOST_COMMANDS = frozenset(
    {
        MsgType.HELLO,
        MsgType.DRIVE,
        MsgType.STOP,
        MsgType.PING,
        MsgType.SET_TELEMETRY,
        MsgType.RESET_COUNTERS,
    }
)


class IntegratingPlant:
    """A trivial `MotorPlant`: each encoder counts ``counts_per_pwm_s`` per PWM unit per
    second, so ``pwm=100`` for 1 s gives 200 counts with the default. Thread-safe."""

    def __init__(self, *, counts_per_pwm_s: float = 2.0) -> None:
        self._counts_per_pwm_s = counts_per_pwm_s
        self._lock = threading.Lock()
        self._pwm = (0, 0)
        self._counts = [0.0, 0.0]
        self._since_s = time.monotonic()

    def _advance(self) -> None:
        now = time.monotonic()
        dt = now - self._since_s
        self._since_s = now
        for i in range(2):
            self._counts[i] += self._pwm[i] * self._counts_per_pwm_s * dt

    def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
        with self._lock:
            self._advance()
            self._pwm = (left_pwm, right_pwm)

    def read_encoders(self) -> tuple[int, int]:
        with self._lock:
            self._advance()
            return int(self._counts[0]), int(self._counts[1])


@dataclass(frozen=True)
class ReceivedCommand:
    """A valid frame the simulated firmware received, with ``time.monotonic()``."""

    time_s: float
    frame: Frame


class SimulatedUno:
    """A pure-Python Uno behind a pseudo-terminal.

    Parameters
    ----------
    plant : MotorPlant, optional
        What the motors drive. ``apply_pwm`` is called (from the simulator's thread) on
        every PWM change, ``read_encoders`` for every telemetry frame. Default: an
        `IntegratingPlant`.
    link_path : path, optional
        Also publish the port as a symlink at this path, re-pointed on `replug` and
        removed on `unplug` (like ``/dev/serial/by-id/...``). `port` is then this path.
    banner_protocol_version, motor_count, firmware : what ``BANNER`` announces;
        change ``banner_protocol_version`` to play a wrong firmware.
    deadman_ms : motors to zero when no ``DRIVE`` arrived for this long.
    ack_delay_s : how long the firmware takes to handle a command before its reply goes
        out; it reads no further command meanwhile (bytes wait in the 64-byte buffer).
        A little delay makes a host that does not wait for ACKs visible in
        `max_outstanding_commands` / `rx_overruns`.
    telemetry_period_ms : telemetry period at boot (the real firmware boots with 0).
    on_command : optional, called (in the simulator's thread) with each valid frame
        received, before its reply goes out.
    on_deadman : optional, called (in the simulator's thread, after the motors went to
        zero) with the ``time.monotonic()`` of each deadman trip.
    keep_received : keep every valid frame received in `received` (for tests); a
        long-running Uno turns it off, as the list grows with every command.
    """

    def __init__(
        self,
        plant: MotorPlant | None = None,
        *,
        link_path: str | os.PathLike[str] | None = None,
        banner_protocol_version: int = PROTOCOL_VERSION,
        motor_count: int = 2,
        firmware: str = "floornav-sim 1.0.0",
        deadman_ms: int = DEADMAN_MS,
        ack_delay_s: float = 0.0,
        telemetry_period_ms: int = 0,
        on_command: Callable[[ReceivedCommand], None] | None = None,
        on_deadman: Callable[[float], None] | None = None,
        keep_received: bool = True,
    ) -> None:
        if not 0 <= banner_protocol_version <= 255:
            raise ValueError(
                f"banner_protocol_version must be 0..255, got {banner_protocol_version}"
            )
        if deadman_ms <= 0:
            raise ValueError(f"deadman_ms must be positive, got {deadman_ms}")
        if ack_delay_s < 0:
            raise ValueError(f"ack_delay_s must be >= 0, got {ack_delay_s}")
        parse_telemetry_period(telemetry_period_ms.to_bytes(2, "little"))  # range check
        self.plant: MotorPlant = plant if plant is not None else IntegratingPlant()
        self.link_path = Path(link_path) if link_path is not None else None
        self.banner = Banner(banner_protocol_version, motor_count, firmware)
        self.deadman_s = deadman_ms / 1000.0
        self.ack_delay_s = ack_delay_s
        self._boot_telemetry_period_ms = telemetry_period_ms
        self._on_command = on_command
        self._on_deadman = on_deadman
        self._keep_received = keep_received

        self._lock = threading.RLock()  # guards what other threads read; plants may call back
        self._calls: queue.SimpleQueue[tuple[Callable[[], None], threading.Event]] = (
            queue.SimpleQueue()
        )
        self._thread: threading.Thread | None = None
        self._running = False
        self._wake_r = -1
        self._wake_w = -1
        self._master = -1
        self._slave = -1
        self._slave_path = ""
        self._silent = False
        self._thread_error: BaseException | None = None

        # Observations for tests (cumulative over reboots unless said otherwise).
        self.received: list[ReceivedCommand] = []
        self.deadman_trips: list[float] = []  # time.monotonic() of each trip
        self.max_outstanding_commands = 0
        self.max_rx_backlog_bytes = 0
        self.boots = 0
        self.unknown_frames = 0

        # Firmware state, (re)set by _boot_state().
        self._boot_s = 0.0
        self._decoder = FrameDecoder()
        self._rx_overruns = 0
        self._flags = 0
        self._telemetry_period_ms = 0
        self._encoder_offset = (0, 0)
        self._pwm = (0, 0)
        self._next_telemetry_s = 0.0
        self._last_drive_s = 0.0
        self._ever_driven = False
        self._tx_seq = 0
        self._deadman_armed = False
        self._queue: deque[Frame] = deque()  # decoded, not yet handled (in the RX buffer)
        self._reply: tuple[float, bytes] | None = None  # (due time, bytes) being handled
        self._boot_state()

    # -- lifecycle ----------------------------------------------------------------------

    @property
    def port(self) -> str:
        """The path a host opens: `link_path` if given, else the current pty slave."""
        if self.link_path is not None:
            return str(self.link_path)
        if not self._slave_path:
            raise RuntimeError("the simulated Uno is not started (call start())")
        return self._slave_path

    @property
    def pty_path(self) -> str:
        """The current pty slave path ("" while unplugged)."""
        return self._slave_path

    def start(self) -> Self:
        if self._thread is not None:
            raise RuntimeError("the simulated Uno is already started")
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._plug_in()
        self._running = True
        self._thread = threading.Thread(target=self._run, name="simulated-uno", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the simulator thread and remove the pty (and the symlink)."""
        if self._thread is None:
            return
        self._call(self._stop_running)
        self._thread.join(timeout=2.0)
        self._thread = None
        self._unplug_now()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

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

    def unplug(self) -> None:
        """Pull the USB cable: close the pty (the host's reads fail), remove the symlink,
        the firmware loses power."""
        self._call(self._unplug_now)

    def replug(self) -> None:
        """Plug the cable back in: a new pty (a new path; the symlink follows) and a
        freshly booted firmware that sends its boot banner."""

        def plug() -> None:
            self._unplug_now()
            self._boot_state()
            self._plug_in()

        self._call(plug)

    def reset(self) -> None:
        """Reboot the firmware (like a reset button) keeping the port open."""
        self._call(self._reboot_in_place)

    def go_silent(self, silent: bool = True) -> None:
        """Stop answering and sending anything while keeping the port open (bytes from
        the host are drained and lost); ``go_silent(False)`` comes back."""

        def set_silent() -> None:
            self._silent = silent

        self._call(set_silent)

    def send_garbage(self, data: bytes) -> None:
        """Write raw bytes to the host, e.g. noise or a frame with a broken CRC."""
        self._call(lambda: self._write(bytes(data)))

    # -- observations -------------------------------------------------------------------

    @property
    def pwm(self) -> tuple[int, int]:
        with self._lock:
            return self._pwm

    @property
    def telemetry_period_ms(self) -> int:
        with self._lock:
            return self._telemetry_period_ms

    @property
    def rx_overruns(self) -> int:
        """Bytes lost because the 64-byte receive buffer was full (the firmware counts
        the times it found the buffer full; both are zero for a well-behaved host)."""
        with self._lock:
            return self._rx_overruns

    @property
    def decoder_stats(self) -> DecoderStats:
        """The simulated firmware's receive counters since boot or RESET_COUNTERS."""
        with self._lock:
            stats = self._decoder.stats
            return DecoderStats(stats.frames, stats.crc_errors, stats.garbage_bytes, stats.oversize)

    def commands(self, *types: MsgType) -> list[ReceivedCommand]:
        """Received valid frames, optionally only of the given types."""
        with self._lock:
            return [c for c in self.received if not types or c.frame.type in types]

    def count(self, msg_type: MsgType) -> int:
        return len(self.commands(msg_type))

    # -- the thread ---------------------------------------------------------------------

    def _call(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` in the simulator thread (or here when it is not running)."""
        if self._thread is None or not self._thread.is_alive():
            fn()
            return
        if threading.current_thread() is self._thread:
            fn()
            return
        done = threading.Event()
        self._calls.put((fn, done))
        os.write(self._wake_w, b"x")
        if not done.wait(timeout=2.0):
            raise RuntimeError("the simulated Uno thread did not answer within 2 s")
        if self._thread_error is not None:
            raise RuntimeError("the simulated Uno thread failed") from self._thread_error

    def _stop_running(self) -> None:
        self._running = False

    def _run(self) -> None:
        try:
            while self._running:
                now = time.monotonic()
                self._service(now)
                timeout = max(0.0, self._next_deadline_s(now) - time.monotonic())
                fds = [self._wake_r] + ([self._master] if self._master >= 0 else [])
                readable, _, _ = select.select(fds, [], [], timeout)
                if self._wake_r in readable:
                    self._run_calls()
                if self._master >= 0 and self._master in readable:
                    self._receive()
        except BaseException as exc:  # keep the reason for _call(); tests see it
            self._thread_error = exc
            raise
        finally:
            self._run_calls()

    def _run_calls(self) -> None:
        with contextlib.suppress(BlockingIOError):
            os.read(self._wake_r, 4096)
        while True:
            try:
                fn, done = self._calls.get_nowait()
            except queue.Empty:
                return
            try:
                fn()
            finally:
                done.set()

    def _next_deadline_s(self, now: float) -> float:
        deadlines = [now + 0.5]
        if self._reply is not None:
            deadlines.append(self._reply[0])
        if self._deadman_armed:
            deadlines.append(self._last_drive_s + self.deadman_s)
        if self._telemetry_period_ms and self._master >= 0:
            deadlines.append(self._next_telemetry_s)
        return min(deadlines)

    # -- pty handling -------------------------------------------------------------------

    def _plug_in(self) -> None:
        master, slave = os.openpty()
        # Raw, so nothing is echoed or translated before the host opens (and sets) it.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_path = os.ttyname(slave)
        if self.link_path is not None:
            tmp = self.link_path.with_name(self.link_path.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(self._slave_path)
            tmp.replace(self.link_path)  # atomic re-point
        self._send_frame(MsgType.BANNER, self.banner.payload())  # boot banner

    def _unplug_now(self) -> None:
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1
        self._slave_path = ""
        with self._lock:
            self._pwm_set(0, 0)
        self._deadman_armed = False
        self._reply = None

    def _write(self, data: bytes) -> None:
        if self._master < 0 or self._silent:
            return
        # Nobody reading / port gone: lost, like a UART with nobody listening.
        with contextlib.suppress(OSError):
            os.write(self._master, data)

    def _send_frame(self, msg_type: MsgType, payload: bytes = b"", seq: int = 0) -> None:
        self._write(encode_frame(Frame(seq=seq, type=msg_type, payload=payload)))

    # -- the simulated firmware ---------------------------------------------------------

    def _boot_state(self) -> None:
        with self._lock:
            self._boot_s = time.monotonic()
            self._decoder = FrameDecoder()
            self._rx_overruns = 0
            self._flags = 0
            self._telemetry_period_ms = self._boot_telemetry_period_ms
            self._encoder_offset = self.plant.read_encoders()
            self._pwm = (0, 0)
            self.boots += 1
        self.plant.apply_pwm(0, 0)
        self._next_telemetry_s = self._boot_s + self._telemetry_period_ms / 1000.0
        self._last_drive_s = self._boot_s
        self._ever_driven = False
        self._tx_seq = 0
        self._deadman_armed = False
        self._queue.clear()
        self._reply = None
        self._silent = False

    def _reboot_in_place(self) -> None:
        self._boot_state()
        self._send_frame(MsgType.BANNER, self.banner.payload())

    def _pwm_set(self, left: int, right: int) -> None:
        """Caller holds the lock."""
        if (left, right) != self._pwm:
            self._pwm = (left, right)
            self.plant.apply_pwm(left, right)

    def _receive(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""  # EIO: no slave open; cannot happen while we hold the slave fd
        if not data or self._silent:
            return
        with self._lock:
            backlog = sum(FRAME_OVERHEAD + len(f.payload) for f in self._queue)
            space = max(0, UNO_RX_BUFFER_BYTES - backlog)
            accepted = data[:space]
            self._rx_overruns += len(data) - len(accepted)
            frames = self._decoder.feed(accepted)
            self._queue.extend(frames)
            backlog += sum(FRAME_OVERHEAD + len(f.payload) for f in frames)
            self.max_rx_backlog_bytes = max(self.max_rx_backlog_bytes, backlog)
            outstanding = len(self._queue) + (1 if self._reply is not None else 0)
            self.max_outstanding_commands = max(self.max_outstanding_commands, outstanding)
        self._service(time.monotonic())

    def _service(self, now: float) -> None:
        if self._master < 0:
            return
        if self._reply is not None and now >= self._reply[0]:
            self._write(self._reply[1])
            self._reply = None
        while self._reply is None and self._queue:
            frame = self._queue.popleft()
            reply = self._handle(frame, now)
            if reply is None:
                continue
            if self.ack_delay_s > 0:
                self._reply = (now + self.ack_delay_s, reply)
            else:
                self._write(reply)
        if self._deadman_armed and now - self._last_drive_s >= self.deadman_s:
            self._deadman_armed = False
            with self._lock:
                self._pwm_set(0, 0)
                self._flags |= Telemetry.DEADMAN_TRIPPED
                self.deadman_trips.append(now)
            if self._on_deadman is not None:
                self._on_deadman(now)
        if self._telemetry_period_ms and now >= self._next_telemetry_s:
            self._write(self._telemetry_frame(now))
            period_s = self._telemetry_period_ms / 1000.0
            self._next_telemetry_s = max(self._next_telemetry_s + period_s, now)

    def _ack(self, seq: int, status: AckStatus = AckStatus.OK) -> bytes:
        return encode_frame(Frame(seq=seq, type=MsgType.ACK, payload=Ack(seq, status).payload()))

    def _handle(self, frame: Frame, now: float) -> bytes | None:
        """Act on one valid frame; return the reply bytes."""
        command = ReceivedCommand(now, frame)
        if self._keep_received:
            with self._lock:
                self.received.append(command)
        if self._on_command is not None:
            self._on_command(command)
        if frame.type not in _HOST_COMMANDS:
            # Like the firmware: counted with the garbage, since nothing acted on them.
            self.unknown_frames += 1
            with self._lock:
                self._decoder.stats.garbage_bytes += FRAME_OVERHEAD + len(frame.payload)
            return self._ack(frame.seq, AckStatus.UNKNOWN_TYPE)
        msg = MsgType(frame.type)
        try:
            if msg is MsgType.HELLO:
                payload = self.banner.payload()
                return encode_frame(Frame(seq=frame.seq, type=MsgType.BANNER, payload=payload))
            if msg is MsgType.DRIVE:
                left, right = parse_drive(frame.payload)
                with self._lock:
                    self._pwm_set(left, right)
                    self._flags &= ~(Telemetry.DEADMAN_TRIPPED | Telemetry.STOPPED)
                self._last_drive_s = now
                self._ever_driven = True
                self._deadman_armed = True
            elif msg is MsgType.STOP:
                if frame.payload:
                    raise ProtocolError("STOP takes no payload")
                with self._lock:
                    self._pwm_set(0, 0)
                    self._flags |= Telemetry.STOPPED
                self._deadman_armed = False
            elif msg is MsgType.PING:
                if frame.payload:
                    raise ProtocolError("PING takes no payload")
            elif msg is MsgType.SET_TELEMETRY:
                period = parse_telemetry_period(frame.payload)
                with self._lock:
                    self._telemetry_period_ms = period
                self._next_telemetry_s = now + period / 1000.0
            elif msg is MsgType.RESET_COUNTERS:
                if frame.payload:
                    raise ProtocolError("RESET_COUNTERS takes no payload")
                with self._lock:
                    self._encoder_offset = self.plant.read_encoders()
                    self._decoder.stats = DecoderStats()
                    self._rx_overruns = 0
        except ProtocolError:
            return self._ack(frame.seq, AckStatus.BAD_ARGUMENT)
        return self._ack(frame.seq)

    def _telemetry_frame(self, now: float) -> bytes:
        left, right = self.plant.read_encoders()
        with self._lock:
            # Like the firmware: 0xFFFF until the first DRIVE since boot.
            since_drive_ms = int((now - self._last_drive_s) * 1000) if self._ever_driven else 0xFFFF
            stats = self._decoder.stats
            telemetry = Telemetry(
                uptime_ms=int((now - self._boot_s) * 1000),
                encoder_left=left - self._encoder_offset[0],
                encoder_right=right - self._encoder_offset[1],
                pwm_left=self._pwm[0],
                pwm_right=self._pwm[1],
                ms_since_command=since_drive_ms,
                crc_errors=stats.crc_errors,
                garbage_bytes=stats.garbage_bytes,
                rx_overruns=self._rx_overruns,
                flags=self._flags,
            )
        self._tx_seq = (self._tx_seq + 1) & 0xFF
        payload = telemetry.payload()
        return encode_frame(Frame(seq=self._tx_seq, type=MsgType.TELEMETRY, payload=payload))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m app.sim.sim_uno",
        description="Run a simulated Uno on a pseudo-terminal until Ctrl-C.",
    )
    parser.add_argument("--link", help="also publish the port as a symlink at this path")
    parser.add_argument(
        "--protocol-version", type=int, default=PROTOCOL_VERSION, help="version in BANNER"
    )
    args = parser.parse_args(argv)
    uno = SimulatedUno(link_path=args.link, banner_protocol_version=args.protocol_version)
    with uno:
        try:
            print(f"simulated Uno on {uno.port}", flush=True)
            if uno.link_path is not None:
                print(f"  (symlink to {uno.pty_path})", flush=True)
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        print(f"received {len(uno.received)} commands; bye", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
