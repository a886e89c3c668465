"""The operator surfaces as one service the runtime runs: uvicorn serving the API and
dashboard on the runtime's event loop, and the viser 3D view (own thread and port,
started from the app's lifespan, reached through the ``/viser`` proxy)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import uvicorn
from fastapi import APIRouter, FastAPI

from app import systemd
from app.runtime import Runtime
from app.web.app import create_app
from app.web.viser_proxy import viser_router
from app.web.viser_view import ViserView

log = logging.getLogger("floornav.web")

UVICORN_SETTINGS: dict[str, object] = {
    "log_level": "warning",
    # Through our handlers: one format, and client text in uvicorn's messages gets the
    # same control-character escaping.
    "log_config": None,
    "ws_max_size": 1 << 20,
    # The video frames are JPEG: deflating them gains nothing, and with five viewers it
    # took a fifth of the event loop's time (py-spy, scripts/measure_streaming.py).
    "ws_per_message_deflate": False,
}
"""What the daemon's uvicorn runs with, besides the app, address and lifespan."""

PROJECT_STATIC = Path(__file__).resolve().parents[2] / "static"


def static_dir() -> Path | None:
    """The dashboard's files: beside the source tree (a checkout), else ``./static``
    (the Docker image's working directory)."""
    for candidate in (PROJECT_STATIC, Path.cwd() / "static"):
        if (candidate / "index.html").is_file():
            return candidate
    return None


class _EmbeddedServer(uvicorn.Server):
    """uvicorn without its own signal handlers: the runtime owns SIGTERM/SIGINT (it must
    stop the motors first)."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


class WebService:
    """Build with the runtime and the API token; the runtime runs `serve` as a stage."""

    name = "web"

    def __init__(self, runtime: Runtime, *, token: str) -> None:
        config = runtime.config
        self.runtime = runtime
        self.view = ViserView(runtime, port=config.viser.port) if config.viser.enabled else None
        proxy: APIRouter | None = None
        if self.view is not None:
            view = self.view
            proxy = viser_router(lambda: view.port)
        self.app: FastAPI = create_app(
            runtime, token=token, static_dir=static_dir(), viser_router=proxy
        )
        self.app.router.lifespan_context = self._lifespan
        self.server = _EmbeddedServer(
            uvicorn.Config(
                self.app,
                host=config.web.host,
                port=config.web.port,
                lifespan="on",
                **UVICORN_SETTINGS,  # type: ignore[arg-type]
            )
        )

    @contextlib.asynccontextmanager
    async def _lifespan(self, app: FastAPI) -> AsyncIterator[None]:
        view_task: asyncio.Task[None] | None = None
        if self.view is not None:
            # viser serves from its own thread; bound to localhost, reached via /viser.
            await asyncio.to_thread(self.view.start)
            view_task = asyncio.create_task(self.view.run(), name="viser-view")
        web = self.runtime.config.web
        log.info(
            "dashboard and API on http://%s:%d/", web.host, web.port, extra={"event": "web_started"}
        )
        try:
            yield
        finally:
            if view_task is not None:
                view_task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await view_task
            if self.view is not None:
                await asyncio.to_thread(self.view.stop)

    @property
    def started(self) -> bool:
        return bool(self.server.started)

    async def serve(self) -> None:
        web = self.runtime.config.web
        ready = asyncio.create_task(self._notify_when_started())
        try:
            await self.server.serve()
        except SystemExit as exc:  # uvicorn exits when it cannot bind
            raise OSError(f"web server could not start on {web.host}:{web.port}") from exc
        finally:
            ready.cancel()
        if not self.server.started and not self.server.should_exit:
            raise OSError(f"web server could not start on {web.host}:{web.port}")

    async def _notify_when_started(self) -> None:
        while not self.server.started:
            await asyncio.sleep(0.05)
        systemd.notify("READY=1\nSTATUS=serving the dashboard and API")

    def request_stop(self) -> None:
        self.server.should_exit = True
