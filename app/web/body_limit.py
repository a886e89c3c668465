"""A bound on request bodies, enforced before anything reads them.

FastAPI reads (and JSON-parses) a route's whole body before its dependencies run, the
token check included, so without a bound anyone who can reach the port could make the
daemon's event loop receive and parse any number of megabytes. `BodyLimitMiddleware`
answers 413 from the headers alone when ``Content-Length`` is too large (the body is
never read; a client that sent ``Expect: 100-continue`` never even sends it), and
counts a chunked body as it arrives, answering 413 as soon as it passes the bound.

Every route takes small JSON bodies (the largest, a point-pair calibration, is ~40 kB)
and calibration images come from the camera, not from uploads: one bound serves all.
"""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

MAX_REQUEST_BODY_BYTES = 1 << 20
"""1 MiB."""


class BodyLimitMiddleware:
    """Pure ASGI middleware: HTTP requests with a body over ``max_body_bytes`` get 413
    with ``{"detail": ...}`` and ``Connection: close``; WebSockets pass untouched
    (uvicorn's ``ws_max_size`` bounds their messages)."""

    def __init__(self, app: ASGIApp, max_body_bytes: int = MAX_REQUEST_BODY_BYTES) -> None:
        if max_body_bytes < 0:
            raise ValueError(f"max_body_bytes must be >= 0, got {max_body_bytes}")
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        content_length: bytes | None = None
        chunked = False
        for name, value in scope["headers"]:
            if name == b"content-length":
                content_length = value
            elif name == b"transfer-encoding":
                chunked = True
        if content_length is not None:
            # The server already refused a malformed Content-Length and never passes
            # more bytes than it declares, so the header alone decides.
            if content_length.strip().isdigit() and int(content_length) > self.max_body_bytes:
                await self._too_large(send)
                return
            await self.app(scope, receive, send)
            return
        if not chunked:  # no body at all
            await self.app(scope, receive, send)
            return
        # Chunked: read ahead up to the bound (at most max_body_bytes are held), then
        # hand the app the same messages; one byte over and the rest is never read.
        buffered: list[Message] = []
        received = 0
        while True:
            message = await receive()
            buffered.append(message)
            if message["type"] != "http.request":
                break  # the client went away: the app sees it as it would have
            received += len(message.get("body", b""))
            if received > self.max_body_bytes:
                await self._too_large(send)
                return
            if not message.get("more_body", False):
                break

        async def replay() -> Message:
            return buffered.pop(0) if buffered else await receive()

        await self.app(scope, replay, send)

    async def _too_large(self, send: Send) -> None:
        body = json.dumps(
            {"detail": f"request body larger than {self.max_body_bytes} bytes"}
        ).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    # The unread body would otherwise be parsed as the next request.
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
