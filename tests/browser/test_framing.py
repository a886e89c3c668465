"""A page of another origin (another port of the same host, as in the issue's probe)
cannot frame the dashboard: Chromium refuses the frame (CSP frame-ancestors 'none',
X-Frame-Options DENY), so the framing page never reaches the stored token or a live
control socket."""

from __future__ import annotations

import http.server
import threading
import time
from collections.abc import Iterator

import pytest
from playwright.sync_api import Page

from tests.browser.conftest import LiveServer

from ..conftest import free_port

pytestmark = pytest.mark.browser


@pytest.fixture
def hostile_origin(live_server: LiveServer) -> Iterator[str]:
    """An http server on another port whose page frames the dashboard."""
    page = (
        "<!doctype html><title>elsewhere</title>"
        f'<iframe id="victim" src="{live_server.base_url}/" width="800" height="600"></iframe>'
    ).encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, format: str, *args: object) -> None:
            pass

    port = free_port()
    server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        server.shutdown()
        server.server_close()


def test_another_origin_cannot_frame_the_dashboard(
    page: Page, live_server: LiveServer, hostile_origin: str
) -> None:
    refused: list[str] = []
    page.on("console", lambda message: refused.append(message.text))
    page.goto(hostile_origin)
    frame = page.frame_locator("#victim")
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not any("frame" in m.lower() for m in refused):
        time.sleep(0.1)
    # The dashboard never loads inside the frame: no E-STOP, no script of ours ran.
    assert frame.locator("#estop").count() == 0
    assert any("frame-ancestors" in m or "X-Frame-Options" in m for m in refused), refused
