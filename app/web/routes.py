"""The REST API under ``/api`` and ``/metrics``.

Handlers are ``async def`` on purpose: they then run on the event loop's thread, the
one the daemon's stages and the service's methods live on (a plain ``def`` would run in
a worker thread and race with them).
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from fastapi import APIRouter, Body, Depends, HTTPException, Query, Request, Response
from numpy.typing import NDArray
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.requests import ClientDisconnect

from app.config import FloornavConfig
from app.fileio import json_safe
from app.mapping.calibration import (
    BoardPlacement,
    FloorCalibration,
    find_chessboard,
    floor_homography_from_chessboard,
    homography_from_point_pairs,
)
from app.mapping.calibration_files import save_floor_calibration
from app.web.config_patch import (
    LIVE_KEYS,
    ConfigConflictError,
    ConfigPatchError,
    apply_config_patch,
    config_patch_model,
    patch_openapi,
)
from app.web.context import WebContext
from app.web.schemas import (
    BOARD_PATTERN_REGEX,
    ERROR_RESPONSES,
    ESTOP_OPENAPI,
    REFUSED_RESPONSE,
    STOP_RESPONSES,
    CalibrationRequest,
    CalibrationResponse,
    ChessboardCalibrationRequest,
    CommandResponse,
    EstopResetResponse,
    FaultResetResponse,
    TeleopReleaseRequest,
    TeleopRequest,
    check_board_pattern,
    estop_source,
)
from app.web.video import encode_jpeg

PREVIEW_JPEG_QUALITY = 85


def public_config(config: FloornavConfig) -> dict[str, Any]:
    """The configuration as JSON, with the token hidden."""
    document = config.model_dump(mode="json")
    if document["web"]["token"]:
        document["web"]["token"] = "<set>"
    return {"config": json_safe(document), "live_keys": list(LIVE_KEYS)}


def _draw_preview(image: NDArray[np.uint8], pattern: tuple[int, int] | None) -> tuple[bytes, int]:
    canvas = np.ascontiguousarray(image.copy())
    found = 0
    if pattern is not None:
        corners = find_chessboard(image, pattern)
        if corners is not None:
            found = len(corners)
            if canvas.ndim == 2:
                canvas = np.asarray(cv2.cvtColor(canvas, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
            cv2.drawChessboardCorners(canvas, pattern, corners.reshape(-1, 1, 2), True)
    return encode_jpeg(canvas, PREVIEW_JPEG_QUALITY), found


def build_api_router(ctx: WebContext) -> APIRouter:
    """``/api/*`` and ``/metrics`` for one app."""
    service = ctx.service
    write = [Depends(ctx.auth.require)]
    read = [Depends(ctx.auth.require_for_reads)]
    router = APIRouter()

    def command_response(detail: str = "") -> CommandResponse:
        return CommandResponse(state=service.state, detail=detail)

    @router.get("/api/status", dependencies=read, tags=["status"], responses=ERROR_RESPONSES)
    async def get_status() -> dict[str, Any]:
        """The daemon's snapshot: state, fps, frame age, stage timings, pose, devices,
        ``zone_floor_confidence`` (how sure perception is that the safe zone ahead is
        floor; null before the first frame), ``zone_known_floor`` (the share of the
        zone's ground the map knows is floor; at ``zone_min_known_floor`` or more the
        zone is floor whatever perception says) and the protective stop holding the robot
        back, if any (``stop_cause``, ``stop_reason``)."""
        result: dict[str, Any] = json_safe(service.status())
        return result

    @router.get(
        "/api/auth", dependencies=write, status_code=204, tags=["status"], responses=ERROR_RESPONSES
    )
    async def check_token() -> Response:
        """204 if the bearer token is right (the dashboard's login check), else 401."""
        return Response(status_code=204)

    @router.post(
        "/api/start",
        dependencies=write,
        tags=["control"],
        responses={**ERROR_RESPONSES, **REFUSED_RESPONSE},
    )
    async def start() -> CommandResponse:
        """Start exploring (409 with the reason when the state does not allow it)."""
        await service.start()
        return command_response()

    # Stopping never needs a token: an operator without one (a new browser, a phone)
    # must still be able to stop the robot. Everything that moves it does need one.
    @router.post("/api/stop", tags=["control"], responses=STOP_RESPONSES)
    async def stop() -> CommandResponse:
        """Stop exploring; the motors go to zero at once (teleop stays possible). No token
        needed."""
        await service.stop()
        return command_response()

    @router.post(
        "/api/estop", tags=["control"], responses=STOP_RESPONSES, openapi_extra=ESTOP_OPENAPI
    )
    async def estop(request: Request) -> CommandResponse:
        """Latch the e-stop; zero until reset (which needs the token). No token needed.
        Never refused for its body: the optional ``{"source": label}`` is read as far as
        it can be (control characters escaped, cut to 64 characters, else ``api``)."""
        client = request.client.host if request.client else "unknown"
        raw = b""
        with contextlib.suppress(ClientDisconnect):  # latched all the same
            raw = await request.body()
        service.estop(f"{estop_source(raw)} ({client})")
        return command_response()

    @router.post(
        "/api/estop/reset", dependencies=write, tags=["control"], responses=ERROR_RESPONSES
    )
    async def reset_estop() -> EstopResetResponse:
        """Clear a latched e-stop; ``was_estopped`` says whether one was latched."""
        was = service.reset_estop()
        return EstopResetResponse(state=service.state, was_estopped=was)

    @router.post(
        "/api/fault/reset", dependencies=write, tags=["control"], responses=ERROR_RESPONSES
    )
    async def reset_fault() -> FaultResetResponse:
        """Clear a latched fault (a cause that kept repeating, or a device gone too long)
        once its cause is fixed; autonomy stays stopped until started again."""
        fault = service.reset_fault()
        return FaultResetResponse(
            state=service.state, cleared=fault.reason if fault is not None else None
        )

    @router.post(
        "/api/teleop",
        dependencies=write,
        tags=["control"],
        responses={**ERROR_RESPONSES, **REFUSED_RESPONSE},
    )
    async def teleop(body: TeleopRequest) -> CommandResponse:
        """Drive by hand; repeat at >= 10 Hz, the robot stops 0.5 s after the last one."""
        service.teleop(body.driver, body.v_m_s, body.omega_rad_s, take_over=body.take_over)
        return command_response()

    @router.post(
        "/api/teleop/release", dependencies=write, tags=["control"], responses=ERROR_RESPONSES
    )
    async def release_teleop(
        body: Annotated[TeleopReleaseRequest | None, Body()] = None,
    ) -> CommandResponse:
        """End teleop (of ``driver`` only, if given)."""
        service.release_teleop(body.driver if body else None)
        return command_response()

    @router.post(
        "/api/calibrate",
        dependencies=write,
        tags=["calibration"],
        responses={**ERROR_RESPONSES, **REFUSED_RESPONSE},
    )
    async def calibrate(body: CalibrationRequest) -> CalibrationResponse:
        """Fit the floor homography on the current frame (a chessboard on the floor, or
        4+ clicked pixels with their floor positions) and save it; the map restarts. With
        ``save`` false only the fit's errors come back: nothing live changes."""
        intrinsics = service.intrinsics
        detected: dict[str, NDArray[np.float32] | None] = {}

        def fit(image: NDArray[np.uint8]) -> FloorCalibration:
            if isinstance(body, ChessboardCalibrationRequest):
                pattern = check_board_pattern(body.pattern)
                placement = BoardPlacement(body.board_x_m, body.board_y_m, body.board_yaw_rad)
                calibration = floor_homography_from_chessboard(
                    image, pattern, body.square_m, intrinsics=intrinsics, placement=placement
                )
                # Detected again (cheap next to the fit) so the wizard can draw them.
                detected["corners"] = find_chessboard(image, pattern)
                return calibration
            height, width = image.shape[:2]
            return homography_from_point_pairs(
                np.asarray([pair.image_px for pair in body.pairs], dtype=np.float64),
                np.asarray([pair.ground_m for pair in body.pairs], dtype=np.float64),
                (width, height),
                intrinsics=intrinsics,
            )

        path = Path(service.config.mapping.floor_calibration_file)

        def save(calibration: FloorCalibration) -> None:
            save_floor_calibration(path, calibration)

        # save false is a preview: fit and answer, the live calibration stays.
        calibration = await service.calibrate_with(
            fit, save if body.save else None, apply=body.save
        )
        corners = detected.get("corners")
        return CalibrationResponse(
            reprojection_rms_px=calibration.reprojection_rms_px,
            ground_rms_m=calibration.ground_rms_m,
            points=calibration.points,
            inliers=calibration.inliers,
            image_size=list(calibration.image_size),
            board_origin_px=None
            if calibration.board_origin_px is None
            else list(calibration.board_origin_px),
            corners_px=None if corners is None else [[float(u), float(v)] for u, v in corners],
            saved_to=str(path) if body.save else None,
        )

    @router.get(
        "/api/calibrate/preview",
        dependencies=read,
        tags=["calibration"],
        response_class=Response,
        responses={200: {"content": {"image/jpeg": {}}}, **ERROR_RESPONSES, **REFUSED_RESPONSE},
    )
    async def calibrate_preview(
        pattern: Annotated[str | None, Query(pattern=BOARD_PATTERN_REGEX)] = None,
    ) -> Response:
        """The newest camera frame as JPEG; with ``pattern`` (COLSxROWS) the detected
        chessboard corners are drawn and their count is in ``X-Chessboard-Corners``."""
        frame = service.frames.peek()
        if frame is None:
            raise HTTPException(409, detail="no camera frame yet")
        try:
            size = check_board_pattern(pattern) if pattern is not None else None
        except ValueError as exc:
            raise HTTPException(422, detail=str(exc)) from exc
        jpeg, found = await asyncio.to_thread(_draw_preview, frame.image, size)
        return Response(jpeg, media_type="image/jpeg", headers={"X-Chessboard-Corners": str(found)})

    @router.get("/api/config", dependencies=read, tags=["config"], responses=ERROR_RESPONSES)
    async def get_config() -> dict[str, Any]:
        """The running configuration (``web.token`` hidden) and the live-key patterns."""
        return public_config(service.config)

    @router.patch(
        "/api/config",
        dependencies=write,
        tags=["config"],
        responses={**ERROR_RESPONSES, **REFUSED_RESPONSE},
        openapi_extra=patch_openapi(config_patch_model(service.config)),
    )
    async def patch_config(patch: Annotated[dict[str, Any], Body()]) -> dict[str, Any]:
        """Merge nested sections (``{"steering": {"cruise_speed_m_s": 0.2}}``) into the
        running configuration. Only live keys, JSON types and the bounds in the schema
        are accepted (422 names the key); values that are each fine but make an invalid
        configuration together (a safe zone turned inside out) get 409."""
        try:
            new = apply_config_patch(service.config, patch)
        except ConfigConflictError as exc:
            raise HTTPException(409, detail=str(exc)) from exc
        except ConfigPatchError as exc:
            raise HTTPException(422, detail=str(exc)) from exc
        service.update_config(new)
        return public_config(new)

    @router.get(
        "/metrics",
        dependencies=read,
        tags=["status"],
        response_class=Response,
        responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}, **ERROR_RESPONSES},
    )
    async def metrics() -> Response:
        """Prometheus text format."""
        return Response(generate_latest(ctx.registry), media_type=CONTENT_TYPE_LATEST)

    return router
