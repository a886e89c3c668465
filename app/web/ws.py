"""The WebSockets: ``/ws/telemetry``, ``/ws/video`` and ``/ws/control``.

Every socket checks the Origin first (no Origin, the server's own host:port, or
``web.allowed_origins``; otherwise the handshake is closed with code 1008) and then the
token where one is needed (HTTP 401 on the handshake; see `app.web.auth` for how to
present it). A client offering the ``floornav`` subprotocol gets it selected.

Senders never queue: each client has its own loop that waits for a value newer than the
one it sent last (`app.channels.SlotReader`) and awaits the send, so a slow client gets
fewer, never older, values and never holds up another client.

Messages
--------
``/ws/telemetry``: text ``{"type": "status", "sent_wall_s", ...Runtime.status()}`` at
``web.telemetry_hz``; NaN becomes null.

``/ws/video[?ack=N]``: per frame a text header ``{"type": "frame", "seq", "capture_s",
"capture_wall_s", "sent_s", "sent_wall_s", "width", "height", "method", "bytes",
"encode_ms", "skipped"}`` (``*_s`` monotonic, ``*_wall_s`` epoch seconds), then one
binary message with the JPEG. Browsers buffer everything a socket delivers, so a
browser should connect with ``?ack=1`` and send ``{"type": "ack", "seq": n}`` after
drawing each frame: at most N frames are then unacknowledged and each one sent is the
newest at that moment.

``/ws/control`` (no token needed to stop): the server first sends ``{"type": "hello",
"driver", "authenticated"}``; a client without the token may only send ``stop`` and
``estop``. It then answers every message ``{"type": "teleop", "v_m_s", "omega_rad_s",
"take_over"?}``, ``{"type": "release" | "estop" | "estop_reset" | "start" | "stop"}``
(each may carry an ``"id"`` that is echoed) with ``{"type": "ack" | "error", "detail",
"state", "id"?}``.
Closing the socket releases that connection's teleop.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, WebSocket
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError
from starlette.websockets import WebSocketDisconnect

from app.channels import LatestSlot, SlotReader
from app.control.teleop_limits import TeleopAngularSpeed, TeleopLinearSpeed
from app.fileio import json_safe
from app.runtime import CommandRefusedError
from app.web.auth import offered_subprotocol, origin_allowed, token_matches, websocket_token
from app.web.context import WebContext
from app.web.service import RobotService
from app.web.session import session_cookie_matches

log = logging.getLogger("floornav.web")

POLICY_VIOLATION = 1008
MAX_VIDEO_ACK_WINDOW = 8


class _Message(BaseModel):
    """Strict like the REST bodies (`app.web.schemas`): JSON numbers for numbers (an
    integer will do for a float), ``true``/``false`` for flags."""

    model_config = ConfigDict(extra="forbid", strict=True)
    id: Annotated[str | int | None, Field(union_mode="left_to_right")] = None
    """Echoed in the reply, so a client can match replies to requests."""


class TeleopMessage(_Message):
    type: Literal["teleop"]
    v_m_s: TeleopLinearSpeed
    omega_rad_s: TeleopAngularSpeed
    take_over: bool = False


class SimpleMessage(_Message):
    type: Literal["release", "estop", "estop_reset", "start", "stop"]


ControlMessage = Annotated[TeleopMessage | SimpleMessage, Field(discriminator="type")]
_CONTROL_ADAPTER: TypeAdapter[TeleopMessage | SimpleMessage] = TypeAdapter(ControlMessage)
_driver_numbers = itertools.count(1)


async def admit(websocket: WebSocket, ctx: WebContext, *, needs_token: bool) -> bool:
    """Check Origin and token, then accept; False (and the handshake refused) if not."""
    allowed = ctx.service.config.web.allowed_origins
    if not origin_allowed(websocket.headers.get("origin"), websocket.headers.get("host"), allowed):
        await websocket.close(code=POLICY_VIOLATION, reason="origin not allowed")
        return False
    # A read-only socket also takes the dashboard's session cookie (`app.web.session`);
    # the control socket never does (`has_token` below decides what it may do).
    reader_ok = not needs_token or has_token(websocket, ctx)
    if not reader_ok and not session_cookie_matches(websocket.cookies, ctx.token):
        denial = JSONResponse(
            {
                "detail": "missing or wrong bearer token (subprotocol bearer.<token> or "
                "Authorization header)"
            },
            status_code=401,
            headers={"WWW-Authenticate": "Bearer"},
        )
        try:
            await websocket.send_denial_response(denial)
        except RuntimeError:  # the server cannot send HTTP responses on a WebSocket
            await websocket.close(code=POLICY_VIOLATION, reason="missing or wrong token")
        return False
    await websocket.accept(subprotocol=offered_subprotocol(websocket))
    return True


def has_token(websocket: WebSocket, ctx: WebContext) -> bool:
    """True if the client presented the right token (header or subprotocol)."""
    return token_matches(websocket_token(websocket), ctx.token)


async def _until_disconnect(
    websocket: WebSocket, on_text: Callable[[str], None] | None = None
) -> None:
    """Read what a send-mostly client sends (text to ``on_text``, the rest dropped),
    until it goes away."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        text = message.get("text")
        if on_text is not None and text is not None:
            on_text(text)


