"""The simulated Uno against the protocol spec, driven through its pty with raw bytes
(no host driver involved)."""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.hardware.protocol import (
    FRAME_OVERHEAD,
    MAX_FRAME,
    Ack,
    AckStatus,
    Banner,
    Frame,
    FrameDecoder,
    MsgType,
    Telemetry,
    drive_payload,
    encode_frame,
    telemetry_period_payload,
)
from app.sim.sim_uno import UNO_RX_BUFFER_BYTES, IntegratingPlant, SimulatedUno

PROJECT_ROOT = Path(__file__).resolve().parents[2]


class RawHost:
    """The host end of the pty, opened like pyserial does, speaking raw frames."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.decoder = FrameDecoder()
        self.frames: list[Frame] = []
        self.seq = 0

    def close(self) -> None:
        os.close(self.fd)

    def send(self, msg_type: int, payload: bytes = b"", seq: int | None = None) -> int:
        if seq is None:
            self.seq = (self.seq + 1) & 0xFF
            seq = self.seq
        os.write(self.fd, encode_frame(Frame(seq, msg_type, payload)))
        return seq

    def read_once(self, timeout_s: float) -> None:
        ready, _, _ = select.select([self.fd], [], [], timeout_s)
        if ready:
            self.frames.extend(self.decoder.feed(os.read(self.fd, 4096)))

    def pump(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            self.read_once(remaining)

    def drain(self) -> None:
        """Forget every frame received so far (including those still in the pty)."""
        self.pump(0.005)
        self.frames.clear()

    def expect(self, msg_type: MsgType, timeout_s: float = 0.5) -> Frame:
        deadline = time.monotonic() + timeout_s
        while True:
            for i, frame in enumerate(self.frames):
                if frame.type == msg_type:
                    del self.frames[: i + 1]
                    return frame
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"no {msg_type.name} within {timeout_s} s")
            self.read_once(remaining)

    def command(self, msg_type: MsgType, payload: bytes = b"") -> Ack:
        seq = self.send(msg_type, payload)
        ack = Ack.parse(self.expect(MsgType.ACK).payload)
        assert ack.acked_seq == seq
        return ack


@pytest.fixture
def uno() -> Iterator[SimulatedUno]:
    with SimulatedUno() as sim:
        yield sim


@pytest.fixture
def host(uno: SimulatedUno) -> Iterator[RawHost]:
    raw = RawHost(uno.port)
    yield raw
    raw.close()


def test_hello_gets_banner_and_every_command_its_ack(uno: SimulatedUno, host: RawHost) -> None:
    host.send(MsgType.HELLO, seq=42)
    banner = Banner.parse(host.expect(MsgType.BANNER).payload)
    assert banner == Banner(1, 2, "floornav-sim 1.0.0")
    for msg_type, payload in [
        (MsgType.DRIVE, drive_payload(10, -20)),
        (MsgType.PING, b""),
        (MsgType.SET_TELEMETRY, telemetry_period_payload(0)),
        (MsgType.RESET_COUNTERS, b""),
        (MsgType.STOP, b""),
    ]:
        assert host.command(msg_type, payload).status == AckStatus.OK
    assert [c.frame.type for c in uno.commands()] == [
        MsgType.HELLO,
        MsgType.DRIVE,
        MsgType.PING,
        MsgType.SET_TELEMETRY,
        MsgType.RESET_COUNTERS,
        MsgType.STOP,
    ]


def test_bad_arguments_and_unknown_types_are_refused(uno: SimulatedUno, host: RawHost) -> None:
    bad_pwm = (300).to_bytes(2, "little", signed=True) * 2
    assert host.command(MsgType.DRIVE, bad_pwm).status == AckStatus.BAD_ARGUMENT
    assert host.command(MsgType.DRIVE, b"\x01").status == AckStatus.BAD_ARGUMENT
    assert host.command(MsgType.SET_TELEMETRY, (5).to_bytes(2, "little")).status == (
        AckStatus.BAD_ARGUMENT
    )
    assert host.command(0x7F, b"").status == AckStatus.UNKNOWN_TYPE  # type: ignore[arg-type]
    assert uno.pwm == (0, 0)
    assert uno.unknown_frames == 1
    assert uno.decoder_stats.garbage_bytes == FRAME_OVERHEAD  # counted like the firmware


def test_drive_sets_pwm_and_drives_the_plant() -> None:
    calls: list[tuple[int, int]] = []

    class Plant(IntegratingPlant):
        def apply_pwm(self, left_pwm: int, right_pwm: int) -> None:
            calls.append((left_pwm, right_pwm))
            super().apply_pwm(left_pwm, right_pwm)

    with SimulatedUno(Plant()) as uno:
        host = RawHost(uno.port)
        try:
            host.command(MsgType.DRIVE, drive_payload(120, -60))
            assert uno.pwm == (120, -60)
            host.command(MsgType.STOP)
            assert uno.pwm == (0, 0)
        finally:
            host.close()
    assert calls[-2:] == [(120, -60), (0, 0)]


def test_deadman_fires_250_ms_after_the_last_drive_and_ping_does_not_refresh(
    uno: SimulatedUno, host: RawHost
) -> None:
    host.command(MsgType.DRIVE, drive_payload(100, 100))
    last_drive_s = uno.commands(MsgType.DRIVE)[-1].time_s
    for _ in range(4):  # PINGs for 0.16 s: not a refresh (slack for a loaded machine)
        time.sleep(0.04)
        host.command(MsgType.PING)
    assert uno.pwm == (100, 100)
    time.sleep(0.25)
    assert uno.pwm == (0, 0)
    assert len(uno.deadman_trips) == 1
    delay_s = uno.deadman_trips[0] - last_drive_s
    print(f"deadman fired {delay_s * 1000:.1f} ms after the last DRIVE")
    assert 0.25 <= delay_s < 0.35


def test_telemetry_stream_encoders_flags_and_reset(uno: SimulatedUno, host: RawHost) -> None:
    host.command(MsgType.SET_TELEMETRY, telemetry_period_payload(20))
    host.command(MsgType.DRIVE, drive_payload(200, -100))
    time.sleep(0.2)
    host.drain()
    first = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    second = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    assert (first.pwm_left, first.pwm_right) == (200, -100)
    assert 10 <= second.uptime_ms - first.uptime_ms <= 40  # every 20 ms
    assert first.encoder_left > 0 > first.encoder_right  # integrating plant
    assert not first.deadman_tripped
    time.sleep(0.3)  # deadman
    host.drain()
    tripped = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    assert tripped.deadman_tripped and (tripped.pwm_left, tripped.pwm_right) == (0, 0)
    assert tripped.ms_since_command >= 250
    host.command(MsgType.RESET_COUNTERS)
    host.drain()
    reset = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    assert (reset.encoder_left, reset.encoder_right) == (0, 0)
    host.command(MsgType.STOP)
    host.drain()
    stopped = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    assert stopped.flags & Telemetry.STOPPED


def test_crc_errors_and_garbage_are_counted_and_ignored(uno: SimulatedUno, host: RawHost) -> None:
    corrupt = bytearray(encode_frame(Frame(1, MsgType.DRIVE, drive_payload(255, 255))))
    corrupt[-1] ^= 0x55
    os.write(host.fd, b"\x01\x02\x03" + bytes(corrupt))
    assert host.command(MsgType.PING).status == AckStatus.OK
    assert uno.pwm == (0, 0)
    stats = uno.decoder_stats
    assert stats.crc_errors == 1
    assert stats.garbage_bytes >= 3
    host.command(MsgType.SET_TELEMETRY, telemetry_period_payload(20))
    telemetry = Telemetry.parse(host.expect(MsgType.TELEMETRY).payload)
    assert telemetry.crc_errors == 1 and telemetry.garbage_bytes >= 3


def test_rx_buffer_overruns_when_a_host_does_not_wait_for_acks() -> None:
    """The negative control for the host's one-command-in-flight test."""
    with SimulatedUno(ack_delay_s=0.005) as uno:
        host = RawHost(uno.port)
        try:
            burst = b"".join(
                encode_frame(Frame(i, MsgType.DRIVE, drive_payload(i, i))) for i in range(10)
            )
            os.write(host.fd, burst)
            host.pump(0.1)
        finally:
            host.close()
        assert len(burst) > UNO_RX_BUFFER_BYTES
        assert uno.max_outstanding_commands > 1
        assert uno.max_rx_backlog_bytes > MAX_FRAME
        assert uno.rx_overruns > 0
        acks = [Ack.parse(f.payload) for f in host.frames if f.type == MsgType.ACK]
        assert 0 < len(acks) < 10


