"""The MQTT bridge: a robot that a broker (Mosquitto, EMQX, ...) carries to fleet
dashboards and home automation. Off unless ``[mqtt] url`` is set.

Topics, under ``<topic_prefix>/<robot_id>/``:

``availability``
    ``online`` (retained) while connected; ``offline`` (retained) on a clean exit, and as
    the last will the broker publishes when the daemon vanishes.
``state``
    Retained JSON, published when it changes (checked 5 times a second; the pose counts
    as a change once it moved 5 cm): ``state``, ``autonomous``, ``estop``, ``fault``,
    ``stop_cause``/``stop_reason`` (what holds the robot back now), ``last_stop``,
    ``teleop_driver``, ``devices_problem``, ``pose``, ``t`` (epoch seconds).
``telemetry``
    JSON every ``telemetry_period_s``: the command sent to the wheels (speeds, PWM,
    source), fps, the capture-to-command latency (p50/p95 of the last 60), frame age,
    clearance ahead, explored floor (m^2), distance, the Uno link's state.
``map``
    The dashboard's map picture (`app.web.map_view.draw_map`, 10 m around the robot) as
    PNG, retained, at most every ``map_period_s`` and only when the map or the pose
    changed; drawn and encoded in a worker thread.
``cmd``
    Commands in: JSON ``{"cmd": "stop" | "estop" | "start" | "estop_reset" | "teleop",
    "id"?: str | int, "token"?: str}``; teleop adds ``v_m_s``, ``omega_rad_s`` and
    optionally ``take_over`` (repeat at >= 10 Hz, like ``POST /api/teleop``). The REST
    API's rules: ``stop`` and ``estop`` are always obeyed (an ``estop`` even when the rest
    of its message is malformed); ``start``, ``estop_reset`` and ``teleop`` need the
    daemon's token in ``token``. Payloads over 4 KiB, not JSON, not a known command, or
    retained (the broker would replay them after every reconnect) are refused.
``cmd/result``
    One reply per command: ``{"cmd", "ok", "state", "id"?, "error"?}``. ``stop`` and
    ``estop`` replies come once the Uno acknowledged PWM 0/0 (at most 1 s later) and add
    ``latency_ms`` (command received -> PWM 0/0 acknowledged) and ``pwm_zero_wall_s``
    (epoch seconds of that acknowledgement; null when the wheels were already at zero).

Home Assistant (``homeassistant = true``): retained discovery messages under
``<homeassistant_prefix>/`` for a state sensor (attributes: the state message) and a
stop button. A start button needs the token in its ``payload_press``, and discovery
messages are readable by every client allowed to subscribe to them, so it is published
only with ``homeassistant_start_token = true`` (then restrict ``<homeassistant_prefix>/#``
to Home Assistant in the broker's ACL); otherwise its topic is cleared (an empty
retained message removes a stale entity).

Losing the broker never touches driving: everything here is asynchronous on the event
loop (connecting runs in a worker thread), `aiomqtt.MqttError` ends only the session,
and the bridge reconnects with a doubling backoff (``reconnect_min_s`` ..
``reconnect_max_s``, each wait 50-90 % of it). ``Runtime.status()["mqtt"]`` and the
``floornav_mqtt_*`` metrics show the state, reconnects and the last error.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import random
import time
from collections.abc import Awaitable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import aiomqtt
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from app.channels import wait_event
from app.config import MqttConfig
from app.control.teleop_limits import TeleopAngularSpeed, TeleopLinearSpeed
from app.fileio import json_safe
from app.runtime import CommandRefusedError
from app.runtime.service_status import register_status
from app.runtime.telemetry import newest, percentiles_ms
from app.web.auth import token_matches
from app.web.map_view import PoseTrail, draw_map
from app.web.service import RobotService

log = logging.getLogger("floornav.mqtt")

MAX_COMMAND_BYTES = 4096
STATE_CHECK_PERIOD_S = 0.2
POSE_CHANGE_M = 0.05
MAP_SIZE_M = 10.0
MAP_PX = 480
PWM_ZERO_TIMEOUT_S = 1.0
"""How long a stop/estop reply waits for the Uno to acknowledge PWM 0/0."""
ALREADY_STOPPED_WAIT_S = 0.1
"""...when the wheels were at zero already (a command in flight may still come)."""
LATENCY_SAMPLES = 60
CLIENT_TIMEOUT_S = 5.0
"""aiomqtt's bound on CONNACK, SUBACK, PUBACK and a clean disconnect."""
STOP_PUBLISH_TIMEOUT_S = 1.0
"""How long a clean exit waits for the broker to take ``offline``."""
DRIVER = "mqtt"
"""The teleop driver name of commands from MQTT."""

