"""`UnoLink` against the simulated Uno over a real pty (pyserial-asyncio underneath), plus
a fake transport where a scripted device is simpler.

Timing figures are printed: run with ``-s`` to see them.
"""

from __future__ import annotations

import asyncio
import itertools
import statistics
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import ClassVar

import pytest

from app.hardware.interfaces import DeviceState
from app.hardware.protocol import (
    MAX_FRAME,
    PROTOCOL_VERSION,
    Ack,
    Banner,
    Frame,
    FrameDecoder,
    MsgType,
    ProtocolError,
    encode_frame,
)
from app.hardware.serial_link import (
    CommandTimeoutError,
    DeviceResetError,
    FirmwareMismatchError,
    HandshakeError,
    LinkSilentError,
    LinkUnavailableError,
    NotConnectedError,
    PortNotFoundError,
    PortOpenError,
    PySerialTransport,
    ReceivedTelemetry,
    UnoLink,
    UnoLinkConfig,
    resolve_port,
)
from app.sim.sim_uno import SimulatedUno


@pytest.fixture
def link_path(tmp_path: Path) -> Path:
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    return by_id / "usb-floornav-sim-if00"


@pytest.fixture
def uno(link_path: Path) -> Iterator[SimulatedUno]:
    with SimulatedUno(link_path=link_path) as sim:
        yield sim


@pytest.fixture
async def link(uno: SimulatedUno) -> AsyncIterator[UnoLink]:
    async with UnoLink(uno.port) as connected:
        assert connected.state is DeviceState.CONNECTED, connected.status()
        yield connected


async def eventually(predicate: Callable[[], object], timeout_s: float = 1.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.005)


# -- handshake --------------------------------------------------------------------------


async def test_handshake_stops_then_enables_telemetry(uno: SimulatedUno, link: UnoLink) -> None:
    assert link.banner is not None and link.banner.firmware == "floornav-sim 1.0.0"
    assert "floornav-sim" in link.status().detail
    types = [c.frame.type for c in uno.commands()]
    assert types[:3] == [MsgType.HELLO, MsgType.STOP, MsgType.SET_TELEMETRY]
    assert uno.telemetry_period_ms == link.config.telemetry_period_ms == 50
    await eventually(lambda: link.latest_telemetry(max_age_s=0.1) is not None)
    received = link.telemetry
    assert received is not None and received.age_s() < 0.1
    assert link.commanded == (0, 0)


async def test_wrong_protocol_version_fails_and_never_sends_motion(link_path: Path) -> None:
    with SimulatedUno(link_path=link_path, banner_protocol_version=2, firmware="old-fw 0.9") as uno:
        async with UnoLink(uno.port) as link:
            status = link.status()
            assert status.state is DeviceState.FAILED
            assert "protocol version 2" in status.detail and "old-fw 0.9" in status.detail
            assert isinstance(link.last_error, FirmwareMismatchError)
            with pytest.raises(NotConnectedError, match="failed"):
                await link.drive(100, 100)
            await asyncio.sleep(0.35)  # a few retries with backoff, each refused again
            assert link.stats.connect_attempts >= 2
            assert link.state is not DeviceState.CONNECTED
        # Nothing but HELLO ever reached the wrong firmware.
        assert uno.count(MsgType.HELLO) >= 2
        assert {c.frame.type for c in uno.commands()} == {MsgType.HELLO}
        assert uno.pwm == (0, 0)


async def test_no_banner_is_a_clear_handshake_error() -> None:
    class Mute:
        """A `ByteTransport` whose device never answers."""

        written: ClassVar[list[bytes]] = []

        async def open(self, port: str, *, baudrate: int) -> None:
            pass

        async def read(self, timeout_s: float | None) -> bytes:
            await asyncio.sleep(timeout_s if timeout_s is not None else 3600)
            return b""

        def write(self, data: bytes) -> None:
            self.written.append(data)

        async def close(self) -> None:
            pass

    config = UnoLinkConfig(handshake_timeout_s=0.12, hello_retry_s=0.05)
    link = UnoLink("fake://mute", config=config, transport_factory=Mute)
    status = await link.start()
    try:
        assert status.state is DeviceState.FAILED
        assert isinstance(link.last_error, HandshakeError)
        assert "no BANNER" in status.detail
        sent = [bytes(w[4:5]) for w in Mute.written]
        assert sent and set(sent) == {bytes([MsgType.HELLO])}  # HELLO retried, nothing else
    finally:
        await link.stop()
    assert link.state is DeviceState.DISCONNECTED


