"""The viser 3D view through the dashboard's /viser proxy (kept short: WebGL in software
costs one to two cores). The door needs the session cookie, which the page gets the way
the dashboard does: ``POST /api/session`` with the bearer token."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import TOKEN, LiveServer

pytestmark = pytest.mark.browser


def test_viser_view_loads_through_the_proxy(
    page: Page, robot: LiveServer, screenshots: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The daemon's uvicorn logs to a logger that does not propagate to caplog's.
    uvicorn_log = logging.getLogger("uvicorn.error")
    uvicorn_log.addHandler(caplog.handler)
    try:
        _view_through_the_proxy(page, robot, screenshots)
    finally:
        uvicorn_log.removeHandler(caplog.handler)
    assert "Exception in ASGI application" not in caplog.text
    web_errors = [
        r
        for r in caplog.records
        if r.levelno >= logging.ERROR and r.name.startswith(("uvicorn", "floornav.viser"))
    ]
    assert not web_errors, [r.getMessage() for r in web_errors]


def _view_through_the_proxy(page: Page, robot: LiveServer, screenshots: Path) -> None:
    refused = page.goto(f"{robot.base_url}/viser/")
    assert refused is not None and refused.status == 401  # no cookie yet
    # As static/app.js does once the token is accepted (the cookie is HttpOnly: the
    # page never sees it, the browser sends it).
    status = page.evaluate(
        """async (token) => (await fetch("/api/session", {
            method: "POST",
            headers: {Authorization: `Bearer ${token}`},
            credentials: "same-origin",
        })).status""",
        TOKEN,
    )
    assert status == 204
    assert page.evaluate("document.cookie") == ""  # HttpOnly
    cookies = page.context.cookies(robot.base_url)
    session = next(c for c in cookies if c["name"] == "floornav_session")
    assert session["httpOnly"] and session["sameSite"] == "Strict" and session["expires"] == -1
    opened = page.goto(f"{robot.base_url}/viser/")
    assert opened is not None and opened.status == 200
    expect(page.locator("canvas").first).to_be_visible(timeout=60_000)
    # The scene arrives over the proxied WebSocket: viser counts the client.
    clients = 0
    for _ in range(100):
        assert robot.view.server is not None
        clients = len(robot.view.server.get_clients())
        if clients:
            break
        page.wait_for_timeout(100)
    assert clients >= 1, "no viser client connected through /viser"
    # viser fades the scene in once the first messages are applied; a software-rendered
    # canvas needs a few seconds for that.
    page.wait_for_timeout(5000)
    close = page.locator(".mantine-Notification-closeButton")
    if close.count():
        # The "software WebGL" notice covers part of the scene. A synthetic click: a
        # real one waits for animation frames, which software WebGL on a busy machine
        # delivers seconds apart (a click took 26 s once).
        close.first.dispatch_event("click")
        page.wait_for_timeout(500)
    page.screenshot(path=str(screenshots / "viser.png"))
    summary = robot.view.timing_summary()
    print(f"\nviser update timings (ms): {summary}; map updates {robot.view.map_updates}")
    assert summary["pose"]["n"] and summary["map"]["n"]
    # Closing the tab ends the relay quietly (it used to log a traceback each time).
    page.close()
    assert robot.view.server is not None
    for _ in range(100):
        if not robot.view.server.get_clients():
            break
        time.sleep(0.1)
    assert not robot.view.server.get_clients()
    time.sleep(0.5)