TOKENLESS_COMMANDS = frozenset({"stop", "estop"})
"""Commands obeyed without the token: the ones that stop the robot."""


# -- commands -------------------------------------------------------------------------


class _Command(BaseModel):
    """Strict like the REST bodies: JSON numbers for numbers, booleans for flags."""

    model_config = ConfigDict(extra="forbid", strict=True)
    id: Annotated[str | int | None, Field(union_mode="left_to_right")] = None
    """Echoed in the reply."""
    token: Annotated[str | None, Field(max_length=512)] = None


class TeleopCommand(_Command):
    cmd: Literal["teleop"]
    v_m_s: TeleopLinearSpeed
    omega_rad_s: TeleopAngularSpeed
    take_over: bool = False


class SimpleCommand(_Command):
    cmd: Literal["stop", "estop", "start", "estop_reset"]


Command = TeleopCommand | SimpleCommand
_COMMAND_ADAPTER: TypeAdapter[Command] = TypeAdapter(Annotated[Command, Field(discriminator="cmd")])


@dataclass(frozen=True)
class ParsedCommand:
    """A command payload read: the command, or why it is refused (``error``). An
    ``estop`` whose message is otherwise malformed still has ``estop_anyway``."""

    command: Command | None
    error: str | None = None
    cmd: str | None = None
    """The ``cmd`` field as sent, when it was a string (for the reply)."""
    id: str | int | None = None
    estop_anyway: bool = False


def parse_command(payload: object) -> ParsedCommand:
    """Read one ``cmd`` payload (never raises)."""
    if isinstance(payload, str):
        payload = payload.encode()
    if not isinstance(payload, bytes | bytearray):
        return ParsedCommand(None, "send a JSON object")
    if len(payload) > MAX_COMMAND_BYTES:
        return ParsedCommand(
            None, f"the payload is {len(payload)} bytes; commands are at most {MAX_COMMAND_BYTES}"
        )
    try:
        raw = json.loads(payload)
    except (ValueError, RecursionError):
        return ParsedCommand(None, "not JSON: send a JSON object")
    if not isinstance(raw, dict):
        return ParsedCommand(None, 'send a JSON object such as {"cmd": "stop"}')
    cmd = raw.get("cmd") if isinstance(raw.get("cmd"), str) else None
    ident = raw.get("id")
    ident = ident if isinstance(ident, str | int) and not isinstance(ident, bool) else None
    try:
        command = _COMMAND_ADAPTER.validate_python(raw)
    except ValidationError as exc:
        return ParsedCommand(
            None, _validation_message(exc), cmd, ident, estop_anyway=cmd == "estop"
        )
    return ParsedCommand(command, None, command.cmd, command.id)


def refusal(command: Command, token: str) -> str | None:
    """Why ``command`` may not be carried out for lack of the token, or None."""
    if command.cmd in TOKENLESS_COMMANDS or token_matches(command.token, token):
        return None
    why = "a wrong token" if command.token is not None else "no token"
    return f'{command.cmd} needs the robot\'s token in "token" ({why} given)'


