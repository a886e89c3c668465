"""In Chromium against the running daemon: what a page without the token may do (stop,
and nothing that moves the robot or changes it), and the API docs page, which must
render offline under the same strict content security policy as the dashboard."""

from __future__ import annotations

from typing import Any

import pytest
from playwright.sync_api import Page, Route, expect

from tests.browser.conftest import LiveServer, run_async, wait_for

pytestmark = pytest.mark.browser

FETCH = """async ([method, path, body]) => {
    const init = {method, headers: {}};
    if (body !== null) {
        init.headers["Content-Type"] = "application/json";
        init.body = JSON.stringify(body);
    }
    const response = await fetch(path, init);
    return response.status;
}"""

MOVING_OR_CHANGING: list[tuple[str, str, dict[str, Any] | None]] = [
    ("POST", "/api/start", None),
    ("POST", "/api/teleop", {"v_m_s": 0.1, "omega_rad_s": 0.0}),
    ("POST", "/api/estop/reset", None),
    ("POST", "/api/fault/reset", None),
    ("PATCH", "/api/config", {"drive": {"cruise_speed_m_s": 0.1}}),
    ("POST", "/api/calibrate", {"pattern": "9x6", "square_m": 0.025, "save": False}),
]


def test_a_page_without_the_token_can_stop_and_nothing_else(page: Page, robot: LiveServer) -> None:
    # A blank page of the dashboard's origin: same cookies and Origin as the dashboard,
    # no token anywhere.
    page.goto(f"{robot.base_url}/favicon.ico")
    refused = {
        f"{method} {path}": page.evaluate(FETCH, [method, path, body])
        for method, path, body in MOVING_OR_CHANGING
    }
    assert refused == {f"{method} {path}": 401 for method, path, _ in MOVING_OR_CHANGING}
    status = robot.status()
    assert not status["autonomous"] and status["state"] != "teleop"

    run_async(robot, robot.runtime.start)
    wait_for(lambda: robot.status()["autonomous"], 5.0, "autonomy on")
    assert page.evaluate(FETCH, ["POST", "/api/stop", None]) == 200
    wait_for(lambda: not robot.status()["autonomous"], 2.0, "the stop")
    assert page.evaluate(FETCH, ["POST", "/api/estop", {"source": "a page without token"}]) == 200
    wait_for(lambda: robot.status()["state"] == "estopped", 2.0, "the e-stop")
    # ... and the e-stop stays latched: the reset needs the token.
    assert page.evaluate(FETCH, ["POST", "/api/estop/reset", None]) == 401
    assert robot.status()["state"] == "estopped"


def test_the_api_docs_render_offline_under_the_csp(page: Page, live_server: LiveServer) -> None:
    elsewhere: list[str] = []

    def only_this_origin(route: Route) -> None:
        if route.request.url.startswith(live_server.base_url):
            route.continue_()
        else:  # a CDN: offline on the robot's network
            elsewhere.append(route.request.url)
            route.abort()

    page.route("**/*", only_this_origin)
    problems: list[str] = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda error: problems.append(str(error)))
    page.add_init_script(
        """document.addEventListener("securitypolicyviolation", (event) => {
            console.error(`CSP violation: ${event.violatedDirective} ${event.blockedURI}`);
        });"""
    )
    page.goto(f"{live_server.base_url}/docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("floornav", timeout=15_000)
    expect(page.locator(".opblock-summary-path", has_text="/api/estop").first).to_be_visible()
    # The bearer scheme is there to enter the token into.
    expect(page.locator(".swagger-ui .auth-wrapper .authorize")).to_be_visible()
    assert elsewhere == []
    assert problems == []
