"""The deployment files (Dockerfile, systemd unit) and the sd_notify client.

No container engine runs here, so the Dockerfile is checked by reading it; the unit is
checked by reading it and, where systemd-analyze exists, by systemd's own verifier.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from app import systemd

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
UNIT = ROOT / "deploy" / "floornav.service"


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined, comments dropped."""
    instructions: list[tuple[str, str]] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.startswith("#"):
            continue  # a comment inside a continued instruction
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        full = (pending + line).strip()
        pending = ""
        keyword, _, args = full.partition(" ")
        instructions.append((keyword.upper(), args.strip()))
    return instructions


def unit_entries(text: str) -> dict[str, list[tuple[str, str]]]:
    """Section -> (key, value) in order; systemd allows repeated keys (DeviceAllow=)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = line[1:-1]
            sections.setdefault(current, [])
            continue
        key, sep, value = line.partition("=")
        assert sep, f"not KEY=VALUE in [{current}]: {line!r}"
        sections[current].append((key.strip(), value.strip()))
    return sections


def values(entries: list[tuple[str, str]], key: str) -> list[str]:
    return [v for k, v in entries if k == key]


# -- Dockerfile ---------------------------------------------------------------------------


def test_dockerfile_runs_as_a_non_root_user_after_installing() -> None:
    steps = dockerfile_instructions(DOCKERFILE.read_text())
    keywords = [k for k, _ in steps]
    assert steps[0] == ("FROM", "python:3.11-slim-bookworm")
    users = [(i, args) for i, (k, args) in enumerate(steps) if k == "USER"]
    assert users, "no USER instruction: the container would run as root"
    last_index, last_user = users[-1]
    assert last_user not in ("root", "0", "0:0")
    install = next(i for i, (k, a) in enumerate(steps) if k == "RUN" and "pip install" in a)
    assert install < last_index, "pip install must run before switching to the user"
    assert "RUN" not in keywords[last_index:], "no RUN as the unprivileged user is expected"
    useradd = next(a for k, a in steps if k == "RUN" and "useradd" in a)
    assert "dialout" in useradd and "video" in useradd, "the user needs the device groups"


def test_dockerfile_exposes_the_api_and_checks_its_health() -> None:
    steps = dockerfile_instructions(DOCKERFILE.read_text())
    assert ("EXPOSE", "8080") in steps
    health = [a for k, a in steps if k == "HEALTHCHECK"]
    assert len(health) == 1
    assert "/api/status" in health[0] and "urllib.request" in health[0]
    assert "CMD" in health[0]
    cmd = [a for k, a in steps if k == "CMD"]
    assert cmd and "floornav" in cmd[-1] and "run" in cmd[-1]
    env = " ".join(a for k, a in steps if k == "ENV")
    assert "FLOORNAV_WEB__HOST=0.0.0.0" in env, "the API must listen beyond the container"


def test_dockerignore_keeps_the_build_context_small_but_complete() -> None:
    ignored = {
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    }
    assert {".git", ".venv", "tests"} <= ignored
    steps = dockerfile_instructions(DOCKERFILE.read_text())
    for keyword, args in steps:
        if keyword == "COPY":
            *sources, _dest = args.split()
            for source in sources:
                assert source not in ignored, f"COPY {source} but .dockerignore drops it"
                assert (ROOT / source).exists(), f"COPY {source}: no such file in the project"


# -- systemd unit ------------------------------------------------------------------------


def test_unit_is_a_watched_notify_service_running_unprivileged() -> None:
    service = unit_entries(UNIT.read_text())["Service"]
    expected = {
        "Type": "notify",
        "WatchdogSec": "10",
        "Restart": "on-failure",
        "User": "floornav",
        "WorkingDirectory": "/opt/floornav",
        "EnvironmentFile": "-/etc/floornav/env",
        "ExecStart": "/opt/floornav/.venv/bin/floornav run --config /etc/floornav/config.toml",
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
    }
    for key, value in expected.items():
        assert values(service, key) == [value], key
    groups = values(service, "SupplementaryGroups")[0].split()
    assert set(groups) == {"dialout", "video"}


def test_unit_hardening_still_allows_the_uno_and_the_webcam() -> None:
    service = unit_entries(UNIT.read_text())["Service"]
    # PrivateDevices=yes would hide /dev/ttyACM* and /dev/video* altogether.
    assert values(service, "PrivateDevices") in ([], ["no"])
    assert values(service, "DevicePolicy") == ["closed"]
    allowed = {v.split()[0] for v in values(service, "DeviceAllow")}
    assert {"char-ttyACM", "char-video4linux"} <= allowed
    assert all(v.split()[1] == "rw" for v in values(service, "DeviceAllow"))
    # numba's JIT writes executable pages.
    assert values(service, "MemoryDenyWriteExecute") in ([], ["no"])
    assert unit_entries(UNIT.read_text())["Install"] == [("WantedBy", "multi-user.target")]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze absent")
def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    # /opt/floornav is not installed here: point ExecStart at a binary that exists.
    text = UNIT.read_text().replace(
        "ExecStart=/opt/floornav/.venv/bin/floornav ", "ExecStart=/bin/true "
    )
    unit = tmp_path / "floornav.service"
    unit.write_text(text)
    result = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "" and result.stderr.strip() == "", result.stderr


# -- sd_notify ---------------------------------------------------------------------------


@pytest.fixture
def notify_socket(monkeypatch: pytest.MonkeyPatch) -> Iterator[socket.socket]:
    """A datagram socket playing systemd, named by $NOTIFY_SOCKET (a short /tmp path:
    unix socket paths are limited to 107 bytes)."""
    folder = tempfile.mkdtemp(prefix="fn-notify-")
    path = os.path.join(folder, "notify")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    try:
        yield server
    finally:
        server.close()
        shutil.rmtree(folder, ignore_errors=True)


def test_notify_sends_one_datagram_per_call(notify_socket: socket.socket) -> None:
    assert systemd.notify("READY=1")
    assert notify_socket.recv(4096) == b"READY=1"
    assert systemd.notify("WATCHDOG=1\nSTATUS=exploring")
    assert notify_socket.recv(4096) == b"WATCHDOG=1\nSTATUS=exploring"


def test_notify_never_blocks_when_nobody_reads(notify_socket: socket.socket) -> None:
    """A notify socket whose reader stopped (a wedged manager, a runner that set
    $NOTIFY_SOCKET and never reads) fills after ~10 datagrams; a blocking send would then
    hang the daemon's event loop. Later messages are dropped instead."""
    started = time.monotonic()
    sent = [systemd.notify("WATCHDOG=1") for _ in range(50)]
    assert time.monotonic() - started < 1.0
    assert sent[0] is True
    assert sent[-1] is False, "the queue filled: the rest were dropped, not waited for"
    assert notify_socket.recv(4096) == b"WATCHDOG=1"


def test_notify_reaches_an_abstract_socket(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"floornav-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(b"\0" + name.encode())
        server.settimeout(2.0)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert systemd.notify("STOPPING=1")
        assert server.recv(4096) == b"STOPPING=1"


def test_notify_is_a_no_op_outside_systemd(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert systemd.notify("READY=1") is False
    monkeypatch.setenv("NOTIFY_SOCKET", "/nonexistent/floornav/notify")
    assert systemd.notify("READY=1") is False


def test_watchdog_interval_is_half_the_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    assert systemd.watchdog_interval_s() == pytest.approx(5.0)
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert systemd.watchdog_interval_s() == pytest.approx(5.0)
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert systemd.watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_PID")
    for off in ("", "0", "soon"):
        monkeypatch.setenv("WATCHDOG_USEC", off)
        assert systemd.watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert systemd.watchdog_interval_s() is None