def _validation_message(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors(include_input=False, include_url=False):
        key = ".".join(str(p) for p in error["loc"] if not isinstance(p, int))
        parts.append(f"{key}: {error['msg']}" if key else error["msg"])
    return "; ".join(parts)


def _reply(cmd: str | None, ident: str | int | None, **fields: Any) -> dict[str, Any]:
    reply: dict[str, Any] = {"cmd": cmd, **fields}
    if ident is not None:
        reply["id"] = ident
    return reply


# -- what is published ------------------------------------------------------------------


@dataclass(frozen=True)
class Topics:
    prefix: str
    robot_id: str

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.robot_id}"

    @property
    def availability(self) -> str:
        return f"{self.base}/availability"

    @property
    def state(self) -> str:
        return f"{self.base}/state"

    @property
    def telemetry(self) -> str:
        return f"{self.base}/telemetry"

    @property
    def map(self) -> str:
        return f"{self.base}/map"

    @property
    def cmd(self) -> str:
        return f"{self.base}/cmd"

    @property
    def cmd_result(self) -> str:
        return f"{self.base}/cmd/result"


def state_message(status: dict[str, Any]) -> dict[str, Any]:
    """The retained state from a `Runtime.status` snapshot (no time-varying ages, so it
    changes only when something happened; the pose is compared separately)."""
    last = status.get("last_stop")
    return {
        "state": status.get("state"),
        "autonomous": status.get("autonomous"),
        "estop": status.get("estop"),
        "fault": status.get("fault"),
        "stop_cause": status.get("stop_cause"),
        "stop_reason": status.get("stop_reason"),
        "last_stop": None
        if not isinstance(last, dict)
        else {k: last.get(k) for k in ("cause", "reason", "t", "latched")},
        "teleop_driver": status.get("teleop_driver"),
        "devices_problem": status.get("devices_problem"),
        "pose": status.get("pose"),
    }


