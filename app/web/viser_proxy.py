"""Serve the viser view (its own server on a localhost port) under the API's ``/viser/``.

viser cannot be mounted inside FastAPI, so its page is fetched and its WebSocket relayed.
The viser client opens its WebSocket at the page's URL without the trailing slash
(``/viser/`` -> ``ws://host/viser``) and offers the subprotocol ``viser-v<version>``;
viser's server refuses connections without it, and browsers drop a connection whose
answer does not echo it, so the proxy passes it through both ways.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

import httpx
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.typing import Subprotocol

log = logging.getLogger("floornav.viser")

# Headers that describe the upstream connection, not the content.
_HOP_BY_HOP = {"connection", "keep-alive", "transfer-encoding", "content-length", "server", "date"}


def viser_router(viser_port: int | Callable[[], int], viser_host: str = "127.0.0.1") -> APIRouter:
    """Routes ``GET /viser/{path}`` and ``WebSocket /viser`` relayed to the viser server
    at ``viser_host:viser_port``. The port may be a callable, read at each request: the
    view binds (and reads back) its port only when the app starts."""
    router = APIRouter()

    def port() -> int:
        return viser_port() if callable(viser_port) else viser_port

    @router.get("/viser", include_in_schema=False)
    async def viser_page_redirect() -> RedirectResponse:
        # Relative asset and WebSocket URLs only work from the folder URL.
        return RedirectResponse("/viser/", status_code=307)

    @router.get("/viser/{path:path}", include_in_schema=False)
    async def viser_http(path: str, request: Request) -> Response:
        headers = {}
        if "accept-encoding" in request.headers:
            headers["Accept-Encoding"] = request.headers["accept-encoding"]
        url = f"http://{viser_host}:{port()}/{path}"
        try:
            async with httpx.AsyncClient(timeout=10.0) as client:
                upstream = await client.send(
                    client.build_request("GET", url, params=request.query_params, headers=headers),
                    stream=True,
                )
                # Raw bytes: a gzip body stays gzip, with its Content-Encoding header.
                body = b"".join([chunk async for chunk in upstream.aiter_raw()])
                await upstream.aclose()
        except httpx.HTTPError as exc:
            return Response(
                f"viser view unavailable: {exc}", status_code=502, media_type="text/plain"
            )
        passed = {k: v for k, v in upstream.headers.items() if k.lower() not in _HOP_BY_HOP}
        return Response(body, status_code=upstream.status_code, headers=passed)

    @router.websocket("/viser")
    async def viser_socket(websocket: WebSocket) -> None:
        offered = [str(p) for p in websocket.scope.get("subprotocols", [])]
        protocols = [Subprotocol(p) for p in offered if p.startswith("viser-v")]
        try:
            upstream = await connect(
                f"ws://{viser_host}:{port()}/",
                subprotocols=protocols or None,
                max_size=None,  # viser sends whole scenes and images in one message
                compression=None,
                open_timeout=5.0,
            )
        except (OSError, TimeoutError, WebSocketException) as exc:
            log.warning("viser upstream unreachable: %s", exc, extra={"event": "viser_proxy"})
            await websocket.close(code=1011, reason="viser view unavailable")
            return
        async with upstream:
            await websocket.accept(subprotocol=upstream.subprotocol)
            await _relay(websocket, upstream)

    return router


async def _relay(browser: WebSocket, upstream: ClientConnection) -> None:
    """Copy messages both ways until either side closes."""

    async def browser_to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            await upstream.send(data if data is not None else message.get("text") or "")

    async def viser_to_browser() -> None:
        async for data in upstream:
            if isinstance(data, bytes):
                await browser.send_bytes(data)
            else:
                await browser.send_text(data)

    tasks = [asyncio.create_task(browser_to_viser()), asyncio.create_task(viser_to_browser())]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            with contextlib.suppress(ConnectionClosed, WebSocketDisconnect, RuntimeError):
                task.result()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        with contextlib.suppress(RuntimeError):
            await browser.close()
