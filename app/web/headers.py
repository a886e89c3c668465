"""Security headers on every HTTP response, and the API docs page served offline.

The dashboard runs no inline script or style and talks only to its own origin, so its
Content-Security-Policy is ``default-src 'self'``; ``frame-ancestors 'none'`` (with
``X-Frame-Options: DENY`` for old browsers) keeps any other page from framing it and
reaching the stored token and the control socket. The viser client (a prebuilt React
app) is one inline loader script that injects the app, its styles at run time, and
compiles WebAssembly, so ``/viser/`` gets a policy that allows exactly that (the
loader by its hash), and may be framed by the dashboard only.
"""

from __future__ import annotations

import base64
import hashlib
import re
from importlib import resources
from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, HTMLResponse
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

DASHBOARD_CSP = (
    "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
    "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)


def inline_script_hashes(html: str) -> list[str]:
    """CSP source expressions (``'sha256-...'``) of the inline scripts of a page."""
    hashes = []
    for match in re.finditer(r"<script\b([^>]*)>(.*?)</script>", html, re.DOTALL | re.IGNORECASE):
        attributes, body = match.groups()
        if "src=" not in attributes.lower() and body.strip():
            digest = hashlib.sha256(body.encode()).digest()
            hashes.append(f"'sha256-{base64.b64encode(digest).decode()}'")
    return hashes


def _viser_loader_hashes() -> list[str]:
    # viser's page is one inline loader script that unpacks the app and injects it; its
    # hash (of the installed viser version) allows exactly that script, and
    # 'strict-dynamic' what it injects.
    try:
        page = resources.files("viser") / "client" / "build" / "index.html"
        return inline_script_hashes(page.read_text(encoding="utf-8"))
    except (ModuleNotFoundError, OSError):
        return []


VISER_CSP = (
    f"default-src 'self'; script-src 'self' {' '.join(_viser_loader_hashes())} "
    "'strict-dynamic' 'wasm-unsafe-eval' blob:; "
    "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
    "connect-src 'self' data: blob:; worker-src 'self' blob:; object-src 'none'; "
    "base-uri 'self'; form-action 'none'; frame-ancestors 'self'"
)
COMMON_HEADERS = {
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
    "cross-origin-opener-policy": "same-origin",
}


def policy_for(path: str) -> tuple[str, str]:
    """(Content-Security-Policy, X-Frame-Options) for a request path."""
    if path == "/viser" or path.startswith("/viser/"):
        return VISER_CSP, "SAMEORIGIN"
    return DASHBOARD_CSP, "DENY"


class SecurityHeadersMiddleware:
    """Adds the headers above to every HTTP response (errors and 413s included); a
    header the route set itself is kept."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        csp, frame_options = policy_for(scope.get("path", ""))

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in (
                    ("content-security-policy", csp),
                    ("x-frame-options", frame_options),
                    *COMMON_HEADERS.items(),
                ):
                    if name not in headers:
                        headers[name] = value
            await send(message)

        await self.app(scope, receive, send_with_headers)


# --- /docs without a CDN -------------------------------------------------------------
# FastAPI's own /docs page loads Swagger UI from a CDN and starts it with an inline
# script; both fail here (offline robots, and the CSP above). The same Swagger UI (5.x,
# which reads OpenAPI 3.1) comes from the fastapi-swagger wheel, and the page starts it
# from a file of ours.
SWAGGER_PACKAGE = "fastapi_swagger.resources"
SWAGGER_FILES = {
    "swagger-ui-bundle.js": "text/javascript",
    "swagger-ui.css": "text/css",
}
DOCS_INIT = Path(__file__).with_name("docs_init.js")
DOCS_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>floornav API</title>
<link rel="icon" href="/favicon.svg">
<link rel="stylesheet" href="/docs-assets/swagger-ui.css">
</head>
<body>
<div id="swagger-ui"></div>
<script src="/docs-assets/swagger-ui-bundle.js"></script>
<script src="/docs-assets/docs-init.js"></script>
</body>
</html>
"""


def docs_router() -> APIRouter:
    """``GET /docs`` (Swagger UI over ``/openapi.json``) and its assets, all local."""
    router = APIRouter(include_in_schema=False)

    @router.get("/docs")
    async def docs_page() -> HTMLResponse:
        return HTMLResponse(DOCS_PAGE)

    @router.get("/docs-assets/{name}")
    async def docs_asset(name: str) -> FileResponse:
        if name == "docs-init.js":
            return FileResponse(DOCS_INIT, media_type="text/javascript")
        media_type = SWAGGER_FILES.get(name)
        if media_type is None:
            raise HTTPException(404, detail=f"no docs asset {name!r}")
        with resources.as_file(resources.files(SWAGGER_PACKAGE) / name) as path:
            return FileResponse(path, media_type=media_type)

    return router
