"""Token sources, the token file, and the WebSocket Origin and token checks."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.config import FloornavConfig, WebConfig
from app.web.auth import TOKEN_ENV, TokenError, origin_allowed, resolve_token, token_matches

from .conftest import AUTH, TOKEN


def config_with(**web: object) -> FloornavConfig:
    return FloornavConfig(web=WebConfig.model_validate(web))


def test_token_file_is_created_0600_once_and_reused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    path = tmp_path / "conf" / "token"
    config = config_with(token_file=str(path))
    token, generated = resolve_token(config, tmp_path)
    assert generated and len(token) >= 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.read_text().strip() == token
    again, generated_again = resolve_token(config, tmp_path)
    assert (again, generated_again) == (token, False)
    assert sorted(p.name for p in path.parent.iterdir()) == ["token"]  # no temp left


def test_relative_token_file_lives_in_the_state_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    token, generated = resolve_token(config_with(token_file="token"), tmp_path)
    assert generated and (tmp_path / "token").read_text().strip() == token


def test_token_sources_in_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "token"
    path.write_text("from-the-file-0123456789\n")
    monkeypatch.setenv(TOKEN_ENV, "from-the-environment-0123")
    config = config_with(token="from-the-config-0123456", token_file=str(path))
    assert resolve_token(config, tmp_path) == ("from-the-environment-0123", False)
    monkeypatch.delenv(TOKEN_ENV)
    assert resolve_token(config, tmp_path) == ("from-the-config-0123456", False)
    assert resolve_token(config_with(token_file=str(path)), tmp_path) == (
        "from-the-file-0123456789",
        False,
    )


def test_malformed_tokens_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(TOKEN_ENV, "short")
    with pytest.raises(TokenError, match=TOKEN_ENV):
        resolve_token(config_with(), tmp_path)
    monkeypatch.delenv(TOKEN_ENV)
    empty = tmp_path / "empty"
    empty.write_text("\n")
    with pytest.raises(TokenError, match="empty"):
        resolve_token(config_with(token_file=str(empty)), tmp_path)
    with pytest.raises(ValueError, match="token"):
        config_with(token="has spaces in it, 0123456789")


def test_token_comparison() -> None:
    assert token_matches(TOKEN, TOKEN)
    assert not token_matches(None, TOKEN)
    assert not token_matches(TOKEN[:-1], TOKEN)
    assert not token_matches("ü" * 30, TOKEN)  # non-ASCII must not raise


@pytest.mark.parametrize(
    ("origin", "host", "allowed", "ok"),
    [
        (None, "robot:8080", [], True),  # scripts send no Origin
        ("http://robot:8080", "robot:8080", [], True),
        ("http://ROBOT:8080/", "robot:8080", [], True),
        ("http://robot", "robot:80", [], True),  # default port spelled out or not
        ("https://robot", "robot", [], True),
        ("http://robot:8081", "robot:8080", [], False),
        ("http://evil.example", "robot:8080", [], False),
        ("http://robot.evil.example:8080", "robot:8080", [], False),
        ("null", "robot:8080", [], False),  # sandboxed iframes, file:// pages
        ("http://laptop:5173", "robot:8080", ["http://laptop:5173"], True),
        ("http://robot:8080", None, [], False),
        ("http://robot:99999", "robot:8080", [], False),
    ],
)
def test_origin_rules(origin: str | None, host: str | None, allowed: list[str], ok: bool) -> None:
    assert origin_allowed(origin, host, allowed) is ok


@pytest.mark.parametrize("path", ["/ws/control", "/ws/video", "/ws/telemetry"])
def test_foreign_origins_are_closed_with_1008(client: TestClient, path: str) -> None:
    with (
        pytest.raises(WebSocketDisconnect) as closed,
        client.websocket_connect(path, headers={**AUTH, "origin": "http://evil.example"}),
    ):
        pass
    assert closed.value.code == 1008


def test_same_origin_and_listed_origins_are_accepted(client: TestClient) -> None:
    # TestClient's Host is "testserver".
    with client.websocket_connect("/ws/control", headers={**AUTH, "origin": "http://testserver"}):
        pass


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Authorization": "Bearer wrong-token-0123456789"},
        {"sec-websocket-protocol": "floornav, bearer.wrong-token-0123456789"},
        {"sec-websocket-protocol": "floornav"},
    ],
    ids=["none", "wrong-header", "wrong-subprotocol", "no-token-subprotocol"],
)
def test_control_socket_without_the_token_can_only_stop(
    client: TestClient, headers: dict[str, str]
) -> None:
    with client.websocket_connect("/ws/control", headers=headers) as socket:
        hello = socket.receive_json()
        assert hello["type"] == "hello" and hello["authenticated"] is False
        for message in (
            {"type": "start"},
            {"type": "estop_reset"},
            {"type": "teleop", "v_m_s": 0.1, "omega_rad_s": 0.0},
            {"type": "release"},
        ):
            socket.send_json(message)
            reply = socket.receive_json()
            assert reply["type"] == "error" and "token" in reply["detail"], message
        socket.send_json({"type": "stop", "id": 1})
        assert socket.receive_json()["type"] == "ack"
        socket.send_json({"type": "estop", "id": 2})
        reply = socket.receive_json()
        assert reply["type"] == "ack" and reply["state"] == "estopped"


def test_control_socket_token_by_subprotocol_or_header(client: TestClient) -> None:
    with client.websocket_connect(
        "/ws/control", subprotocols=["floornav", f"bearer.{TOKEN}"]
    ) as socket:
        # The server selects "floornav" and never echoes the token.
        assert socket.accepted_subprotocol == "floornav"
        assert socket.receive_json()["authenticated"] is True
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        assert socket.accepted_subprotocol is None
        assert socket.receive_json()["type"] == "hello"


def test_token_file_mode_survives_a_permissive_umask(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    old = os.umask(0)
    try:
        resolve_token(config_with(token_file=str(tmp_path / "token")), tmp_path)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "token").stat().st_mode) == 0o600
