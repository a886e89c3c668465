"""The dashboard in Debian's chromium against a real daemon on the simulator."""

from __future__ import annotations

import math
import re
import statistics
import time
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import TOKEN, LiveServer, wait_for, wait_js
from tests.browser.shots import save_screenshot

pytestmark = pytest.mark.browser

LATENCY_FRAMES = 30


def open_dashboard(page: Page, server: LiveServer) -> None:
    page.goto(f"{server.base_url}/?token={TOKEN}")
    # The control socket greets with our driver name once the token is accepted.
    expect(page.locator("#me")).to_have_text(re.compile(r"^ws-\d+$"), timeout=15_000)
    expect(page.locator("#conn-control")).to_have_class("dot on")


def focus_the_page(page: Page) -> None:
    """Keys go to the page, not to a button or field."""
    page.evaluate("document.activeElement && document.activeElement.blur()")


def test_video_frames_arrive_with_low_latency(
    page: Page, robot: LiveServer, screenshots: Path
) -> None:
    open_dashboard(page, robot)
    expect(page.locator("#latency")).to_have_text(re.compile(r"^-?\d+$"), timeout=20_000)
    start = page.evaluate("window.floornav.frames")
    wait_js(page, f"window.floornav.frames >= {start + LATENCY_FRAMES}", LATENCY_FRAMES)
    latencies = page.evaluate(f"window.floornav.latenciesMs.slice(-{LATENCY_FRAMES})")
    server_part = page.evaluate(f"window.floornav.serverMs.slice(-{LATENCY_FRAMES})")
    assert len(latencies) == LATENCY_FRAMES
    ordered = sorted(latencies)
    median = statistics.median(ordered)
    p95 = ordered[min(len(ordered) - 1, math.ceil(0.95 * len(ordered)) - 1)]
    print(
        f"\nglass-to-browser latency over {len(latencies)} frames: "
        f"median {median:.1f} ms, p95 {p95:.1f} ms, max {ordered[-1]:.1f} ms; "
        f"capture-to-send in the daemon median {statistics.median(server_part):.1f} ms"
    )
    status = robot.status()
    print(
        f"daemon meanwhile: perception {status['stage_ms'].get('perception')} ms, "
        f"frame age at pick-up {status['pickup_age_ms']} ms, {status['fps']} fps"
    )
    # The map and the health table are filled in too.
    expect(page.locator("#map")).to_have_attribute("src", re.compile("^blob:"))
    expect(page.locator("#h-serial")).to_contain_text("connected")
    page.wait_for_timeout(700)  # one more map refresh with the frames' evidence
    save_screenshot(page, screenshots / "dashboard.png")
    # What the video path adds to the daemon's own capture-to-send (the socket, the
    # JPEG's decode, the page) is held to 100 ms, frame by frame. The whole glass-to-
    # browser figure is not: it waits for perception's overlay, and perception's speed
    # is the machine's (14 ms for floornet on a quiet core, 75 ms in one CI run where
    # this test's chromium and the suite shared the two cores: a 161.8 ms median then,
    # of which 137.3 ms were the daemon's). The daemon's share is measured by its runs.
    added = sorted(total - daemon for total, daemon in zip(latencies, server_part, strict=True))
    assert all(daemon >= 0.0 for daemon in server_part)
    added_median = statistics.median(added)
    assert added_median <= 100.0, (
        f"the video path adds {added_median:.1f} ms (median) to the daemon's capture-to-send"
    )


def test_keyboard_teleop_moves_and_stops_on_key_up(page: Page, robot: LiveServer) -> None:
    open_dashboard(page, robot)
    before = robot.sim_pose()
    focus_the_page(page)
    page.keyboard.down("ArrowUp")
    try:
        wait_for(lambda: robot.status()["state"] == "teleop", 2.0, "teleop state")
        # Moving is the point, not how fast: with this test's chromium on the robot's two
        # cores (and CI beside them) the key's commands can come late, and a fixed second
        # once saw 2 cm.
        wait_for(
            lambda: math.dist(before[:2], robot.sim_pose()[:2]) > 0.03,
            5.0,
            "the simulated robot 3 cm on while ArrowUp is held",
        )
    finally:
        page.keyboard.up("ArrowUp")
    released = time.monotonic()

    def stopped() -> bool:
        drive = robot.runtime.drives.peek()
        return drive is not None and drive.twist.v_m_s == 0 and drive.twist.omega_rad_s == 0

    wait_for(stopped, 0.6, "a zero command within 0.6 s of the key-up")
    print(f"\nkey-up to zero command: {(time.monotonic() - released) * 1000:.0f} ms")
    wait_for(lambda: robot.status()["teleop_driver"] is None, 1.0, "teleop released")


