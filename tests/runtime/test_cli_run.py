"""`floornav run` as a user runs it: bad config fails before any device, SIGTERM ends
with the motors at zero and a report, --duration-s writes the report's fields."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ..conftest import free_port

PROJECT = Path(__file__).resolve().parents[2]


def floornav(
    *args: str, env: dict[str, str] | None = None, **kwargs: object
) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "app", *args],
        cwd=PROJECT,
        env={**os.environ, **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,  # type: ignore[call-overload]
    )


def test_invalid_config_exits_before_touching_hardware(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[drive]\nmax_linear_speed_m_s = 9.0\n[serial]\nbackend = "sim"\nbogus = 1\n')
    proc = floornav("run", "--config", str(bad), "--duration-s", "5")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "drive.max_linear_speed_m_s" in err and "serial.bogus" in err
    assert "floornav daemon" not in out  # no banner: nothing was opened


@pytest.mark.sim
def test_sigterm_stops_the_motors_and_writes_the_report(tmp_path: Path) -> None:
    report = tmp_path / "r.json"
    proc = floornav(
        "run",
        "--duration-s",
        "120",
        "--report",
        str(report),
        env={
            "FLOORNAV_RUNTIME__LOG_JSON": "true",
            "FLOORNAV_WEB__PORT": str(free_port()),
            "FLOORNAV_VISER__PORT": str(free_port()),
            "FLOORNAV_TOKEN": "sigterm-test-token-00000000",
        },
    )
    assert proc.stderr is not None
    deadline = time.monotonic() + 60
    started = False
    lines = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if json.loads(line).get("event") == "start":
            started = True
            break
    assert started, "".join(lines)
    time.sleep(1.5)  # let it drive
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    events = [json.loads(line).get("event") for line in err.splitlines() if line.startswith("{")]
    assert "motors_zero" in events and "shutdown" in events
    assert "floornav daemon" in out and "simulated Uno" in out  # the banner
    data = json.loads(report.read_text())
    assert data["shutdown_reason"] == "SIGTERM"
    assert data["final_motor_pwm"] == [0, 0]
    assert data["collisions"] == 0
    for key in (
        "frames",
        "fps",
        "latency_ms",
        "stage_ms",
        "coverage_ratio",
        "map_iou",
        "distance_m",
        "estops",
        "watchdog_stops",
        "rss_mb",
    ):
        assert key in data
    assert set(data["latency_ms"]) >= {"p50", "p95", "max"}
    assert set(data["latency_from_arrival_ms"]) >= {"p50", "p95", "max"}
    assert set(data["rss_mb"]) >= {"after_first_minute", "end", "steady_median", "peak"}
    assert isinstance(data["serial"]["deadman_trips_seen"], int)


def test_simulated_camera_with_a_real_uno_is_refused_naming_the_key() -> None:
    proc = floornav(
        "run",
        "--duration-s",
        "5",
        env={"FLOORNAV_SERIAL__BACKEND": "port", "FLOORNAV_SERIAL__PORT": "/dev/null-uno"},
    )
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "camera.source" in err


@pytest.mark.sim
def test_systemd_gets_ready_and_watchdog_pings(tmp_path: Path) -> None:
    """Under systemd (Type=notify, WatchdogSec): READY=1 once the API serves, then
    WATCHDOG=1 at half the watchdog interval while the stages run."""
    import socket as socketlib

    address = tmp_path / "notify.sock"
    sock = socketlib.socket(socketlib.AF_UNIX, socketlib.SOCK_DGRAM)
    sock.bind(str(address))
    sock.settimeout(60)
    port = free_port()
    proc = floornav(
        "run",
        "--duration-s",
        "30",
        env={
            "NOTIFY_SOCKET": str(address),
            "WATCHDOG_USEC": "400000",  # pings every 0.2 s
            "FLOORNAV_WEB__PORT": str(port),
            "FLOORNAV_VISER__ENABLED": "false",
            "FLOORNAV_TOKEN": "systemd-test-token-0000000",
        },
    )
    try:
        messages: list[str] = []
        start = time.monotonic()
        while time.monotonic() - start < 60:
            messages.append(sock.recv(4096).decode())
            if (
                any("READY=1" in m for m in messages)
                and sum("WATCHDOG=1" in m for m in messages) >= 5
            ):
                break
        assert any("READY=1" in m for m in messages), messages
        assert sum("WATCHDOG=1" in m for m in messages) >= 5
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=20)
        sock.close()
    assert proc.returncode == 0


async def test_startup_objects_are_frozen_once_the_first_map_exists() -> None:
    import asyncio
    import gc
    from types import SimpleNamespace

    from app.channels import LatestSlot
    from app.daemon import _freeze_startup_objects

    maps: LatestSlot[int] = LatestSlot("maps")
    runtime = SimpleNamespace(maps=maps)
    before = gc.get_freeze_count()  # the test session froze what collection imported
    made_since = [[k] for k in range(1000)]  # tracked objects the freeze must take
    task = asyncio.create_task(_freeze_startup_objects(runtime))  # type: ignore[arg-type]
    await asyncio.sleep(0.25)
    assert not task.done() and gc.get_freeze_count() == before  # waits for the pipeline
    maps.publish(1)
    await asyncio.wait_for(task, 2.0)
    assert gc.get_freeze_count() >= before + len(made_since)


async def test_the_running_daemon_trims_its_heap_periodically_off_the_event_loop() -> None:
    import asyncio
    import threading

    from app.daemon import release_freed_memory_every

    loop_thread = threading.get_ident()
    trims: list[int] = []

    def release() -> bool:
        trims.append(threading.get_ident())
        return True

    task = asyncio.create_task(release_freed_memory_every(0.02, release))
    await asyncio.sleep(0.2)
    assert not task.done()
    task.cancel()
    assert len(trims) >= 3
    assert loop_thread not in trims  # a trim holds malloc's locks: never on the loop


async def test_without_glibc_the_periodic_trim_ends_quietly() -> None:
    import asyncio

    from app.daemon import release_freed_memory_every

    calls: list[float] = []

    def unavailable() -> bool:
        calls.append(0.0)
        return False

    await asyncio.wait_for(release_freed_memory_every(0.01, unavailable), 2.0)
    assert len(calls) == 1


RELEASE_CHILD = """
import sys
from app.daemon import release_freed_memory

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

