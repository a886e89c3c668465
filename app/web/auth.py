"""Bearer-token authentication and the WebSocket Origin check.

HTTP: ``Authorization: Bearer <token>`` on every state-changing request (and on the
read-only ones when ``web.require_token_for_status``, where the session cookie of
`app.web.session` also does); missing or wrong gives 401 with
``WWW-Authenticate: Bearer``.

WebSockets: browsers cannot set headers on a WebSocket, so a browser offers two
subprotocols, ``new WebSocket(url, ["floornav", "bearer." + token])``; the server
selects ``floornav`` (it never echoes the token). Scripts may send the Authorization
header instead. Tokens therefore use only subprotocol-safe characters
(`app.config.WEB_TOKEN_PATTERN`).
"""

from __future__ import annotations

import os
import re
import secrets
from pathlib import Path
from typing import Annotated
from urllib.parse import urlsplit

from fastapi import HTTPException, Request, Security, WebSocket, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.datastructures import Headers

from app.config import WEB_TOKEN_PATTERN, FloornavConfig
from app.web.session import session_cookie_matches

TOKEN_ENV = "FLOORNAV_TOKEN"
SUBPROTOCOL = "floornav"
TOKEN_SUBPROTOCOL_PREFIX = "bearer."
BEARER_SCHEME = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="The daemon's token (`web.token`, `$FLOORNAV_TOKEN` or `web.token_file`).",
)
_DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}


class TokenError(ValueError):
    """A configured token is unusable; the message says where it came from."""


def _check_token(token: str, source: str) -> str:
    if not token or not re.fullmatch(WEB_TOKEN_PATTERN, token):
        raise TokenError(
            f"{source}: the token must be 16 or more characters from A-Z a-z 0-9 . _ ~ -"
        )
    return token


def resolve_token(config: FloornavConfig, state_dir: Path | None = None) -> tuple[str, bool]:
    """The API token and whether it was generated just now (print it once, then).

    Sources in order: the ``FLOORNAV_TOKEN`` environment variable, ``web.token``, the
    file ``web.token_file`` (``~`` expanded; a relative path is taken inside
    ``state_dir`` when given). A missing file is created atomically with mode 0600 and a
    fresh ``secrets.token_urlsafe(24)``.

    Raises
    ------
    TokenError
        A token from any source is malformed (an empty file, a typo'd variable).
    """
    from_env = os.environ.get(TOKEN_ENV)
    if from_env is not None:
        return _check_token(from_env.strip(), f"${TOKEN_ENV}"), False
    if config.web.token:
        return config.web.token, False
    path = Path(config.web.token_file).expanduser()
    if not path.is_absolute() and state_dir is not None:
        path = state_dir / path
    if path.exists():
        return _check_token(path.read_text(encoding="ascii").strip(), str(path)), False
    token = secrets.token_urlsafe(24)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    # Write under a temporary name created 0600 (no window in which another user could
    # read it), then link it into place: if two daemons race, the first token wins.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(token + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            return _check_token(path.read_text(encoding="ascii").strip(), str(path)), False
    finally:
        tmp.unlink(missing_ok=True)
    return token, True


def _bearer_from_headers(headers: Headers) -> str | None:
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and credentials.strip():
        return credentials.strip()
    return None


def _bearer_from_subprotocols(headers: Headers) -> str | None:
    offered = (p.strip() for p in headers.get("sec-websocket-protocol", "").split(","))
    for protocol in offered:
        if protocol.startswith(TOKEN_SUBPROTOCOL_PREFIX):
            return protocol[len(TOKEN_SUBPROTOCOL_PREFIX) :]
    return None


def token_matches(presented: str | None, expected: str) -> bool:
    """Constant-time comparison; a missing token never matches."""
    if presented is None:
        return False
    return secrets.compare_digest(presented.encode(), expected.encode())


def offered_subprotocol(websocket: WebSocket) -> str | None:
    """``floornav`` when the client offered it (the server must then select it, or
    browsers drop the connection), else None."""
    offered = websocket.headers.get("sec-websocket-protocol", "")
    return SUBPROTOCOL if SUBPROTOCOL in (p.strip() for p in offered.split(",")) else None


def websocket_token(websocket: WebSocket) -> str | None:
    """The token a WebSocket client presented (Authorization header or subprotocol)."""
    return _bearer_from_headers(websocket.headers) or _bearer_from_subprotocols(websocket.headers)


class BearerAuth:
    """FastAPI dependencies checking the token of HTTP requests."""

    def __init__(self, token: str, *, protect_reads: bool) -> None:
        self.token = token
        self.protect_reads = protect_reads

    def _check(self, request: Request) -> None:
        if not token_matches(_bearer_from_headers(request.headers), self.token):
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                detail="missing or wrong bearer token (Authorization: Bearer <token>)",
                headers={"WWW-Authenticate": "Bearer"},
            )

    async def require(
        self,
        request: Request,
        _: Annotated[HTTPAuthorizationCredentials | None, Security(BEARER_SCHEME)] = None,
    ) -> None:
        """Dependency of state-changing endpoints (the ``Security`` parameter declares the
        bearer scheme in OpenAPI; the check itself is `_check`'s, with our 401 body)."""
        self._check(request)

    async def require_for_reads(self, request: Request) -> None:
        """Dependency of read-only endpoints (open unless configured otherwise); the
        session cookie (`app.web.session`) is as good as the header here."""
        if self.protect_reads and not session_cookie_matches(request.cookies, self.token):
            self._check(request)


def _netloc(scheme: str, host: str, port: int | None) -> str:
    host = host.lower()
    if port is None or port == _DEFAULT_PORTS.get(scheme):
        return host
    return f"{host}:{port}"


def origin_allowed(origin: str | None, host_header: str | None, allowed: list[str]) -> bool:
    """True for no Origin (scripts), the server's own host:port, or a listed origin."""
    if origin is None:
        return True
    normalised = origin.strip().rstrip("/").lower()
    if normalised in (a.strip().rstrip("/").lower() for a in allowed):
        return True
    if not host_header:
        return False
    try:
        parts = urlsplit(normalised)
        host = urlsplit(f"//{host_header.strip()}")
        origin_netloc = _netloc(parts.scheme, parts.hostname or "", parts.port)
        request_netloc = _netloc(parts.scheme, host.hostname or "", host.port)
    except ValueError:  # a malformed port
        return False
    return bool(parts.hostname) and origin_netloc == request_netloc
