"""The one door to the 3D view: the session cookie (``POST /api/session``), the ``/viser``
proxy's credential and Origin checks, the browser->viser message filter (no share
links), viser bound to localhost, and a closed tab leaving no traceback.

Real servers throughout: viser's own, uvicorn in a thread for the proxy, and a
``websockets`` client standing in for the browser.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
import pytest
import viser
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.typing import Origin, Subprotocol

from app.config import FloornavConfig, ViserConfig
from app.web import create_app
from app.web.session import COOKIE_NAME, session_cookie_matches, session_value
from app.web.viser_proxy import BLOCKED_MESSAGE_TYPES, refusal, viser_router
from app.web.viser_view import ViserView

from ..conftest import free_port
from .conftest import TOKEN, serve_in_thread
from .fakes import FakeService

VISER_PROTOCOL = f"viser-v{viser.__version__}"
CAMERA = {
    "type": "ViewerCameraMessage",
    "wxyz": (1.0, 0.0, 0.0, 0.0),
    "position": (0.0, 0.0, 3.0),
    "fov": 1.0,
    "near": 0.01,
    "far": 100.0,
    "image_height": 480,
    "image_width": 640,
    "look_at": (0.0, 0.0, 0.0),
    "up_direction": (0.0, 0.0, 1.0),
}


def bearer() -> dict[str, str]:
    """A fresh Authorization header (starlette's TestClient adds the handshake headers
    to the dict it is given, so the shared ``AUTH`` may carry a stale Sec-WebSocket-Key
    once a WebSocket test ran)."""
    return {"Authorization": f"Bearer {TOKEN}"}


def pack(message: object) -> bytes:
    """A message as viser's client sends it: one msgpack map with its "type"."""
    return msgspec.msgpack.encode(message)


def protected_service() -> FakeService:
    config = FloornavConfig()
    web = config.web.model_copy(update={"require_token_for_status": True})
    return FakeService(config.model_copy(update={"web": web}))


# -- a real viser server, and a spy standing in for one --------------------------------


@pytest.fixture(scope="module")
def viser_view() -> Iterator[ViserView]:
    """The daemon's view (share disabled) with a scene big enough to stream for a while."""
    view = ViserView(FakeService(), port=free_port())
    view.start()
    assert view.server is not None
    rng = np.random.default_rng(0)
    view.server.scene.add_point_cloud(
        "/cloud", rng.random((50_000, 3), dtype=np.float32), colors=(200, 0, 0)
    )
    try:
        yield view
    finally:
        view.stop()


@dataclass
class SpyViser:
    """A WebSocket server speaking viser's subprotocol that records what reaches it."""

    port: int
    received: list[bytes | str]
    connected: asyncio.Event
    server: Server | None = None


@contextlib.asynccontextmanager
async def spy_viser() -> AsyncIterator[SpyViser]:
    spy = SpyViser(0, [], asyncio.Event())

    async def handler(connection: ServerConnection) -> None:
        spy.connected.set()
        await connection.send(b"hello from viser")
        with contextlib.suppress(ConnectionClosed):
            async for message in connection:
                spy.received.append(message)

    async with serve(
        handler,
        "127.0.0.1",
        0,
        select_subprotocol=lambda _, offered: next(
            (Subprotocol(p) for p in offered if p.startswith("viser-v")), None
        ),
    ) as server:
        spy.port = next(iter(server.sockets)).getsockname()[1]
        spy.server = server
        yield spy


# -- the API (uvicorn in a thread) -----------------------------------------------------


@dataclass
class Api:
    port: int

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/viser"


def start_api(
    service: FakeService, viser_port: Callable[[], int]
) -> tuple[Api, Callable[[], None]]:
    """The app with the proxy, served by uvicorn in its own thread; returns the stopper."""
    app = create_app(service, token=TOKEN, static_dir=None, viser_router=viser_router(viser_port))
    # log_config=None: leave the test's logging alone (caplog sees uvicorn's records).
    served = serve_in_thread(app, log_config=None, log_level=None)
    return Api(served.port), served.stop