def test_estop_button_stops_the_robot(page: Page, robot: LiveServer, screenshots: Path) -> None:
    open_dashboard(page, robot)
    focus_the_page(page)
    page.keyboard.down("ArrowUp")
    try:
        wait_for(lambda: robot.status()["state"] == "teleop", 2.0, "teleop state")
        page.locator("#estop").click()
        wait_for(lambda: robot.status()["state"] == "estopped", 1.0, "state estopped")
    finally:
        page.keyboard.up("ArrowUp")
    wait_for(
        lambda: (
            (robot.status()["command"] or {}).get("v_m_s") == 0.0
            and robot.status()["command"]["left_pwm"] == 0
            and robot.status()["command"]["right_pwm"] == 0
        ),
        1.0,
        "a zero command",
    )
    expect(page.locator("#state")).to_have_text("estopped")
    expect(page.locator("#stop-estop")).to_contain_text("E-STOP latched")
    save_screenshot(page, screenshots / "estop.png")
    # Teleop is refused while latched, and the dashboard says so.
    page.keyboard.down("ArrowLeft")
    page.wait_for_timeout(300)
    page.keyboard.up("ArrowLeft")
    expect(page.locator("#control-message")).to_contain_text("e-stop is latched")
    assert robot.status()["state"] == "estopped"
    # Reset from the dashboard.
    page.locator("#estop-reset").click()
    wait_for(lambda: robot.status()["state"] != "estopped", 2.0, "e-stop reset")


def test_space_bar_is_an_estop(page: Page, robot: LiveServer) -> None:
    open_dashboard(page, robot)
    focus_the_page(page)
    page.keyboard.press("Space")
    wait_for(lambda: robot.status()["state"] == "estopped", 1.0, "state estopped")


def test_calibration_wizard_shows_why_it_failed(
    page: Page, robot: LiveServer, screenshots: Path
) -> None:
    open_dashboard(page, robot)
    page.locator("#calib-open").click()
    page.locator("#calib-detect").click()
    expect(page.locator("#calib-preview")).to_be_visible(timeout=10_000)
    expect(page.locator("#calib-info")).to_contain_text("No 9x6 board found")
    page.locator("#calib-accept").click()
    error = page.locator("#calib-error")
    expect(error).to_be_visible(timeout=20_000)
    text = error.inner_text()
    print(f"\ncalibration error shown: {text}")
    assert "422" in text or "409" in text
    assert robot.status()["state"] != "calibrating"
    save_screenshot(page, screenshots / "calibration.png")
    page.locator("#calib-cancel").click()
    expect(page.locator("#calib-dialog")).not_to_be_visible()


def test_safe_zone_editor_patches_the_live_config(page: Page, robot: LiveServer) -> None:
    open_dashboard(page, robot)
    page.locator("#zone-toggle").click()
    slider = page.locator("#zone-top_y_frac")
    expect(slider).to_have_value("0.8", timeout=5_000)
    slider.fill("0.75")
    page.locator("#zone-apply").click()
    expect(page.locator("#zone-message")).to_contain_text("applied")
    assert robot.runtime.config.perception.safe_zone.top_y_frac == pytest.approx(0.75)
    # An impossible zone is refused with the reason.
    page.locator("#zone-top_y_frac").fill("1")
    page.locator("#zone-bottom_y_frac").fill("0.5")
    page.locator("#zone-apply").click()
    expect(page.locator("#zone-message")).to_contain_text("refused")
    assert robot.runtime.config.perception.safe_zone.top_y_frac == pytest.approx(0.75)
    page.locator("#zone-revert").click()
    page.locator("#zone-top_y_frac").fill("0.8")
    page.locator("#zone-apply").click()
    expect(page.locator("#zone-message")).to_contain_text("applied")
    assert robot.runtime.config.perception.safe_zone.top_y_frac == pytest.approx(0.8)


def test_phone_layout(page: Page, robot: LiveServer, screenshots: Path) -> None:
    page.set_viewport_size({"width": 390, "height": 844})
    open_dashboard(page, robot)
    wait_js(page, "window.floornav.frames > 3", 10)
    estop_box = page.locator("#estop").bounding_box()
    assert estop_box is not None and estop_box["y"] + estop_box["height"] < 844 / 3
    # Nothing wider than the screen: no sideways scrolling on a phone.
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    # The pad is on the first screen too (tests/browser/test_operator_stop.py drives it).
    pad_box = page.locator("#pad").bounding_box()
    assert pad_box is not None and pad_box["y"] + pad_box["height"] <= 844
    save_screenshot(page, screenshots / "dashboard-phone.png")
