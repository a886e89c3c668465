"""Request bodies over 1 MiB get 413 before anything reads them, token or not; smaller
ones reach the routes (and their token check) unchanged.

The ASGI-level tests call the app with a ``receive`` that counts what it hands out, so
"the body was not read" is asserted, not inferred from timing. The live-server tests
speak raw HTTP/1.1 to uvicorn: the 413 arrives although the body is never sent (or
never finished), which no server waiting for it could answer."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.web import create_app
from app.web.body_limit import MAX_REQUEST_BODY_BYTES, BodyLimitMiddleware

from .conftest import AUTH, TOKEN
from .fakes import FakeService

CHUNK_BYTES = 64 * 1024
OVERSIZED_BYTES = 2 * 1024 * 1024


class CountingBody:
    """An ASGI ``receive`` streaming ``total`` bytes in chunks, counting what it gave."""

    def __init__(self, total: int, chunk: int = CHUNK_BYTES, payload: bytes = b"") -> None:
        self.remaining = total
        self.chunk = chunk
        self.payload = payload
        self.calls = 0
        self.bytes_read = 0

    async def __call__(self) -> dict[str, Any]:
        self.calls += 1
        if self.payload:
            body, self.payload = self.payload, b""
            self.remaining = 0
        else:
            body = b"x" * min(self.chunk, self.remaining)
            self.remaining -= len(body)
        self.bytes_read += len(body)
        return {"type": "http.request", "body": body, "more_body": self.remaining > 0}


class Recorder:
    """An ASGI ``send`` keeping the response."""

    def __init__(self) -> None:
        self.status: int | None = None
        self.headers: dict[bytes, bytes] = {}
        self.body = b""

    async def __call__(self, message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            self.status = message["status"]
            self.headers = dict(message.get("headers", []))
        elif message["type"] == "http.response.body":
            self.body += message.get("body", b"")


def http_scope(path: str, headers: list[tuple[bytes, bytes]]) -> dict[str, Any]:
    return {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": [(b"host", b"testserver"), *headers],
        "client": ("127.0.0.1", 50000),
        "server": ("testserver", 80),
    }


async def test_declared_oversized_body_is_refused_unread(
    app: FastAPI, service: FakeService
) -> None:
    body = CountingBody(OVERSIZED_BYTES)
    response = Recorder()
    scope = http_scope("/api/estop", [(b"content-length", str(OVERSIZED_BYTES).encode())])
    start = time.perf_counter()
    await app(scope, body, response)
    elapsed_s = time.perf_counter() - start
    assert response.status == 413
    assert "larger than" in json.loads(response.body)["detail"]
    assert response.headers[b"connection"] == b"close"
    assert body.calls == 0, "the body was read before the 413"
    assert service.calls == []
    assert elapsed_s < 0.05, f"413 took {elapsed_s * 1e3:.1f} ms"


async def test_chunked_oversized_body_is_cut_off_at_the_limit(
    app: FastAPI, service: FakeService
) -> None:
    body = CountingBody(OVERSIZED_BYTES)
    response = Recorder()
    await app(http_scope("/api/estop", [(b"transfer-encoding", b"chunked")]), body, response)
    assert response.status == 413
    # Read only until one byte over the limit: the chunk that passed it, nothing after.
    assert MAX_REQUEST_BODY_BYTES < body.bytes_read <= MAX_REQUEST_BODY_BYTES + CHUNK_BYTES
    assert body.remaining > 0
    assert service.calls == []


async def test_chunked_body_within_the_limit_reaches_the_route(
    app: FastAPI, service: FakeService
) -> None:
    payload = json.dumps({"source": "chunked"}).encode()
    body = CountingBody(len(payload), payload=payload)
    response = Recorder()
    headers = [
        (b"transfer-encoding", b"chunked"),
        (b"content-type", b"application/json"),
        (b"authorization", AUTH["Authorization"].encode()),
    ]
    await app(http_scope("/api/estop", headers), body, response)
    assert response.status == 200, response.body
    assert service.calls and "chunked" in str(service.calls[-1])


def test_oversized_body_without_token_gets_413_not_401(client: TestClient) -> None:
    response = client.post(
        "/api/estop",
        content=b"{" + b" " * OVERSIZED_BYTES + b"}",
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 413
    assert response.json()["detail"].startswith("request body larger than")


def test_body_just_under_the_limit_still_meets_the_token_check(client: TestClient) -> None:
    small = json.dumps({"driver": "padded"}).encode()
    padded = small + b" " * (MAX_REQUEST_BODY_BYTES - 1 - len(small))  # valid JSON
    assert len(padded) == MAX_REQUEST_BODY_BYTES - 1
    response = client.post(
        "/api/teleop/release",
        content=padded,
        headers={"content-type": "application/json", "Authorization": "Bearer wrong-token-0123"},
    )
    assert response.status_code == 401


def test_normal_requests_still_work(client: TestClient, service: FakeService) -> None:
    assert client.get("/api/status").status_code == 200
    response = client.post("/api/estop", json={"source": "test"}, headers=AUTH)
    assert response.status_code == 200
    assert service.estopped


def test_websockets_pass_through(client: TestClient) -> None:
    with client.websocket_connect(
        "/ws/telemetry", subprotocols=["floornav", f"bearer.{TOKEN}"]
    ) as ws:
        assert isinstance(ws.receive_json(), dict)


def test_rejects_a_negative_limit(app: FastAPI) -> None:
    with pytest.raises(ValueError, match="max_body_bytes"):
        BodyLimitMiddleware(app, max_body_bytes=-1)


# -- over a real socket ---------------------------------------------------------------


@pytest.fixture
def live_port() -> Iterator[int]:
    app = create_app(FakeService(), token=TOKEN, static_dir=None)
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="off")
    )
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(server.serve(),), daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)
    try:
        yield int(server.servers[0].sockets[0].getsockname()[1])
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        loop.close()


def read_response(sock: socket.socket) -> tuple[int, bytes]:
    """Status and body of one HTTP/1.1 response with a Content-Length."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"connection closed before a response: {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    while len(body) < int(headers["content-length"]):
        chunk = sock.recv(65536)
        assert chunk, "connection closed inside the response body"
        body += chunk
    return int(lines[0].split()[1]), body


def test_live_server_answers_413_without_waiting_for_the_body(live_port: int) -> None:
    head = (
        "POST /api/estop HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        f"Content-Length: {OVERSIZED_BYTES}\r\n\r\n"
    ).encode()
    timings_ms = []
    for _ in range(3):
        with socket.create_connection(("127.0.0.1", live_port), timeout=5) as sock:
            start = time.perf_counter()
            sock.sendall(head)  # and not one byte of the body
            status, body = read_response(sock)
            timings_ms.append((time.perf_counter() - start) * 1e3)
        assert status == 413, body
    # Best of three: the answer cannot have waited for a body that was never sent, so
    # only scheduling noise separates it from the short-circuit's own cost.
    assert min(timings_ms) < 50, timings_ms


def test_live_server_cuts_off_a_chunked_body(live_port: int) -> None:
    head = (
        b"POST /api/estop HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n"
    )
    chunk = f"{CHUNK_BYTES:x}\r\n".encode() + b" " * CHUNK_BYTES + b"\r\n"
    chunks_past_limit = MAX_REQUEST_BODY_BYTES // CHUNK_BYTES + 1
    with socket.create_connection(("127.0.0.1", live_port), timeout=5) as sock:
        # Just past the limit, and never the last chunk: a server waiting for the whole
        # body would never answer.
        sock.sendall(head + chunk * chunks_past_limit)
        status, body = read_response(sock)
    assert status == 413, body
