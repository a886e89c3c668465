"""The telemetry, video and control sockets (TestClient: one event loop for all)."""

from __future__ import annotations

import json
import time
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession

from app.config import SafeZoneConfig
from app.web.video import heading_arrow_px, heading_for, render_overlay

from .conftest import AUTH
from .fakes import FakeService, drive_msg, floor_msg


def receive_frame(socket: WebSocketTestSession) -> tuple[dict[str, Any], np.ndarray]:
    header = socket.receive_json()
    assert header["type"] == "frame"
    jpeg = socket.receive_bytes()
    assert len(jpeg) == header["bytes"]
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "not a JPEG"
    return header, image


def test_video_sends_decodable_jpegs_with_times(client: TestClient, service: FakeService) -> None:
    client.portal.call(service.floors.publish, floor_msg(1))
    with client.websocket_connect("/ws/video") as socket:
        header, image = receive_frame(socket)
        assert header["seq"] == 1 and image.shape == (120, 160, 3)
        assert header["sent_s"] >= header["capture_s"]
        # capture_wall_s is the capture instant on the wall clock.
        assert abs(header["capture_wall_s"] - time.time()) < 5.0
        assert header["sent_wall_s"] >= header["capture_wall_s"]
        client.portal.call(service.floors.publish, floor_msg(2))
        assert receive_frame(socket)[0]["seq"] == 2


def test_video_is_newest_only(client: TestClient, service: FakeService) -> None:
    with client.websocket_connect("/ws/video") as socket:
        client.portal.call(service.floors.publish, floor_msg(1))
        assert receive_frame(socket)[0]["seq"] == 1

        def burst() -> None:  # ten results while the client is busy elsewhere
            for seq in range(2, 12):
                service.floors.publish(floor_msg(seq))

        client.portal.call(burst)
        header, _ = receive_frame(socket)
        assert header["seq"] == 11 and header["skipped"] == 9
        client.portal.call(service.floors.publish, floor_msg(12))
        assert receive_frame(socket)[0]["seq"] == 12  # nothing older was queued


def test_video_clients_share_one_encode(client: TestClient, service: FakeService) -> None:
    encoder = client.app.state.web.encoder  # type: ignore[attr-defined]
    with (
        client.websocket_connect("/ws/video") as first,
        client.websocket_connect("/ws/video") as second,
    ):
        client.portal.call(service.floors.publish, floor_msg(1))
        a, image_a = receive_frame(first)
        b, image_b = receive_frame(second)
        assert a["seq"] == b["seq"] == 1
        assert np.array_equal(image_a, image_b)
    assert encoder.encodes == 1


def test_overlay_draws_floor_zone_and_heading() -> None:
    floor = floor_msg(1, width=320, height=240)
    zone = SafeZoneConfig()
    plain = render_overlay(floor, zone, None)
    with_heading = render_overlay(floor, zone, 0.5)
    # Floor tinted: the floor rows changed, the wall rows (top) did not.
    assert np.array_equal(plain[:50], floor.image[:50])
    assert not np.array_equal(plain[200:], floor.image[200:])
    start, end = heading_arrow_px(320, 240, 0.5)
    assert end[0] < start[0] and end[1] < start[1]  # positive heading = to the left
    assert not np.array_equal(plain, with_heading)


def test_heading_shown_only_for_recent_autonomy() -> None:
    floor = floor_msg(1)
    assert heading_for(floor, drive_msg(0.3)) == 0.3
    assert heading_for(floor, None) is None
    assert heading_for(floor, drive_msg(None)) is None


def test_telemetry_streams_status(service: FakeService) -> None:
    from app.web import create_app

    from .conftest import TOKEN

    web = service.config.web.model_copy(update={"telemetry_hz": 30.0})
    service.config = service.config.model_copy(update={"web": web})
    with (
        TestClient(create_app(service, token=TOKEN, static_dir=None)) as client,
        client.websocket_connect("/ws/telemetry") as socket,
    ):
        first = socket.receive_text()
        assert "NaN" not in first
        message = json.loads(first)
        assert message["type"] == "status" and message["state"] == "idle"
        service.state = service.state.RUNNING
        states = {socket.receive_json()["state"] for _ in range(5)}
        assert "running" in states


def control_exchange(socket: WebSocketTestSession, message: dict[str, Any]) -> dict[str, Any]:
    socket.send_json(message)
    reply: dict[str, Any] = socket.receive_json()
    return reply


