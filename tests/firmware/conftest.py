"""Fixtures for the firmware tests: build the Uno sketch and the simavr harness once per
session (``make -C firmware``), then run a fresh simulated Uno for each test and talk to
it over the harness's pty with pyserial, exactly like the host driver would."""

from __future__ import annotations

import os
import queue
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import serial

from app.hardware.protocol import (
    Ack,
    Frame,
    FrameDecoder,
    MsgType,
    Telemetry,
    encode_frame,
    telemetry_period_payload,
)

PROJECT_ROOT = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = PROJECT_ROOT / "firmware"
BUILD_DIR = PROJECT_ROOT / "build" / "firmware"
ELF = BUILD_DIR / "uno" / "floornav_uno.elf"
HARNESS = BUILD_DIR / "sim" / "harness"

# What `make -C firmware` needs, by Debian package (scripts/install-firmware-deps).
REQUIREMENTS: dict[str, Callable[[], bool]] = {
    "make": lambda: shutil.which("make") is not None,
    "cc": lambda: shutil.which("cc") is not None,
    "gcc-avr": lambda: shutil.which("avr-gcc") is not None,
    "avr-libc": lambda: Path("/usr/lib/avr/include/avr/io.h").is_file(),
    "arduino-mk": lambda: Path("/usr/share/arduino/Arduino.mk").is_file(),
    "arduino-core-avr": lambda: Path(
        "/usr/share/arduino/hardware/arduino/avr/cores/arduino/Arduino.h"
    ).is_file(),
    "libsimavr-dev": lambda: Path("/usr/include/simavr/sim_avr.h").is_file(),
    "libsimavrparts1": lambda: any(Path("/usr/lib").glob("*/libsimavrparts.so*")),
}


@pytest.fixture(scope="session")
def firmware_build() -> tuple[Path, Path]:
    """Build the sketch and the harness once; skip when the toolchain is not installed."""
    missing = [name for name, present in REQUIREMENTS.items() if not present()]
    if missing:
        reason = (
            f"firmware toolchain missing ({', '.join(missing)}): run scripts/install-firmware-deps"
        )
        if os.environ.get("FLOORNAV_REQUIRE_FIRMWARE") == "1":
            pytest.fail(reason)  # CI installs the toolchain: a skip there would hide a gap
        pytest.skip(reason)
    result = subprocess.run(
        ["make", "-C", str(FIRMWARE_DIR)], capture_output=True, text=True, timeout=300
    )
    if result.returncode != 0:
        pytest.fail(f"make -C firmware failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}")
    return ELF, HARNESS


@dataclass(frozen=True)
class MotorEvent:
    """One `MOTOR` line of the harness: the H-bridge outputs changed."""

    t_ms: float  # simulated time of the change
    left: int
    right: int
    wall: float  # time.monotonic() when the line was read