@contextlib.contextmanager
def running_api(service: FakeService, viser_port: Callable[[], int]) -> Iterator[Api]:
    api, stop = start_api(service, viser_port)
    try:
        yield api
    finally:
        stop()


@contextlib.asynccontextmanager
async def running_api_async(
    service: FakeService, viser_port: Callable[[], int]
) -> AsyncIterator[Api]:
    """`running_api` for tests whose own loop serves the upstream (the spy): stopping
    must not block that loop."""
    api, stop = await asyncio.to_thread(start_api, service, viser_port)
    try:
        yield api
    finally:
        await asyncio.to_thread(stop)


@contextlib.asynccontextmanager
async def tab_to_spy() -> AsyncIterator[tuple[SpyViser, ClientConnection]]:
    """A browser tab (with the token) on ``/viser``, relayed to the spy."""
    async with (
        spy_viser() as spy,
        running_api_async(FakeService(), lambda: spy.port) as api,
        connect(
            api.ws_url, subprotocols=[Subprotocol(VISER_PROTOCOL)], additional_headers=bearer()
        ) as socket,
    ):
        yield spy, socket


@pytest.fixture
def uvicorn_errors(caplog: pytest.LogCaptureFixture) -> Iterator[pytest.LogCaptureFixture]:
    """caplog, also attached to uvicorn's logger (an earlier uvicorn.Config in this
    process may have stopped it propagating)."""
    logger = logging.getLogger("uvicorn.error")
    logger.addHandler(caplog.handler)
    caplog.set_level(logging.INFO)
    try:
        yield caplog
    finally:
        logger.removeHandler(caplog.handler)


def assert_no_errors_logged(caplog: pytest.LogCaptureFixture) -> None:
    bad = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not bad, [r.getMessage() for r in bad]
    assert "Exception in ASGI application" not in caplog.text


# -- the session cookie ----------------------------------------------------------------


def test_post_session_sets_an_httponly_strict_browser_session_cookie(client: TestClient) -> None:
    response = client.post("/api/session", headers=bearer())
    assert response.status_code == 204
    assert response.content == b""
    cookie = response.headers["set-cookie"]
    value = session_value(TOKEN)
    assert cookie == f"{COOKIE_NAME}={value}; HttpOnly; SameSite=Strict; Path=/"
    assert TOKEN not in cookie  # an HMAC of the token, never the token
    assert len(value) == 64 and value != session_value(TOKEN + "x")


@pytest.mark.parametrize(
    "headers", [{}, {"Authorization": "Bearer wrong-token-0123456789"}], ids=["none", "wrong"]
)
def test_post_session_needs_the_bearer_token(client: TestClient, headers: dict[str, str]) -> None:
    response = client.post("/api/session", headers=headers)
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert "set-cookie" not in response.headers


def test_a_session_cookie_does_not_open_a_session(client: TestClient) -> None:
    client.cookies.set(COOKIE_NAME, session_value(TOKEN))
    assert client.post("/api/session").status_code == 401


def test_delete_session_expires_the_cookie(client: TestClient) -> None:
    response = client.delete("/api/session")  # no token needed
    assert response.status_code == 204
    cookie = response.headers["set-cookie"]
    assert cookie.startswith(f"{COOKIE_NAME}=;")
    for attribute in ("HttpOnly", "SameSite=Strict", "Path=/", "Max-Age=0"):
        assert attribute in cookie


def test_session_routes_are_documented(client: TestClient) -> None:
    operations = client.get("/openapi.json").json()["paths"]["/api/session"]
    assert operations["post"]["tags"] == ["auth"]
    assert {"204", "401"} <= set(operations["post"]["responses"])
    assert "204" in operations["delete"]["responses"]


