"""The session cookie: what lets a browser page that cannot set headers (the 3D view's
page and its WebSocket, ``<img src="/api/map.png">``) prove it belongs to the operator.

The dashboard, once it has the bearer token, calls ``POST /api/session`` with
``Authorization: Bearer <token>``; the answer (204) sets

    floornav_session=<value>; HttpOnly; SameSite=Strict; Path=/

with no Max-Age (it ends with the browser session; ``Secure`` is added when the request
came over https). The value is not the token but ``HMAC-SHA256(token,
"floornav-session-v1")``: a leaked cookie (it is HttpOnly, so scripts never see it)
does not give the bearer token, and changing the token invalidates every cookie.
``DELETE /api/session`` expires the cookie (no token needed).

The cookie opens the read-only endpoints when ``web.require_token_for_status`` is set
(`app.web.auth.BearerAuth.require_for_reads`) and the ``/viser`` proxy
(`app.web.viser_proxy`); state-changing endpoints still need the bearer header, so a
forged cross-site request cannot drive the robot with it.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Mapping
from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends, Request, Response, status

if TYPE_CHECKING:
    from app.web.auth import BearerAuth

COOKIE_NAME = "floornav_session"
_CONTEXT = b"floornav-session-v1"
_ATTRIBUTES = "HttpOnly; SameSite=Strict; Path=/"
_EXPIRED = "Max-Age=0; Expires=Thu, 01 Jan 1970 00:00:00 GMT"


def session_value(token: str) -> str:
    """The cookie's value for ``token`` (hex HMAC-SHA256; never the token itself)."""
    return hmac.new(token.encode(), _CONTEXT, hashlib.sha256).hexdigest()


def session_cookie_matches(cookies: Mapping[str, str], token: str) -> bool:
    """Whether ``cookies`` (``request.cookies`` or ``websocket.cookies``) carry the
    session cookie for ``token``; constant-time, a missing cookie never matches."""
    presented = cookies.get(COOKIE_NAME)
    if not presented:
        return False
    return hmac.compare_digest(presented.encode(), session_value(token).encode())


def _set_cookie_header(request: Request, value: str, *extra: str) -> str:
    parts = [f"{COOKIE_NAME}={value}", _ATTRIBUTES, *extra]
    if request.url.scheme == "https":
        parts.append("Secure")
    return "; ".join(parts)


def build_session_router(auth: BearerAuth) -> APIRouter:
    """``POST /api/session`` (bearer token required) and ``DELETE /api/session``."""
    router = APIRouter(tags=["auth"])

    @router.post(
        "/api/session",
        status_code=status.HTTP_204_NO_CONTENT,
        response_class=Response,
        dependencies=[Depends(auth.require)],
        responses={
            204: {
                "description": "Session cookie set: `Set-Cookie: floornav_session=...; "
                "HttpOnly; SameSite=Strict; Path=/` (a browser-session cookie)",
                "headers": {"Set-Cookie": {"schema": {"type": "string"}}},
            },
            401: {"description": "Missing or wrong bearer token"},
        },
    )
    async def open_session(request: Request) -> Response:
        """Exchange the bearer token for the session cookie, which authenticates what a
        browser cannot add a header to: the 3D view at ``/viser/`` (its page and
        WebSocket) and, with ``web.require_token_for_status``, the read-only endpoints.
        It never authenticates a state-changing request."""
        cookie = _set_cookie_header(request, session_value(auth.token))
        return Response(status_code=status.HTTP_204_NO_CONTENT, headers={"Set-Cookie": cookie})

    @router.delete(
        "/api/session",
        status_code=status.HTTP_204_NO_CONTENT,
        response_class=Response,
        responses={
            204: {
                "description": "Session cookie expired",
                "headers": {"Set-Cookie": {"schema": {"type": "string"}}},
            }
        },
    )
    async def close_session(request: Request) -> Response:
        """Expire the session cookie (log out of the 3D view); no token needed."""
        cookie = _set_cookie_header(request, "", _EXPIRED)
        return Response(status_code=status.HTTP_204_NO_CONTENT, headers={"Set-Cookie": cookie})

    return router
