"""The MQTT bridge (`app.bridges.mqtt`, issue 14).

Unit tests (no broker): command parsing and authorization, the replies, the state and
Home Assistant messages, the configuration, and a bridge without a broker that keeps
retrying without ever raising.

Broker tests (``-m broker``): a real Mosquitto on a free port with a password file and
an ACL, two daemons on the simulator (``floornav run``) connected to it as robots
``r1`` and ``r2``: availability and state arrive within 2 s of a daemon being ready; an
``estop`` for r1 stops r1 (PWM 0/0; median over 20 tries) and never r2; a ``start``
without the token is refused; the broker killed for 30 s and restarted: both keep
driving, without a protective stop, and reconnect within 5 s; a daemon killed outright
gets its last will ``offline`` published.
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from app.bridges import bridge_services
from app.bridges.mqtt import (
    MAX_COMMAND_BYTES,
    MqttBridge,
    SimpleCommand,
    TeleopCommand,
    parse_command,
    pose_moved,
    refusal,
    state_message,
)
from app.config import ConfigError, FloornavConfig, MqttConfig, load_config
from app.control.mux import Twist
from app.messages import DriveMsg, State
from app.runtime.service_status import service_status
from tests.stall_witness import shared_witness

from ..conftest import PROJECT_ROOT, free_port
from ..web.fakes import FakeService

TOKEN = "mqtt-test-token-0123456789"
MOSQUITTO = Path("/usr/sbin/mosquitto")
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"


# -- parsing and authorization ------------------------------------------------------------


def test_commands_parse_strictly() -> None:
    stop = parse_command(b'{"cmd": "stop"}')
    assert isinstance(stop.command, SimpleCommand) and stop.error is None
    teleop = parse_command(
        json.dumps({"cmd": "teleop", "v_m_s": 0.2, "omega_rad_s": 0, "id": 7, "token": TOKEN})
    )
    assert isinstance(teleop.command, TeleopCommand)
    assert teleop.command.omega_rad_s == 0.0 and teleop.id == 7
    assert parse_command(b'{"cmd": "start", "id": "a"}').id == "a"


@pytest.mark.parametrize(
    ("payload", "error"),
    [
        (b"", "not JSON"),
        (b"stop", "not JSON"),
        (b"\xff\xfe", "not JSON"),
        (b"[1, 2]", "JSON object"),
        (b'"stop"', "JSON object"),
        (b"[" * 2000 + b"]" * 2000, "not JSON"),  # nesting deeper than json allows
        (b'{"cmd": "dance"}', "cmd"),
        (b'{"command": "stop"}', "cmd"),
        (b'{"cmd": "stop", "extra": 1}', "extra"),
        (b'{"cmd": "teleop", "v_m_s": "fast", "omega_rad_s": 0}', "v_m_s"),
        (b'{"cmd": "teleop", "v_m_s": 9, "omega_rad_s": 0}', "v_m_s"),
        (b'{"cmd": "teleop", "v_m_s": true, "omega_rad_s": 0}', "v_m_s"),
        (b'{"cmd": "start", "token": 12345}', "token"),
        (b'{"cmd": "stop", "id": [1]}', "id"),
        (b'{"cmd": "stop", "pad": "' + b"x" * MAX_COMMAND_BYTES + b'"}', "at most 4096"),
        (None, "JSON object"),
        (3.5, "JSON object"),
    ],
)
def test_malformed_payloads_are_refused_with_a_reason(payload: object, error: str) -> None:
    parsed = parse_command(payload)
    assert parsed.command is None
    assert parsed.error is not None and error in parsed.error
    assert not parsed.estop_anyway


def test_an_estop_is_obeyed_whatever_else_its_message_holds() -> None:
    parsed = parse_command(b'{"cmd": "estop", "id": "x", "source": "panic button"}')
    assert parsed.command is None and parsed.estop_anyway
    assert parsed.cmd == "estop" and parsed.id == "x"


@pytest.mark.parametrize(
    ("payload", "allowed"),
    [
        ({"cmd": "stop"}, True),
        ({"cmd": "estop", "token": "wrong"}, True),
        ({"cmd": "start"}, False),
        ({"cmd": "start", "token": "wrong-token-0000000000"}, False),
        ({"cmd": "start", "token": TOKEN}, True),
        ({"cmd": "estop_reset"}, False),
        ({"cmd": "estop_reset", "token": TOKEN}, True),
        ({"cmd": "teleop", "v_m_s": 0.1, "omega_rad_s": 0.0}, False),
        ({"cmd": "teleop", "v_m_s": 0.1, "omega_rad_s": 0.0, "token": TOKEN}, True),
    ],
)
def test_moving_the_robot_needs_the_token(payload: dict[str, Any], allowed: bool) -> None:
    command = parse_command(json.dumps(payload)).command
    assert command is not None
    why_not = refusal(command, TOKEN)
    assert (why_not is None) is allowed
    if not allowed:
        assert why_not is not None and "token" in why_not


# -- the bridge without a broker ------------------------------------------------------------


class Recorder:
    """Stands in for the aiomqtt client: records what is published."""

    def __init__(self) -> None:
        self.published: list[tuple[str, Any]] = []

    async def publish(self, topic: str, payload: Any = None, **_: Any) -> None:
        self.published.append((topic, payload))


def make_bridge(**mqtt: Any) -> tuple[MqttBridge, FakeService, Recorder]:
    service = FakeService()
    config = MqttConfig(url="mqtt://127.0.0.1:1", robot_id="r1", **mqtt)
    bridge = MqttBridge(service, TOKEN, config)  # type: ignore[arg-type]
    recorder = Recorder()
    bridge._client = recorder  # type: ignore[assignment]
    return bridge, service, recorder


async def settle(bridge: MqttBridge) -> None:
    if bridge._tasks:
        await asyncio.gather(*bridge._tasks)


def results(recorder: Recorder) -> list[dict[str, Any]]:
    return [json.loads(p) for t, p in recorder.published if t == "floornav/r1/cmd/result"]


async def test_start_without_the_token_is_refused_and_answered() -> None:
    bridge, service, recorder = make_bridge()
    reply = await bridge.handle(b'{"cmd": "start", "id": 3}')
    await settle(bridge)
    assert reply["ok"] is False and "token" in reply["error"] and reply["id"] == 3
    assert service.calls == []
    assert results(recorder) == [reply]
    reply = await bridge.handle(json.dumps({"cmd": "start", "token": TOKEN}).encode())
    await settle(bridge)
    assert reply == {"cmd": "start", "ok": True, "state": "running"}
    assert service.calls == [("start",)]
    assert bridge.status()["refused"] == 1 and bridge.status()["commands"] == 2


async def test_a_refusal_of_the_runtime_is_answered() -> None:
    bridge, service, _recorder = make_bridge()
    service.refuse["start"] = "e-stop is latched: reset it first"
    reply = await bridge.handle(json.dumps({"cmd": "start", "token": TOKEN}))
    await settle(bridge)
    assert reply["ok"] is False and reply["error"] == "e-stop is latched: reset it first"


async def test_garbage_gets_a_refusal_and_never_raises() -> None:
    bridge, service, recorder = make_bridge()
    for payload in (b"\x00\x01", b"{", b"x" * 100_000, b'{"cmd": 5}', b"[]", None):
        reply = await bridge.handle(payload)
        assert reply["ok"] is False and reply["error"]
    await settle(bridge)
    assert service.calls == []
    assert len(results(recorder)) == 6


async def test_estop_reply_waits_for_pwm_zero_and_gives_the_latency() -> None:
    bridge, service, recorder = make_bridge()
    now = time.monotonic()
    service.drives.publish(DriveMsg(Twist(0.3, 0.0), 150, 150, "autonomy", now, now))
    received = time.monotonic()
    reply = await bridge.handle(b'{"cmd": "estop", "id": 1}', received)
    assert reply["ok"] is True and service.calls == [("estop", "mqtt")]
    assert results(recorder) == []  # not before the wheels are at zero
    await asyncio.sleep(0.03)
    service.drives.publish(DriveMsg(Twist(), 0, 0, "estop", time.monotonic(), received))
    await settle(bridge)
    (result,) = results(recorder)
    assert result["id"] == 1 and result["state"] == "estopped"
    assert 25 <= result["latency_ms"] < 500
    assert abs(result["pwm_zero_wall_s"] - time.time()) < 1.0


async def test_stop_of_a_standing_robot_is_answered_at_once() -> None:
    bridge, _service, recorder = make_bridge()
    started = time.monotonic()
    await bridge.handle(b'{"cmd": "stop"}')
    await settle(bridge)
    (result,) = results(recorder)
    assert result["ok"] is True and result["latency_ms"] is None
    assert result["already_stopped"] is True
    assert time.monotonic() - started < 0.5


async def test_a_malformed_estop_still_stops() -> None:
    bridge, service, _recorder = make_bridge()
    reply = await bridge.handle(b'{"cmd": "estop", "why": "smoke"}')
    await settle(bridge)
    assert service.calls == [("estop", "mqtt")]
    assert reply["ok"] is True and "why" in reply["warning"]


async def test_retained_commands_are_refused() -> None:
    bridge, service, recorder = make_bridge()
    assert recorder.published == []
    reply = await bridge.handle(
        json.dumps({"cmd": "start", "token": TOKEN, "id": 1}).encode(), retained=True
    )
    await settle(bridge)
    assert reply["ok"] is False and "retained" in reply["error"] and reply["id"] == 1
    assert service.calls == []
    assert results(recorder) == [reply]


async def test_teleop_and_estop_reset_with_the_token() -> None:
    bridge, service, recorder = make_bridge()
    await bridge.handle(
        json.dumps({"cmd": "teleop", "v_m_s": 0.1, "omega_rad_s": -0.5, "token": TOKEN})
    )
    await bridge.handle(json.dumps({"cmd": "estop_reset", "token": TOKEN}))
    await settle(bridge)
    assert service.calls == [("teleop", "mqtt", 0.1, -0.5, False), ("reset_estop",)]
    assert results(recorder)[1]["was_estopped"] is False


def test_state_message_changes_only_with_events_or_5_cm() -> None:
    status = FakeService().status() | {
        "pose": {"x_m": 1.0, "y_m": 2.0, "theta_rad": 0.1},
        "last_stop": {"cause": "camera", "reason": "gap", "t": 5.0, "age_s": 3.2},
    }
    state = state_message(status)
    assert state["state"] == "idle" and state["last_stop"] == {
        "cause": "camera",
        "reason": "gap",
        "t": 5.0,
        "latched": None,
    }  # no age: it would change every check
    assert not pose_moved(state["pose"], {"x_m": 1.03, "y_m": 2.03, "theta_rad": 3.0})
    assert pose_moved(state["pose"], {"x_m": 1.06, "y_m": 2.0, "theta_rad": 0.1})


def test_home_assistant_discovery() -> None:
    bridge, _, _ = make_bridge(homeassistant=True)
    messages = bridge.discovery()
    sensor = json.loads(messages["homeassistant/sensor/r1_state/config"])
    assert sensor["state_topic"] == "floornav/r1/state"
    assert sensor["availability_topic"] == "floornav/r1/availability"
    assert sensor["device"]["identifiers"] == ["floornav_r1"]
    stop = json.loads(messages["homeassistant/button/r1_stop/config"])
    assert stop["command_topic"] == "floornav/r1/cmd"
    assert json.loads(stop["payload_press"]) == {"cmd": "stop"}
    assert messages["homeassistant/button/r1_start/config"] == b""  # removed: no token
    assert TOKEN not in json.dumps({k: v.decode() for k, v in messages.items()})
    bridge, _, _ = make_bridge(homeassistant=True, homeassistant_start_token=True)
    start = json.loads(bridge.discovery()["homeassistant/button/r1_start/config"])
    assert json.loads(start["payload_press"]) == {"cmd": "start", "token": TOKEN}


def test_configuration() -> None:
    assert FloornavConfig().mqtt.url is None
    assert bridge_services_for(FloornavConfig()) == []
    config = MqttConfig(url="mqtts://broker.example")
    assert config.broker() == ("broker.example", 8883, True)
    assert MqttConfig(url="mqtt://10.0.0.2").broker() == ("10.0.0.2", 1883, False)
    assert MqttConfig(url="mqtt://h:1999").broker() == ("h", 1999, False)
    assert MqttConfig(url="").url is None


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("url", "http://broker", "scheme"),
        ("url", "mqtt://user:secret@broker", "password"),
        ("url", "mqtt://", "host"),
        ("url", "mqtt://broker:99999", "out of range"),
        ("url", "mqtt://broker/topic", "only scheme"),
        ("robot_id", "a/b", "robot_id"),
        ("robot_id", "bot+1", "robot_id"),
        ("robot_id", "", "robot_id"),
        ("topic_prefix", "fleet/#", "topic_prefix"),
        ("reconnect_max_s", 0.1, "reconnect_max_s"),
    ],
)
def test_bad_mqtt_settings_name_the_key(
    tmp_path: Path, key: str, value: object, message: str
) -> None:
    path = tmp_path / "c.toml"
    path.write_text(f"[mqtt]\n{key} = {json.dumps(value)}\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "mqtt" in str(info.value) and message in str(info.value)


def bridge_services_for(config: FloornavConfig) -> list[Any]:
    class Holder:
        pass

    holder = Holder()
    holder.config = config  # type: ignore[attr-defined]
    return bridge_services(holder, TOKEN)  # type: ignore[arg-type]


async def test_without_a_broker_it_retries_and_never_raises() -> None:
    service = FakeService()
    port = free_port()  # nothing listens there
    config = MqttConfig(url=f"mqtt://127.0.0.1:{port}", reconnect_min_s=0.05, reconnect_max_s=0.1)
    bridge = MqttBridge(service, TOKEN, config)  # type: ignore[arg-type]
    task = asyncio.ensure_future(bridge.serve())
    await asyncio.sleep(0.6)
    status = service_status(service, "mqtt")
    assert status is not None and status["state"] == "connecting"
    assert status["last_error"] and status["reconnects"] == 0
    assert not task.done()
    bridge.request_stop()
    await asyncio.wait_for(task, 2.0)  # ends at once, without an exception
    assert bridge.status()["state"] == "stopped"


def test_metrics_show_the_bridge_only_when_configured() -> None:
    from prometheus_client import generate_latest

    from app.web.metrics import build_registry

    service = FakeService()
    registry, _ = build_registry(service)  # type: ignore[arg-type]
    assert b"floornav_mqtt" not in generate_latest(registry)
    assert service_status(service, "mqtt") is None
    bridge = MqttBridge(service, TOKEN, MqttConfig(url="mqtt://127.0.0.1:1"))  # type: ignore[arg-type]
    text = generate_latest(registry)
    assert b"floornav_mqtt_connected 0.0" in text
    assert b"floornav_mqtt_reconnects_total 0.0" in text
    bridge.state, bridge.connects = "connected", 3
    text = generate_latest(registry)
    assert b"floornav_mqtt_connected 1.0" in text
    assert b"floornav_mqtt_reconnects_total 2.0" in text


# -- a real broker, two daemons ---------------------------------------------------------


@dataclass
class Broker:
    port: int
    directory: Path
    proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        log = (self.directory / "mosquitto.log").open("ab")
        self.proc = subprocess.Popen(
            [str(MOSQUITTO), "-c", str(self.directory / "mosquitto.conf")],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with socket.socket() as sock:
                if sock.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.02)
        raise RuntimeError(f"mosquitto did not listen on {self.port}")

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self.proc = None


@dataclass
class Subscriber:
    """A test client subscribed to everything (paho, in its own thread), keeping each
    message with its arrival time."""

    port: int
    messages: list[tuple[float, str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id="tester")
        self.client.username_pw_set("tester", "tester-pass")
        self.client.reconnect_delay_set(0.05, 0.2)
        self.client.on_connect = lambda c, *_: c.subscribe(
            [("floornav/#", 1), ("homeassistant/#", 1)]
        )
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", self.port, keepalive=10)
        self.client.loop_start()

    def _on_message(self, client: Any, userdata: Any, message: Any) -> None:
        with self.lock:
            self.messages.append((time.monotonic(), message.topic, bytes(message.payload)))

    def since(self, t0: float, topic: str) -> list[tuple[float, bytes]]:
        with self.lock:
            return [(t, p) for t, tp, p in self.messages if tp == topic and t >= t0]

    def wait(
        self, topic: str, t0: float, timeout_s: float, match: Any = lambda p: True
    ) -> tuple[float, bytes] | None:
        deadline = time.monotonic() + timeout_s
        while True:
            for t, payload in self.since(t0, topic):
                if match(payload):
                    return t, payload
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)

    def publish(self, topic: str, payload: dict[str, Any] | str) -> None:
        data = payload if isinstance(payload, str) else json.dumps(payload)
        self.client.publish(topic, data, qos=1).wait_for_publish(5)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


@dataclass
class Daemon:
    robot_id: str
    web_port: int
    proc: subprocess.Popen[bytes]
    log_path: Path
    started_s: float
    ready_s: float | None = None

    def status(self) -> dict[str, Any]:
        url = f"http://127.0.0.1:{self.web_port}/api/status"
        with urllib.request.urlopen(url, timeout=5) as response:
            data: dict[str, Any] = json.load(response)
        return data

    def poll_ready(self) -> bool:
        """True once the API answers (``ready_s`` is then that moment)."""
        if self.ready_s is not None:
            return True
        if self.proc.poll() is not None:
            raise RuntimeError(f"{self.robot_id} exited:\n{self.log_tail()}")
        try:
            urllib.request.urlopen(
                f"http://127.0.0.1:{self.web_port}/api/status", timeout=0.5
            ).close()
        except OSError:
            return False
        self.ready_s = time.monotonic()
        return True

    def log_tail(self) -> str:
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-30:])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(20)
        # Its whole session: the simulated Uno is a child process.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)


@dataclass
class Fleet:
    broker: Broker
    subscriber: Subscriber
    r1: Daemon
    r2: Daemon


def write_broker_files(directory: Path, port: int, robots: list[str]) -> None:
    users = {robot: f"{robot}-pass" for robot in robots} | {"tester": "tester-pass"}
    passwd = directory / "passwd"
    for i, (user, password) in enumerate(users.items()):
        create = ["-c"] if i == 0 else []
        subprocess.run(
            [MOSQUITTO_PASSWD, *create, "-b", str(passwd), user, password],
            check=True,
            capture_output=True,
        )
    acl = ["user tester", "topic readwrite #", ""]
    for robot in robots:  # each robot only under its own topics (and discovery)
        acl += [
            f"user {robot}",
            f"topic readwrite floornav/{robot}/#",
            "topic write homeassistant/#",
            "",
        ]
    (directory / "acl").write_text("\n".join(acl))
    (directory / "mosquitto.conf").write_text(
        "\n".join(
            [
                f"listener {port} 127.0.0.1",
                "allow_anonymous false",
                f"password_file {passwd}",
                f"acl_file {directory / 'acl'}",
                "persistence false",
                f"user {getpass.getuser()}",  # started as root it would switch to mosquitto
                "",
            ]
        )
    )
    for robot in robots:
        (directory / f"{robot}.password").write_text(f"{robot}-pass\n")


FLEET_ENV = {
    # Two daemons share the test machine (2 cores in CI, with the broker and pytest): a
    # 10 fps camera keeps them from starving each other, and longer stop deadlines (1.5 s
    # perception age, 1 s of Uno silence instead of 200 ms) keep a busy machine's hiccup
    # (measured: the simulated Uno's process starved for 200 ms at load 12) from counting
    # as a protective stop, so a stop seen here would come from a stall of the daemon
    # itself, the thing a broker outage must not cause.
    "FLOORNAV_CAMERA__FPS_HZ": "10",
    "FLOORNAV_SAFETY__PERCEPTION_MAX_AGE_S": "1.5",
    "FLOORNAV_SAFETY__CAMERA_MAX_AGE_S": "1.5",
    "FLOORNAV_SERIAL__SILENCE_TIMEOUT_MS": "1000",
}


def start_daemon(robot: str, broker: Broker, directory: Path, **env: str) -> Daemon:
    web_port = free_port()
    log_path = directory / f"{robot}.log"
    environment = {
        **os.environ,
        "FLOORNAV_MQTT__URL": f"mqtt://127.0.0.1:{broker.port}",
        "FLOORNAV_MQTT__ROBOT_ID": robot,
        "FLOORNAV_MQTT__USERNAME": robot,
        "FLOORNAV_MQTT__PASSWORD_FILE": str(directory / f"{robot}.password"),
        "FLOORNAV_MQTT__KEEPALIVE_S": "5",
        "FLOORNAV_WEB__PORT": str(web_port),
        "FLOORNAV_VISER__ENABLED": "false",
        "FLOORNAV_TOKEN": TOKEN,
        **FLEET_ENV,
        **env,
    }
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [str(PROJECT_ROOT / ".venv" / "bin" / "floornav"), "run"],
            cwd=PROJECT_ROOT,
            env=environment,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    return Daemon(robot, web_port, proc, log_path, time.monotonic())


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    missing = [str(p) for p in (MOSQUITTO, Path(MOSQUITTO_PASSWD)) if not p.exists()]
    if missing:
        reason = (
            f"Mosquitto is not installed ({', '.join(missing)}): run scripts/install-broker-deps"
        )
        if os.environ.get("FLOORNAV_REQUIRE_BROKER") == "1":
            pytest.fail(reason)  # CI installs it: a skip there would hide a gap
        pytest.skip(reason)
    directory = tmp_path_factory.mktemp("mqtt")
    broker = Broker(free_port(), directory)
    write_broker_files(directory, broker.port, ["r1", "r2"])
    broker.start()
    subscriber = Subscriber(broker.port)
    daemons: list[Daemon] = []
    try:
        r1 = start_daemon(
            "r1",
            broker,
            directory,
            FLOORNAV_MQTT__HOMEASSISTANT="true",
        )
        daemons.append(r1)
        r2 = start_daemon("r2", broker, directory)
        daemons.append(r2)
        # Both polled together, so each one's ready time is when its API first answered.
        if not wait_until(lambda: all([d.poll_ready() for d in daemons]), 120.0, 0.02):
            raise RuntimeError("\n".join(f"{d.robot_id}:\n{d.log_tail()}" for d in daemons))
        yield Fleet(broker, subscriber, r1, r2)
    finally:
        for daemon in daemons:
            daemon.stop()
        subscriber.close()
        broker.kill()


def wait_until(predicate: Any, timeout_s: float, period_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return False


def driving(daemon: Daemon) -> bool:
    status = daemon.status()
    command = status.get("command") or {}
    return status["state"] == "running" and (command.get("left_pwm"), command.get("right_pwm")) != (
        0,
        0,
    )


PROTECTIVE = ("link", "camera", "stale")
MACHINE_STALL_STOPS_S = 0.2
"""A stall of the whole machine this long may explain a protective stop (see its use)."""


def protective_stops(status: dict[str, Any]) -> int:
    return sum(status["stops_by_cause"].get(cause, 0) for cause in PROTECTIVE)


@pytest.mark.broker
def test_availability_and_state_arrive_within_2_s_of_ready(fleet: Fleet) -> None:
    sub = fleet.subscriber
    for daemon in (fleet.r1, fleet.r2):
        assert daemon.ready_s is not None
        base = f"floornav/{daemon.robot_id}"
        online = sub.wait(f"{base}/availability", 0.0, 5.0, lambda p: p == b"online")
        state = sub.wait(f"{base}/state", 0.0, 5.0)
        assert online is not None and state is not None
        # Relative to the API answering (the daemon ready); the bridge starts with it.
        print(
            f"\n{daemon.robot_id}: online {online[0] - daemon.ready_s:+.2f} s, state "
            f"{state[0] - daemon.ready_s:+.2f} s after the API answered "
            f"({daemon.ready_s - daemon.started_s:.1f} s after the process started)"
        )
        assert online[0] - daemon.ready_s < 2.0
        assert state[0] - daemon.ready_s < 2.0
        assert json.loads(state[1])["state"] in {s.value for s in State}
        mqtt = daemon.status()["mqtt"]
        assert mqtt["state"] == "connected" and mqtt["robot_id"] == daemon.robot_id
    # r1 announces itself to Home Assistant, r2 does not.
    assert sub.wait("homeassistant/sensor/r1_state/config", 0.0, 5.0) is not None
    assert sub.wait("homeassistant/button/r1_stop/config", 0.0, 5.0) is not None
    assert not any(t.startswith("homeassistant/") and "r2" in t for _, t, _ in sub.messages)
    telemetry = sub.wait("floornav/r1/telemetry", 0.0, 5.0)
    assert telemetry is not None and "fps" in json.loads(telemetry[1])
    picture = sub.wait("floornav/r1/map", 0.0, 15.0)
    assert picture is not None and picture[1].startswith(b"\x89PNG")
    metrics = urllib.request.urlopen(f"http://127.0.0.1:{fleet.r1.web_port}/metrics").read()
    assert b"floornav_mqtt_connected 1.0" in metrics


@pytest.mark.broker
def test_start_without_the_token_is_refused(fleet: Fleet) -> None:
    sub = fleet.subscriber
    t0 = time.monotonic()
    sub.publish("floornav/r2/cmd", {"cmd": "start", "id": "no-token"})
    sub.publish("floornav/r2/cmd", {"cmd": "start", "id": "bad", "token": "x" * 24})
    sub.publish("floornav/r2/cmd", "not json")
    for ident in ("no-token", "bad"):
        reply = sub.wait(
            "floornav/r2/cmd/result", t0, 5.0, lambda p, i=ident: b'"' + i.encode() in p
        )
        assert reply is not None
        result = json.loads(reply[1])
        assert result["ok"] is False and "token" in result["error"] and result["cmd"] == "start"
    garbage = sub.wait("floornav/r2/cmd/result", t0, 5.0, lambda p: b"not JSON" in p)
    assert garbage is not None and json.loads(garbage[1])["ok"] is False


@pytest.mark.broker
def test_estop_stops_that_robot_within_100_ms_and_never_the_other(fleet: Fleet) -> None:
    sub, r1, r2 = fleet.subscriber, fleet.r1, fleet.r2
    r2_before = r2.status()
    end_to_end_ms, in_daemon_ms = [], []
    for attempt in range(20):
        assert wait_until(lambda: driving(r1), 10.0), (r1.status(), r1.log_tail())
        t0 = time.monotonic()
        published_wall = time.time()
        sub.publish("floornav/r1/cmd", {"cmd": "estop", "id": attempt})
        reply = sub.wait(
            "floornav/r1/cmd/result", t0, 5.0, lambda p, i=attempt: json.loads(p).get("id") == i
        )
        assert reply is not None, f"no reply to estop {attempt}"
        result = json.loads(reply[1])
        assert result["ok"] is True and result["state"] == "estopped", result
        assert result["pwm_zero_wall_s"] is not None, result
        end_to_end_ms.append((result["pwm_zero_wall_s"] - published_wall) * 1000)
        in_daemon_ms.append(result["latency_ms"])
        status = r1.status()
        assert status["state"] == "estopped"
        assert (status["command"]["left_pwm"], status["command"]["right_pwm"]) == (0, 0)
        for cmd in ("estop_reset", "start"):
            t1 = time.monotonic()
            sub.publish("floornav/r1/cmd", {"cmd": cmd, "id": f"{cmd}{attempt}", "token": TOKEN})
            ok = sub.wait(
                "floornav/r1/cmd/result",
                t1,
                5.0,
                lambda p, i=f"{cmd}{attempt}": json.loads(p).get("id") == i,
            )
            assert ok is not None and json.loads(ok[1])["ok"] is True, ok
    median = statistics.median(end_to_end_ms)
    print(
        f"\nestop -> PWM 0/0 acknowledged, 20 tries: publish-to-ack median {median:.1f} ms "
        f"(max {max(end_to_end_ms):.1f}); in the daemon median "
        f"{statistics.median(in_daemon_ms):.1f} ms (max {max(in_daemon_ms):.1f})"
    )
    assert median < 100.0, end_to_end_ms
    r2_after = r2.status()
    assert r2_after["estops"] == r2_before["estops"] == 0
    assert r2_after["mqtt"]["commands"] == r2_before["mqtt"]["commands"]
    assert r2_after["state"] != "estopped"
    assert r1.status()["estops"] >= 20


@pytest.mark.broker
def test_a_30_s_broker_outage_never_touches_driving(fleet: Fleet) -> None:
    daemons = (fleet.r1, fleet.r2)
    witness = shared_witness()
    assert all(wait_until(lambda d=d: d.status()["state"] == "running", 10.0) for d in daemons)
    before = {d.robot_id: d.status() for d in daemons}
    outage_start = time.monotonic()
    fleet.broker.kill()
    assert all(
        wait_until(lambda d=d: d.status()["mqtt"]["state"] != "connected", 5.0) for d in daemons
    )
    states: dict[str, set[str]] = {d.robot_id: set() for d in daemons}
    outage_end = time.monotonic() + 30.0
    while time.monotonic() < outage_end:
        for d in daemons:
            states[d.robot_id].add(d.status()["state"])
        time.sleep(0.25)
    during = {d.robot_id: d.status() for d in daemons}
    restarted = time.monotonic()
    fleet.broker.start()
    reconnected: dict[str, float] = {}
    deadline = restarted + 10.0
    while len(reconnected) < len(daemons) and time.monotonic() < deadline:
        for d in daemons:
            if d.robot_id not in reconnected and d.status()["mqtt"]["state"] == "connected":
                reconnected[d.robot_id] = time.monotonic() - restarted
        time.sleep(0.05)
    print(f"\nreconnected after the broker restarted: {reconnected} s")
    # A protective stop during the outage is the outage's doing unless the whole machine
    # stalled (`tests.stall_witness`): a stall of MACHINE_STALL_STOPS_S or more can age a
    # map past its 0.5 s (two daemons share 2 cores; seen once in CI, with one such stop
    # before the outage too).
    stalls = [
        (a, b)
        for a, b in witness.settled_gaps(outage_start, restarted)
        if b - a >= MACHINE_STALL_STOPS_S
    ]
    for d in daemons:
        rid = d.robot_id
        assert rid in reconnected and reconnected[rid] < 5.0, reconnected
        extra_stops = protective_stops(during[rid]) - protective_stops(before[rid])
        assert extra_stops <= len(stalls), (during[rid], stalls)
        assert "fault" not in states[rid], states
        if extra_stops:
            print(
                f"{rid}: {extra_stops} protective stop(s) during the outage, with the whole "
                f"machine stalled for {[round(b - a, 2) for a, b in stalls]} s"
            )
        else:
            assert "protective_stop" not in states[rid], states
        # It drove on: a stopped robot adds nothing; an exploring one also spends some of
        # the 30 s turning on the spot, so the distance itself is not the point.
        assert during[rid]["distance_m"] - before[rid]["distance_m"] > 0.5
        mqtt = d.status()["mqtt"]
        assert mqtt["reconnects"] == before[rid]["mqtt"]["reconnects"] + 1
        assert mqtt["last_error"]
    # The state is back on the new broker (retained messages died with the old one).
    sub = fleet.subscriber
    for d in daemons:
        assert sub.wait(f"floornav/{d.robot_id}/state", restarted, 5.0) is not None
        assert sub.wait(f"floornav/{d.robot_id}/availability", restarted, 5.0) is not None


@pytest.mark.broker
def test_a_killed_daemon_gets_its_last_will(fleet: Fleet) -> None:
    sub, r2 = fleet.subscriber, fleet.r2
    assert wait_until(lambda: r2.status()["mqtt"]["state"] == "connected", 10.0)
    t0 = time.monotonic()
    r2.proc.send_signal(signal.SIGKILL)
    r2.proc.wait(10)
    will = sub.wait("floornav/r2/availability", t0, 5.0, lambda p: p == b"offline")
    assert will is not None
    print(f"\nlast will 'offline' {(will[0] - t0) * 1000:.0f} ms after SIGKILL")
    # r1 is untouched and still online; stopped cleanly it says offline itself.
    r1 = fleet.r1
    assert r1.status()["mqtt"]["state"] == "connected"
    t1 = time.monotonic()
    r1.proc.send_signal(signal.SIGTERM)
    assert r1.proc.wait(30) == 0
    goodbye = sub.wait("floornav/r1/availability", t1, 5.0, lambda p: p == b"offline")
    assert goodbye is not None
    assert "MQTT: offline published" in r1.log_path.read_text(errors="replace")