class SimUno:
    """A simulated Uno: the serial port to its firmware and the harness's reports."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.port: serial.Serial | None = None
        self.decoder = FrameDecoder()
        self.backlog: list[Frame] = []
        self.boot_banner: Frame | None = None
        self._seq = 0
        self._lines: queue.Queue[str] = queue.Queue()
        self._motors: list[MotorEvent] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read_stdout, daemon=True)
        self._reader.start()

    # -- harness ------------------------------------------------------------------------

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            now = time.monotonic()
            if line.startswith("MOTOR "):
                fields = dict(item.split("=", 1) for item in line.split()[1:])
                event = MotorEvent(
                    float(fields["t_ms"]), int(fields["left"]), int(fields["right"]), now
                )
                with self._cond:
                    self._motors.append(event)
                    self._cond.notify_all()
            else:
                self._lines.put(line.strip())

    def harness_line(self, timeout: float = 5.0) -> str:
        try:
            return self._lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"harness printed nothing in {timeout} s") from None

    def command(self, line: str) -> None:
        """Send a line to the harness (START, ENC left_hz right_hz)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def set_encoders(self, left_hz: int, right_hz: int) -> None:
        self.command(f"ENC {left_hz} {right_hz}")

    def motor_events(self) -> list[MotorEvent]:
        with self._cond:
            return list(self._motors)

    def wait_motor(
        self, predicate: Callable[[MotorEvent], bool], timeout: float, start: int = 0
    ) -> MotorEvent | None:
        """The first MOTOR event from index ``start`` on that satisfies ``predicate``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for event in self._motors[start:]:
                    if predicate(event):
                        return event
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)

    # -- serial -------------------------------------------------------------------------

    def next_seq(self) -> int:
        self._seq = (self._seq + 1) % 256
        return self._seq

    def write(self, data: bytes) -> None:
        assert self.port is not None
        self.port.write(data)

    def send(self, msg_type: int, payload: bytes = b"", seq: int | None = None) -> int:
        seq = self.next_seq() if seq is None else seq
        self.write(encode_frame(Frame(seq, msg_type, payload)))
        return seq

    def _pump(self) -> None:
        assert self.port is not None
        data = self.port.read(max(1, self.port.in_waiting))
        if data:
            self.backlog.extend(self.decoder.feed(data))

    def recv(
        self, match: Callable[[Frame], bool] | None = None, timeout: float = 1.0
    ) -> Frame | None:
        """The first received frame that ``match`` accepts (any frame when None), taken out
        of the backlog; frames that do not match stay there."""
        deadline = time.monotonic() + timeout
        while True:
            for i, frame in enumerate(self.backlog):
                if match is None or match(frame):
                    return self.backlog.pop(i)
            if time.monotonic() >= deadline:
                return None
            self._pump()

    def collect(self, duration: float) -> list[Frame]:
        """Everything received during ``duration`` seconds (and the backlog)."""
        deadline = time.monotonic() + duration
        while time.monotonic() < deadline:
            self._pump()
        frames, self.backlog = self.backlog, []
        return frames

    def request(self, msg_type: int, payload: bytes = b"", timeout: float = 1.0) -> Frame:
        """Send a command and return its reply (the ACK or BANNER echoing its seq)."""
        seq = self.send(msg_type, payload)
        reply_type = MsgType.BANNER if msg_type == MsgType.HELLO else MsgType.ACK
        reply = self.recv(lambda f: f.type == reply_type and f.seq == seq, timeout)
        assert reply is not None, f"no reply to {msg_type!r} seq {seq} within {timeout} s"
        return reply

    def ack(self, msg_type: int, payload: bytes = b"") -> Ack:
        reply = self.request(msg_type, payload)
        ack = Ack.parse(reply.payload)
        assert ack.acked_seq == reply.seq
        return ack

    def telemetry(self) -> Telemetry:
        """One TELEMETRY snapshot: switch it on at 20 ms, take one frame, switch it off."""
        assert self.ack(MsgType.SET_TELEMETRY, telemetry_period_payload(20)).status == 0
        frame = self.recv(lambda f: f.type == MsgType.TELEMETRY, timeout=1.0)
        assert frame is not None, "no TELEMETRY within 1 s"
        assert self.ack(MsgType.SET_TELEMETRY, telemetry_period_payload(0)).status == 0
        self.backlog = [f for f in self.backlog if f.type != MsgType.TELEMETRY]
        return Telemetry.parse(frame.payload)


@pytest.fixture
def uno(firmware_build: tuple[Path, Path], tmp_path: Path) -> Iterator[SimUno]:
    """A freshly booted simulated Uno whose boot banner has arrived."""
    elf, harness = firmware_build
    with (tmp_path / "harness.stderr").open("w") as stderr:
        proc = subprocess.Popen(
            [str(harness), str(elf)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            bufsize=1,
        )
    uno = SimUno(proc)
    try:
        line = uno.harness_line()
        assert line.startswith("PTY /dev/"), f"unexpected first harness line {line!r}"
        # Open the pty before the CPU starts: pyserial flushes input on open.
        uno.port = serial.Serial(line.split()[1], 115200, timeout=0.01)
        uno.command("START")
        assert uno.harness_line() == "STARTED"
        uno.boot_banner = uno.recv(timeout=2.0)
        assert uno.boot_banner is not None, "no boot banner within 2 s"
        yield uno
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if uno.port is not None:
            uno.port.close()
