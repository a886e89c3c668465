"""Strict input: wrong JSON types are refused (422 naming the field), the configuration's
safety floors and speed limits hold against ``PATCH /api/config`` (and config.toml), an
e-stop is never refused for its label, and no client text puts a control character into
the log."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.config import ConfigError, load_config
from app.logs import JsonFormatter, TextFormatter, escape_control
from app.mapping.calibration import apply_homography
from app.web import create_app
from app.web.schemas import estop_source

from ..mapping.test_calibration import GROUND, camera_homography
from ..runtime.test_calibrate import publish_frame, standalone_runtime
from .conftest import AUTH, TOKEN
from .fakes import FakeService
from .test_rest import board_image, pairs

JSON = {"content-type": "application/json"}
FORGED = "panel\n12:00:00.000 INFO    e-stop reset by admin"


def refused(response: Any, named: str) -> None:
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and named in detail, detail


# -- request bodies ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ({"v_m_s": True, "omega_rad_s": 0}, "body.v_m_s"),
        ({"v_m_s": "0.1", "omega_rad_s": 0}, "body.v_m_s"),
        ({"v_m_s": 0.1, "omega_rad_s": "0"}, "body.omega_rad_s"),
        ({"v_m_s": 0.1, "omega_rad_s": False}, "body.omega_rad_s"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "take_over": 0}, "body.take_over"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "take_over": "true"}, "body.take_over"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "driver": 7}, "body.driver"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "driver": "pad\nINFO forged"}, "body.driver"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "driver": "pad\x00"}, "body.driver"),
        ({"v_m_s": 0.1, "omega_rad_s": 0, "driver": "pad\u2028"}, "body.driver"),
    ],
)
def test_teleop_types_are_strict(
    client: TestClient, service: FakeService, body: dict[str, Any], named: str
) -> None:
    refused(client.post("/api/teleop", headers=AUTH, json=body), named)
    assert service.calls == []


def test_integers_still_count_as_numbers(client: TestClient, service: FakeService) -> None:
    body = {"v_m_s": 0, "omega_rad_s": -1, "take_over": True, "driver": "pad 1"}
    assert client.post("/api/teleop", headers=AUTH, json=body).status_code == 200
    assert service.calls == [("teleop", "pad 1", 0.0, -1.0, True)]
    assert all(isinstance(value, float) for value in service.calls[0][2:4])


def test_teleop_release_driver_is_strict(client: TestClient, service: FakeService) -> None:
    for driver in (3, "a\rb"):
        response = client.post("/api/teleop/release", headers=AUTH, json={"driver": driver})
        refused(response, "body.driver")
    assert service.calls == []


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ({"pattern": "7x5", "square_m": "0.04"}, "square_m"),
        ({"pattern": "7x5", "square_m": True}, "square_m"),
        ({"pattern": "7x5", "square_m": 0.04, "save": 0}, "save"),
        ({"pattern": "7x5", "square_m": 0.04, "board_x_m": "0.4"}, "board_x_m"),
        ({"pairs": [{"image_px": ["1", 2], "ground_m": [1, 2]}] * 4}, "image_px"),
        ({"pairs": [{"image_px": [1, 2], "ground_m": [True, 2]}] * 4}, "ground_m"),
    ],
)
def test_calibration_types_are_strict(
    client: TestClient, service: FakeService, body: dict[str, Any], named: str
) -> None:
    service.publish_frame(board_image())
    refused(client.post("/api/calibrate", headers=AUTH, json=body), named)
    assert service.calls == []


def test_point_pairs_may_be_integers(client: TestClient, service: FakeService) -> None:
    service.publish_frame(board_image())
    pixels = apply_homography(camera_homography(), GROUND).round().astype(int).tolist()
    body = {"pairs": pairs(pixels, GROUND.tolist()), "save": False}
    response = client.post("/api/calibrate", headers=AUTH, json=body)
    assert response.status_code == 200, response.text


# -- the control socket --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("message", "named"),
    [
        ({"type": "teleop", "v_m_s": True, "omega_rad_s": 0}, "v_m_s"),
        ({"type": "teleop", "v_m_s": "0.1", "omega_rad_s": 0}, "v_m_s"),
        ({"type": "teleop", "v_m_s": 0.1, "omega_rad_s": 0, "take_over": 0}, "take_over"),
        ({"type": "stop", "id": 1.5}, "id"),
    ],
)
def test_control_messages_are_strict(
    client: TestClient, service: FakeService, message: dict[str, Any], named: str
) -> None:
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        socket.receive_json()
        socket.send_json(message)
        reply = socket.receive_json()
        assert reply["type"] == "error" and named in reply["detail"], reply
        socket.send_json({"type": "teleop", "v_m_s": 0, "omega_rad_s": 1})  # ints are fine
        assert socket.receive_json()["type"] == "ack"
    assert [c[0] for c in service.calls] == ["teleop", "release_teleop"]


def test_a_control_socket_estop_is_never_refused_for_its_form(
    client: TestClient, service: FakeService
) -> None:
    with client.websocket_connect("/ws/control", headers=dict(AUTH)) as socket:
        socket.receive_json()
        socket.send_json({"type": "estop", "id": 3, "source": "panel"})  # an extra field
        reply = socket.receive_json()
        assert reply["type"] == "ack" and reply["detail"] == "estop" and reply["id"] == 3
        assert reply["state"] == "estopped" and "source" in reply["warning"]
    assert service.calls[0][0] == "estop"


# -- the e-stop's label ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "source"),
    [
        (json.dumps({"source": FORGED}), "panel\\n12:00:00.000 INFO    e-stop reset by admin"),
        (json.dumps({"source": "a\x00b\x1b[2Jc\u2028d"}), "a\\x00b\\x1b[2Jc\\u2028d"),
        (json.dumps({"source": "x" * 200}), "x" * 64),  # cut, not refused
        (json.dumps({"source": ""}), "api"),
        (json.dumps({"source": 5}), "api"),
        (json.dumps({"source": "pad", "extra": 1}), "pad"),
        ("[1, 2]", "api"),
        ("{not json", "api"),
        ("", "api"),
    ],
)
def test_an_estop_is_never_refused_for_its_label(
    client: TestClient, service: FakeService, raw: str, source: str
) -> None:
    response = client.post("/api/estop", headers=JSON, content=raw)
    assert response.status_code == 200, response.text
    assert response.json()["state"] == "estopped"
    (call,) = service.calls
    assert call[0] == "estop" and call[1] == f"{source} (testclient)"
    assert estop_source(raw.encode()) == source


def test_the_estop_body_is_documented(client: TestClient) -> None:
    operation = client.get("/openapi.json").json()["paths"]["/api/estop"]["post"]
    body = operation["requestBody"]
    assert "source" in body["description"] and "never refused" in body["description"]
    assert body["content"]["application/json"]["schema"]["examples"] == [{"source": "dashboard"}]


def test_a_speed_limit_can_always_be_lowered(client: TestClient, service: FakeService) -> None:
    # Below the cruise speed too: the drive limiter clamps cruising to the limit.
    response = client.patch(
        "/api/config", headers=AUTH, json={"drive": {"max_linear_speed_m_s": 0.1}}
    )
    assert response.status_code == 200, response.text
    assert service.config.drive.max_linear_speed_m_s == 0.1


# -- PATCH /api/config ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("patch", "named"),
    [
        # JSON types, strictly
        ({"steering": {"cruise_speed_m_s": "0.2"}}, "steering.cruise_speed_m_s"),
        ({"steering": {"cruise_speed_m_s": True}}, "steering.cruise_speed_m_s"),
        ({"safety": {"auto_resume": 1}}, "safety.auto_resume"),
        ({"perception": {"safe_zone": {"top_y_frac": "0.7"}}}, "perception.safe_zone.top_y_frac"),
        ({"perception": {"smoothing_sigma_px": [3]}}, "perception.smoothing_sigma_px"),
        # limits the hardware sets
        ({"drive": {"max_linear_speed_m_s": 2.0}}, "drive.max_linear_speed_m_s"),
        ({"drive": {"max_angular_speed_rad_s": 6.0}}, "drive.max_angular_speed_rad_s"),
        # stop layers the network cannot switch off
        ({"safety": {"min_clearance_m": 0}}, "safety.min_clearance_m"),
        ({"safety": {"min_clearance_m": 0.05}}, "safety.min_clearance_m"),
        ({"safety": {"min_clearance_floor_m": 0.0}}, "safety.min_clearance_floor_m"),
        ({"safety": {"perception_max_age_s": 5.0}}, "safety.perception_max_age_s"),
        ({"safety": {"camera_max_age_s": 5.0}}, "safety.camera_max_age_s"),
        ({"safety": {"teleop_timeout_s": 5.0}}, "safety.teleop_timeout_s"),
        ({"safety": {"autonomy_timeout_s": 5.0}}, "safety.autonomy_timeout_s"),
        ({"safety": {"fault_latch_repeats": 100}}, "safety.fault_latch_repeats"),
        ({"safety": {"fault_latch_window_s": 0.001}}, "safety.fault_latch_window_s"),
        ({"safety": {"device_lost_latch_s": 600.0}}, "safety.device_lost_latch_s"),
        ({"drive": {"max_wheel_speed_m_s": 0.1}}, "drive.max_wheel_speed_m_s"),
    ],
)
def test_config_patch_refusals_name_the_key(
    client: TestClient, service: FakeService, patch: dict[str, Any], named: str
) -> None:
    refused(client.patch("/api/config", headers=AUTH, json=patch), named)
    assert service.calls == []


def test_config_patch_within_the_limits(client: TestClient, service: FakeService) -> None:
    patch = {
        "steering": {"cruise_speed_m_s": 0.45, "turn_speed_rad_s": 2},  # an int: fine
        "drive": {"max_linear_speed_m_s": 0.5, "max_angular_speed_rad_s": 5},
        "safety": {"min_clearance_m": 0.1, "auto_resume": False, "resume_after_clear_s": 2},
    }
    response = client.patch("/api/config", headers=AUTH, json=patch)
    assert response.status_code == 200, response.text
    config = service.config
    assert config.steering.cruise_speed_m_s == 0.45 and config.drive.max_linear_speed_m_s == 0.5
    assert config.steering.turn_speed_rad_s == 2.0 and config.safety.min_clearance_m == 0.1
    assert not config.safety.auto_resume
    assert "safety.*" not in response.json()["live_keys"]


# -- config.toml is held to the same rules -------------------------------------------------


@pytest.mark.parametrize(
    ("toml", "key"),
    [
        ("[safety]\nmin_clearance_m = 0.05\n", "safety.min_clearance_m"),
        ("[safety]\nmin_clearance_floor_m = 0.3\n", "safety.min_clearance_m"),  # the default
        ("[drive]\nmax_linear_speed_m_s = 0.6\n", "drive.max_linear_speed_m_s"),
        ("[drive]\nwheel_base_m = 0.8\n", "drive.max_angular_speed_rad_s"),  # 1.25 < 1.5
    ],
)
def test_config_files_are_held_to_the_same_limits(tmp_path: Path, toml: str, key: str) -> None:
    path = tmp_path / "config.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(path)


def test_a_config_file_may_lower_the_floor(tmp_path: Path) -> None:
    path = tmp_path / "config.toml"
    path.write_text("[safety]\nmin_clearance_floor_m = 0.0\nmin_clearance_m = 0.0\n")
    assert load_config(path).safety.min_clearance_m == 0.0


# -- control characters never reach the log ------------------------------------------------


@pytest.fixture
def log_output() -> Iterator[tuple[io.StringIO, logging.Handler]]:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    logger = logging.getLogger("floornav")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield stream, handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)


@pytest.mark.parametrize("formatter", [TextFormatter(), JsonFormatter()], ids=["text", "json"])
def test_an_estop_with_a_forged_line_logs_one_line(
    log_output: tuple[io.StringIO, logging.Handler], formatter: logging.Formatter
) -> None:
    """Through the real Runtime: its "E-STOP latched" and state lines stay one line each,
    and neither the NUL nor the separator gets through."""
    stream, handler = log_output
    handler.setFormatter(formatter)
    with standalone_runtime() as runtime:
        with TestClient(create_app(runtime, token=TOKEN, static_dir=None)) as client:
            source = FORGED + "\x00\u2028"
            response = client.post("/api/estop", json={"source": source})
        assert response.status_code == 200 and runtime.shared.mux.estopped
    lines = stream.getvalue().splitlines()
    estop_lines = [line for line in lines if "E-STOP latched" in line]
    assert len(estop_lines) == 1
    assert not any(line.startswith("12:00:00.000") for line in lines)  # nothing forged
    assert "e-stop reset by admin" in estop_lines[0]  # still there, escaped
    output = stream.getvalue()
    assert "\x00" not in output and "\u2028" not in output
    if isinstance(formatter, JsonFormatter):
        for line in lines:
            json.loads(line)


@pytest.mark.parametrize("formatter", [TextFormatter(), JsonFormatter()], ids=["text", "json"])
def test_the_formatters_escape_every_control_character(
    log_output: tuple[io.StringIO, logging.Handler], formatter: logging.Formatter
) -> None:
    stream, handler = log_output
    handler.setFormatter(formatter)
    log = logging.getLogger("floornav.test")
    log.warning("GET %s failed", "/api/x\r\nInjected: 1\x00", extra={"who\n": "a\tb\x1b"})
    try:
        raise ValueError("bad\x00value")
    except ValueError:
        log.exception("it broke")
    output = stream.getvalue()
    assert all(ch not in output for ch in "\x00\x1b\r\t\u2028")
    lines = output.splitlines()
    assert "Injected" in lines[0]  # still in the first record's line
    if isinstance(formatter, TextFormatter):
        assert "/api/x\\r\\nInjected: 1\\x00" in lines[0] and "who\\n=a\\tb\\x1b" in lines[0]
        assert lines[1].endswith("it broke")
        assert lines[2] == "Traceback (most recent call last):"  # it keeps its lines
        assert lines[-1] == "ValueError: bad\\x00value"
    else:
        first, second = (json.loads(line) for line in lines)
        assert first["msg"] == "GET /api/x\\r\\nInjected: 1\\x00 failed"
        assert first["who\\n"] == "a\\tb\\x1b"
        assert second["exc"].startswith("Traceback (most recent call last):\n")


def test_escape_control() -> None:
    assert escape_control("a\nb\rc\td\x00e\x7f\x85f\u2028\u2029 é") == (
        "a\\nb\\rc\\td\\x00e\\x7f\\x85f\\u2028\\u2029 é"
    )


def test_a_preview_through_the_api_changes_nothing_live() -> None:
    with standalone_runtime() as runtime:
        publish_frame(runtime)
        runtime.shared.autonomous = True
        live, mapper = runtime.calibration, runtime.mapper
        pixels = apply_homography(camera_homography(), GROUND)
        body = {"pairs": pairs(pixels.tolist(), GROUND.tolist())}
        with TestClient(create_app(runtime, token=TOKEN, static_dir=None)) as client:
            response = client.post("/api/calibrate", headers=AUTH, json={**body, "save": False})
        assert response.status_code == 200, response.text
        assert response.json()["saved_to"] is None
        assert runtime.calibration is live and runtime.mapper is mapper
        assert runtime.shared.autonomous


def test_a_failed_calibration_is_counted_in_the_metrics() -> None:
    with standalone_runtime() as runtime:
        publish_frame(runtime)
        runtime.shared.autonomous = True
        with TestClient(create_app(runtime, token=TOKEN, static_dir=None)) as client:
            body = {"pattern": "7x5", "square_m": 0.04, "save": True}
            response = client.post("/api/calibrate", headers=AUTH, json=body)
            assert response.status_code == 409 and "not found" in response.json()["detail"]
            metrics = client.get("/metrics").text
            status = client.get("/api/status").json()
    assert 'floornav_stops_total{cause="calibration"} 1.0' in metrics
    assert status["last_stop"]["cause"] == "calibration"
    assert status["last_stop"]["reason"].startswith("calibration failed: ")
    assert status["last_stop"]["reason"].endswith("; autonomy stays off until started")