def test_control_socket_commands(client: TestClient, service: FakeService) -> None:
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        hello = socket.receive_json()
        driver = hello["driver"]
        reply = control_exchange(
            socket, {"type": "teleop", "v_m_s": 0.2, "omega_rad_s": -0.4, "id": 1}
        )
        assert reply == {"type": "ack", "detail": "teleop", "id": 1, "state": "teleop"}
        assert service.calls[-1] == ("teleop", driver, 0.2, -0.4, False)
        control_exchange(
            socket, {"type": "teleop", "v_m_s": 0, "omega_rad_s": 0, "take_over": True}
        )
        assert service.calls[-1][-1] is True
        assert control_exchange(socket, {"type": "release"})["type"] == "ack"
        assert service.calls[-1] == ("release_teleop", driver)
        assert control_exchange(socket, {"type": "estop"})["state"] == "estopped"
        assert control_exchange(socket, {"type": "estop_reset"})["was_estopped"] is True
        assert control_exchange(socket, {"type": "start"})["state"] == "running"
        assert control_exchange(socket, {"type": "stop"})["state"] == "idle"
    # Leaving releases this connection's teleop (and only its own).
    assert service.calls[-1] == ("release_teleop", driver)
    verbs = [c[0] for c in service.calls]
    assert verbs == [
        "teleop", "teleop", "release_teleop", "estop", "reset_estop", "start", "stop",
        "release_teleop",
    ]  # fmt: skip


def test_each_control_connection_is_its_own_driver(client: TestClient) -> None:
    with (
        client.websocket_connect("/ws/control", headers=dict(AUTH)) as first,
        client.websocket_connect("/ws/control", headers=dict(AUTH)) as second,
    ):
        assert first.receive_json()["driver"] != second.receive_json()["driver"]


@pytest.mark.parametrize(
    ("message", "named"),
    [
        ('{"type": "teleop", "v_m_s": NaN, "omega_rad_s": 0, "id": "a"}', "v_m_s"),
        ('{"type": "teleop", "v_m_s": 0.1, "omega_rad_s": 11}', "omega_rad_s"),
        ('{"type": "teleop", "v_m_s": 0.1}', "omega_rad_s"),
        ('{"type": "fly"}', "fly"),
        ('{"type": "stop", "extra": 1}', "extra"),
        ("[]", "object"),
        ("nonsense", "JSON"),
    ],
)
def test_control_errors_keep_the_connection(
    client: TestClient, service: FakeService, message: str, named: str
) -> None:
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        socket.receive_json()
        socket.send_text(message)
        reply = socket.receive_json()
        assert reply["type"] == "error" and named.lower() in reply["detail"].lower()
        if '"id": "a"' in message:
            assert reply["id"] == "a"
        socket.send_bytes(b"\x00")
        assert socket.receive_json()["type"] == "error"
        assert control_exchange(socket, {"type": "stop"})["type"] == "ack"
    assert [c[0] for c in service.calls] == ["stop", "release_teleop"]


def test_refused_control_commands_are_errors(client: TestClient, service: FakeService) -> None:
    service.refuse = {"teleop": "e-stop is latched: reset it first"}
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        socket.receive_json()
        reply = control_exchange(socket, {"type": "teleop", "v_m_s": 0.1, "omega_rad_s": 0})
        assert reply["type"] == "error" and reply["detail"] == "e-stop is latched: reset it first"


def test_video_ack_mode_holds_frames_until_acked(client: TestClient, service: FakeService) -> None:
    with client.websocket_connect("/ws/video?ack=1") as socket:
        client.portal.call(service.floors.publish, floor_msg(1))
        assert receive_frame(socket)[0]["seq"] == 1
        # Not acked yet: newer results are not sent, only the newest once acked.
        for seq in (2, 3, 4):
            client.portal.call(service.floors.publish, floor_msg(seq))
        socket.send_json({"type": "ack", "seq": 1})
        header, _ = receive_frame(socket)
        assert header["seq"] == 4 and header["skipped"] == 2
        socket.send_text("not json")  # ignored, no credit
        socket.send_json({"type": "ack", "seq": 4})
        client.portal.call(service.floors.publish, floor_msg(5))
        assert receive_frame(socket)[0]["seq"] == 5


@pytest.mark.parametrize("ack", ["x", "-1", "9"])
def test_video_ack_window_is_checked(client: TestClient, ack: str) -> None:
    from starlette.websockets import WebSocketDisconnect

    with (
        pytest.raises(WebSocketDisconnect) as closed,
        client.websocket_connect(f"/ws/video?ack={ack}"),
    ):
        pass
    assert closed.value.code == 1008