# -- commands ---------------------------------------------------------------------------


async def test_drive_ack_round_trip_median(uno: SimulatedUno, link: UnoLink) -> None:
    link.stats.rtt_s.clear()
    call_s: list[float] = []
    for i in range(300):
        pwm = (i % 200) - 100
        t0 = time.perf_counter()
        await link.drive(pwm, -pwm)
        call_s.append(time.perf_counter() - t0)
        assert link.commanded == (pwm, -pwm)
    assert uno.pwm == (pwm, -pwm)
    median_ms = link.stats.rtt_median_ms()
    p95_ms = link.stats.rtt_percentile_ms(95)
    call_median_ms = statistics.median(call_s) * 1000
    call_p95_ms = statistics.quantiles(call_s, n=20)[-1] * 1000
    print(
        f"\ncommand->ACK vs simulated Uno over a pty: median {median_ms:.3f} ms, "
        f"p95 {p95_ms:.3f} ms; drive() call median {call_median_ms:.3f} ms, "
        f"p95 {call_p95_ms:.3f} ms (n=300)"
    )
    assert median_ms is not None and median_ms <= 5.0
    assert call_median_ms <= 5.0
    assert link.stats.timeouts == 0


async def test_drive_rejects_out_of_range_pwm_locally(uno: SimulatedUno, link: UnoLink) -> None:
    with pytest.raises(ProtocolError):
        await link.drive(256, 0)
    assert uno.count(MsgType.DRIVE) == 0 and link.commanded == (0, 0)


async def test_heartbeat_keeps_motors_running_past_the_deadman(
    uno: SimulatedUno, link: UnoLink
) -> None:
    await link.drive(80, 80)
    await asyncio.sleep(0.7)
    assert uno.pwm == (80, 80)
    assert uno.deadman_trips == []
    drives = uno.commands(MsgType.DRIVE)
    assert len(drives) >= 6
    gaps = [b.time_s - a.time_s for a, b in itertools.pairwise(drives)]
    assert max(gaps) < 0.2
    pings_while_moving = [c for c in uno.commands(MsgType.PING) if c.time_s > drives[0].time_s]
    assert pings_while_moving == []
    await link.stop_motors()
    assert uno.pwm == (0, 0)
    await asyncio.sleep(0.25)  # stopped: PING keeps the link checked, no DRIVE
    assert uno.count(MsgType.DRIVE) == len(drives)
    assert uno.commands(MsgType.PING)


async def test_deadman_stops_the_motors_when_the_host_freezes(
    uno: SimulatedUno, link: UnoLink
) -> None:
    await link.drive(80, 80)
    await asyncio.sleep(0.15)
    time.sleep(0.45)  # the host's event loop hangs: no heartbeat goes out
    assert uno.pwm == (0, 0)
    assert len(uno.deadman_trips) == 1
    last_drive = uno.commands(MsgType.DRIVE)[-1]
    delay_s = uno.deadman_trips[0] - last_drive.time_s
    print(f"\nhost frozen: the simulated firmware stopped the motors {delay_s * 1000:.0f} ms after")
    assert 0.25 <= delay_s < 0.32
    await eventually(lambda: link.stats.deadman_trips_seen == 1)  # reported by telemetry


