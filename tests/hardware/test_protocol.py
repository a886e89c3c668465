from __future__ import annotations

import pytest

from app.hardware.protocol import (
    MAX_FRAME,
    Ack,
    Banner,
    Frame,
    FrameDecoder,
    MsgType,
    ProtocolError,
    Telemetry,
    crc16_ccitt,
    drive_payload,
    encode_frame,
    parse_drive,
)


def test_crc_check_value() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1


def test_drive_frame_exact_bytes() -> None:
    wire = encode_frame(Frame(seq=7, type=MsgType.DRIVE, payload=drive_payload(100, -100)))
    body = bytes([4, 7, 0x02, 100, 0, 0x9C, 0xFF])
    assert wire[:2] == b"\xaa\x55" and wire[2:9] == body
    assert int.from_bytes(wire[9:], "little") == crc16_ccitt(body)
    assert parse_drive(FrameDecoder().feed(wire)[0].payload) == (100, -100)


def test_decoder_survives_garbage_split_and_crc_errors() -> None:
    good = [encode_frame(Frame(seq=i, type=MsgType.PING)) for i in range(3)]
    corrupt = bytearray(encode_frame(Frame(seq=9, type=MsgType.STOP)))
    corrupt[-1] ^= 0xFF
    stream = b"\x00\xaa\x12" + good[0] + bytes(corrupt) + b"\xaa" + good[1] + good[2]
    decoder = FrameDecoder()
    frames = []
    for i in range(0, len(stream), 3):  # arrives in small pieces
        frames += decoder.feed(stream[i : i + 3])
    assert [f.seq for f in frames] == [0, 1, 2]
    assert decoder.stats.crc_errors == 1
    assert decoder.stats.garbage_bytes >= 3


def test_decoder_rejects_oversize_length_and_resyncs() -> None:
    decoder = FrameDecoder()
    frames = decoder.feed(b"\xaa\x55\xff\x00" + encode_frame(Frame(seq=1, type=MsgType.HELLO)))
    assert [f.type for f in frames] == [MsgType.HELLO]
    assert decoder.stats.oversize == 1


def test_messages_round_trip() -> None:
    banner = Banner(1, 2, "floornav-fw 1.0.0")
    assert Banner.parse(banner.payload()) == banner
    assert Ack.parse(Ack(5, 0).payload()) == Ack(5, 0)
    t = Telemetry(123456, -5, 7, 200, -200, 30, 1, 2, 3, Telemetry.DEADMAN_TRIPPED)
    assert Telemetry.parse(t.payload()) == t and t.deadman_tripped
    assert len(encode_frame(Frame(0, MsgType.TELEMETRY, t.payload()))) <= MAX_FRAME


@pytest.mark.parametrize(
    "call",
    [
        lambda: drive_payload(300, 0),
        lambda: parse_drive(b"\x00"),
        lambda: encode_frame(Frame(seq=300, type=1)),
        lambda: encode_frame(Frame(seq=0, type=1, payload=bytes(33))),
        lambda: Ack.parse(b""),
        lambda: Telemetry.parse(b"\x00" * 3),
        lambda: Banner.parse(b"\x01"),
    ],
)
def test_bad_payloads_raise_protocol_error(call: object) -> None:
    with pytest.raises(ProtocolError):
        call()  # type: ignore[operator]
