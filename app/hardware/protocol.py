"""The floornav serial protocol (``docs/protocol.md``): frame encoding and a streaming
decoder, as pure functions of bytes. Used by the host driver, the simulated Uno and the
firmware tests; the Arduino sketch implements the same rules in C++."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

PROTOCOL_VERSION = 1
SYNC = b"\xaa\x55"
MAX_PAYLOAD = 32
HEADER_LEN = 5  # sync(2) + len + seq + type
FRAME_OVERHEAD = HEADER_LEN + 2  # + crc16
MAX_FRAME = FRAME_OVERHEAD + MAX_PAYLOAD
PWM_LIMIT = 255
DEADMAN_MS = 250


class MsgType(IntEnum):
    HELLO = 0x01
    DRIVE = 0x02
    STOP = 0x03
    PING = 0x04
    SET_TELEMETRY = 0x05
    RESET_COUNTERS = 0x06
    BANNER = 0x81
    ACK = 0x82
    TELEMETRY = 0x83


class AckStatus(IntEnum):
    OK = 0
    BAD_ARGUMENT = 1
    UNKNOWN_TYPE = 2


class ProtocolError(ValueError):
    """A payload that does not match its message type."""


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF). ``crc16_ccitt(b"123456789")`` is
    0x29B1."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes = b""


def encode_frame(frame: Frame) -> bytes:
    """Frame -> bytes on the wire."""
    if not 0 <= frame.seq <= 255:
        raise ProtocolError(f"seq must be 0..255, got {frame.seq}")
    if not 0 <= frame.type <= 255:
        raise ProtocolError(f"type must be 0..255, got {frame.type}")
    if len(frame.payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((len(frame.payload), frame.seq, frame.type)) + frame.payload
    return SYNC + body + struct.pack("<H", crc16_ccitt(body))


@dataclass
class DecoderStats:
    frames: int = 0
    crc_errors: int = 0
    garbage_bytes: int = 0
    oversize: int = 0


class FrameDecoder:
    """Streaming decoder: feed it bytes as they arrive, get whole valid frames.

    Garbage before a sync pattern, oversize lengths and CRC failures are counted in
    ``stats`` and skipped; after a bad frame the decoder resynchronises on the next
    ``0xAA 0x55``. Never raises on input bytes.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.stats = DecoderStats()

    def feed(self, data: bytes) -> list[Frame]:
        self._buffer.extend(data)
        frames: list[Frame] = []
        buf = self._buffer
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # Keep a trailing 0xAA: it may be the first half of a sync pattern.
                keep = 1 if buf.endswith(SYNC[:1]) else 0
                self.stats.garbage_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if start:
                self.stats.garbage_bytes += start
                del buf[:start]
            if len(buf) < HEADER_LEN:
                break
            length = buf[2]
            if length > MAX_PAYLOAD:
                self.stats.oversize += 1
                self.stats.garbage_bytes += 2
                del buf[:2]
                continue
            total = FRAME_OVERHEAD + length
            if len(buf) < total:
                break
            body = bytes(buf[2 : HEADER_LEN + length])
            (crc,) = struct.unpack_from("<H", buf, HEADER_LEN + length)
            if crc != crc16_ccitt(body):
                self.stats.crc_errors += 1
                del buf[:2]  # resync from just after this sync pattern
                continue
            frames.append(Frame(seq=body[1], type=body[2], payload=body[3:]))
            self.stats.frames += 1
            del buf[:total]
        return frames


# -- typed messages -------------------------------------------------------------------


def clamp_pwm(value: int) -> int:
    return max(-PWM_LIMIT, min(PWM_LIMIT, int(value)))


def drive_payload(left_pwm: int, right_pwm: int) -> bytes:
    for name, value in (("left_pwm", left_pwm), ("right_pwm", right_pwm)):
        if not -PWM_LIMIT <= value <= PWM_LIMIT:
            raise ProtocolError(f"{name} must be within +-{PWM_LIMIT}, got {value}")
    return struct.pack("<hh", left_pwm, right_pwm)


def parse_drive(payload: bytes) -> tuple[int, int]:
    if len(payload) != 4:
        raise ProtocolError(f"DRIVE payload must be 4 bytes, got {len(payload)}")
    left, right = struct.unpack("<hh", payload)
    if not (-PWM_LIMIT <= left <= PWM_LIMIT and -PWM_LIMIT <= right <= PWM_LIMIT):
        raise ProtocolError(f"DRIVE pwm out of range: {left}, {right}")
    return int(left), int(right)


def telemetry_period_payload(period_ms: int) -> bytes:
    if period_ms != 0 and not 20 <= period_ms <= 1000:
        raise ProtocolError(f"telemetry period must be 0 or 20..1000 ms, got {period_ms}")
    return struct.pack("<H", period_ms)


def parse_telemetry_period(payload: bytes) -> int:
    if len(payload) != 2:
        raise ProtocolError(f"SET_TELEMETRY payload must be 2 bytes, got {len(payload)}")
    (period,) = struct.unpack("<H", payload)
    if period != 0 and not 20 <= period <= 1000:
        raise ProtocolError(f"telemetry period out of range: {period}")
    return int(period)


@dataclass(frozen=True)
class Banner:
    protocol_version: int
    motor_count: int
    firmware: str

    def payload(self) -> bytes:
        return bytes((self.protocol_version, self.motor_count)) + self.firmware.encode("ascii")

    @classmethod
    def parse(cls, payload: bytes) -> Banner:
        if len(payload) < 2:
            raise ProtocolError(f"BANNER payload too short ({len(payload)} bytes)")
        try:
            firmware = payload[2:].decode("ascii")
        except UnicodeDecodeError as exc:
            raise ProtocolError("BANNER firmware name is not ASCII") from exc
        return cls(payload[0], payload[1], firmware)


@dataclass(frozen=True)
class Ack:
    acked_seq: int
    status: int

    def payload(self) -> bytes:
        return bytes((self.acked_seq, self.status))

    @classmethod
    def parse(cls, payload: bytes) -> Ack:
        if len(payload) != 2:
            raise ProtocolError(f"ACK payload must be 2 bytes, got {len(payload)}")
        return cls(payload[0], payload[1])


_TELEMETRY = struct.Struct("<IiihhHHHHB")


@dataclass(frozen=True)
class Telemetry:
    uptime_ms: int
    encoder_left: int
    encoder_right: int
    pwm_left: int
    pwm_right: int
    ms_since_command: int
    crc_errors: int
    garbage_bytes: int
    rx_overruns: int
    flags: int

    DEADMAN_TRIPPED = 0x01
    STOPPED = 0x02

    def payload(self) -> bytes:
        return _TELEMETRY.pack(
            self.uptime_ms & 0xFFFFFFFF,
            self.encoder_left,
            self.encoder_right,
            self.pwm_left,
            self.pwm_right,
            min(self.ms_since_command, 0xFFFF),
            self.crc_errors & 0xFFFF,
            self.garbage_bytes & 0xFFFF,
            self.rx_overruns & 0xFFFF,
            self.flags,
        )

    @classmethod
    def parse(cls, payload: bytes) -> Telemetry:
        if len(payload) != _TELEMETRY.size:
            raise ProtocolError(
                f"TELEMETRY payload must be {_TELEMETRY.size} bytes, got {len(payload)}"
            )
        return cls(*_TELEMETRY.unpack(payload))

    @property
    def deadman_tripped(self) -> bool:
        return bool(self.flags & self.DEADMAN_TRIPPED)