async def test_at_most_one_command_in_flight(link_path: Path) -> None:
    # Slow firmware: 3 ms per command, so a host that did not wait would pile them up.
    with SimulatedUno(link_path=link_path, ack_delay_s=0.003) as uno:
        async with UnoLink(uno.port) as link:

            async def hammer(k: int) -> None:
                for i in range(15):
                    await link.drive(k * 10 + i, -i)
                    if i % 5 == 0:
                        await link.ping()

            await asyncio.gather(*(hammer(k) for k in range(5)))
            await asyncio.sleep(0.15)  # and the heartbeat on top
            assert link.stats.timeouts == 0
        assert uno.count(MsgType.DRIVE) >= 75
        assert uno.max_outstanding_commands == 1
        assert uno.max_rx_backlog_bytes <= MAX_FRAME
        assert uno.rx_overruns == 0


async def test_garbage_and_bad_frames_from_the_device_are_counted_and_ignored(
    uno: SimulatedUno, link: UnoLink
) -> None:
    corrupt = bytearray(encode_frame(Frame(3, MsgType.ACK, bytes([3, 0]))))
    corrupt[5] ^= 0x01  # payload bit flip: CRC fails
    truncated = encode_frame(Frame(4, MsgType.TELEMETRY, bytes(25)))[:12]
    oversize = b"\xaa\x55\x40\x00\x82"
    stale_ack = encode_frame(Frame(0, MsgType.ACK, bytes([200, 0])))  # answers nothing
    bad_payload = encode_frame(Frame(0, MsgType.TELEMETRY, b"\x01\x02"))
    uno.send_garbage(b"hello world\x00\xff" + bytes(corrupt) + oversize + stale_ack)
    uno.send_garbage(bad_payload + truncated)
    timed_out = 0
    for _ in range(20):
        try:
            await link.drive(30, 30)  # meanwhile everything keeps working
        except CommandTimeoutError:
            timed_out += 1  # the truncated frame swallowed this command's ACK
    assert timed_out <= 1
    await asyncio.sleep(0.1)
    stats = link.stats
    print(f"\ncounted: {stats}")
    assert stats.garbage_bytes >= 13
    assert stats.crc_errors >= 2  # the corrupt frame, the truncated one (swallowed a frame)
    assert stats.oversize_frames == 1
    # The injected stale ACK, plus the late ACK of a command that timed out (unless the
    # truncated frame swallowed that ACK outright).
    assert 1 <= stats.stale_acks <= 1 + timed_out
    assert stats.malformed_frames == 1
    assert stats.timeouts <= 1  # the truncated frame may have eaten one ACK
    assert link.state is DeviceState.CONNECTED
    assert uno.pwm == (30, 30)


async def test_telemetry_callback_and_async_iterator(uno: SimulatedUno) -> None:
    seen: list[ReceivedTelemetry] = []
    async with UnoLink(uno.port, on_telemetry=seen.append) as link:
        await link.drive(100, 50)
        updates = link.telemetry_updates()
        first = await asyncio.wait_for(anext(updates), 0.5)
        second = await asyncio.wait_for(anext(updates), 0.5)
        await updates.aclose()
        assert second.data.uptime_ms > first.data.uptime_ms
        await eventually(lambda: seen and seen[-1].data.pwm_left == 100)
        assert seen[-1].data.encoder_left >= 0


async def test_stop_sends_stop_and_closes(uno: SimulatedUno) -> None:
    link = UnoLink(uno.port)
    await link.start()
    await link.drive(60, 60)
    await link.stop()
    assert link.state is DeviceState.DISCONNECTED
    assert uno.commands()[-1].frame.type == MsgType.STOP
    assert uno.pwm == (0, 0)
    with pytest.raises(NotConnectedError):
        await link.drive(60, 60)


# -- failures and reconnection ----------------------------------------------------------


async def test_pulled_cable_is_detected_and_zero_commanded_fast(
    uno: SimulatedUno, link: UnoLink
) -> None:
    await link.drive(100, 100)
    t0 = time.perf_counter()
    uno.unplug()
    await link.wait_state(DeviceState.FAILED, timeout_s=1.0)
    detect_ms = (time.perf_counter() - t0) * 1000
    print(f"\npulled cable: FAILED and zero commanded {detect_ms:.1f} ms after the unplug")
    assert detect_ms < 300
    assert link.commanded == (0, 0)
    assert "cable pulled" in link.status().detail
    with pytest.raises(NotConnectedError):
        await link.drive(100, 100)