def test_session_cookie_matches() -> None:
    assert session_cookie_matches({COOKIE_NAME: session_value(TOKEN)}, TOKEN)
    assert not session_cookie_matches({}, TOKEN)
    assert not session_cookie_matches({COOKIE_NAME: ""}, TOKEN)
    assert not session_cookie_matches({COOKIE_NAME: TOKEN}, TOKEN)  # the token is no cookie
    assert not session_cookie_matches({COOKIE_NAME: "ü" * 64}, TOKEN)  # must not raise


def test_cookie_opens_reads_but_never_writes_when_reads_need_the_token() -> None:
    service = protected_service()
    with TestClient(create_app(service, token=TOKEN, static_dir=None)) as client:
        for path in ("/api/status", "/api/config", "/api/map.json", "/api/map.png"):
            assert client.get(path).status_code == 401, path
        client.cookies.set(COOKIE_NAME, "0" * 64)
        assert client.get("/api/status").status_code == 401  # a wrong cookie
        client.cookies.clear()
        assert client.post("/api/session", headers=bearer()).status_code == 204
        assert client.cookies.get(COOKIE_NAME) == session_value(TOKEN)
        assert client.get("/api/status").status_code == 200
        assert client.get("/api/map.json").status_code == 200
        assert client.get("/api/map.png").status_code == 409  # no map yet, but let in
        assert client.get("/api/auth").status_code == 401  # the token check stays bearer
        assert client.post("/api/start").status_code == 401
        assert client.patch("/api/config", json={}).status_code == 401
        assert service.calls == []


def test_cookie_opens_the_read_sockets_but_not_control() -> None:
    service = protected_service()
    with TestClient(create_app(service, token=TOKEN, static_dir=None)) as client:
        with pytest.raises(WebSocketDenialResponse):
            client.websocket_connect("/ws/telemetry").__enter__()
        assert client.post("/api/session", headers=bearer()).status_code == 204
        with client.websocket_connect("/ws/telemetry") as socket:
            assert socket.receive_json()["type"] == "status"
        with client.websocket_connect("/ws/control") as socket:
            assert socket.receive_json()["authenticated"] is False  # stop and e-stop only


def test_map_is_open_when_reads_are(client: TestClient) -> None:
    assert client.get("/api/map.json").status_code == 200


# -- the /viser door -------------------------------------------------------------------


@pytest.fixture
def door(viser_view: ViserView) -> Iterator[TestClient]:
    """The app with the proxy to the real view; reads are open (the door is not)."""
    app = create_app(
        FakeService(),
        token=TOKEN,
        static_dir=None,
        viser_router=viser_router(lambda: viser_view.port),
    )
    with TestClient(app) as client:
        yield client


def test_viser_page_needs_the_cookie_or_the_token(door: TestClient) -> None:
    response = door.get("/viser/")
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert "/api/session" in response.json()["detail"]
    wrong = {"Authorization": "Bearer wrong-0123456789abc"}
    assert door.get("/viser/", headers=wrong).status_code == 401
    assert door.get("/viser/", headers=bearer()).status_code == 200
    door.cookies.set(COOKIE_NAME, "0" * 64)
    assert door.get("/viser/").status_code == 401


def test_the_session_cookie_opens_the_viser_page(door: TestClient) -> None:
    assert door.post("/api/session", headers=bearer()).status_code == 204
    page = door.get("/viser/")
    assert page.status_code == 200 and "<html" in page.text.lower()
    assert door.delete("/api/session").status_code == 204
    assert door.get("/viser/").status_code == 401


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Authorization": "Bearer wrong-token-0123456789"},
        {"cookie": f"{COOKIE_NAME}={'0' * 64}"},
        {"cookie": f"{COOKIE_NAME}={TOKEN}"},
    ],
    ids=["none", "wrong-bearer", "wrong-cookie", "token-as-cookie"],
)
def test_viser_socket_needs_credentials(door: TestClient, headers: dict[str, str]) -> None:
    with (
        pytest.raises(WebSocketDenialResponse) as denied,
        door.websocket_connect("/viser", headers=headers, subprotocols=[VISER_PROTOCOL]),
    ):
        pass
    assert denied.value.status_code == 401
    assert denied.value.headers["www-authenticate"] == "Bearer"