blocks = [bytearray(32 * 1024) for _ in range(6000)]  # ~190 MB on the heap
kept = blocks[::100]  # pins scattered chunks: the heap cannot shrink from its top alone
del blocks
before = rss_mb()
assert release_freed_memory()
print(before, rss_mb())
"""


def test_freed_heap_memory_goes_back_to_the_system_after_the_warm_up() -> None:
    """What the kernel warm-up freed must not stay resident for the daemon's life."""
    out = subprocess.run(
        [sys.executable, "-c", RELEASE_CHILD], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    before, after = map(float, out.stdout.split())
    assert before - after > 100, (before, after)


COMPILER_PAGES_CHILD = """
import mmap
import os
import sys
import numba
import numpy as np
from app.daemon import release_compiler_code

def private_clean_kb(name):
    # Only this process's own unmodified pages can be reclaimed; pages other processes
    # map too (the test runner has LLVM's) stay.
    total, inside = 0, False
    for line in open("/proc/self/smaps"):
        fields = line.split()
        if "-" in fields[0] and len(fields) >= 5:
            inside = len(fields) >= 6 and name in fields[5]
        elif fields[0] == "Private_Clean:" and inside:
            total += int(fields[1])
    return total

# The mechanism, on a file no other process maps: 16 MB mapped like a library's code.
path = sys.argv[1]
with open(path, "wb") as out:
    out.write(bytes(range(256)) * (16 * 4096))
    out.flush()
    os.fsync(out.fileno())  # clean pages, as a library's are (dirty ones need writing)
with open(path, "rb") as source:
    mapped = mmap.mmap(source.fileno(), 0, flags=mmap.MAP_PRIVATE, prot=mmap.PROT_READ)
touched = sum(mapped[i] for i in range(0, len(mapped), 4096))
before = private_clean_kb(path)
advised = release_compiler_code(path)
after = private_clean_kb(path)
assert mapped[:256] == bytes(range(256)) and mapped[-1] == 255  # read back, intact

# The compiler's own library: found, and numba still runs and compiles after.
@numba.njit(nogil=True)
def add(a, b):
    return a + b

assert add(1, 2) == 3
compiler_advised = release_compiler_code()
assert add(1, 2) == 3
assert add(np.float32(1.5), np.float32(2.0)) == 3.5
print(advised, before, after, compiler_advised)
"""


def test_the_compilers_code_pages_go_back_once_the_kernels_are_ready(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-c", COMPILER_PAGES_CHILD, str(tmp_path / "code.bin")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    advised, before_kb, after_kb, compiler_advised = map(int, out.stdout.split())
    if advised == 0:
        pytest.skip("this kernel has no MADV_PAGEOUT (Linux 5.4+)")
    assert advised == 16 * 1024 * 1024  # the whole mapping
    assert compiler_advised > 10 * 1024 * 1024  # LLVM's mappings were found
    assert before_kb == 16 * 1024  # touched, clean, this process's alone
    assert after_kb < 1024


def test_releasing_the_compilers_code_without_that_library_does_nothing() -> None:
    from app.daemon import release_compiler_code

    assert release_compiler_code("no-such-library-in-this-process") == 0