async def test_replug_reconnects_fast_and_never_rearms_motion(
    uno: SimulatedUno, link: UnoLink
) -> None:
    await link.drive(120, 120)
    uno.unplug()
    await link.wait_state(DeviceState.FAILED, timeout_s=1.0)
    await asyncio.sleep(0.4)  # cable out for a while: retries find no port
    assert link.state is not DeviceState.CONNECTED
    drives_before = uno.count(MsgType.DRIVE)
    t0 = time.perf_counter()
    uno.replug()
    await link.wait_state(DeviceState.CONNECTED, timeout_s=1.0)
    reconnect_ms = (time.perf_counter() - t0) * 1000
    print(f"\nreplug: CONNECTED again {reconnect_ms:.1f} ms after the port came back")
    assert reconnect_ms < 1000
    assert link.stats.reconnects == 1
    await asyncio.sleep(0.35)  # heartbeats go out: PINGs only
    assert uno.pwm == (0, 0)
    assert link.commanded == (0, 0)
    assert uno.count(MsgType.DRIVE) == drives_before  # no DRIVE since the replug
    # Heartbeat PINGs keep the link alive (polled: on a loaded machine they may lag).
    deadline = time.monotonic() + 1.0
    while uno.count(MsgType.PING) < 2 and time.monotonic() < deadline:
        await asyncio.sleep(0.02)
    assert uno.count(MsgType.PING) >= 2
    assert uno.count(MsgType.DRIVE) == drives_before
    await link.drive(40, 40)  # a new command, made after the reconnect
    await asyncio.sleep(0.35)
    assert uno.pwm == (40, 40)


async def test_a_drive_racing_a_failure_is_not_replayed(uno: SimulatedUno, link: UnoLink) -> None:
    uno.go_silent()  # the ACK will never come; then the link fails on silence
    with pytest.raises((CommandTimeoutError, NotConnectedError)):
        await link.drive(90, 90)
    await link.wait_state(DeviceState.FAILED, timeout_s=1.0)
    uno.go_silent(False)
    await link.wait_state(DeviceState.CONNECTED, timeout_s=1.0)
    await asyncio.sleep(0.25)
    assert uno.pwm == (0, 0) and link.commanded == (0, 0)


async def test_silence_is_detected(uno: SimulatedUno, link: UnoLink) -> None:
    await link.drive(50, 50)
    t0 = time.perf_counter()
    awake0_s = link.stall_clock.awake_s()
    uno.go_silent()
    await link.wait_state(DeviceState.FAILED, timeout_s=1.0 + link.config.max_excused_stall_s)
    detect_ms = (time.perf_counter() - t0) * 1000
    # Silence is judged on the time the host could listen: stalls of this process or
    # of the kernel's tty layer (a loaded machine) are excused, and printed.
    awake_ms = (link.stall_clock.awake_s() - awake0_s) * 1000
    print(f"\nsilent device: FAILED {detect_ms:.0f} ms after it went quiet ({awake_ms:.0f} awake)")
    assert isinstance(link.last_error, LinkSilentError)
    assert 150 < awake_ms < 400
    assert link.commanded == (0, 0)
    uno.go_silent(False)  # it comes back on the same port
    await link.wait_state(DeviceState.CONNECTED, timeout_s=1.0)


async def test_silence_during_a_stall_of_the_kernel_tty_layer_is_excused_up_to_a_cap(
    uno: SimulatedUno,
) -> None:
    # The probe is off so that only this test's stall is on the clock: the kernel stops
    # delivering bytes (the device's and the probe's alike) and never starts again.
    config = UnoLinkConfig(max_excused_stall_s=0.6)
    async with UnoLink(uno.port, config=config, probe_kernel_tty=False) as link:
        assert link.state is DeviceState.CONNECTED, link.status()
        uno.go_silent()
        t0 = time.monotonic()
        link.stall_clock.begin_stall(t0)
        await asyncio.sleep(0.5)
        # Neither silence nor the heartbeat's missing ACKs have failed the link yet.
        assert link.state is DeviceState.CONNECTED, link.status()
        await link.wait_state(DeviceState.FAILED, timeout_s=2.0)
        failed_after_s = time.monotonic() - t0
        print(f"\nsilent through a kernel stall: FAILED after {failed_after_s * 1000:.0f} ms")
        assert failed_after_s >= 0.6 + 0.15  # the cap, then (most of) the silence timeout
        link.stall_clock.end_stall(time.monotonic())
        uno.go_silent(False)


