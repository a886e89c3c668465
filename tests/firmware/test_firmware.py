"""The Uno firmware (firmware/floornav_uno) running in simavr, driven over its serial
port with the host's protocol code. Timings are wall-clock unless they say simulated."""

from __future__ import annotations

import itertools
import random
import statistics
import struct
import time
from collections.abc import Callable

import pytest

from app.hardware.protocol import (
    DEADMAN_MS,
    PROTOCOL_VERSION,
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

from .conftest import MotorEvent, SimUno

pytestmark = pytest.mark.firmware


def stopped(event: MotorEvent) -> bool:
    return event.left == 0 and event.right == 0


def driving(left: int, right: int) -> Callable[[MotorEvent], bool]:
    return lambda event: event.left == left and event.right == right


@pytest.mark.firmware
def test_boot_banner_names_protocol_and_firmware(uno: SimUno) -> None:
    assert uno.boot_banner is not None
    assert uno.boot_banner.type == MsgType.BANNER
    banner = Banner.parse(uno.boot_banner.payload)
    assert banner.protocol_version == PROTOCOL_VERSION == 1
    assert banner.motor_count == 2
    assert banner.firmware.startswith("floornav-fw ")


@pytest.mark.firmware
def test_hello_answers_with_banner(uno: SimUno) -> None:
    reply = uno.request(MsgType.HELLO)  # the BANNER echoes the HELLO's seq
    assert uno.boot_banner is not None
    assert Banner.parse(reply.payload) == Banner.parse(uno.boot_banner.payload)
    assert Banner.parse(reply.payload).protocol_version == 1


@pytest.mark.firmware
def test_drive_acks_and_sets_both_motors(uno: SimUno) -> None:
    for left, right in [(120, -80), (255, -255), (-1, 1), (0, 37)]:
        seen = len(uno.motor_events())
        ack = uno.ack(MsgType.DRIVE, drive_payload(left, right))
        assert ack.status == AckStatus.OK
        event = uno.wait_motor(driving(left, right), timeout=0.5, start=seen)
        assert event is not None, f"no MOTOR left={left} right={right}: {uno.motor_events()}"
    tele = uno.telemetry()
    assert (tele.pwm_left, tele.pwm_right) == (0, 37)
    assert tele.ms_since_command < DEADMAN_MS
    assert tele.flags == 0


@pytest.mark.firmware
def test_malformed_drive_is_refused_and_not_acted_on(uno: SimUno) -> None:
    for payload in [struct.pack("<hh", 300, 0), struct.pack("<hh", 0, -256), b"\x10\x00\x10"]:
        assert uno.ack(MsgType.DRIVE, payload).status == AckStatus.BAD_ARGUMENT
    assert uno.ack(MsgType.PING, b"\x00").status == AckStatus.BAD_ARGUMENT
    time.sleep(0.05)
    assert [(e.left, e.right) for e in uno.motor_events()] == [(0, 0)]
    tele = uno.telemetry()
    assert tele.ms_since_command == 0xFFFF  # never driven
    assert (tele.crc_errors, tele.garbage_bytes) == (0, 0)


@pytest.mark.firmware
def test_unknown_type_is_refused_and_counted(uno: SimUno) -> None:
    assert uno.ack(0x42, b"\x01\x02\x03").status == AckStatus.UNKNOWN_TYPE
    tele = uno.telemetry()
    assert tele.garbage_bytes == 7 + 3
    assert tele.crc_errors == 0


@pytest.mark.firmware
def test_deadman_stops_motors_250ms_after_last_drive(uno: SimUno) -> None:
    sent = time.monotonic()
    assert uno.ack(MsgType.DRIVE, drive_payload(200, 200)).status == AckStatus.OK
    go = uno.wait_motor(driving(200, 200), timeout=0.5)
    stop = uno.wait_motor(stopped, timeout=1.0, start=len(uno.motor_events()))
    assert go is not None
    assert stop is not None, "the deadman never stopped the motors"
    simulated = stop.t_ms - go.t_ms
    wall = stop.wall - sent
    print(f"\ndeadman: motors stopped {simulated:.1f} ms (simulated), {wall * 1000:.0f} ms (wall)")
    assert DEADMAN_MS - 2 <= simulated <= DEADMAN_MS + 5
    assert 0.150 <= wall <= 0.400
    tele = uno.telemetry()
    assert tele.flags & Telemetry.DEADMAN_TRIPPED
    assert not tele.flags & Telemetry.STOPPED
    assert tele.ms_since_command >= DEADMAN_MS
    assert (tele.pwm_left, tele.pwm_right) == (0, 0)


@pytest.mark.firmware
def test_each_drive_refreshes_the_deadman(uno: SimUno) -> None:
    last: MotorEvent | None = None
    for i in range(6):  # 0.6 s of driving, a DRIVE every 100 ms
        seen = len(uno.motor_events())
        assert uno.ack(MsgType.DRIVE, drive_payload(100 + i, 100)).status == AckStatus.OK
        last = uno.wait_motor(driving(100 + i, 100), timeout=0.5, start=seen)
        assert last is not None
        time.sleep(0.1)
    assert last is not None
    events = uno.motor_events()
    stop = uno.wait_motor(stopped, timeout=1.0, start=1)
    assert stop is not None
    assert stop.t_ms - last.t_ms == pytest.approx(DEADMAN_MS, abs=5)
    assert all(not stopped(e) for e in events[1:]), "stopped while DRIVEs kept coming"


@pytest.mark.firmware
def test_ping_and_hello_do_not_refresh_the_deadman(uno: SimUno) -> None:
    assert uno.ack(MsgType.DRIVE, drive_payload(-90, 90)).status == AckStatus.OK
    go = uno.wait_motor(driving(-90, 90), timeout=0.5)
    assert go is not None
    deadline = time.monotonic() + 0.5
    while time.monotonic() < deadline:  # keep the link busy past the deadman
        assert uno.ack(MsgType.PING).status == AckStatus.OK
        uno.request(MsgType.HELLO)
        time.sleep(0.03)
    stop = uno.wait_motor(stopped, timeout=0.1, start=1)
    assert stop is not None, "PING/HELLO kept the motors running"
    assert stop.t_ms - go.t_ms == pytest.approx(DEADMAN_MS, abs=5)


@pytest.mark.firmware
def test_stop_stops_at_once(uno: SimUno) -> None:
    assert uno.ack(MsgType.DRIVE, drive_payload(150, 150)).status == AckStatus.OK
    go = uno.wait_motor(driving(150, 150), timeout=0.5)
    assert go is not None
    time.sleep(0.05)
    sent = time.monotonic()
    assert uno.ack(MsgType.STOP).status == AckStatus.OK
    stop = uno.wait_motor(stopped, timeout=0.5, start=1)
    assert stop is not None
    assert stop.wall - sent < 0.050
    assert stop.t_ms - go.t_ms < DEADMAN_MS - 100
    tele = uno.telemetry()
    assert tele.flags == Telemetry.STOPPED


@pytest.mark.firmware
def test_crc_failures_and_garbage_are_counted_never_acted_on(uno: SimUno) -> None:
    good = encode_frame(Frame(50, MsgType.DRIVE, drive_payload(222, 222)))
    bad_crc = good[:-1] + bytes([good[-1] ^ 0x01])
    bad_payload = good[:6] + bytes([good[6] ^ 0x40]) + good[7:]
    garbage = b"\x00hello\x55\xaa\x01"
    oversize = b"\xaa\x55\x21\x01\x02"  # len 33: not a frame (2 garbage bytes + 3 more)
    uno.write(bad_crc)
    uno.write(bad_payload)
    uno.write(garbage)
    uno.write(oversize)
    time.sleep(0.05)
    assert uno.ack(MsgType.PING).status == AckStatus.OK  # resynchronised
    assert [f for f in uno.backlog if f.type == MsgType.ACK] == []  # nothing else answered
    assert [(e.left, e.right) for e in uno.motor_events()] == [(0, 0)]
    expected = FrameDecoder()
    expected.feed(bad_crc + bad_payload + garbage + oversize)
    tele = uno.telemetry()
    assert tele.crc_errors == expected.stats.crc_errors == 2
    # After a CRC failure the rest of that frame is hunted through as garbage, like the host.
    assert tele.garbage_bytes == expected.stats.garbage_bytes > len(garbage) + 2
    assert tele.ms_since_command == 0xFFFF


@pytest.mark.firmware
def test_garbled_stream_matches_the_host_decoder(uno: SimUno) -> None:
    """A seeded mix of good DRIVEs, corrupted and truncated frames and noise: the firmware
    acts on exactly the frames the host's FrameDecoder accepts and counts the same."""
    rng = random.Random(7)
    stream = bytearray()
    good_seqs = []
    for seq in range(1, 61):
        good = encode_frame(Frame(seq, MsgType.DRIVE, drive_payload(seq, -seq)))
        bad = bytearray(encode_frame(Frame(seq, MsgType.DRIVE, drive_payload(200, 200))))
        kind = rng.choice(["good", "good", "crc", "payload", "truncated", "noise", "oversize"])
        if kind == "good":
            stream += good
            good_seqs.append(seq)
        elif kind == "crc":
            bad[-2] ^= 0xFF
            stream += bad
        elif kind == "payload":
            bad[rng.randrange(3, len(bad) - 2)] ^= 1 << rng.randrange(8)
            stream += bad
        elif kind == "truncated":
            stream += bad[: rng.randrange(1, len(bad) - 1)]
        elif kind == "noise":
            stream += bytes(rng.choice([0xAA, 0x55, rng.randrange(256)]) for _ in range(9))
        else:
            stream += b"\xaa\x55" + bytes([rng.randrange(33, 256)])
    stream += encode_frame(Frame(99, MsgType.DRIVE, drive_payload(5, 5)))  # flushes both
    expected = FrameDecoder()
    expected_seqs = [f.seq for f in expected.feed(bytes(stream))]
    assert expected_seqs[-1] == 99

    for i in range(0, len(stream), 16):  # ~4 kB/s: well below what overruns the Uno
        uno.write(bytes(stream[i : i + 16]))
        time.sleep(0.004)
    frames = uno.collect(0.1)
    acked = [Ack.parse(f.payload).acked_seq for f in frames if f.type == MsgType.ACK]
    assert acked == expected_seqs
    assert set(good_seqs) <= set(acked)
    assert all(e.left != 200 for e in uno.motor_events()), "acted on a corrupted frame"
    tele = uno.telemetry()
    assert tele.crc_errors == expected.stats.crc_errors > 0
    assert tele.garbage_bytes == expected.stats.garbage_bytes > 0
    assert tele.rx_overruns == 0


@pytest.mark.firmware
def test_receive_buffer_overrun_is_survived_and_counted(uno: SimUno) -> None:
    # 40 HELLOs in one write: each 7-byte HELLO asks for a 26-byte BANNER, so the Uno
    # blocks on its transmit buffer while the 64-byte receive buffer overflows.
    uno.write(b"".join(encode_frame(Frame(i, MsgType.HELLO)) for i in range(40)))
    banners = [f for f in uno.collect(0.6) if f.type == MsgType.BANNER]
    assert 0 < len(banners) < 40  # some were lost in the overflow
    assert uno.ack(MsgType.PING).status == AckStatus.OK
    assert uno.ack(MsgType.DRIVE, drive_payload(60, 60)).status == AckStatus.OK
    assert uno.wait_motor(driving(60, 60), timeout=0.5) is not None
    tele = uno.telemetry()
    print(f"\noverrun burst: {len(banners)}/40 banners, telemetry {tele}")
    assert tele.rx_overruns > 0
    assert uno.ack(MsgType.STOP).status == AckStatus.OK


@pytest.mark.firmware
def test_encoders_count_quadrature_pulses(uno: SimUno) -> None:
    uno.set_encoders(400, -200)
    assert uno.ack(MsgType.SET_TELEMETRY, telemetry_period_payload(100)).status == 0
    samples = []
    while len(samples) < 5:
        frame = uno.recv(lambda f: f.type == MsgType.TELEMETRY, timeout=1.0)
        assert frame is not None
        samples.append(Telemetry.parse(frame.payload))
    first, last = samples[1], samples[-1]  # skip the one the encoders started within
    seconds = (last.uptime_ms - first.uptime_ms) / 1000
    assert (last.encoder_left - first.encoder_left) / seconds == pytest.approx(400, rel=0.05)
    assert (last.encoder_right - first.encoder_right) / seconds == pytest.approx(-200, rel=0.05)


@pytest.mark.firmware
def test_reset_counters_zeroes_encoders_and_error_counters(uno: SimUno) -> None:
    uno.set_encoders(1000, 1000)
    time.sleep(0.1)
    uno.set_encoders(0, 0)
    noise = b"\x01\x02\x03" + encode_frame(Frame(1, MsgType.PING))[:-1] + b"\x00"
    uno.write(noise)
    time.sleep(0.05)
    expected = FrameDecoder()
    expected.feed(noise)
    before = uno.telemetry()
    assert before.encoder_left > 0 and before.encoder_right > 0
    assert before.crc_errors == expected.stats.crc_errors == 1
    assert before.garbage_bytes == expected.stats.garbage_bytes > 0
    assert uno.ack(MsgType.RESET_COUNTERS).status == AckStatus.OK
    after = uno.telemetry()
    assert (after.encoder_left, after.encoder_right) == (0, 0)
    assert (after.crc_errors, after.garbage_bytes, after.rx_overruns) == (0, 0, 0)
    assert after.uptime_ms > before.uptime_ms


@pytest.mark.firmware
def test_set_telemetry_sends_at_the_period(uno: SimUno) -> None:
    for bad in [b"\x0a\x00", b"\xe9\x03", b"\x32"]:  # 10 ms, 1001 ms, short payload
        assert uno.ack(MsgType.SET_TELEMETRY, bad).status == AckStatus.BAD_ARGUMENT
    assert uno.collect(0.1) == []  # still off

    assert uno.ack(MsgType.SET_TELEMETRY, telemetry_period_payload(50)).status == 0
    frames = []
    while len(frames) < 9:
        frame = uno.recv(lambda f: f.type == MsgType.TELEMETRY, timeout=0.5)
        assert frame is not None
        frames.append((time.monotonic(), Telemetry.parse(frame.payload)))
    uptimes = [t.uptime_ms for _, t in frames]
    steps = [b - a for a, b in itertools.pairwise(uptimes)]
    walls = [b[0] - a[0] for a, b in itertools.pairwise(frames)]
    print(f"\ntelemetry steps (simulated ms) {steps}, wall median {statistics.median(walls):.3f} s")
    assert all(49 <= step <= 52 for step in steps)
    assert statistics.mean(steps) == pytest.approx(50, abs=0.5)
    assert statistics.median(walls) == pytest.approx(0.050, abs=0.015)

    assert uno.ack(MsgType.SET_TELEMETRY, telemetry_period_payload(0)).status == 0
    uno.backlog.clear()
    assert [f for f in uno.collect(0.2) if f.type == MsgType.TELEMETRY] == []


@pytest.mark.firmware
def test_command_round_trip(uno: SimUno) -> None:
    times = []
    for i in range(60):
        start = time.perf_counter()
        ack = uno.ack(MsgType.DRIVE, drive_payload(i, -i))
        times.append(time.perf_counter() - start)
        assert ack.status == AckStatus.OK
    assert uno.ack(MsgType.STOP).status == AckStatus.OK
    times.sort()
    median = statistics.median(times) * 1000
    p95 = times[int(0.95 * (len(times) - 1))] * 1000
    print(f"\nDRIVE -> ACK round trip: median {median:.2f} ms, p95 {p95:.2f} ms")
    assert median <= 20