def test_unplug_and_replug_move_the_symlink(tmp_path: Path) -> None:
    link = tmp_path / "by-id" / "usb-sim-uno"
    link.parent.mkdir()
    with SimulatedUno(link_path=link) as uno:
        assert uno.port == str(link)
        first = uno.pty_path
        assert os.path.realpath(link) == first
        host = RawHost(uno.port)
        try:
            uno.unplug()
            assert not link.exists() and not link.is_symlink()
            # The host's reads fail like a pulled cable's: EIO, or nothing though "ready".
            ready, _, _ = select.select([host.fd], [], [], 0.5)
            assert ready
            with contextlib.suppress(OSError):
                assert os.read(host.fd, 100) == b""
        finally:
            host.close()
        uno.replug()
        assert os.path.realpath(link) == uno.pty_path
        assert uno.boots == 2
        host = RawHost(uno.port)
        try:
            assert host.command(MsgType.PING).status == AckStatus.OK
        finally:
            host.close()


def test_go_silent_answers_nothing_until_it_comes_back(uno: SimulatedUno, host: RawHost) -> None:
    # A boot banner sent before the silence (whether it reaches this end of the pty
    # depends on when it was opened) is not an answer: forget it first.
    host.pump(0.2)
    host.drain()
    uno.go_silent()
    host.send(MsgType.PING)
    host.pump(0.1)
    assert host.frames == []
    uno.go_silent(False)
    assert host.command(MsgType.PING).status == AckStatus.OK