async def test_device_reboot_is_detected_and_not_rearmed(uno: SimulatedUno, link: UnoLink) -> None:
    await link.drive(70, 70)
    uno.reset()  # boots with motors stopped and telemetry off
    await link.wait_state(DeviceState.FAILED, timeout_s=1.0)
    assert isinstance(link.last_error, DeviceResetError)
    await link.wait_state(DeviceState.CONNECTED, timeout_s=1.0)
    await asyncio.sleep(0.2)
    assert uno.pwm == (0, 0)


async def test_missing_port_fails_clearly_then_connects_when_it_appears(link_path: Path) -> None:
    link = UnoLink(link_path)
    status = await link.start()
    try:
        assert status.state is DeviceState.FAILED
        assert f"serial port {link_path} does not exist" in status.detail
        assert isinstance(link.last_error, PortNotFoundError)
        with pytest.raises(LinkUnavailableError, match="does not exist"):
            await link.wait_connected(timeout_s=0.3)
        with SimulatedUno(link_path=link_path) as uno:
            t0 = time.perf_counter()
            await link.wait_connected(timeout_s=1.0)
            print(f"\nport appeared: connected after {(time.perf_counter() - t0) * 1000:.1f} ms")
            await link.drive(10, 10)
            assert uno.pwm == (10, 10)
            await link.stop()
    finally:
        await link.stop()


def test_resolve_port_follows_symlinks_and_explains_failures(tmp_path: Path) -> None:
    with SimulatedUno(link_path=tmp_path / "uno") as uno:
        assert resolve_port(uno.port) == uno.pty_path
    dangling = tmp_path / "gone"
    dangling.symlink_to(tmp_path / "ttyACM9")
    with pytest.raises(PortNotFoundError, match=r"symlink to .*ttyACM9"):
        resolve_port(dangling)
    with pytest.raises(PortNotFoundError, match="does not exist"):
        resolve_port(tmp_path / "nothing")
    regular = tmp_path / "file"
    regular.write_text("")
    with pytest.raises(PortOpenError, match="not a serial device"):
        resolve_port(regular)
    assert resolve_port("socket://localhost:7777") == "socket://localhost:7777"


async def test_library_errors_become_our_errors() -> None:
    with pytest.raises(PortOpenError, match="/dev/null"):  # a char device but no tty
        await PySerialTransport().open("/dev/null", baudrate=115200)


def test_config_refuses_heartbeats_slower_than_the_deadman() -> None:
    with pytest.raises(ValueError, match="deadman"):
        UnoLinkConfig(heartbeat_period_s=0.3)
    with pytest.raises(ValueError, match="silence_timeout_s"):
        UnoLinkConfig(silence_timeout_s=0.05)


# -- a STOP never waits behind a command ------------------------------------------------


class HeldDriveAcks:
    """A `ByteTransport` with a scripted Uno that answers at once, except that it holds
    back the ACKs of DRIVE while `hold_drive_acks` is set: a lost or slow ACK on a noisy
    cable. It records every frame the host wrote, with ``time.monotonic()``."""

    instances: ClassVar[list[HeldDriveAcks]] = []

    def __init__(self) -> None:
        self.hold_drive_acks = False
        self.held: list[bytes] = []
        self.frames: list[tuple[float, Frame]] = []
        self._decoder = FrameDecoder()
        self._replies: asyncio.Queue[bytes] = asyncio.Queue()
        HeldDriveAcks.instances.append(self)

    async def open(self, port: str, *, baudrate: int) -> None:
        pass

    async def read(self, timeout_s: float | None) -> bytes:
        try:
            async with asyncio.timeout(timeout_s):
                return await self._replies.get()
        except TimeoutError:
            return b""

    def write(self, data: bytes) -> None:
        for frame in self._decoder.feed(data):
            self.frames.append((time.monotonic(), frame))
            if frame.type == MsgType.HELLO:
                banner = Banner(PROTOCOL_VERSION, 2, "held-acks 1.0")
                reply = encode_frame(Frame(frame.seq, MsgType.BANNER, banner.payload()))
            else:
                reply = encode_frame(Frame(frame.seq, MsgType.ACK, Ack(frame.seq, 0).payload()))
            if frame.type == MsgType.DRIVE and self.hold_drive_acks:
                self.held.append(reply)
            else:
                self._replies.put_nowait(reply)

    def release(self) -> None:
        for reply in self.held:
            self._replies.put_nowait(reply)
        self.held.clear()

    def sent(self) -> list[MsgType]:
        return [MsgType(frame.type) for _, frame in self.frames]

    async def close(self) -> None:
        pass


