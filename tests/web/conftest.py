"""Fixtures: a fake service, the app around it and a TestClient sharing one event loop."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.config import FloornavConfig
from app.web import create_app
from app.web.server import PROJECT_STATIC

from .fakes import FakeService

TOKEN = "test-token-0123456789abcdef"
# Read-only: Starlette's TestClient writes the handshake's headers into a dict passed to
# websocket_connect, which would leak them into every later request using it.
AUTH: Mapping[str, str] = MappingProxyType({"Authorization": f"Bearer {TOKEN}"})


@pytest.fixture
def service(tmp_path: Path) -> FakeService:
    config = FloornavConfig().model_copy(
        update={
            "mapping": FloornavConfig().mapping.model_copy(
                update={"floor_calibration_file": str(tmp_path / "floor.json")}
            )
        }
    )
    return FakeService(config)


@pytest.fixture
def app(service: FakeService) -> FastAPI:
    return create_app(service, token=TOKEN, static_dir=None)


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    # The context manager keeps one event loop (portal) for all requests and sockets,
    # so slots published through ``client.portal`` wake the app's waiters.
    with TestClient(app) as test_client:
        yield test_client


@pytest.fixture
def dashboard(service: FakeService) -> TestClient:
    """The app as the daemon builds it: with the dashboard's files at ``/``."""
    return TestClient(create_app(service, token=TOKEN, static_dir=PROJECT_STATIC))


@dataclass(frozen=True)
class ServedApp:
    """An app served by uvicorn on a loopback port in its own thread and event loop."""

    port: int
    loop: asyncio.AbstractEventLoop
    stop: Callable[[], None]
    """Ends the server and its thread (blocks until they are gone)."""


def serve_in_thread(app: FastAPI, **config: object) -> ServedApp:
    """Serve ``app`` on a free loopback port; ``config`` goes to `uvicorn.Config`."""
    settings: dict[str, object] = {"log_level": "warning", "lifespan": "off", **config}
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, **settings))  # type: ignore[arg-type]
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(server.serve(),), daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)

    def stop() -> None:
        server.should_exit = True
        thread.join(timeout=10)
        assert not thread.is_alive(), "uvicorn did not stop"
        loop.close()

    return ServedApp(server.servers[0].sockets[0].getsockname()[1], loop, stop)
