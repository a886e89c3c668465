"""`create_app`: the FastAPI application around a `RobotService`.

Routes (details in ``docs`` at ``/docs`` and in `app.web.routes` / `app.web.ws`):
``/api/*`` REST (with ``/api/map.*`` from `app.web.map_view` and ``/api/session`` from
`app.web.session`), ``/metrics`` Prometheus, ``/ws/telemetry``, ``/ws/video``,
``/ws/control``, the optional viser proxy router, and the dashboard's static files at
``/`` (mounted last, so they never shadow the API).
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount, Router
from starlette.types import Scope

from app.mapping.calibration import CalibrationError
from app.runtime import CommandRefusedError
from app.web.auth import BearerAuth
from app.web.body_limit import MAX_REQUEST_BODY_BYTES, BodyLimitMiddleware
from app.web.context import WebContext
from app.web.contract import allowed_methods, document_error_responses
from app.web.headers import SecurityHeadersMiddleware, docs_router
from app.web.map_view import map_router
from app.web.metrics import build_registry
from app.web.routes import build_api_router
from app.web.service import RobotService
from app.web.session import build_session_router
from app.web.video import FrameEncoder
from app.web.ws import build_ws_router

log = logging.getLogger("floornav.web")


def _validation_detail(exc: RequestValidationError) -> tuple[str, list[dict[str, object]]]:
    """One readable message and the structured errors (without the offending input,
    which may be NaN and would not even serialise as strict JSON)."""
    errors: list[dict[str, object]] = []
    parts = []
    for error in exc.errors():
        loc = [str(p) for p in error.get("loc", ())]
        message = str(error.get("msg", "invalid"))
        errors.append({"loc": loc, "msg": message, "type": str(error.get("type", ""))})
        parts.append(f"{'.'.join(loc)}: {message}" if loc else message)
    return "; ".join(parts) or "invalid request", errors


class StaticFallback(Mount):
    """The dashboard's files at ``/``, for the paths no other route serves. A plain mount
    at ``/`` matches every path fully, so a wrong method on an API path (``GET
    /api/teleop``) reached the files and got their 404 instead of the router's 405 with
    its ``Allow``."""

    def __init__(self, router: Router, directory: Path) -> None:
        super().__init__("/", app=StaticFiles(directory=directory, html=True), name="static")
        self._router = router

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        for route in self._router.routes:
            if route is not self and route.matches(scope)[0] is not Match.NONE:
                return Match.NONE, {}
        return super().matches(scope)


def create_app(
    service: RobotService,
    *,
    token: str,
    static_dir: Path | None,
    viser_router: APIRouter | None = None,
) -> FastAPI:
    """The web app for ``service``.

    Parameters
    ----------
    service : the daemon (`app.runtime.Runtime`) or a fake
    token : the bearer token (`app.web.auth.resolve_token`)
    static_dir : the dashboard's files, served at ``/`` (index.html); None: no dashboard
    viser_router : routes of the viser proxy, included as they are
    """
    if not token:
        raise ValueError("create_app needs a non-empty token")
    web_config = service.config.web
    registry, web_metrics = build_registry(service)
    ctx = WebContext(
        service=service,
        token=token,
        auth=BearerAuth(token, protect_reads=web_config.require_token_for_status),
        registry=registry,
        metrics=web_metrics,
        encoder=FrameEncoder(
            web_config.jpeg_quality,
            lambda: service.config.perception.safe_zone,
            on_encoded=web_metrics.jpeg_encode_seconds.observe,
        ),
    )
    app = FastAPI(
        title="floornav",
        summary="Monocular floor navigation robot: status, control, calibration, config",
        description=(
            "State-changing endpoints need `Authorization: Bearer <token>`. WebSockets "
            "(not listed here): `/ws/telemetry`, `/ws/video`, `/ws/control`; a browser "
            'authenticates them with the subprotocols `["floornav", "bearer.<token>"]`. '
            "`POST /api/session` exchanges the token for the session cookie that opens "
            "the 3D view at `/viser/` (and the read-only endpoints when they need the token)."
        ),
        version="1",
        docs_url=None,  # served by `docs_router` from local files
        redoc_url=None,
    )
    app.state.web = ctx
    # Outside the routes, hence before the token check: FastAPI reads a route's whole
    # body before its dependencies run.
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=MAX_REQUEST_BODY_BYTES)
    # Added last, so it is outermost: even a 413 from the body limit carries the headers.
    app.add_middleware(SecurityHeadersMiddleware)

    @app.exception_handler(CommandRefusedError)
    async def refused(request: Request, exc: CommandRefusedError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=409)

    # A well-formed calibration request that cannot be fitted on the current frame (no
    # board in view, points that fix no plane) conflicts with what the camera sees, it
    # is not malformed: 409, as the OpenAPI document says (422 is for the body itself).
    @app.exception_handler(CalibrationError)
    async def calibration_failed(request: Request, exc: CalibrationError) -> JSONResponse:
        return JSONResponse({"detail": f"calibration failed: {exc}"}, status_code=409)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail, errors = _validation_detail(exc)
        return JSONResponse({"detail": detail, "errors": errors}, status_code=422)

    # Starlette's own (its router raises 404 and 405 with it); FastAPI's is a subclass.
    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(app, request.url.path))
        return JSONResponse(
            {"detail": str(exc.detail)}, status_code=exc.status_code, headers=headers
        )

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("%s %s failed", request.method, request.url.path)
        return JSONResponse({"detail": f"internal error: {type(exc).__name__}"}, status_code=500)

    app.include_router(docs_router())
    app.include_router(build_api_router(ctx))
    app.include_router(build_ws_router(ctx))
    app.include_router(build_session_router(ctx.auth))
    # The map follows web.require_token_for_status like the other reads.
    app.include_router(map_router(service, dependencies=[Depends(ctx.auth.require_for_reads)]))
    if viser_router is not None:
        app.include_router(viser_router)
    if static_dir is not None:
        app.router.routes.append(StaticFallback(app.router, static_dir))
    document_error_responses(app)
    return app
