"""A real daemon for the browser tests: the `Runtime` on the simulator, the web app
(uvicorn) and the viser view, all in one background thread with its own event loop;
Playwright (sync) drives Debian's chromium from the test thread.

Sync Playwright refuses to run inside an event loop, hence the thread. The server is
session-scoped (numba compiles the pipeline on the first frames); each test starts from
a clean state (`robot` fixture: no e-stop, no teleop driver).
"""

from __future__ import annotations

import asyncio
import gc
import os
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import pytest
from playwright.sync_api import Page

from app.config import load_config
from app.devices import open_devices
from app.runtime import Runtime
from app.web.server import WebService
from app.web.viser_view import ViserView

from ..conftest import free_port

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = Path("/usr/bin/chromium")
# Each run writes its screenshots here (not tracked); a chosen set is kept in
# docs/screenshots/. FLOORNAV_SCREENSHOTS moves them elsewhere.
SCREENSHOTS = Path(os.environ.get("FLOORNAV_SCREENSHOTS", ROOT / "build" / "screenshots"))
TOKEN = "browser-test-token-0123456789"
# measured-facts: Debian's chromium headless, no sandbox (root in CI), software GL.
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
FIRST_FRAME_TIMEOUT_S = 240.0  # a cold numba cache compiles the pipeline first

T = TypeVar("T")


@dataclass
class LiveServer:
    """Handles on the running daemon, for the tests' thread."""

    base_url: str
    runtime: Runtime
    view: ViserView
    loop: asyncio.AbstractEventLoop
    errors: list[BaseException] = field(default_factory=list)

    def call(self, fn: Callable[[], T], timeout_s: float = 10.0) -> T:
        """Run ``fn`` in the daemon's loop thread (the Runtime's methods expect that)."""

        async def run() -> T:
            return fn()

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(timeout_s)

    def status(self) -> dict[str, Any]:
        return self.call(self.runtime.status)

    def sim_pose(self) -> tuple[float, float, float]:
        sim = self.runtime.devices.sim
        assert sim is not None
        pose = sim.robot.pose
        return (pose.x_m, pose.y_m, pose.theta_rad)


def _serve(ready: threading.Event, holder: dict[str, Any], stop: threading.Event) -> None:
    async def main() -> None:
        web_port, viser_port = free_port(), free_port()
        config = load_config(
            ROOT / "config.toml",
            runtime={"autostart": False, "log_level": "warning"},
            web={"port": web_port},
            viser={"enabled": True, "port": viser_port},
        )
        with open_devices(config) as devices:
            runtime = Runtime(config, devices)
            # The daemon's own wiring (`floornav run` uses the same service).
            web = WebService(runtime, token=TOKEN)
            assert web.view is not None
            loop = asyncio.get_running_loop()
            holder["server"] = LiveServer(f"http://127.0.0.1:{web_port}", runtime, web.view, loop)
            run_task = asyncio.create_task(runtime.run(install_signals=False, services=[web]))
            while not web.started and not run_task.done():
                await asyncio.sleep(0.05)
            ready.set()
            try:
                while not stop.is_set() and not run_task.done():
                    await asyncio.sleep(0.1)
            finally:
                runtime.request_shutdown("tests finished")
                await asyncio.gather(run_task, return_exceptions=True)

    try:
        asyncio.run(main())
    except BaseException as exc:  # reported by the fixture
        holder["error"] = exc
        ready.set()


@pytest.fixture(scope="session")
def live_server() -> Iterator[LiveServer]:
    if not CHROMIUM.exists():
        if os.environ.get("FLOORNAV_REQUIRE_BROWSER"):
            pytest.fail("FLOORNAV_REQUIRE_BROWSER is set but /usr/bin/chromium is missing")
        pytest.skip("Debian's chromium is not installed (scripts/install-browser-deps)")
    ready, stop = threading.Event(), threading.Event()
    holder: dict[str, Any] = {}
    thread = threading.Thread(target=_serve, args=(ready, holder, stop), daemon=True, name="daemon")
    thread.start()
    ready.wait(60)
    if "error" in holder or "server" not in holder:
        raise RuntimeError(f"the test daemon did not start: {holder.get('error')!r}")
    server: LiveServer = holder["server"]
    deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
    while server.runtime.floors.peek() is None or server.runtime.maps.peek() is None:
        if time.monotonic() > deadline:
            raise RuntimeError("no perceived frame within the start-up timeout")
        time.sleep(0.2)
    # Like `floornav run` (app/daemon.py): freeze what exists once the pipeline runs.
    # By now this process also holds every earlier test's objects, and a full collection
    # over them stalls the test daemon's threads (the simulated Uno's link faulted and
    # the video latency doubled in one CI run).
    gc.collect()
    gc.freeze()
    try:
        yield server
    finally:
        gc.unfreeze()
        stop.set()
        thread.join(30)


@pytest.fixture
def robot(live_server: LiveServer) -> LiveServer:
    """The daemon with no e-stop latched and nobody driving, and the Uno connected."""

    def clean() -> None:
        live_server.runtime.reset_estop()
        live_server.runtime.release_teleop()
        # A fault latched by an earlier test (a starved simulated Uno under load) must
        # not fail every later test at its setup.
        live_server.runtime.reset_fault()

    live_server.call(clean)
    deadline = time.monotonic() + 15
    while live_server.status()["serial"]["state"] != "connected" or live_server.status()["fault"]:
        live_server.call(live_server.runtime.reset_fault)
        if time.monotonic() > deadline:
            pytest.fail(f"daemon not healthy: {live_server.status()['fault']}")
        time.sleep(0.1)
    return live_server


@pytest.fixture(scope="session")
def browser_type_launch_args(browser_type_launch_args: dict[str, Any]) -> dict[str, Any]:
    return {
        **browser_type_launch_args,
        "executable_path": str(CHROMIUM),
        "args": CHROMIUM_FLAGS,
        "headless": True,
    }


@pytest.fixture(scope="session")
def browser_context_args(browser_context_args: dict[str, Any]) -> dict[str, Any]:
    return {**browser_context_args, "viewport": {"width": 1280, "height": 900}}


@pytest.fixture(scope="session")
def screenshots() -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    return SCREENSHOTS


# -- helpers the browser tests share ----------------------------------------------------


def wait_for(condition: Callable[[], object], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def wait_js(page: Page, expression: str, timeout_s: float = 10.0) -> None:
    """Wait until ``expression`` is truthy in the page. Polled with evaluate:
    ``page.wait_for_function`` compiles its predicate with eval, which the dashboard's
    Content-Security-Policy refuses."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {expression}")
        page.wait_for_timeout(20)


def run_async(server: LiveServer, make: Callable[[], Coroutine[Any, Any, Any]]) -> Any:
    """Run a coroutine of the daemon on its event loop and wait for its result."""
    return asyncio.run_coroutine_threadsafe(make(), server.loop).result(30)