def test_wrong_firmware_banner() -> None:
    with SimulatedUno(banner_protocol_version=2, firmware="other-fw 9") as uno:
        host = RawHost(uno.port)
        try:
            host.send(MsgType.HELLO)
            assert Banner.parse(host.expect(MsgType.BANNER).payload) == Banner(2, 2, "other-fw 9")
        finally:
            host.close()


def _popen_with_ctrl_c(args: list[str], **kwargs: Any) -> subprocess.Popen[str]:
    """Start ``args`` with SIGINT at its default, as a terminal's Ctrl-C finds it. A
    parent that ignores SIGINT (pytest started with ``&`` from a script) hands the
    ignore down through exec, and the child would never see the signal; a handled
    signal is reset to the default on exec instead."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen(args, **kwargs)
    finally:
        signal.signal(signal.SIGINT, previous)


def test_cli_prints_the_port_and_stops_on_ctrl_c() -> None:
    with _popen_with_ctrl_c(
        [sys.executable, "-m", "app.sim.sim_uno"],
        cwd=PROJECT_ROOT,
        stdout=subprocess.PIPE,
        text=True,
    ) as proc:
        try:
            assert proc.stdout is not None
            line = proc.stdout.readline()
            assert line.startswith("simulated Uno on /dev/pts/")
            host = RawHost(line.split()[-1])
            try:
                assert host.command(MsgType.PING).status == AckStatus.OK
            finally:
                host.close()
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=5) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