def pose_moved(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """True if the pose moved more than `POSE_CHANGE_M` (or appeared/vanished)."""
    if a is None or b is None:
        return a is not b
    try:
        return math.hypot(a["x_m"] - b["x_m"], a["y_m"] - b["y_m"]) > POSE_CHANGE_M
    except (KeyError, TypeError):
        return a != b


def _without_pose(state: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in state.items() if k != "pose"}


def _next_tick(tick: float, period_s: float, now: float) -> float:
    """The tick after ``tick`` on a fixed grid, skipping the ones already past."""
    tick += period_s
    return tick if tick > now else now + period_s


# -- the bridge -------------------------------------------------------------------------


class MqttBridge:
    """The `app.runtime.core.Service` speaking MQTT for one robot (see the module)."""

    name = "mqtt"

    def __init__(self, service: RobotService, token: str, config: MqttConfig | None = None):
        self.service = service
        self.token = token
        self.config = config if config is not None else service.config.mqtt
        broker = self.config.broker()
        if broker is None:
            raise ValueError("mqtt.url is not set: the bridge is off")
        self.host, self.port, self.tls = broker
        self.topics = Topics(self.config.topic_prefix, self.config.robot_id)
        self.state = "connecting"
        self.connects = 0
        self.last_error: str | None = None
        self.connected_s: float | None = None
        self.disconnected_s: float | None = None
        self.commands = 0
        self.refused = 0
        self._stop = asyncio.Event()
        self._client: aiomqtt.Client | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._trail = PoseTrail()
        self._explored: tuple[int, float] = (-1, 0.0)
        register_status(service, self.name, self.status)

    # -- Service --------------------------------------------------------------------------

    def request_stop(self) -> None:
        self._stop.set()

    async def serve(self) -> None:
        """Connect, publish and take commands until `request_stop`; a lost broker means
        reconnecting, never an exception out of here."""
        config = self.config
        backoff = config.reconnect_min_s
        failures = 0
        try:
            while not self._stop.is_set():
                self.state = "connecting"
                try:
                    client = await self._make_client()
                    async with client:
                        self._connected()
                        failures, backoff = 0, config.reconnect_min_s
                        await self._session(client)
                except (aiomqtt.MqttError, OSError) as exc:
                    failures += 1
                    self._lost(exc, failures)
                except Exception as exc:  # a bug here must not stop the robot either
                    failures += 1
                    log.exception("MQTT bridge failed; reconnecting", extra={"event": "mqtt_bug"})
                    self._lost(exc, failures)
                finally:
                    self._client = None
                if self._stop.is_set():
                    break
                delay = backoff * random.uniform(0.5, 0.9)
                backoff = min(backoff * 2.0, config.reconnect_max_s)
                await wait_event(self._stop, delay)
        finally:
            self.state = "stopped"
            for task in list(self._tasks):
                task.cancel()

    def status(self) -> dict[str, Any]:
        """For ``Runtime.status()["mqtt"]`` and the metrics."""
        now = time.monotonic()
        return {
            "state": self.state,
            "broker": f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}",
            "robot_id": self.config.robot_id,
            "topic": self.topics.base,
            "reconnects": max(0, self.connects - 1),
            "last_error": self.last_error,
            "connected_for_s": round(now - self.connected_s, 1)
            if self.state == "connected" and self.connected_s is not None
            else None,
            "commands": self.commands,
            "refused": self.refused,
        }

    # -- connection -----------------------------------------------------------------------

    async def _make_client(self) -> aiomqtt.Client:
        config = self.config
        password = None
        if config.password_file:
            path = Path(config.password_file).expanduser()
            text = await asyncio.to_thread(path.read_text, encoding="utf-8")
            password = text.splitlines()[0] if text else ""
        return aiomqtt.Client(
            self.host,
            self.port,
            username=config.username or None,
            password=password,
            identifier=f"floornav-{config.robot_id}",
            will=aiomqtt.Will(self.topics.availability, b"offline", qos=1, retain=True),
            keepalive=config.keepalive_s,
            timeout=CLIENT_TIMEOUT_S,
            max_queued_outgoing_messages=200,
            tls_params=aiomqtt.TLSParameters(ca_certs=config.ca_file or None) if self.tls else None,
        )

    def _connected(self) -> None:
        self.connects += 1
        now = time.monotonic()
        self.connected_s = now
        self.state = "connected"
        if self.connects == 1:
            log.info(
                "MQTT connected to %s:%d as %s",
                self.host,
                self.port,
                self.topics.base,
                extra={"event": "mqtt_connected", "robot_id": self.config.robot_id},
            )
        else:
            down_s = now - self.disconnected_s if self.disconnected_s is not None else None
            log.info(
                "MQTT reconnected to %s:%d%s",
                self.host,
                self.port,
                f" after {down_s:.1f} s" if down_s is not None else "",
                extra={"event": "mqtt_reconnected", "down_s": down_s},
            )
        self.disconnected_s = None

    def _lost(self, exc: BaseException, failures: int) -> None:
        self.last_error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if self.disconnected_s is None:
            self.disconnected_s = time.monotonic()
        self.state = "connecting"
        if self._stop.is_set():
            return
        # One warning per outage; the retries after it at debug level.
        level = logging.WARNING if failures == 1 else logging.DEBUG
        log.log(
            level,
            "MQTT: no connection to %s:%d (%s); driving goes on, reconnecting",
            self.host,
            self.port,
            self.last_error,
            extra={"event": "mqtt_lost", "error": self.last_error},
        )

    async def _session(self, client: aiomqtt.Client) -> None:
        """One connection: returns on `request_stop` (after publishing ``offline``),
        raises MqttError when the connection fails."""
        self._client = client
        topics = self.topics
        await client.subscribe(topics.cmd, qos=1)
        await client.publish(topics.availability, b"online", qos=1, retain=True)
        if self.config.homeassistant:
            await self._publish_discovery(client)
        loops: list[Coroutine[Any, Any, None]] = [
            self._command_loop(client),
            self._report_loop(client),
            self._map_loop(client),
        ]
        tasks = [asyncio.ensure_future(loop) for loop in loops]
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            done, _ = await asyncio.wait([*tasks, stop], return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in [*tasks, stop]:
                task.cancel()
            await asyncio.gather(*tasks, stop, return_exceptions=True)
        for task in tasks:
            error = task.exception() if task in done and not task.cancelled() else None
            if error is not None:
                raise error
        if stop in done:
            # Bounded: the daemon gives its services 3 s to stop.
            await client.publish(
                topics.availability, b"offline", qos=1, retain=True, timeout=STOP_PUBLISH_TIMEOUT_S
            )
            log.info("MQTT: offline published, disconnecting", extra={"event": "mqtt_stop"})
            return
        raise aiomqtt.MqttError("a session loop ended")  # pragma: no cover - they loop

    # -- commands -------------------------------------------------------------------------

    async def _command_loop(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            received_s = time.monotonic()
            try:
                await self.handle(message.payload, received_s, retained=message.retain)
            except Exception:  # a bug in one command must not end the session
                log.exception("MQTT command failed")

    async def handle(
        self, payload: object, received_s: float | None = None, *, retained: bool = False
    ) -> dict[str, Any]:
        """Carry out one command payload and publish (also return) the reply. Never
        raises for what the payload holds. A stop/estop reply is published once the
        wheels are at zero; the one returned says only that it was carried out.

        A retained command (the broker replays it to every new subscriber, so after each
        reconnect) is refused: commands are events, and a stale start must not run."""
        received_s = time.monotonic() if received_s is None else received_s
        self.commands += 1
        service = self.service
        parsed = parse_command(payload)
        if retained:
            parsed = ParsedCommand(
                None,
                "retained commands are ignored (the broker replays them after every "
                "reconnect): publish commands without the retain flag",
                parsed.cmd,
                parsed.id,
            )
        command = parsed.command
        if command is None:
            if parsed.estop_anyway:
                # An e-stop is never refused for its form (an extra field, an odd id).
                watch = self._drive_watch()
                service.estop("mqtt")
                reply = _reply(
                    "estop",
                    parsed.id,
                    ok=True,
                    state=service.state.value,
                    warning=parsed.error,
                )
                self._spawn(self._reply_when_stopped(reply, watch, received_s))
                return reply
            self.refused += 1
            reply = _reply(parsed.cmd, parsed.id, ok=False, error=parsed.error)
            reply["state"] = service.state.value
            self._spawn(self._publish_result(reply))
            return reply
        why_not = refusal(command, self.token)
        if why_not is not None:
            self.refused += 1
            log.warning(
                "MQTT %s refused: %s", command.cmd, why_not, extra={"event": "mqtt_refused"}
            )
            reply = _reply(command.cmd, command.id, ok=False, error=why_not)
            reply["state"] = service.state.value
            self._spawn(self._publish_result(reply))
            return reply
        reply = _reply(command.cmd, command.id, ok=True)
        stop_watch = self._drive_watch() if command.cmd in TOKENLESS_COMMANDS else None
        try:
            if isinstance(command, TeleopCommand):
                service.teleop(
                    DRIVER, command.v_m_s, command.omega_rad_s, take_over=command.take_over
                )
            elif command.cmd == "estop":
                service.estop("mqtt")
            elif command.cmd == "stop":
                await service.stop()
            elif command.cmd == "estop_reset":
                reply["was_estopped"] = service.reset_estop()
            elif command.cmd == "start":
                await service.start()
        except CommandRefusedError as exc:
            self.refused += 1
            reply.update(ok=False, error=str(exc))
        reply["state"] = service.state.value
        if stop_watch is not None:
            self._spawn(self._reply_when_stopped(reply, stop_watch, received_s))
        else:
            self._spawn(self._publish_result(reply))
        return reply

    def _drive_watch(self) -> tuple[int, bool]:
        """(slot version, wheels already at zero) of the drive commands, taken before a
        stop so its reply can wait for the PWM 0/0 that follows."""
        drives = self.service.drives
        last = drives.peek()
        return drives.version, last is None or (last.left_pwm, last.right_pwm) == (0, 0)

    async def _reply_when_stopped(
        self, reply: dict[str, Any], watch: tuple[int, bool], received_s: float
    ) -> None:
        version, already = watch
        drives = self.service.drives
        sent_s: float | None = None
        try:
            async with asyncio.timeout(ALREADY_STOPPED_WAIT_S if already else PWM_ZERO_TIMEOUT_S):
                while True:
                    version, drive = await drives.next(version)
                    if (drive.left_pwm, drive.right_pwm) == (0, 0):
                        sent_s = drive.sent_s
                        break
        except TimeoutError:
            pass
        if sent_s is not None:
            reply["latency_ms"] = round(max(0.0, sent_s - received_s) * 1000, 2)
            reply["pwm_zero_wall_s"] = round(time.time() - (time.monotonic() - sent_s), 4)
        else:
            reply["latency_ms"] = None
            reply["pwm_zero_wall_s"] = None
            reply["already_stopped"] = already
        reply["state"] = self.service.state.value
        await self._publish_result(reply)

    async def _publish_result(self, reply: dict[str, Any]) -> None:
        client = self._client
        if client is None:
            return
        with contextlib.suppress(aiomqtt.MqttError):
            await client.publish(self.topics.cmd_result, json.dumps(json_safe(reply)), qos=1)

    def _spawn(self, coro: Awaitable[None]) -> None:
        task: asyncio.Task[None] = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- state, telemetry, map ------------------------------------------------------------

    async def _report_loop(self, client: aiomqtt.Client) -> None:
        """The state when it changed (checked every `STATE_CHECK_PERIOD_S`) and the
        telemetry every ``telemetry_period_s``, from one status snapshot per tick."""
        topics = self.topics
        period_s = self.config.telemetry_period_s
        last_state: dict[str, Any] | None = None
        next_state = next_telemetry = time.monotonic()
        while True:
            status = json_safe(self.service.status())
            assert isinstance(status, dict)
            now = time.monotonic()
            if now >= next_state:
                next_state = _next_tick(next_state, STATE_CHECK_PERIOD_S, now)
                state = state_message(status)
                if (
                    last_state is None
                    or _without_pose(state) != _without_pose(last_state)
                    or pose_moved(state["pose"], last_state["pose"])
                ):
                    payload = json.dumps({**state, "t": round(time.time(), 3)})
                    await client.publish(topics.state, payload, qos=1, retain=True)
                    last_state = state
            if now >= next_telemetry:
                next_telemetry = _next_tick(next_telemetry, period_s, now)
                payload = json.dumps(json_safe(self.telemetry(status)))
                await client.publish(topics.telemetry, payload, qos=0)
            await asyncio.sleep(max(0.0, min(next_state, next_telemetry) - time.monotonic()))

    def telemetry(self, status: dict[str, Any]) -> dict[str, Any]:
        """The telemetry message from a status snapshot and the latency window."""
        service = self.service
        latency = percentiles_ms(newest(service.latencies, LATENCY_SAMPLES))
        serial = status.get("serial")
        return {
            "t": round(time.time(), 3),
            "state": status.get("state"),
            "command": status.get("command"),
            "fps": status.get("fps"),
            "latency_ms": {"p50": latency["p50"], "p95": latency["p95"]},
            "frame_age_ms": status.get("frame_age_ms"),
            "clearance_ahead_m": status.get("clearance_ahead_m"),
            "zone_floor_confidence": status.get("zone_floor_confidence"),
            "explored_m2": self._explored_m2(),
            "distance_m": status.get("distance_m"),
            "serial": serial.get("state") if isinstance(serial, dict) else None,
        }

    def _explored_m2(self) -> float | None:
        """Free floor in the map (m^2), counted once per map snapshot."""
        snapshot = self.service.world_maps.peek()
        if snapshot is None:
            return None
        if self._explored[0] != snapshot.seq:
            area = snapshot.free_cells * snapshot.grid.cell_m**2
            self._explored = (snapshot.seq, round(area, 2))
        return self._explored[1]

    async def _map_loop(self, client: aiomqtt.Client) -> None:
        last_key: tuple[Any, ...] | None = None
        while True:
            snapshot = self.service.world_maps.peek()
            if snapshot is not None:
                pose = self.service.odometry.pose
                key = (
                    snapshot.free_cells,
                    snapshot.occupied_cells,
                    snapshot.goal_xy,
                    round(pose.x_m / POSE_CHANGE_M),
                    round(pose.y_m / POSE_CHANGE_M),
                    round(pose.theta_rad, 1),
                )
                if key != last_key:
                    try:
                        picture = await asyncio.to_thread(
                            draw_map, self.service, self._trail, MAP_SIZE_M, MAP_PX
                        )
                    except Exception:  # the map is not worth the state and commands
                        log.exception("MQTT map picture failed")
                        picture, last_key = None, key
                    if picture is not None:
                        await client.publish(self.topics.map, picture.png, qos=0, retain=True)
                        last_key = key
            # Until the first picture is out, look again soon (the map comes after start).
            await asyncio.sleep(self.config.map_period_s if last_key is not None else 0.5)

    # -- Home Assistant -------------------------------------------------------------------

    def discovery(self) -> dict[str, bytes]:
        """Home Assistant discovery topics and their (retained) payloads; an empty payload
        removes the start button when it is not configured."""
        config, topics = self.config, self.topics
        robot = config.robot_id
        prefix = config.homeassistant_prefix
        common = {
            "availability_topic": topics.availability,
            "payload_available": "online",
            "payload_not_available": "offline",
            "device": {
                "identifiers": [f"floornav_{robot}"],
                "name": f"floornav {robot}",
                "manufacturer": "floornav",
                "model": "floornav robot",
            },
        }
        sensor = {
            **common,
            "name": "State",
            "unique_id": f"floornav_{robot}_state",
            "state_topic": topics.state,
            "value_template": "{{ value_json.state }}",
            "json_attributes_topic": topics.state,
            "icon": "mdi:robot",
        }
        stop = {
            **common,
            "name": "Stop",
            "unique_id": f"floornav_{robot}_stop",
            "command_topic": topics.cmd,
            "payload_press": json.dumps({"cmd": "stop"}),
            "icon": "mdi:stop",
        }
        out = {
            f"{prefix}/sensor/{robot}_state/config": json.dumps(sensor).encode(),
            f"{prefix}/button/{robot}_stop/config": json.dumps(stop).encode(),
            f"{prefix}/button/{robot}_start/config": b"",
        }
        if config.homeassistant_start_token:
            start = {
                **common,
                "name": "Start",
                "unique_id": f"floornav_{robot}_start",
                "command_topic": topics.cmd,
                "payload_press": json.dumps({"cmd": "start", "token": self.token}),
                "icon": "mdi:play",
            }
            out[f"{prefix}/button/{robot}_start/config"] = json.dumps(start).encode()
        return out

    async def _publish_discovery(self, client: aiomqtt.Client) -> None:
        for topic, payload in self.discovery().items():
            await client.publish(topic, payload, qos=1, retain=True)


__all__ = [
    "MqttBridge",
    "ParsedCommand",
    "Topics",
    "parse_command",
    "refusal",
    "state_message",
]