async def run_sender(
    websocket: WebSocket,
    send_loop: Callable[[], Awaitable[None]],
    on_text: Callable[[str], None] | None = None,
) -> None:
    """Run ``send_loop`` until it ends or the client disconnects, whichever is first
    (without a reader, a client that leaves while no new value comes would never be
    noticed). Text the client sends meanwhile goes to ``on_text``."""
    sender = asyncio.ensure_future(send_loop())
    watcher = asyncio.ensure_future(_until_disconnect(websocket, on_text))
    try:
        await asyncio.wait({sender, watcher}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (sender, watcher):
            task.cancel()
        for task in (sender, watcher):
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, OSError):
                await task
    error = sender.exception() if sender.done() and not sender.cancelled() else None
    if error is not None and not isinstance(error, WebSocketDisconnect | OSError | RuntimeError):
        raise error  # a bug, not a client gone (RuntimeError: sending after close)


class TelemetryHub:
    """One status snapshot per tick, shared by all telemetry clients; runs only while
    somebody listens (``status()`` is not free)."""

    def __init__(self, service: RobotService) -> None:
        self.service = service
        self.slot: LatestSlot[str] = LatestSlot("telemetry")
        self.clients = 0
        self._task: asyncio.Task[None] | None = None

    def snapshot(self) -> str:
        status = json_safe(self.service.status())
        return json.dumps({"type": "status", "sent_wall_s": time.time(), **status})

    def attach(self) -> SlotReader[str]:
        """A reader whose first value is a fresh snapshot."""
        self.clients += 1
        if self._task is None or self._task.done():
            self.slot.publish(self.snapshot())
            self._task = asyncio.ensure_future(self._produce())
        reader = SlotReader(self.slot)
        reader.version -= 1  # hand out the current snapshot at once
        return reader

    def detach(self) -> None:
        self.clients -= 1
        if self.clients <= 0 and self._task is not None:
            self._task.cancel()
            self._task = None

    async def _produce(self) -> None:
        while True:
            await asyncio.sleep(1.0 / self.service.config.web.telemetry_hz)
            try:
                self.slot.publish(self.snapshot())
            except Exception:  # a status bug must not kill telemetry for everybody
                log.exception("telemetry snapshot failed")


