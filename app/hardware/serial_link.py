"""The host side of the Uno serial link (``docs/protocol.md``): an asyncio driver that
keeps a differential-drive Arduino Uno connected, handshaken, fed and safe.

Layers, bottom up:

- `PySerialTransport`: our thin wrapper around pyserial-asyncio. Opens a port, hands
  out the bytes that arrived, writes bytes, closes. Library errors become our own
  `LinkError` subclasses. Anything with the same four methods (`ByteTransport`) can
  replace it, e.g. a fake in tests.
- `UnoLink`: the driver. A supervisor task opens the port, handshakes (``HELLO`` →
  ``BANNER``, protocol version check), sends ``STOP`` and ``SET_TELEMETRY``, then runs a
  reader and a heartbeat until the link breaks (read error, or silence), and reconnects
  with exponential backoff. At most one command is in flight (the Uno has a 64-byte
  receive buffer), except ``STOP``: `UnoLink.stop_motors` sends it at once, beside a
  command still waiting for its ACK, and drops any ``DRIVE`` that was queued before it.
  After any failure the commanded PWM is zero and stays zero until the
  caller sends a new `UnoLink.drive` *after* the reconnect (a generation counter ties
  every command to the connection it was made on).

Safety numbers live in `UnoLinkConfig`, each with the reason for its default.

Example::

    async with UnoLink("/dev/serial/by-id/usb-Arduino_Uno_1234-if00") as link:
        await link.wait_connected(timeout_s=5.0)
        await link.drive(120, 120)
        ...
        await link.stop_motors()
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import statistics
import time
from collections import deque
from collections.abc import AsyncGenerator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

import serial
import serial_asyncio

from app.hardware.interfaces import DeviceState, DeviceStatus
from app.hardware.protocol import (
    DEADMAN_MS,
    PROTOCOL_VERSION,
    Ack,
    AckStatus,
    Banner,
    Frame,
    FrameDecoder,
    MsgType,
    ProtocolError,
    Telemetry,
    drive_payload,
    encode_frame,
    telemetry_period_payload,
)
from app.hardware.stall_clock import StallClock, TtyDeliveryProbe

log = logging.getLogger(__name__)

MOTOR_COUNT = 2
SILENCE_SLICE_FRACTION = 0.25
"""The reader listens for silence in slices of this fraction of the timeout, so that a
stall of the host (which a device on the same machine shares) is seen and not counted."""
STALL_TOLERANCE_S = 0.02
"""A read returning this much later than scheduled is still ordinary scheduling delay;
beyond it, the excess was a stall of this process."""

# -- errors -----------------------------------------------------------------------------


class LinkError(Exception):
    """Base of every error of the Uno link (library errors are turned into these)."""


class PortNotFoundError(LinkError):
    """The configured serial port does not exist (unplugged, wrong path)."""


class PortOpenError(LinkError):
    """The port exists but cannot be opened (permissions, busy, not a serial device)."""


class LinkLostError(LinkError):
    """The open port failed: a read or write error, or it was closed."""


class LinkSilentError(LinkLostError):
    """No bytes from the device for longer than the silence timeout."""


class DeviceResetError(LinkLostError):
    """The device rebooted while connected (its uptime went backwards)."""


class HandshakeError(LinkError):
    """The device did not answer ``HELLO`` with a usable ``BANNER``."""


class FirmwareMismatchError(HandshakeError):
    """The device runs firmware that speaks another protocol version: never drive it."""


class NotConnectedError(LinkError):
    """A command was given while the link is not connected (or it broke meanwhile)."""


class CommandTimeoutError(LinkError):
    """No ``ACK`` arrived for a command within the ACK timeout."""


class CommandRejectedError(LinkError):
    """The device answered a command with a non-OK ``ACK`` status."""


class LinkUnavailableError(LinkError):
    """`UnoLink.wait_connected` gave up."""


# -- configuration ----------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class UnoLinkConfig:
    """Timing and safety numbers of the link, with the reason for each default."""

    baudrate: int = 115200
    """Fixed by the protocol (``docs/protocol.md``)."""
    handshake_timeout_s: float = 3.0
    """Opening a real Uno's port resets it (DTR); its bootloader runs about 1.6 s before
    the sketch can answer ``HELLO``."""
    hello_retry_s: float = 0.25
    """``HELLO`` is re-sent this often during the handshake (one sent into the
    bootloader is lost)."""
    ack_timeout_s: float = 0.05
    """A command round trip is about 3 ms on an Uno (0.2 ms over a pty); 50 ms leaves
    room for a busy host while keeping heartbeat + ACK well inside the 250 ms deadman."""
    max_consecutive_timeouts: int = 3
    """This many ACK timeouts in a row count as a broken link."""
    heartbeat_period_s: float = 0.1
    """While moving, ``DRIVE`` is re-sent this often (only ``DRIVE`` refreshes the
    firmware's 250 ms deadman): one lost heartbeat does not stop the robot, two do."""
    telemetry_period_ms: int = 50
    """Asked for with ``SET_TELEMETRY`` after the handshake; also what makes silence
    detectable quickly."""
    silence_timeout_s: float = 0.2
    """No byte at all for this long = cable pulled or firmware hung (four telemetry
    periods, two heartbeats)."""
    max_excused_stall_s: float = 2.0
    """A stall of the kernel's tty layer still going on excuses the device's silence for
    at most this long: a kernel that has stopped delivering bytes must not keep a silent
    link looking alive (stalls of the host process itself are measured once they end,
    and excused whole)."""
    backoff_initial_s: float = 0.1
    """First wait before reopening a failed port; doubles on every failed attempt."""
    backoff_max_s: float = 2.0
    """Longest wait between attempts (opening a real Uno resets it: not too often)."""
    port_poll_s: float = 0.02
    """While the port does not exist, look for it this often and reopen as soon as it
    appears (a stat() only, cheap), instead of sleeping out the backoff."""
    close_timeout_s: float = 0.5
    """How long closing may wait for buffered bytes (the final ``STOP``) to go out."""

    def __post_init__(self) -> None:
        positive = (
            "handshake_timeout_s",
            "hello_retry_s",
            "ack_timeout_s",
            "heartbeat_period_s",
            "silence_timeout_s",
            "backoff_initial_s",
            "backoff_max_s",
            "port_poll_s",
            "close_timeout_s",
            "max_excused_stall_s",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be positive, got {self.baudrate}")
        if self.max_consecutive_timeouts < 1:
            raise ValueError(
                f"max_consecutive_timeouts must be >= 1, got {self.max_consecutive_timeouts}"
            )
        telemetry_period_payload(self.telemetry_period_ms)  # 0 or 20..1000 ms
        if self.heartbeat_period_s + self.ack_timeout_s >= DEADMAN_MS / 1000:
            raise ValueError(
                "heartbeat_period_s + ack_timeout_s must stay below the firmware deadman "
                f"({DEADMAN_MS} ms), else the motors stop between heartbeats; got "
                f"{self.heartbeat_period_s} + {self.ack_timeout_s} s"
            )
        if self.silence_timeout_s <= self.heartbeat_period_s:
            raise ValueError(
                "silence_timeout_s must exceed heartbeat_period_s (the heartbeat's ACK is "
                f"the slowest traffic there is); got {self.silence_timeout_s} <= "
                f"{self.heartbeat_period_s}"
            )
        if self.backoff_max_s < self.backoff_initial_s:
            raise ValueError("backoff_max_s must be >= backoff_initial_s")


# -- the transport ----------------------------------------------------------------------


def resolve_port(port: str | os.PathLike[str]) -> str:
    """The device a port path stands for, following symlinks such as
    ``/dev/serial/by-id/usb-Arduino...`` (re-resolved on every open: after a replug the
    link may point to another ``ttyACM``). pyserial URLs (``socket://...``) pass through.

    Raises
    ------
    PortNotFoundError : the path (or the target of the symlink) does not exist.
    PortOpenError : the path exists but is not a character device.
    """
    text = os.fspath(port)
    if "://" in text:
        return text
    path = Path(text)
    if not path.exists():
        if path.is_symlink():
            raise PortNotFoundError(
                f"serial port {text} is a symlink to {os.readlink(path)}, which does not "
                "exist: is the Uno unplugged?"
            )
        by_id = Path("/dev/serial/by-id")
        present = sorted(p.name for p in by_id.iterdir()) if by_id.is_dir() else []
        hint = (
            f"ports in {by_id}: {', '.join(present[:5])}"
            if present
            else "no port in /dev/serial/by-id"
        )
        raise PortNotFoundError(
            f"serial port {text} does not exist: is the Uno plugged in? ({hint})"
        )
    real = path.resolve()
    if not real.is_char_device():
        raise PortOpenError(f"{text} ({real}) is not a serial device")
    return str(real)


class ByteTransport(Protocol):
    """What `UnoLink` needs from a serial port. One instance per open."""

    async def open(self, port: str, *, baudrate: int) -> None:
        """Open ``port``. Raises `PortNotFoundError` or `PortOpenError`."""
        ...

    async def read(self, timeout_s: float | None) -> bytes:
        """All bytes received since the last call, waiting up to ``timeout_s`` for at
        least one; ``b""`` on timeout. Raises `LinkLostError` once the port failed (bytes
        that arrived before the failure are returned first)."""
        ...

    def write(self, data: bytes) -> None:
        """Queue ``data`` for sending. Raises `LinkLostError` if the port failed."""
        ...

    async def close(self) -> None:
        """Send what is queued (waiting a bounded time), then close. Idempotent."""
        ...


class _Receiver(asyncio.Protocol):
    def __init__(self, owner: PySerialTransport) -> None:
        self._owner = owner

    def data_received(self, data: bytes) -> None:
        self._owner._on_data(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._owner._on_lost(exc)


class PySerialTransport:
    """`ByteTransport` over pyserial-asyncio. pyserial errors become `LinkError`s."""

    def __init__(self, *, close_timeout_s: float = 0.5) -> None:
        self._close_timeout_s = close_timeout_s
        self._port = ""
        self._transport: asyncio.Transport | None = None
        self._buffer = bytearray()
        self._data_ready = asyncio.Event()
        self._closed = asyncio.Event()
        self._lost_reason: str | None = None
        self._lost_cause: BaseException | None = None

    async def open(self, port: str, *, baudrate: int) -> None:
        if self._transport is not None:
            raise RuntimeError("transport already open")
        self._port = port
        device = resolve_port(port)
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await serial_asyncio.create_serial_connection(
                loop, lambda: _Receiver(self), device, baudrate=baudrate
            )
        except serial.SerialException as exc:
            raise _open_error(port, device, exc) from exc
        except (OSError, ValueError) as exc:
            raise PortOpenError(f"cannot open serial port {port}: {exc}") from exc
        self._transport = transport

    async def read(self, timeout_s: float | None) -> bytes:
        if not self._buffer and self._lost_reason is None:
            self._data_ready.clear()
            try:
                async with asyncio.timeout(timeout_s):
                    await self._data_ready.wait()
            except TimeoutError:
                pass  # bytes may still have arrived in this same loop iteration
        if self._buffer:
            data = bytes(self._buffer)
            self._buffer.clear()
            return data
        if self._lost_reason is not None:
            raise self._lost_error()
        return b""

    def write(self, data: bytes) -> None:
        if self._lost_reason is not None:
            raise self._lost_error()
        if self._transport is None or self._transport.is_closing():
            raise LinkLostError(f"serial port {self._port} is closed")
        self._transport.write(data)

    async def close(self) -> None:
        transport = self._transport
        if transport is None:
            return
        self._transport = None
        if self._lost_reason is None:
            transport.close()  # flushes what is queued, then connection_lost()
            try:
                async with asyncio.timeout(self._close_timeout_s):
                    await self._closed.wait()
            except TimeoutError:
                transport.abort()
                await asyncio.sleep(0)  # let connection_lost() close the device

    # -- callbacks from pyserial-asyncio --

    def _on_data(self, data: bytes) -> None:
        self._buffer.extend(data)
        self._data_ready.set()

    def _on_lost(self, exc: BaseException | None) -> None:
        if exc is None:
            self._lost_reason = f"serial port {self._port} was closed"
        else:
            self._lost_reason = f"serial port {self._port} failed (cable pulled?): {exc}"
            self._lost_cause = exc
        self._data_ready.set()
        self._closed.set()

    def _lost_error(self) -> LinkLostError:
        error = LinkLostError(self._lost_reason or "serial port lost")
        error.__cause__ = self._lost_cause
        return error


def _open_error(port: str, device: str, exc: serial.SerialException) -> LinkError:
    code = getattr(exc, "errno", None)
    where = port if port == device else f"{port} ({device})"
    if code == errno.ENOENT:
        return PortNotFoundError(f"serial port {where} does not exist: is the Uno plugged in?")
    if code in (errno.EACCES, errno.EPERM):
        return PortOpenError(f"no permission to open {where}: add the user to the 'dialout' group")
    if code == errno.EBUSY:
        return PortOpenError(f"serial port {where} is busy: is another program using it?")
    return PortOpenError(f"cannot open serial port {where}: {exc}")


# -- the link ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ReceivedTelemetry:
    """A telemetry frame and when it arrived (``time.monotonic()``)."""

    data: Telemetry
    received_s: float

    def age_s(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.received_s


@dataclass
class LinkStats:
    """Counters of the link since it was created (over all reconnections)."""

    commands_sent: int = 0
    acks: int = 0
    rejected: int = 0  # ACKs with a non-OK status
    timeouts: int = 0  # commands without an ACK in time
    stale_acks: int = 0  # ACKs for no command in flight (late, after a timeout)
    stops_ahead: int = 0  # STOPs sent beside a command still waiting for its ACK
    drives_dropped: int = 0  # DRIVEs queued before a STOP, so never sent
    heartbeats: int = 0  # DRIVE re-sent or PING sent by the heartbeat
    crc_errors: int = 0  # frames from the device with a bad CRC
    garbage_bytes: int = 0  # bytes from the device outside any frame
    oversize_frames: int = 0
    malformed_frames: int = 0  # valid CRC, but a bad payload or a type we do not expect
    telemetry_frames: int = 0
    deadman_trips_seen: int = 0  # telemetry reported a deadman trip while we drove
    connect_attempts: int = 0
    connects: int = 0
    reconnects: int = 0  # connects after the first
    failures: int = 0
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=2000), repr=False)
    """Command → ACK round trips (write queued → ACK decoded), newest last."""

    def rtt_median_ms(self) -> float | None:
        return statistics.median(self.rtt_s) * 1000 if self.rtt_s else None

    def rtt_percentile_ms(self, percent: int) -> float | None:
        if len(self.rtt_s) < 2:
            return self.rtt_median_ms()
        return statistics.quantiles(self.rtt_s, n=100, method="inclusive")[percent - 1] * 1000


@dataclass(frozen=True)
class _Command:
    epoch: int
    left_pwm: int
    right_pwm: int

    @property
    def moving(self) -> bool:
        return bool(self.left_pwm or self.right_pwm)


@dataclass
class _Pending:
    seq: int
    sent_s: float
    future: asyncio.Future[tuple[Ack, float]]


def _retrieve_exception(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()


class _Connection:
    """One open of the port, from open to close."""

    def __init__(self, transport: ByteTransport, epoch: int, clock: StallClock) -> None:
        loop = asyncio.get_running_loop()
        self.transport = transport
        self.epoch = epoch
        self.clock = clock
        self.decoder = FrameDecoder()
        self.banner: asyncio.Future[Banner] = loop.create_future()
        self.banner.add_done_callback(_retrieve_exception)
        self.failed: asyncio.Future[LinkError] = loop.create_future()
        self.ready = False
        self.consecutive_timeouts = 0
        self.last_uptime_ms: int | None = None
        self.last_telemetry_s = 0.0  # on the awake clock (`awake_s`)
        self.last_flags = 0
        self.tasks: list[asyncio.Task[None]] = []
        self.closed = False

    def awake_s(self) -> float:
        """``time.monotonic()`` less the time the host could not hear the device (the
        link's `StallClock`: its own stalls, seen by the reader, and the kernel's tty
        layer's, seen by the `TtyDeliveryProbe`).

        Silence and ACK timeouts are judged on this clock. While the host does not run
        (a VM paused, the CPU starved, a long GC), a device on the same machine (the
        simulated Uno's process, simavr) does not run either, and when both resume the
        host's timers fire before the device has had a chance to speak: that is not a
        pulled cable. A real Uno keeps talking through a host stall, but its bytes wait
        in the kernel until the host reads them, so for real hardware this clock only
        waits for bytes that are already there."""
        return self.clock.awake_s()

    def note_wait(self, started_s: float, scheduled_s: float, returned_s: float) -> None:
        """A read started at ``started_s`` for at most ``scheduled_s`` returned at
        ``returned_s``: what exceeds the schedule by more than `STALL_TOLERANCE_S` was a
        stall, not time spent listening."""
        late_from_s = started_s + scheduled_s + STALL_TOLERANCE_S
        self.clock.add(late_from_s, returned_s)

    def note_gap(self, returned_s: float, next_started_s: float) -> None:
        """The reader's last read returned at ``returned_s`` and the next began at
        ``next_started_s``: a gap longer than `STALL_TOLERANCE_S` (the process
        descheduled between the two, or frames that took that long to handle) was time
        nobody listened."""
        self.clock.add(returned_s + STALL_TOLERANCE_S, next_started_s)


class UnoLink:
    """The Uno over a serial port, kept connected and safe. See the module docstring.

    Parameters
    ----------
    port : a device path (``/dev/ttyACM0``, ``/dev/serial/by-id/...``, a pty) or a
        pyserial URL. Symlinks are resolved on every (re)open.
    config : timing and safety numbers.
    transport_factory : makes one `ByteTransport` per open (default `PySerialTransport`).
    on_telemetry : called (in the event loop) for every telemetry frame; keep it short.
    """

    def __init__(
        self,
        port: str | os.PathLike[str],
        *,
        config: UnoLinkConfig | None = None,
        transport_factory: Callable[[], ByteTransport] | None = None,
        on_telemetry: Callable[[ReceivedTelemetry], None] | None = None,
        probe_kernel_tty: bool | None = None,
    ) -> None:
        self.port = os.fspath(port)
        self.config = config if config is not None else UnoLinkConfig()
        self._transport_factory: Callable[[], ByteTransport] = (
            transport_factory
            if transport_factory is not None
            else lambda: PySerialTransport(close_timeout_s=self.config.close_timeout_s)
        )
        self._on_telemetry = on_telemetry
        self.stats = LinkStats()
        self.banner: Banner | None = None
        """The BANNER of the current (or last) connection."""
        self.last_error: LinkError | None = None
        """Why the link last failed (kept after a reconnect)."""
        self._status = DeviceStatus(DeviceState.DISCONNECTED, "not started")
        self._last_failure_logged = ""
        self._state_changed = asyncio.Event()
        self._telemetry: ReceivedTelemetry | None = None
        self._subscribers: set[asyncio.Queue[ReceivedTelemetry]] = set()
        self._conn: _Connection | None = None
        self._epoch = 0
        self._command: _Command | None = None
        self._lock = asyncio.Lock()  # one command in flight
        self._pending: _Pending | None = None
        self._stop_lock = asyncio.Lock()  # one priority STOP in flight
        self._stop_pending: _Pending | None = None
        self._stop_generation = 0
        """Counts `stop_motors` calls: a DRIVE queued before a stop is dropped."""
        self._seq = 0
        self._last_tx_s = 0.0
        self._last_drive_tx_s = 0.0
        self._supervisor: asyncio.Task[None] | None = None
        self._first_attempt = asyncio.Event()
        self.stall_clock = StallClock(max_excused_s=self.config.max_excused_stall_s)
        """The time this host could not hear the device (see `_Connection.awake_s`)."""
        if probe_kernel_tty is None:
            probe_kernel_tty = transport_factory is None  # a real serial port
        self.tty_probe = TtyDeliveryProbe(self.stall_clock) if probe_kernel_tty else None
        """Times the kernel's tty layer, which every serial byte passes through."""
        self._probe_task: asyncio.Task[None] | None = None

    # -- lifecycle ----------------------------------------------------------------------

    async def start(self) -> DeviceStatus:
        """Start connecting and return the status after the first attempt. Never raises
        for device trouble: a failed attempt shows as ``FAILED`` (reason in the status
        detail and `last_error`) and is retried with backoff in the background."""
        if self._supervisor is not None:
            raise RuntimeError("UnoLink already started")
        self._first_attempt.clear()
        if self.tty_probe is not None:
            self._probe_task = asyncio.create_task(self.tty_probe.run(), name="tty probe")
        self._supervisor = asyncio.create_task(self._supervise(), name=f"uno-link {self.port}")
        first = asyncio.create_task(self._first_attempt.wait())
        await asyncio.wait({first, self._supervisor}, return_when=asyncio.FIRST_COMPLETED)
        first.cancel()
        if self._supervisor.done():
            self._supervisor.result()  # a bug: let it show
        return self.status()

    async def stop(self) -> None:
        """Send ``STOP`` (if connected), then close the port and stop reconnecting."""
        supervisor, self._supervisor = self._supervisor, None
        if supervisor is None:
            return
        conn = self._conn
        self._command = None
        if conn is not None and self._status.state is DeviceState.CONNECTED:
            with contextlib.suppress(LinkError):
                await self._request(conn, MsgType.STOP)
        supervisor.cancel()
        await asyncio.wait({supervisor})
        probe, self._probe_task = self._probe_task, None
        if probe is not None:
            probe.cancel()
            await asyncio.wait({probe})
        for opened in {conn, self._conn}:  # the supervisor may have opened a newer one
            if opened is not None:
                await self._close_connection(opened)
        self._conn = None
        self._set_state(DeviceState.DISCONNECTED, "stopped")

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    # -- state --------------------------------------------------------------------------

    def status(self) -> DeviceStatus:
        return self._status

    @property
    def state(self) -> DeviceState:
        return self._status.state

    async def wait_state(self, *states: DeviceState, timeout_s: float) -> DeviceStatus:
        """Wait until the state is one of ``states``; `TimeoutError` after ``timeout_s``."""
        async with asyncio.timeout(timeout_s):
            while self._status.state not in states:
                await self._state_changed.wait()
        return self._status

    async def wait_connected(self, timeout_s: float) -> None:
        """Wait until connected; `LinkUnavailableError` (saying why) after ``timeout_s``."""
        try:
            await self.wait_state(DeviceState.CONNECTED, timeout_s=timeout_s)
        except TimeoutError:
            raise LinkUnavailableError(
                f"Uno on {self.port} not connected after {timeout_s} s: {self._status.detail}"
            ) from self.last_error

    @property
    def commanded(self) -> tuple[int, int]:
        """The PWM the link currently keeps the Uno at: (0, 0) unless a `drive` was
        made on the current, healthy connection."""
        command, conn = self._command, self._conn
        if command is None or conn is None or conn.failed.done() or command.epoch != conn.epoch:
            return (0, 0)
        return (command.left_pwm, command.right_pwm)

    @property
    def telemetry(self) -> ReceivedTelemetry | None:
        """The newest telemetry with its receive time (possibly old: see
        `latest_telemetry`)."""
        return self._telemetry

    def latest_telemetry(self, max_age_s: float) -> ReceivedTelemetry | None:
        """The newest telemetry if it is at most ``max_age_s`` old, else None."""
        telemetry = self._telemetry
        if telemetry is None or telemetry.age_s() > max_age_s:
            return None
        return telemetry

    async def telemetry_updates(self) -> AsyncGenerator[ReceivedTelemetry, None]:
        """Yield telemetry as it arrives; a slow consumer gets the newest only."""
        queue: asyncio.Queue[ReceivedTelemetry] = asyncio.Queue(maxsize=1)
        self._subscribers.add(queue)
        try:
            while True:
                yield await queue.get()
        finally:
            self._subscribers.discard(queue)

    # -- commands -----------------------------------------------------------------------

    async def drive(self, left_pwm: int, right_pwm: int) -> None:
        """Command both motors (-255..255, sign = direction) and wait for the ACK. The
        heartbeat keeps re-sending it until the next `drive` / `stop_motors`, or until
        the link fails: after a reconnect the motors stay stopped until a new `drive`.

        Raises
        ------
        ProtocolError (a ValueError) : a PWM out of range; nothing is sent.
        NotConnectedError : the link is not connected; nothing is kept for later.
        CommandTimeoutError, CommandRejectedError : the command is still kept and
            re-sent by the heartbeat.
        """
        payload = drive_payload(left_pwm, right_pwm)
        conn = self._connected()
        self._command = _Command(conn.epoch, left_pwm, right_pwm)
        await self._request(
            conn, MsgType.DRIVE, payload, unless_stopped_since=self._stop_generation
        )

    async def stop_motors(self) -> None:
        """Command zero and send ``STOP`` at once, and wait for its ACK.

        The STOP does not queue behind a command still waiting for its ACK (a lost DRIVE
        ACK would hold it for `UnoLinkConfig.ack_timeout_s`): it is written beside it, and
        a ``DRIVE`` that was queued before this call is dropped, never sent after the
        STOP. When not connected there is nothing to send (the firmware deadman has
        stopped the motors); it returns without error.
        """
        self._command = None
        self._stop_generation += 1
        conn = self._conn
        if conn is None or conn.failed.done() or self._status.state is not DeviceState.CONNECTED:
            return
        async with self._stop_lock:
            if self._lock.locked():
                self.stats.stops_ahead += 1
            await self._exchange(conn, MsgType.STOP, b"", priority=True)

    async def ping(self) -> float:
        """Send ``PING``; return the round trip in seconds."""
        conn = self._connected()
        await self._request(conn, MsgType.PING)
        return self.stats.rtt_s[-1]

    async def reset_counters(self) -> None:
        """Zero the device's encoders and error counters."""
        await self._request(self._connected(), MsgType.RESET_COUNTERS)

    # -- internals: commands ------------------------------------------------------------

    def _connected(self) -> _Connection:
        conn = self._conn
        if conn is None or conn.failed.done() or self._status.state is not DeviceState.CONNECTED:
            raise NotConnectedError(
                f"Uno link on {self.port} is {self._status.state.value}: {self._status.detail}"
            )
        return conn

    async def _request(
        self,
        conn: _Connection,
        msg_type: MsgType,
        payload: bytes = b"",
        *,
        unless_stopped_since: int | None = None,
    ) -> Ack | None:
        """Send one command and wait for its ACK, with at most one command in flight.

        With ``unless_stopped_since`` (a `_stop_generation` read when the command was
        made), the command is dropped, and None returned, if `stop_motors` ran while it
        waited for its turn: a DRIVE must never follow a later STOP onto the wire.
        """
        async with self._lock:
            if unless_stopped_since is not None and unless_stopped_since != self._stop_generation:
                self.stats.drives_dropped += 1
                return None
            return await self._exchange(conn, msg_type, payload, priority=False)

    async def _exchange(
        self, conn: _Connection, msg_type: MsgType, payload: bytes, *, priority: bool
    ) -> Ack:
        """Write one command and wait for its ACK. The caller holds `_lock` (or, for a
        ``priority`` STOP, `_stop_lock`: its ACK is matched in its own slot)."""
        if conn.failed.done():
            raise NotConnectedError(f"link lost before sending {msg_type.name}") from (
                conn.failed.result()
            )
        self._seq = (self._seq + 1) & 0xFF
        loop = asyncio.get_running_loop()
        pending = _Pending(self._seq, time.perf_counter(), loop.create_future())
        pending.future.add_done_callback(_retrieve_exception)
        if priority:
            self._stop_pending = pending
        else:
            self._pending = pending
        try:
            try:
                conn.transport.write(encode_frame(Frame(pending.seq, msg_type, payload)))
            except LinkLostError as exc:
                self._fail(conn, exc)
                raise
            now = time.monotonic()
            self._last_tx_s = now
            if msg_type is MsgType.DRIVE:
                self._last_drive_tx_s = now
            self.stats.commands_sent += 1
            ack, received_s = await self._await_ack(pending, conn)
        except TimeoutError:
            self.stats.timeouts += 1
            conn.consecutive_timeouts += 1
            if conn.consecutive_timeouts >= self.config.max_consecutive_timeouts:
                self._fail(
                    conn,
                    LinkSilentError(
                        f"{conn.consecutive_timeouts} commands in a row without ACK "
                        f"from {self.port}"
                    ),
                )
            raise CommandTimeoutError(
                f"no ACK for {msg_type.name} (seq {pending.seq}) within "
                f"{self.config.ack_timeout_s * 1000:.0f} ms"
            ) from None
        finally:
            if priority:
                self._stop_pending = None
            else:
                self._pending = None
        conn.consecutive_timeouts = 0
        self.stats.acks += 1
        self.stats.rtt_s.append(received_s - pending.sent_s)
        if ack.status != AckStatus.OK:
            self.stats.rejected += 1
            try:
                status = AckStatus(ack.status).name
            except ValueError:
                status = f"status {ack.status}"
            raise CommandRejectedError(f"{msg_type.name} rejected by the Uno: {status}")
        return ack

    async def _await_ack(self, pending: _Pending, conn: _Connection) -> tuple[Ack, float]:
        """The ACK, or `TimeoutError` once ``ack_timeout_s`` has passed on the awake
        clock: time the host could not hear the device is not the device's delay."""
        future = pending.future
        deadline_s = conn.awake_s() + self.config.ack_timeout_s
        while not future.done():
            remaining_s = deadline_s - conn.awake_s()
            if remaining_s <= 0:
                future.cancel()
                raise TimeoutError
            # Waiting does not cancel the future: a stall may leave time to wait on.
            await asyncio.wait([future], timeout=remaining_s)
        return future.result()

    # -- internals: supervisor ----------------------------------------------------------

    def _set_state(self, state: DeviceState, detail: str) -> None:
        previous = self._status.state
        self._status = DeviceStatus(state, detail)
        if state is not previous:
            level = logging.DEBUG if state is DeviceState.CONNECTING else logging.INFO
            if state is DeviceState.FAILED:
                # Say it once per distinct reason, not on every retry of a long outage.
                repeated = detail == self._last_failure_logged
                level = logging.DEBUG if repeated else logging.WARNING
                self._last_failure_logged = detail
            elif state is DeviceState.CONNECTED:
                self._last_failure_logged = ""
            log.log(level, "Uno link %s: %s (%s)", self.port, state.value, detail)
        event, self._state_changed = self._state_changed, asyncio.Event()
        event.set()

    async def _supervise(self) -> None:
        delay_s = self.config.backoff_initial_s
        while True:
            self._set_state(DeviceState.CONNECTING, f"opening {self.port}")
            self.stats.connect_attempts += 1
            error: LinkError
            try:
                conn = await self._connect()
            except LinkError as exc:
                error = exc
                if exc is not self.last_error:  # not yet recorded by _fail()
                    self._record_failure(exc)
                self._first_attempt.set()
            else:
                delay_s = self.config.backoff_initial_s
                self._first_attempt.set()
                try:
                    error = await asyncio.shield(conn.failed)
                finally:
                    await self._close_connection(conn)
            self._set_state(DeviceState.FAILED, f"{error} (next attempt within {delay_s:.1f} s)")
            await self._backoff(delay_s)
            delay_s = min(2 * delay_s, self.config.backoff_max_s)

    def _record_failure(self, exc: LinkError) -> None:
        self.last_error = exc
        self.stats.failures += 1
        self._command = None
        self._set_state(DeviceState.FAILED, str(exc))

    def _fail(self, conn: _Connection, exc: LinkError) -> None:
        """The connection is broken: zero the command at once, wake every waiter."""
        if conn.failed.done():
            return
        conn.failed.set_result(exc)
        if not conn.banner.done():
            conn.banner.set_exception(exc)
        pending = self._pending
        if pending is not None and not pending.future.done():
            pending.future.set_exception(exc)
        if self._conn is conn:
            self._record_failure(exc)

    def _port_exists(self) -> bool:
        return "://" in self.port or os.path.exists(self.port)

    async def _backoff(self, delay_s: float) -> None:
        """Sleep ``delay_s``, but return early when a missing port appears."""
        if self._port_exists():
            await asyncio.sleep(delay_s)
            return
        deadline = time.monotonic() + delay_s
        while (remaining := deadline - time.monotonic()) > 0:
            await asyncio.sleep(min(self.config.port_poll_s, remaining))
            if self._port_exists():
                return

    async def _connect(self) -> _Connection:
        """Open the port and handshake; on success the link is CONNECTED."""
        self._epoch += 1
        transport = self._transport_factory()
        conn = _Connection(transport, self._epoch, self.stall_clock)
        await transport.open(self.port, baudrate=self.config.baudrate)
        self._conn = conn
        conn.tasks.append(asyncio.create_task(self._read_loop(conn), name="uno-link reader"))
        try:
            banner = await self._handshake(conn)
            # Whatever the firmware did before this open, we start from zero.
            await self._request(conn, MsgType.STOP)
            await self._request(
                conn,
                MsgType.SET_TELEMETRY,
                telemetry_period_payload(self.config.telemetry_period_ms),
            )
        except LinkError as exc:
            self._fail(conn, exc)
            await self._close_connection(conn)
            raise
        except BaseException:
            await self._close_connection(conn)
            raise
        if conn.failed.done():  # broke between the last ACK and here
            await self._close_connection(conn)
            raise conn.failed.result()
        conn.ready = True
        conn.last_telemetry_s = conn.awake_s()
        self.stats.connects += 1
        if self.stats.connects > 1:
            self.stats.reconnects += 1
        self._set_state(
            DeviceState.CONNECTED,
            f"{banner.firmware} (protocol {banner.protocol_version}) on {self.port}",
        )
        conn.tasks.append(asyncio.create_task(self._heartbeat(conn), name="uno-link heartbeat"))
        return conn

    async def _handshake(self, conn: _Connection) -> Banner:
        cfg = self.config
        deadline = time.monotonic() + cfg.handshake_timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise HandshakeError(
                    f"no BANNER from {self.port} within {cfg.handshake_timeout_s} s of "
                    "opening it: is the floornav firmware flashed?"
                )
            async with self._lock:
                self._seq = (self._seq + 1) & 0xFF
                conn.transport.write(encode_frame(Frame(self._seq, MsgType.HELLO)))
                try:
                    async with asyncio.timeout(min(cfg.hello_retry_s, remaining)):
                        banner = await asyncio.shield(conn.banner)
                    break
                except TimeoutError:
                    continue
        self.banner = banner
        if banner.protocol_version != PROTOCOL_VERSION or banner.motor_count != MOTOR_COUNT:
            raise FirmwareMismatchError(
                f"the device on {self.port} runs '{banner.firmware}' speaking protocol "
                f"version {banner.protocol_version} with {banner.motor_count} motors; this "
                f"host speaks version {PROTOCOL_VERSION} with {MOTOR_COUNT} motors: refusing "
                "to drive it (flash the floornav firmware)"
            )
        return banner

    async def _close_connection(self, conn: _Connection) -> None:
        if conn.closed:
            return
        conn.closed = True
        current = asyncio.current_task()
        tasks = [task for task in conn.tasks if task is not current]
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)
        await conn.transport.close()

    # -- internals: reader and heartbeat ------------------------------------------------

    async def _read_loop(self, conn: _Connection) -> None:
        cfg = self.config
        silent_since_s = conn.awake_s()
        returned_s = time.monotonic()
        try:
            while True:
                timeout_s = cfg.silence_timeout_s if conn.ready else cfg.handshake_timeout_s
                # Listen in slices so that a stall of this process is measured and not
                # counted as silence (see `_Connection.awake_s`).
                remaining_s = silent_since_s + timeout_s - conn.awake_s()
                if remaining_s <= 0:
                    raise LinkSilentError(
                        f"no bytes from {self.port} for {timeout_s * 1000:.0f} ms: cable "
                        "pulled or firmware hung?"
                    )
                slice_s = min(remaining_s, timeout_s * SILENCE_SLICE_FRACTION)
                started_s = time.monotonic()
                conn.note_gap(returned_s, started_s)
                data = await conn.transport.read(slice_s)
                returned_s = time.monotonic()
                conn.note_wait(started_s, slice_s, returned_s)
                if not data:
                    continue
                silent_since_s = conn.awake_s()
                received_s = time.perf_counter()
                decoder = conn.decoder
                frames = decoder.feed(data)
                self.stats.crc_errors += decoder.stats.crc_errors
                self.stats.garbage_bytes += decoder.stats.garbage_bytes
                self.stats.oversize_frames += decoder.stats.oversize
                decoder.stats.crc_errors = decoder.stats.garbage_bytes = 0
                decoder.stats.oversize = 0
                for frame in frames:
                    self._dispatch(conn, frame, received_s)
                self._check_telemetry_flows(conn)
        except LinkError as exc:
            self._fail(conn, exc)
        except Exception as exc:  # a bug must not leave a dead link looking alive
            log.exception("Uno link reader crashed")
            self._fail(conn, LinkLostError(f"internal error in the reader: {exc!r}"))

    def _check_telemetry_flows(self, conn: _Connection) -> None:
        """Telemetry we asked for stopped while other bytes (ACKs) still flow: the
        firmware rebooted (it boots with telemetry off) or is confused. Reconnect."""
        if not conn.ready or not self.config.telemetry_period_ms or conn.failed.done():
            return
        silent_s = conn.awake_s() - conn.last_telemetry_s
        if silent_s > self.config.silence_timeout_s:
            self._fail(
                conn,
                DeviceResetError(
                    f"no telemetry from {self.port} for {silent_s * 1000:.0f} ms although "
                    f"asked for every {self.config.telemetry_period_ms} ms: did the Uno reboot?"
                ),
            )

    def _dispatch(self, conn: _Connection, frame: Frame, received_s: float) -> None:
        try:
            if frame.type == MsgType.ACK:
                ack = Ack.parse(frame.payload)
                for pending in (self._pending, self._stop_pending):
                    if (
                        pending is not None
                        and pending.seq == ack.acked_seq
                        and not pending.future.done()
                    ):
                        pending.future.set_result((ack, received_s))
                        break
                else:
                    self.stats.stale_acks += 1
            elif frame.type == MsgType.TELEMETRY:
                self._on_telemetry_frame(conn, Telemetry.parse(frame.payload))
            elif frame.type == MsgType.BANNER:
                banner = Banner.parse(frame.payload)
                if not conn.banner.done():
                    conn.banner.set_result(banner)
                elif banner.protocol_version != PROTOCOL_VERSION:
                    self._fail(conn, FirmwareMismatchError(f"late BANNER with {banner}"))
                # else: an answer to a repeated HELLO, or the boot banner after our HELLO
            else:
                self.stats.malformed_frames += 1
        except ProtocolError as exc:
            self.stats.malformed_frames += 1
            log.debug("malformed frame from %s: %s", self.port, exc)

    def _on_telemetry_frame(self, conn: _Connection, data: Telemetry) -> None:
        self.stats.telemetry_frames += 1
        conn.last_telemetry_s = conn.awake_s()
        last = conn.last_uptime_ms
        conn.last_uptime_ms = data.uptime_ms
        if last is not None and 0 < (last - data.uptime_ms) % 2**32 < 2**31:
            self._fail(
                conn,
                DeviceResetError(
                    f"the Uno on {self.port} rebooted (uptime {last} -> {data.uptime_ms} ms)"
                ),
            )
            return
        tripped = data.deadman_tripped and not conn.last_flags & Telemetry.DEADMAN_TRIPPED
        conn.last_flags = data.flags
        if tripped and self.commanded != (0, 0):
            self.stats.deadman_trips_seen += 1
            log.warning("Uno on %s reports a deadman stop while driving", self.port)
        received = ReceivedTelemetry(data, time.monotonic())
        self._telemetry = received
        for queue in self._subscribers:
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(received)
        if self._on_telemetry is not None:
            self._on_telemetry(received)

    async def _heartbeat(self, conn: _Connection) -> None:
        """Re-send the current DRIVE while moving (refreshes the deadman), else PING."""
        period_s = self.config.heartbeat_period_s
        while not conn.failed.done():
            command = self._command
            generation = self._stop_generation
            moving = command is not None and command.epoch == conn.epoch and command.moving
            last_s = self._last_drive_tx_s if moving else self._last_tx_s
            wait_s = last_s + period_s - time.monotonic()
            if wait_s > 0:
                await asyncio.sleep(wait_s)
                continue
            try:
                self.stats.heartbeats += 1
                if moving and command is not None:
                    payload = drive_payload(command.left_pwm, command.right_pwm)
                    await self._request(
                        conn, MsgType.DRIVE, payload, unless_stopped_since=generation
                    )
                else:
                    await self._request(conn, MsgType.PING)
            except (CommandTimeoutError, CommandRejectedError) as exc:
                log.debug("heartbeat on %s: %s", self.port, exc)
            except LinkError:
                return
