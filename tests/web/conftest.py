"""Fixtures: a fake service, the app around it and a TestClient sharing one event loop."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from types import MappingProxyType

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.config import FloornavConfig
from app.web import create_app

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
