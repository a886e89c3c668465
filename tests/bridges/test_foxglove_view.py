"""The Foxglove live view, seen by a real Foxglove WebSocket protocol client: the five
channels advertised with their schemas, one message of each decoded with the protobuf
descriptor the channel advertises, and nothing a client could use to change the robot."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import math
import socket
import struct
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

from app.bridges import bridge_services
from app.bridges.foxglove_view import (
    CAMERA_TOPIC,
    LOG_TOPIC,
    MAP_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    FoxgloveView,
    LogForwarder,
    grid_message,
    mount_from_config,
    mount_from_homography,
)
from app.channels import LatestSlot
from app.config import FloornavConfig, load_config
from app.control.kinematics import WheelOdometry
from app.devices import open_devices
from app.mapping.frames import GroundGrid, Pose2D
from app.messages import DriveMsg, FloorMsg, State, WorldMapMsg
from app.runtime import Runtime
from app.sim.setup import camera_model, sim_floor_calibration

from ..conftest import free_port

SUBPROTOCOL = "foxglove.sdk.v1"
"""What foxglove-sdk's server speaks (the older foxglove.websocket.v1 is refused)."""
SCHEMAS = {
    CAMERA_TOPIC: "foxglove.CompressedImage",
    MAP_TOPIC: "foxglove.Grid",
    TF_TOPIC: "foxglove.FrameTransforms",
    SCENE_TOPIC: "foxglove.SceneUpdate",
    LOG_TOPIC: "foxglove.Log",
}
MESSAGE_DATA = 0x01


# -- a Foxglove WebSocket protocol client ------------------------------------------------