def test_viser_socket_refuses_a_foreign_origin_first(door: TestClient) -> None:
    with (
        pytest.raises(WebSocketDenialResponse) as denied,
        door.websocket_connect(
            "/viser",
            headers={**bearer(), "origin": "http://evil.example"},
            subprotocols=[VISER_PROTOCOL],
        ),
    ):
        pass
    assert denied.value.status_code == 403


@pytest.mark.parametrize("how", ["cookie", "bearer-header", "bearer-subprotocol"])
def test_viser_socket_with_credentials_reaches_viser(door: TestClient, how: str) -> None:
    headers = {"origin": "http://testserver"}
    protocols = [VISER_PROTOCOL]
    if how == "cookie":
        headers["cookie"] = f"{COOKIE_NAME}={session_value(TOKEN)}"
    elif how == "bearer-header":
        headers.update(bearer())
    else:
        protocols.append(f"bearer.{TOKEN}")
    with door.websocket_connect("/viser", headers=headers, subprotocols=protocols) as socket:
        assert socket.accepted_subprotocol == VISER_PROTOCOL  # never the token
        assert socket.receive_bytes()  # viser's first window of scene messages


def test_over_a_real_server_the_handshake_answers_401_and_403(viser_view: ViserView) -> None:
    async def status_of(api: Api, **kwargs: Any) -> int:
        with pytest.raises(InvalidStatus) as refused:
            async with connect(api.ws_url, subprotocols=[Subprotocol(VISER_PROTOCOL)], **kwargs):
                pass
        return refused.value.response.status_code

    async def main(api: Api) -> None:
        assert await status_of(api) == 401
        foreign = Origin("http://evil.example")
        assert await status_of(api, origin=foreign, additional_headers=bearer()) == 403
        cookie = {"cookie": f"{COOKIE_NAME}={session_value(TOKEN)}"}
        async with connect(
            api.ws_url, subprotocols=[Subprotocol(VISER_PROTOCOL)], additional_headers=cookie
        ) as socket:
            assert await asyncio.wait_for(socket.recv(), 10)

    with running_api(FakeService(), lambda: viser_view.port) as api:
        asyncio.run(main(api))


# -- what the browser may send to viser ------------------------------------------------


def test_refusal_rules() -> None:
    assert refusal(pack(CAMERA)) is None
    for name in BLOCKED_MESSAGE_TYPES:
        why = refusal(pack({"type": name}))
        assert why is not None and name in why
    assert refusal(None) is not None  # text
    assert refusal(b"\xc1 not msgpack") is not None
    assert refusal(pack({"no": "type"})) is not None
    assert refusal(pack({"type": "NoSuchMessage\n<script>"})) == "not a well-formed viser message"
    assert refusal(pack({"type": "ViewerCameraMessage"})) is not None  # fields missing
    assert refusal(pack([1, 2, 3])) is not None


def test_share_requests_never_reach_viser(uvicorn_errors: pytest.LogCaptureFixture) -> None:
    """Only well-formed, allowed messages pass; the spy (viser's side) sees exactly them."""
    allowed = [pack(CAMERA), pack({**CAMERA, "fov": 0.5})]

    async def main() -> None:
        async with tab_to_spy() as (spy, socket):
            assert socket.subprotocol == VISER_PROTOCOL
            assert await asyncio.wait_for(socket.recv(), 5) == b"hello from viser"
            await socket.send(pack({"type": "ShareUrlRequest"}))
            await socket.send(allowed[0])
            await socket.send(pack({"type": "ShareUrlDisconnect"}))
            await socket.send(b"\x00garbage")
            await socket.send('{"type": "ShareUrlRequest"}')
            await socket.send(pack({"type": "ShareUrlRequest"}))
            await socket.send(allowed[1])
            deadline = time.monotonic() + 5
            while len(spy.received) < 2 and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            await asyncio.sleep(0.2)  # anything else would have arrived by now
        assert spy.received == allowed

    asyncio.run(main())
    dropped = [r.getMessage() for r in uvicorn_errors.records if "dropped" in r.getMessage()]
    # Logged once per reason, with our words (never the client's bytes).
    assert len(dropped) == 4, dropped
    assert sum("ShareUrlRequest" in m for m in dropped) == 1
    assert not any("garbage" in m for m in dropped)
    assert_no_errors_logged(uvicorn_errors)