def build_ws_router(ctx: WebContext) -> APIRouter:
    """The three WebSockets of one app."""
    router = APIRouter()
    service = ctx.service
    hub = TelemetryHub(service)
    metrics = ctx.metrics

    @router.websocket("/ws/telemetry")
    async def telemetry(websocket: WebSocket) -> None:
        if not await admit(websocket, ctx, needs_token=ctx.protect_reads):
            return
        reader = hub.attach()
        metrics.telemetry_clients.inc()

        async def send_loop() -> None:
            while True:
                await websocket.send_text(await reader.next())

        try:
            await run_sender(websocket, send_loop)
        finally:
            hub.detach()
            metrics.telemetry_clients.dec()

    @router.websocket("/ws/video")
    async def video(websocket: WebSocket) -> None:
        try:
            window = int(websocket.query_params.get("ack", "0"))
        except ValueError:
            window = -1
        if not 0 <= window <= MAX_VIDEO_ACK_WINDOW:
            await websocket.close(POLICY_VIOLATION, f"ack must be 0..{MAX_VIDEO_ACK_WINDOW}")
            return
        if not await admit(websocket, ctx, needs_token=ctx.protect_reads):
            return
        # Browsers read every message off the socket at once, so awaiting the send does
        # not slow the server down for them: with ?ack=N at most N frames are unacked.
        credits = asyncio.BoundedSemaphore(window) if window else None
        reader = SlotReader(service.floors)
        if service.floors.peek() is not None:
            reader.version -= 1  # the newest frame at once, then each newer one
        metrics.video_clients.inc()

        def on_text(text: str) -> None:
            if credits is None:
                return
            with contextlib.suppress(ValueError):  # not JSON, or more acks than frames
                message = json.loads(text)
                if isinstance(message, dict) and message.get("type") == "ack":
                    credits.release()

        async def send_loop() -> None:
            while True:
                if credits is not None:
                    await credits.acquire()  # first the credit, then the newest frame
                floor = await reader.next()
                try:
                    frame = await ctx.encoder.frame_for(floor, service.drives.peek())
                except Exception:
                    log.exception("video frame %d could not be encoded", floor.seq)
                    continue
                header = {
                    "type": "frame",
                    "seq": frame.seq,
                    "capture_s": frame.capture_s,
                    "capture_wall_s": frame.capture_wall_s,
                    "sent_s": time.monotonic(),
                    "sent_wall_s": time.time(),
                    "width": frame.width,
                    "height": frame.height,
                    "method": frame.method,
                    "bytes": len(frame.jpeg),
                    "encode_ms": round(frame.encode_s * 1000, 2),
                    "skipped": reader.skipped,
                }
                await websocket.send_text(json.dumps(header))
                await websocket.send_bytes(frame.jpeg)
                metrics.video_frames_sent.inc()

        try:
            await run_sender(websocket, send_loop, on_text)
        finally:
            metrics.video_clients.dec()

    @router.websocket("/ws/control")
    async def control(websocket: WebSocket) -> None:
        # Admitted without a token (Origin still checked) so that anyone who can see the
        # dashboard can stop the robot; such a client may only stop and e-stop.
        if not await admit(websocket, ctx, needs_token=False):
            return
        authenticated = has_token(websocket, ctx)
        driver = f"ws-{next(_driver_numbers)}"
        metrics.control_clients.inc()
        try:
            await websocket.send_json(
                {"type": "hello", "driver": driver, "authenticated": authenticated}
            )
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    break
                text = message.get("text")
                if text is None:
                    reply = {"type": "error", "detail": "send JSON text messages"}
                else:
                    reply = await handle_control(service, driver, text, authenticated=authenticated)
                await websocket.send_text(json.dumps(reply))
        except (WebSocketDisconnect, OSError):
            pass
        finally:
            metrics.control_clients.dec()
            service.release_teleop(driver)

    return router


TOKENLESS_CONTROL = frozenset({"stop", "estop"})
"""Control messages a client without the token may send: the ones that stop the robot."""


async def handle_control(
    service: RobotService, driver: str, text: str, *, authenticated: bool = True
) -> dict[str, Any]:
    """Carry out one control message; the reply is ``{"type": "ack" | "error", ...}``.
    Without ``authenticated`` only `TOKENLESS_CONTROL` messages are carried out."""
    try:
        message = _CONTROL_ADAPTER.validate_json(text)
    except ValidationError as exc:
        error: dict[str, Any] = {"type": "error", "detail": _validation_message(exc)}
        raw: Any = None
        with contextlib.suppress(ValueError, RecursionError):
            raw = json.loads(text)
        if isinstance(raw, dict):
            if isinstance(raw.get("id"), str | int):
                error["id"] = raw["id"]
            if raw.get("type") == "estop":
                # An e-stop is never refused for its form (an extra field, an odd id).
                service.estop(f"websocket {driver}")
                error.update(type="ack", detail="estop", warning=error["detail"])
                error["state"] = service.state.value
        return error
    reply: dict[str, Any] = {"type": "ack", "detail": message.type}
    if message.id is not None:
        reply["id"] = message.id
    if not authenticated and message.type not in TOKENLESS_CONTROL:
        reply.update(
            type="error",
            detail=f"{message.type} needs the token (subprotocol bearer.<token>); "
            "without it this socket can only stop and e-stop",
            state=service.state.value,
        )
        return reply
    try:
        if isinstance(message, TeleopMessage):
            service.teleop(driver, message.v_m_s, message.omega_rad_s, take_over=message.take_over)
        elif message.type == "release":
            service.release_teleop(driver)
        elif message.type == "estop":
            service.estop(f"websocket {driver}")
        elif message.type == "estop_reset":
            reply["was_estopped"] = service.reset_estop()
        elif message.type == "start":
            await service.start()
        elif message.type == "stop":
            await service.stop()
    except CommandRefusedError as exc:
        reply.update(type="error", detail=str(exc))
    reply["state"] = service.state.value
    return reply


def _validation_message(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors(include_input=False, include_url=False):
        key = ".".join(str(p) for p in error["loc"] if not isinstance(p, int))
        parts.append(f"{key}: {error['msg']}" if key else error["msg"])
    return "; ".join(parts)
