"""The viser 3D view through the dashboard's /viser proxy (kept short: WebGL in software
costs one to two cores)."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import LiveServer

pytestmark = pytest.mark.browser


def test_viser_view_loads_through_the_proxy(
    page: Page, robot: LiveServer, screenshots: Path
) -> None:
    page.goto(f"{robot.base_url}/viser/")
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
        close.first.click()  # the "software WebGL" notice covers part of the scene
        page.wait_for_timeout(500)
    page.screenshot(path=str(screenshots / "viser.png"))
    summary = robot.view.timing_summary()
    print(f"\nviser update timings (ms): {summary}; map updates {robot.view.map_updates}")
    assert summary["pose"]["n"] and summary["map"]["n"]
