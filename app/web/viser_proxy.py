"""Serve the viser view (its own server on a localhost port) under the API's ``/viser/``.

viser cannot be mounted inside FastAPI, so its page is fetched and its WebSocket relayed.
The viser client opens its WebSocket at the page's URL without the trailing slash
(``/viser/`` -> ``ws://host/viser``) and offers the subprotocol ``viser-v<version>``;
viser's server refuses connections without it, and browsers drop a connection whose
answer does not echo it, so the proxy passes it through both ways.

The door: the 3D view shows the home the robot drives through, so its page and its
WebSocket always need credentials, whatever ``web.require_token_for_status`` says: the
session cookie (`app.web.session`; the dashboard sets it) or the bearer token
(``Authorization`` header, or the ``bearer.<token>`` subprotocol on the WebSocket).
Missing: HTTP 401. The WebSocket checks the Origin first (`app.web.auth.origin_allowed`;
a foreign one gets 403). The routes read the token and the allowed origins from the
app's `WebContext` (``app.state.web``), so they must be included by `create_app`.

What the browser sends to viser is checked message by message: viser's client sends one
msgpack map per binary message, ``{"type": <message class>, ...fields}``. Requests for a
public share link (``ShareUrlRequest``, which makes viser open a tunnel to
share.viser.studio, and ``ShareUrlDisconnect``) are dropped, and so is anything that is
not a well-formed viser message: what cannot be checked is not forwarded.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

import httpx
import viser.infra
from fastapi import APIRouter, Depends, HTTPException, Request, WebSocket, status
from fastapi.responses import JSONResponse, RedirectResponse, Response
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect, WebSocketState
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.typing import Subprotocol

from app.web.auth import origin_allowed, token_matches, websocket_token
from app.web.context import WebContext
from app.web.session import session_cookie_matches

log = logging.getLogger("floornav.viser")

# Headers that describe the upstream connection, not the content.
_HOP_BY_HOP = {"connection", "keep-alive", "transfer-encoding", "content-length", "server", "date"}

BLOCKED_MESSAGE_TYPES = frozenset({"ShareUrlRequest", "ShareUrlDisconnect"})
"""viser client->server messages about the public share link (a tunnel through
share.viser.studio); never forwarded."""

POLICY_VIOLATION = 1008
_NO_CREDENTIALS = (
    "the 3D view needs the session cookie (open it from the dashboard, which calls "
    "POST /api/session) or the bearer token"
)
# Close codes an endpoint may send (RFC 6455 7.4; 1005, 1006 and 1015 are not sent).
_SENDABLE_CLOSE_CODES = frozenset({1000, 1001, 1002, 1003, 1007, 1008, 1009, 1010, 1011})


def _context(connection: HTTPConnection) -> WebContext:
    ctx: WebContext = connection.app.state.web
    return ctx


async def require_view_credentials(request: Request) -> None:
    """Dependency of the proxied pages: the session cookie or the bearer header."""
    ctx = _context(request)
    if session_cookie_matches(request.cookies, ctx.token):
        return
    try:
        await ctx.auth.require(request)
    except HTTPException as exc:
        raise HTTPException(exc.status_code, _NO_CREDENTIALS, headers=exc.headers) from None


def _view_credentials_ok(websocket: WebSocket, token: str) -> bool:
    return session_cookie_matches(websocket.cookies, token) or token_matches(
        websocket_token(websocket), token
    )


async def _deny(websocket: WebSocket, status_code: int, detail: str) -> None:
    """Refuse the handshake with an HTTP answer (close 1008 where the server cannot)."""
    headers = {"WWW-Authenticate": "Bearer"} if status_code == 401 else None
    denial = JSONResponse({"detail": detail}, status_code=status_code, headers=headers)
    try:
        await websocket.send_denial_response(denial)
    except RuntimeError:  # the server cannot send HTTP responses on a WebSocket
        await websocket.close(code=POLICY_VIOLATION, reason=detail[:120])


def refusal(data: bytes | None) -> str | None:
    """Why a browser->viser message must not be forwarded, or None to forward it.

    The reason is fixed text or a known message class's name, never the client's input
    (it goes to the log)."""
    if data is None:
        return "a text message (viser's client sends msgpack only)"
    try:
        message = viser.infra.Message.deserialize(data)
    except Exception:  # msgpack, a missing or unknown "type", wrong fields
        return "not a well-formed viser message"
    name = type(message).__name__
    if name in BLOCKED_MESSAGE_TYPES:
        return f"{name} (share links and tunnels are disabled)"
    return None


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

    @router.get(
        "/viser/{path:path}",
        include_in_schema=False,
        dependencies=[Depends(require_view_credentials)],
    )
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
        ctx = _context(websocket)
        allowed = ctx.service.config.web.allowed_origins
        origin = websocket.headers.get("origin")
        if not origin_allowed(origin, websocket.headers.get("host"), allowed):
            await _deny(websocket, status.HTTP_403_FORBIDDEN, "origin not allowed")
            return
        if not _view_credentials_ok(websocket, ctx.token):
            await _deny(websocket, status.HTTP_401_UNAUTHORIZED, _NO_CREDENTIALS)
            return
        offered = [str(p) for p in websocket.scope.get("subprotocols", [])]
        # Only viser's own subprotocol goes upstream (never a bearer.<token>).
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


def _browser_close_code(upstream: ClientConnection) -> tuple[int, str]:
    """Pass viser's close on to the browser (a version mismatch says so), if sendable."""
    code = upstream.close_code
    if code is None:
        return 1011, "viser view failed"
    if code in _SENDABLE_CLOSE_CODES or 3000 <= code <= 4999:
        return code, upstream.close_reason or ""
    return 1011, "viser view closed"


async def _relay(browser: WebSocket, upstream: ClientConnection) -> None:
    """Copy messages both ways until either side closes; the browser's are checked
    (`refusal`) and dropped when they must not reach viser."""
    logged: set[str] = set()

    async def browser_to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            why = refusal(data)
            if why is None:
                assert data is not None
                await upstream.send(data)
            elif why not in logged:  # once per connection and reason
                logged.add(why)
                log.info(
                    "viser proxy: dropped a message from the browser: %s",
                    why,
                    extra={"event": "viser_proxy_dropped"},
                )

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
            # A closed tab or a stopped viser ends the relay; nothing to report.
            with contextlib.suppress(ConnectionClosed, WebSocketDisconnect):
                task.result()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        # Close the browser's side only while it is open: closing a socket the browser
        # already left raised WebSocketDisconnect out of the endpoint, and uvicorn logged
        # "Exception in ASGI application" for every closed 3D-view tab.
        if (
            browser.client_state == WebSocketState.CONNECTED
            and browser.application_state == WebSocketState.CONNECTED
        ):
            code, reason = _browser_close_code(upstream)
            with contextlib.suppress(WebSocketDisconnect, RuntimeError):
                await browser.close(code=code, reason=reason)