def message_class(schema_name: str, schema_b64: str) -> type[Message]:
    """The protobuf class of an advertised channel, from its FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


class FoxgloveClient:
    """Connects, reads ``serverInfo`` and the ``advertise`` messages, subscribes, and
    decodes message-data frames (opcode 1: u8 opcode, u32 subscription id, u64 log
    time, payload; little-endian)."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.statuses: list[dict[str, Any]] = []
        self._classes: dict[int, type[Message]] = {}
        self._topics: dict[int, str] = {}

    @classmethod
    @contextlib.asynccontextmanager
    async def connect(cls, port: int) -> AsyncIterator[FoxgloveClient]:
        async with websockets.connect(
            f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
        ) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            client = cls(ws)
            await client._handshake(set(SCHEMAS))
            yield client

    async def _handshake(self, topics: set[str], timeout_s: float = 5.0) -> None:
        async with asyncio.timeout(timeout_s):
            while not self.server_info or not topics <= set(self.channels):
                self._handle_text(await self.ws.recv())

    def _handle_text(self, frame: str | bytes) -> None:
        assert isinstance(frame, str), "no binary frame before subscribing"
        message = json.loads(frame)
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            for channel in message["channels"]:
                self.channels[channel["topic"]] = channel
        elif message["op"] == "status":
            self.statuses.append(message)

    async def subscribe(self, topics: list[str]) -> None:
        subscriptions = []
        for sub_id, topic in enumerate(topics, start=1):
            channel = self.channels[topic]
            self._classes[sub_id] = message_class(channel["schemaName"], channel["schema"])
            self._topics[sub_id] = topic
            subscriptions.append({"id": sub_id, "channelId": channel["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    async def messages(self, timeout_s: float) -> AsyncIterator[tuple[str, int, Message]]:
        """(topic, log time ns, decoded message) until ``timeout_s`` passes."""
        async with asyncio.timeout(timeout_s):
            while True:
                frame = await self.ws.recv()
                if isinstance(frame, str):
                    self._handle_text(frame)
                    continue
                assert frame[0] == MESSAGE_DATA, f"unexpected opcode {frame[0]}"
                sub_id, log_time_ns = struct.unpack_from("<IQ", frame, 1)
                yield (
                    self._topics[sub_id],
                    log_time_ns,
                    self._classes[sub_id].FromString(frame[13:]),
                )

    async def first_of_each(self, topics: set[str], timeout_s: float) -> dict[str, Message]:
        got: dict[str, Message] = {}
        async for topic, log_time_ns, message in self.messages(timeout_s):
            assert abs(log_time_ns / 1e9 - time.time()) < 60.0, "log time is wall-clock ns"
            got.setdefault(topic, message)
            if topics <= set(got):
                return got
        raise AssertionError("unreachable")


@contextlib.asynccontextmanager
async def logging_meanwhile(text: str, period_s: float = 0.2) -> AsyncIterator[None]:
    """Log ``text`` now and every ``period_s`` until the block ends. The SDK drops what a
    channel logs before it has processed the client's subscribe (on its own thread), so
    one line logged right after subscribing may never reach /log on a busy machine."""

    async def repeat() -> None:
        while True:
            logging.getLogger("floornav.test").warning(text)
            await asyncio.sleep(period_s)

    task = asyncio.create_task(repeat())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def grid_cells(grid: Any) -> tuple[int, int, bytes]:
    """(columns, rows, data) of a decoded foxglove.Grid."""
    rows = len(grid.data) // grid.row_stride
    return grid.column_count, rows, grid.data


# -- fast tests: the pieces ------------------------------------------------------------


def test_the_view_is_off_by_default_and_registered_when_a_port_is_set() -> None:
    assert FloornavConfig().foxglove.port is None
    off = SimpleNamespace(config=load_config(None))
    assert not [s for s in bridge_services(off, "t" * 16) if isinstance(s, FoxgloveView)]  # type: ignore[arg-type]
    on = SimpleNamespace(config=load_config(None, foxglove={"port": 8765, "map_period_s": 2.0}))
    views = [s for s in bridge_services(on, "t" * 16) if isinstance(s, FoxgloveView)]  # type: ignore[arg-type]
    assert len(views) == 1
    assert (views[0].requested_port, views[0].host, views[0].map_period_s) == (
        8765,
        "127.0.0.1",
        2.0,
    )
    assert views[0].name == "foxglove"


def test_the_camera_mount_from_the_calibration_is_the_simulated_one() -> None:
    config = load_config(None)
    model = camera_model(config)
    calibration = sim_floor_calibration(model)
    cx, cy = model.principal_point_px
    K = np.array([[model.fx_px, 0.0, cx], [0.0, model.fy_px, cy], [0.0, 0.0, 1.0]])
    decomposed = mount_from_homography(calibration.H_image_from_ground, K)
    expected = mount_from_config(config)
    assert decomposed is not None
    np.testing.assert_allclose(decomposed.position_m, expected.position_m, atol=2e-3)
    np.testing.assert_allclose(decomposed.rotation_xyzw, expected.rotation_xyzw, atol=2e-3)
    # The optical axis (camera z) looks forward and down by the pitch, x to the right.
    x, y, z, w = expected.rotation_xyzw
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    pitch = config.sim.camera_pitch_rad
    np.testing.assert_allclose(R[:, 2], (math.cos(pitch), 0.0, -math.sin(pitch)), atol=1e-9)
    np.testing.assert_allclose(R[:, 0], (0.0, -1.0, 0.0), atol=1e-9)


def test_the_grid_is_the_map_in_the_world_frame() -> None:
    """An asymmetric map: every cell lands where its world position says."""
    grid = GroundGrid(x_max_m=1.0, y_max_m=0.5, cell_m=0.1, rows=6, cols=4)
    rng = np.random.default_rng(3)
    cells = rng.integers(-1, 2, size=grid.shape).astype(np.int8)
    snapshot = WorldMapMsg(1, 0.0, cells, grid, Pose2D(), None, None, "", 0)
    message = grid_message(snapshot, time.time())
    from foxglove.messages import Grid

    schema = Grid.get_schema()
    decoded = message_class(schema.name, base64.b64encode(schema.data).decode()).FromString(
        message.encode()
    )
    columns, rows, data = grid_cells(decoded)
    assert (columns, rows) == (grid.rows, grid.cols)  # columns along x, rows along y
    origin = (decoded.pose.position.x, decoded.pose.position.y)
    xs, ys = grid.cell_centers()
    occupancy = {-1: -1, 0: 0, 1: 100}
    for r in range(grid.rows):
        for c in range(grid.cols):
            i = math.floor((xs[r, c] - origin[0]) / decoded.cell_size.x)
            j = math.floor((ys[r, c] - origin[1]) / decoded.cell_size.y)
            byte = data[j * decoded.row_stride + i * decoded.cell_stride + 4]
            assert struct.unpack("b", bytes([byte]))[0] == occupancy[int(cells[r, c])]
    assert [f.name for f in decoded.fields] == ["red", "green", "blue", "alpha", "occupancy"]


def test_the_log_handler_never_waits_and_keeps_the_newest() -> None:
    handler = LogForwarder(maxlen=10)
    assert handler.lock is None  # nothing to wait for in the logging thread
    logger = logging.getLogger("test.foxglove.forwarder")
    logger.propagate = False
    logger.addHandler(handler)
    try:
        for i in range(25):
            logger.warning("line %d", i, extra={"event": "x", "n": i})
    finally:
        logger.removeHandler(handler)
    assert handler.dropped == 15
    entries = handler.take(100)
    assert [e.message.split("  [")[0] for e in entries] == [f"line {i}" for i in range(15, 25)]
    assert "n=24" in entries[-1].message


async def test_a_port_in_use_is_logged_and_the_view_just_ends(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        view = FoxgloveView(fake_source(), host="127.0.0.1", port=busy.getsockname()[1])
        with caplog.at_level(logging.ERROR, "floornav.foxglove"):
            await asyncio.wait_for(view.serve(), 5.0)  # returns, raises nothing
    assert "could not start" in caplog.text
    assert not view.serving


FORGING_CLIENT = """
import asyncio, json, sys
import websockets
from app.bridges.foxglove_view import route_sdk_logs
from app.logs import setup_logging
import foxglove

setup_logging("info")
route_sdk_logs()
server = foxglove.start_server(port=0, context=foxglove.Context(), capabilities=[])

async def main():
    url = f"ws://127.0.0.1:{server.port}"
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        await ws.recv()
        await ws.send(json.dumps({"op": "bogus\\n12:00:00.000 ERROR   FORGED"}))
        await asyncio.sleep(0.5)

asyncio.run(main())
server.stop()
"""


def test_what_a_client_sends_cannot_forge_a_log_line() -> None:
    """The SDK quotes an invalid message's text in its error; it reaches stderr only
    through the daemon's logging, which escapes the newline."""
    result = subprocess.run(
        [sys.executable, "-c", FORGING_CLIENT],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).resolve().parents[2],
        check=True,
    )
    assert "bogus\\n12:00:00.000 ERROR   FORGED" in result.stderr
    assert not [line for line in result.stderr.splitlines() if "FORGED" in line.split()[:3]]
    assert not [line for line in result.stderr.splitlines() if line.startswith("12:00:00.000")]


# -- a view on a fake daemon: fast, every topic ------------------------------------------


def fake_source() -> SimpleNamespace:
    """The snapshots a daemon exposes, built by hand (one frame, one map)."""
    config = load_config(None)
    calibration = sim_floor_calibration(camera_model(config))
    h, w = config.camera.height_px, config.camera.width_px
    image = np.full((h, w, 3), 90, np.uint8)
    mask = np.zeros((h, w), bool)
    mask[h // 2 :] = True
    floors: LatestSlot[FloorMsg] = LatestSlot("floors")
    floors.publish(FloorMsg(1, time.monotonic(), time.monotonic(), image, mask, "test", {}, 1.0))
    grid = GroundGrid(x_max_m=2.0, y_max_m=1.0, cell_m=0.05, rows=80, cols=40)
    cells = np.full(grid.shape, -1, np.int8)
    cells[40:, :] = 0
    world_maps: LatestSlot[WorldMapMsg] = LatestSlot("world_maps")
    world_maps.publish(
        WorldMapMsg(
            1, 0.0, cells, grid, Pose2D(), np.array([[0.0, 0.0], [1.0, 0.5]]), (1.0, 0.5), "", 1
        )
    )
    odometry = WheelOdometry(config.drive)
    return SimpleNamespace(
        config=config,
        state=State.IDLE,
        floors=floors,
        drives=LatestSlot[DriveMsg]("drives"),
        world_maps=world_maps,
        odometry=odometry,
        calibration=calibration,
    )


@contextlib.asynccontextmanager
async def serving(view: FoxgloveView) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(view.serve())
    try:
        deadline = time.monotonic() + 5.0
        while not view.serving:
            assert not task.done(), "the view ended before serving"
            assert time.monotonic() < deadline, "the view did not start"
            await asyncio.sleep(0.01)
        yield task
    finally:
        view.request_stop()
        await asyncio.wait_for(task, 5.0)


async def test_every_topic_decodes_and_the_view_stops_on_request() -> None:
    source = fake_source()
    view = FoxgloveView(source, host="127.0.0.1", port=0, image_period_s=0.05)
    async with serving(view) as task:
        port = view.port
        async with FoxgloveClient.connect(port) as client:
            await client.subscribe(list(SCHEMAS))
            async with logging_meanwhile("fake daemon says hi"):
                got = await client.first_of_each(set(SCHEMAS), timeout_s=10.0)
            image = cv2.imdecode(np.frombuffer(got[CAMERA_TOPIC].data, np.uint8), cv2.IMREAD_COLOR)
            assert image.shape == (480, 640, 3)
            assert (
                got[MAP_TOPIC].column_count,
                len(got[MAP_TOPIC].data) // got[MAP_TOPIC].row_stride,
            ) == (80, 40)
            scene_ids = {entity.id for entity in got[SCENE_TOPIC].entities}
            assert {"robot", "safe_zone", "frontier_goal", "frontier_path"} <= scene_ids
            view.request_stop()
            await asyncio.wait_for(task, 5.0)
            # The server is gone: the connection closes and the port is free again.
            with pytest.raises(websockets.ConnectionClosed):
                async with asyncio.timeout(5.0):
                    while True:
                        await client.ws.recv()
    # The port is free again once the SDK's own thread has closed its listener (stop()
    # only asks it to). SO_REUSEADDR, as every server sets it: the closed connection
    # may linger in TIME_WAIT on this port, but no listener may.
    deadline = time.monotonic() + 5.0
    while True:
        with socket.socket() as again:
            again.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                again.bind(("127.0.0.1", port))
                again.listen()
                break
            except OSError:
                assert time.monotonic() < deadline, f"port {port} still in use 5 s after stop"
        await asyncio.sleep(0.02)


# -- the view in a daemon on the simulator -------------------------------------------------


@contextlib.asynccontextmanager
async def daemon_with_view() -> AsyncIterator[tuple[Runtime, FoxgloveView, asyncio.Task[None]]]:
    """A Runtime on the simulator with the view ``bridge_services`` makes from
    ``[foxglove] port`` (exploring, so there is a goal and a path)."""
    config = load_config(
        None,
        perception={"method": "flood_fill", "fill_gaps_px": 15},
        runtime={"autostart": "always", "log_level": "info"},
        foxglove={"port": free_port()},
    )
    with open_devices(config) as devices:
        runtime = Runtime(config, devices)
        (view,) = [s for s in bridge_services(runtime, "t" * 16) if isinstance(s, FoxgloveView)]
        task = asyncio.create_task(runtime.run(install_signals=False, services=[view]))
        try:
            deadline = time.monotonic() + 25.0
            while (
                not view.serving
                or (snapshot := runtime.world_maps.peek()) is None
                or (
                    snapshot.free_cells < 200  # the robot has seen some floor
                )
            ):
                assert not task.done(), f"the daemon ended: {runtime.crash}"
                assert time.monotonic() < deadline, "no map or no view after 25 s"
                await asyncio.sleep(0.05)
            yield runtime, view, task
        finally:
            runtime.request_shutdown("test over")
            await asyncio.wait_for(task, 15.0)


@pytest.mark.sim
async def test_a_foxglove_client_sees_the_daemon_and_cannot_change_it() -> None:
    async with daemon_with_view() as (runtime, view, task):
        config = runtime.config
        async with FoxgloveClient.connect(view.port) as client:
            # Read-only: nothing a client could publish, set or call.
            capabilities = set(client.server_info["capabilities"])
            assert not capabilities & {"clientPublish", "parameters", "services"}
            assert not capabilities & {"parametersSubscribe", "connectionGraph", "assets"}
            for topic, schema in SCHEMAS.items():
                channel = client.channels[topic]
                assert (channel["schemaName"], channel["schemaEncoding"]) == (schema, "protobuf")
                assert channel["encoding"] == "protobuf"

            await client.subscribe(list(SCHEMAS))
            async with logging_meanwhile("hello foxglove"):
                got = await client.first_of_each(set(SCHEMAS), timeout_s=10.0)

            camera = got[CAMERA_TOPIC]
            assert (camera.format, camera.frame_id) == ("jpeg", "camera")
            image = cv2.imdecode(np.frombuffer(camera.data, np.uint8), cv2.IMREAD_COLOR)
            assert image.shape == (config.camera.height_px, config.camera.width_px, 3)

            grid = got[MAP_TOPIC]
            snapshot = runtime.world_maps.peek()
            assert snapshot is not None
            columns, rows, data = grid_cells(grid)
            assert (columns, rows) == (snapshot.grid.rows, snapshot.grid.cols)
            assert grid.frame_id == "world"
            assert math.isclose(grid.cell_size.x, config.mapping.grid_cell_m)
            assert math.isclose(
                grid.pose.position.x,
                snapshot.grid.x_max_m - snapshot.grid.rows * snapshot.grid.cell_m,
            )
            occupancy = np.frombuffer(data, np.int8)[4 :: grid.cell_stride]
            assert set(np.unique(occupancy)) <= {-1, 0, 100}
            assert (occupancy == 0).sum() >= 200  # the floor seen before we connected

            frames = [(t.parent_frame_id, t.child_frame_id) for t in got[TF_TOPIC].transforms]
            assert frames == [("world", "robot"), ("robot", "camera")]
            lens = got[TF_TOPIC].transforms[1].translation
            assert (lens.x, lens.y) == pytest.approx((config.camera.x_m, config.camera.y_m))
            assert lens.z == pytest.approx(config.sim.camera_height_m)

            scene_ids = {entity.id for entity in got[SCENE_TOPIC].entities}
            assert {"robot", "safe_zone"} <= scene_ids

            # The log channel carries the daemon's records (those from before anyone
            # subscribed were kept, up to LOG_BACKLOG_RECORDS; ours follows).
            logs = [got[LOG_TOPIC]]
            if "hello foxglove" not in logs[-1].message:
                async for topic, _, message in client.messages(10.0):
                    if topic == LOG_TOPIC:
                        logs.append(message)
                        if "hello foxglove" in message.message:
                            break
            assert logs[-1].name == "floornav.test"
            assert logs[-1].level == 3  # Warning

            # A client that tries to publish anyway (no clientPublish) changes nothing.
            state = runtime.state
            await client.ws.send(
                json.dumps(
                    {
                        "op": "advertise",
                        "channels": [
                            {"id": 1, "topic": "/cmd", "encoding": "json", "schemaName": "cmd"}
                        ],
                    }
                )
            )
            await client.ws.send(struct.pack("<BI", 1, 1) + b'{"cmd": "estop"}')
            await client.ws.send(
                json.dumps({"op": "setParameters", "parameters": [{"name": "x", "value": 1}]})
            )
            refused = ("clientPublish", "parameters")
            async for _ in client.messages(5.0):
                texts = " ".join(status["message"] for status in client.statuses)
                if all(f"does not support {what}" in texts for what in refused):
                    break
            assert runtime.state is state
            assert not runtime.mux.estopped

        # The view stops on request; the daemon drives on.
        view.request_stop()
        async with asyncio.timeout(5.0):
            while view.serving:
                await asyncio.sleep(0.02)
        await asyncio.sleep(0.5)
        assert not task.done()
        assert runtime.crash is None
