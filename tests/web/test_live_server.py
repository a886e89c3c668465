"""Video over a real server (uvicorn in a thread) with real WebSocket clients: a slow
client gets fewer frames, and never holds up a fast one."""

from __future__ import annotations

import asyncio
import json
import statistics
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
from websockets.asyncio.client import ClientConnection, connect

from app.messages import FloorMsg
from app.web import create_app
from app.web.server import UVICORN_SETTINGS

from .conftest import TOKEN, serve_in_thread
from .fakes import FakeService, floor_msg

PUBLISH_HZ = 30.0
RUN_S = 3.0
SLOW_CLIENT_SLEEP_S = 0.3


@dataclass
class LiveServer:
    service: FakeService
    port: int
    loop: asyncio.AbstractEventLoop

    def publish(self, msg: FloorMsg) -> None:
        """Publish on the server's loop (slots are not thread-safe)."""
        self.loop.call_soon_threadsafe(self.service.floors.publish, msg)


@pytest.fixture
def live_server() -> Iterator[LiveServer]:
    service = FakeService()
    app = create_app(service, token=TOKEN, static_dir=None)
    served = serve_in_thread(app, **UVICORN_SETTINGS)  # as the daemon serves
    try:
        yield LiveServer(service, served.port, served.loop)
    finally:
        served.stop()


@dataclass
class ClientLog:
    frames: int = 0
    seqs: list[int] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    """Capture to fully received, from capture_wall_s (same machine: same clock)."""

    def summary(self) -> str:
        if not self.latencies_ms:
            return "0 frames"
        return (
            f"{self.frames} frames, latency capture->client median "
            f"{statistics.median(self.latencies_ms):.1f} ms, max {max(self.latencies_ms):.1f} ms"
        )


async def read_frames(
    socket: ClientConnection, log: ClientLog, until: float, *, sleep_s: float, ack: bool
) -> None:
    while time.monotonic() < until:
        try:
            header_text = await asyncio.wait_for(socket.recv(), timeout=until - time.monotonic())
            jpeg = await socket.recv()
        except TimeoutError:
            return
        header = json.loads(header_text)
        assert isinstance(jpeg, bytes) and len(jpeg) == header["bytes"]
        log.frames += 1
        log.seqs.append(header["seq"])
        log.latencies_ms.append((time.time() - header["capture_wall_s"]) * 1000)
        if sleep_s:
            await asyncio.sleep(sleep_s)  # a busy client: decoding, a slow tab
        if ack:
            await socket.send(json.dumps({"type": "ack", "seq": header["seq"]}))


@pytest.mark.slow
async def test_a_slow_video_client_does_not_delay_a_fast_one(live_server: LiveServer) -> None:
    images = [floor_msg(i, width=640, height=480) for i in range(4)]
    stop = threading.Event()

    def publisher() -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            template = images[seq % len(images)]
            live_server.publish(
                FloorMsg(seq, time.monotonic(), time.monotonic(), template.image,
                         template.floor_mask, "floornav", {}, 1.0)
            )  # fmt: skip
            time.sleep(1 / PUBLISH_HZ)

    url = f"ws://127.0.0.1:{live_server.port}/ws/video"
    fast, slow, slow_acked = ClientLog(), ClientLog(), ClientLog()
    thread = threading.Thread(target=publisher, daemon=True)
    thread.start()
    try:
        async with (
            # A short close timeout: the slow client's socket still holds unread frames.
            connect(url, close_timeout=0.5) as fast_socket,
            connect(url, close_timeout=0.5) as slow_socket,
            connect(url + "?ack=1", close_timeout=0.5) as acked_socket,
        ):
            until = time.monotonic() + RUN_S
            await asyncio.gather(
                read_frames(fast_socket, fast, until, sleep_s=0.0, ack=False),
                read_frames(slow_socket, slow, until, sleep_s=SLOW_CLIENT_SLEEP_S, ack=False),
                read_frames(acked_socket, slow_acked, until, sleep_s=SLOW_CLIENT_SLEEP_S, ack=True),
            )
            stop.set()
            published = live_server.service.floors.version
    finally:
        stop.set()
        thread.join()
    print(
        f"\n{published} frames published at {PUBLISH_HZ:g} Hz (640x480) in {RUN_S:g} s"
        f"\n  fast client:                      {fast.summary()}"
        f"\n  slow client (0.3 s/frame):        {slow.summary()}"
        f"\n  slow client (0.3 s/frame, ack=1): {slow_acked.summary()}"
    )
    assert fast.frames >= 3 * slow.frames > 0
    assert fast.frames >= 3 * slow_acked.frames > 0
    assert fast.seqs == sorted(fast.seqs) and slow_acked.seqs == sorted(slow_acked.seqs)
    # With acks the slow client skips to the newest frame each time.
    assert all(b - a > 1 for a, b in zip(slow_acked.seqs[1:], slow_acked.seqs[2:], strict=False))


async def test_video_is_sent_uncompressed_even_to_a_client_offering_deflate(
    live_server: LiveServer,
) -> None:
    """JPEG does not deflate: compressing every frame for every viewer only cost the
    event loop time. The client below offers permessage-deflate, as browsers do."""
    live_server.publish(floor_msg(1, width=64, height=48))
    url = f"ws://127.0.0.1:{live_server.port}/ws/video"
    async with connect(url, compression="deflate", close_timeout=0.5) as socket:
        assert socket.response is not None
        assert "Sec-WebSocket-Extensions" not in socket.response.headers
        header = json.loads(await asyncio.wait_for(socket.recv(), timeout=5))
        jpeg = await asyncio.wait_for(socket.recv(), timeout=5)
    assert isinstance(jpeg, bytes) and len(jpeg) == header["bytes"]