def test_viser_itself_opens_no_share_tunnel(
    viser_view: ViserView, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Even a ShareUrlRequest sent to viser directly (not through the proxy)."""
    import viser._viser

    tunnels: list[tuple[Any, ...]] = []
    monkeypatch.setattr(viser._viser, "ViserTunnel", lambda *args: tunnels.append(args))
    caplog.set_level(logging.INFO, logger="floornav.viser")

    async def main() -> None:
        url = f"ws://127.0.0.1:{viser_view.port}/"
        async with connect(url, subprotocols=[Subprotocol(VISER_PROTOCOL)], max_size=None) as ws:
            await ws.send(pack({"type": "ShareUrlRequest"}))
            deadline = time.monotonic() + 5
            while "share link refused" not in caplog.text and time.monotonic() < deadline:
                await asyncio.sleep(0.05)

    asyncio.run(main())
    assert "share link refused" in caplog.text
    assert tunnels == []
    assert viser_view.server is not None
    assert viser_view.server.request_share_url() is None


def test_viser_binds_localhost_only(viser_view: ViserView) -> None:
    assert inspect.signature(ViserView).parameters["host"].default == "127.0.0.1"
    assert viser_view.host == "127.0.0.1"
    assert viser_view.server is not None and viser_view.server.get_host() == "127.0.0.1"
    assert "host" not in ViserConfig.model_fields  # not configurable
    # The daemon's wiring passes no host (so the default holds).
    from app.web import server

    assert "host=" not in inspect.getsource(server.WebService.__init__).split("ViserView(")[1][:80]


# -- a closed 3D-view tab --------------------------------------------------------------


@pytest.mark.parametrize("how", ["close", "abort", "abort-while-streaming"])
def test_a_closed_tab_logs_no_traceback(
    viser_view: ViserView, uvicorn_errors: pytest.LogCaptureFixture, how: str
) -> None:
    async def tab(api: Api) -> None:
        socket: ClientConnection = await connect(
            api.ws_url,
            subprotocols=[Subprotocol(VISER_PROTOCOL)],
            additional_headers={"cookie": f"{COOKIE_NAME}={session_value(TOKEN)}"},
            max_size=None,
        )
        if how != "abort-while-streaming":
            await asyncio.wait_for(socket.recv(), 10)
        if how == "close":
            await socket.close()
        else:
            assert socket.transport is not None
            socket.transport.abort()  # the tab is gone: no close frame
        assert viser_view.server is not None
        deadline = time.monotonic() + 5
        while viser_view.server.get_clients() and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        assert not viser_view.server.get_clients()  # the relay closed viser's side too
        await asyncio.sleep(0.3)

    with running_api(FakeService(), lambda: viser_view.port) as api:
        asyncio.run(tab(api))
    assert_no_errors_logged(uvicorn_errors)


def test_viser_going_away_closes_the_browser_socket(
    uvicorn_errors: pytest.LogCaptureFixture,
) -> None:
    async def main() -> None:
        async with tab_to_spy() as (spy, socket):
            await asyncio.wait_for(socket.recv(), 5)
            await asyncio.wait_for(spy.connected.wait(), 5)
            assert spy.server is not None
            spy.server.close()  # viser stops: 1001 going away
            await spy.server.wait_closed()
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(socket.recv(), 5)
            assert socket.close_code in (1000, 1001)

    asyncio.run(main())
    assert_no_errors_logged(uvicorn_errors)