@pytest.fixture
async def held_link() -> AsyncIterator[tuple[UnoLink, HeldDriveAcks]]:
    HeldDriveAcks.instances.clear()
    # No telemetry (the scripted Uno sends none) and a long heartbeat: only the test's
    # own commands go out.
    config = UnoLinkConfig(
        telemetry_period_ms=0, heartbeat_period_s=0.15, silence_timeout_s=5.0, ack_timeout_s=0.09
    )
    link = UnoLink("fake://held", config=config, transport_factory=HeldDriveAcks)
    await link.start()
    try:
        assert link.state is DeviceState.CONNECTED, link.status()
        yield link, HeldDriveAcks.instances[-1]
    finally:
        await link.stop()


async def unacked_drive(link: UnoLink, device: HeldDriveAcks, pwm: int) -> asyncio.Task[None]:
    """A DRIVE written to the device, its ACK held back: the task still waits for it."""
    device.hold_drive_acks = True
    drive = asyncio.create_task(link.drive(pwm, pwm))
    # Loop turns, not wall time: the DRIVE's 90 ms ACK timeout must not run out first.
    for _ in range(100):
        if MsgType.DRIVE in device.sent():
            return drive
        await asyncio.sleep(0)
    raise AssertionError("the DRIVE was not written")


async def test_stop_goes_out_at_once_beside_a_drive_waiting_for_its_ack(
    held_link: tuple[UnoLink, HeldDriveAcks],
) -> None:
    link, device = held_link
    drive = await unacked_drive(link, device, 100)
    asked_s = time.monotonic()
    await link.stop_motors()  # written and ACKed while the DRIVE still waits for its ACK
    print(f"\nSTOP beside an unacked DRIVE: ACKed {(time.monotonic() - asked_s) * 1000:.1f} ms")
    assert not drive.done()
    assert link.stats.stops_ahead == 1
    device.release()
    await drive
    assert link.commanded == (0, 0)
    assert link.stats.stale_acks == 0 and link.stats.timeouts == 0


async def test_a_drive_queued_before_a_stop_is_never_sent_after_it(
    held_link: tuple[UnoLink, HeldDriveAcks],
) -> None:
    link, device = held_link
    first = await unacked_drive(link, device, 100)
    queued = asyncio.create_task(link.drive(120, 120))  # waits for the first one's ACK
    await asyncio.sleep(0)
    await link.stop_motors()
    device.release()
    await asyncio.gather(first, queued)
    await asyncio.sleep(0.2)  # a heartbeat, which must not re-send the old DRIVE either
    sent = device.sent()
    last_stop = len(sent) - 1 - sent[::-1].index(MsgType.STOP)
    assert MsgType.DRIVE not in sent[last_stop:], sent
    assert link.stats.drives_dropped == 1
    assert link.commanded == (0, 0)


async def test_a_drive_after_the_stop_is_sent(held_link: tuple[UnoLink, HeldDriveAcks]) -> None:
    link, device = held_link
    await link.stop_motors()
    await link.drive(50, 50)
    assert device.sent()[-1] is MsgType.DRIVE
    assert link.commanded == (50, 50)
    assert link.stats.drives_dropped == 0
