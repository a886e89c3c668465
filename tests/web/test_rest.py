"""The REST API against a fake service: every endpoint, auth, validation, refusals."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.mapping.calibration import apply_homography
from app.mapping.calibration_files import load_floor_calibration
from app.messages import State

from ..mapping.test_calibration import (
    GROUND,
    HEIGHT,
    PATTERN,
    SQUARE_M,
    WIDTH,
    camera_homography,
    render_floor_board,
)
from .conftest import AUTH, TOKEN
from .fakes import FakeService, floor_msg

JSON = {"content-type": "application/json"}

STATE_CHANGING: list[tuple[str, str, dict[str, Any] | None]] = [
    ("POST", "/api/start", None),
    ("POST", "/api/estop/reset", None),
    ("POST", "/api/fault/reset", None),
    ("POST", "/api/teleop", {"v_m_s": 0.1, "omega_rad_s": 0.0}),
    ("POST", "/api/teleop/release", None),
    ("POST", "/api/calibrate", {"pattern": "7x5", "square_m": 0.04}),
    ("PATCH", "/api/config", {"steering": {"cruise_speed_m_s": 0.2}}),
    ("GET", "/api/auth", None),
]


@pytest.mark.parametrize(("method", "path", "body"), STATE_CHANGING)
@pytest.mark.parametrize(
    "headers",
    [{}, {"Authorization": "Bearer wrong-token-0123456789"}, {"Authorization": TOKEN}],
    ids=["missing", "wrong", "not-bearer"],
)
def test_state_changing_endpoints_need_the_token(
    client: TestClient,
    service: FakeService,
    method: str,
    path: str,
    body: dict[str, Any] | None,
    headers: dict[str, str],
) -> None:
    response = client.request(method, path, json=body, headers=headers)
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert "token" in response.json()["detail"]
    assert service.calls == []


@pytest.mark.parametrize("path", ["/api/stop", "/api/estop"])
@pytest.mark.parametrize(
    "headers",
    [{}, {"Authorization": "Bearer wrong-token-0123456789"}, AUTH],
    ids=["missing", "wrong", "right"],
)
def test_stopping_needs_no_token(
    client: TestClient, service: FakeService, path: str, headers: dict[str, str]
) -> None:
    response = client.post(path, headers=headers)
    assert response.status_code == 200
    assert [name for name, *_ in service.calls] == [path.removeprefix("/api/")]


def test_status_is_open_and_strict_json(client: TestClient) -> None:
    response = client.get("/api/status")
    assert response.status_code == 200
    status = json.loads(response.text)  # strict: NaN would not parse in a browser
    assert status["state"] == "idle"
    assert status["fps"] == 12.5
    assert status["clearance_ahead_m"] is None  # the fake reports NaN
    assert status["zone_floor_confidence"] is None  # no frame yet
    assert status["stop_cause"] is None and status["stop_reason"] is None
    assert "NaN" not in response.text


def test_status_reports_the_safe_zone_confidence_and_the_stop(
    client: TestClient, service: FakeService
) -> None:
    service.floors.publish(floor_msg(1, zone_floor_confidence=0.31))
    service.stop_cause = "not_floor"
    service.stop_reason = "safe zone is not floor (confidence 0.31 < 0.50): turning"
    status = client.get("/api/status").json()
    assert status["zone_floor_confidence"] == 0.31
    assert status["zone_min_floor_confidence"] == 0.5
    assert status["stop_cause"] == "not_floor"
    assert "not floor" in status["stop_reason"]


def test_reads_need_the_token_when_configured(service: FakeService) -> None:
    from app.web import create_app

    service.config = service.config.model_copy(
        update={"web": service.config.web.model_copy(update={"require_token_for_status": True})}
    )
    with TestClient(create_app(service, token=TOKEN, static_dir=None)) as client:
        for path in ("/api/status", "/api/config", "/metrics"):
            assert client.get(path).status_code == 401, path
            assert client.get(path, headers=AUTH).status_code == 200, path


def test_start_stop_estop_reset_and_auth_check(client: TestClient, service: FakeService) -> None:
    assert client.get("/api/auth", headers=AUTH).status_code == 204
    response = client.post("/api/start", headers=AUTH)
    assert response.status_code == 200 and response.json()["state"] == "running"
    assert client.post("/api/stop", headers=AUTH).json()["state"] == "idle"
    response = client.post("/api/estop", headers=AUTH, json={"source": "dashboard"})
    assert response.json()["state"] == "estopped"
    assert service.calls[-1][0] == "estop" and service.calls[-1][1].startswith("dashboard (")
    client.post("/api/estop", headers=AUTH)  # no body: source "api"
    assert service.calls[-1][1].startswith("api (")
    reset = client.post("/api/estop/reset", headers=AUTH).json()
    assert reset == {"ok": True, "state": "idle", "detail": "", "was_estopped": True}
    assert client.post("/api/estop/reset", headers=AUTH).json()["was_estopped"] is False
    assert client.post("/api/fault/reset", headers=AUTH).json()["cleared"] is None
    assert [c[0] for c in service.calls] == [
        "start", "stop", "estop", "estop", "reset_estop", "reset_estop", "reset_fault",
    ]  # fmt: skip


def test_refused_commands_are_409_with_the_reason(client: TestClient, service: FakeService) -> None:
    service.refuse = {"start": "e-stop is latched: reset it first", "teleop": "no Uno"}
    response = client.post("/api/start", headers=AUTH)
    assert response.status_code == 409
    assert response.json() == {"detail": "e-stop is latched: reset it first"}
    response = client.post("/api/teleop", headers=AUTH, json={"v_m_s": 0.1, "omega_rad_s": 0})
    assert response.status_code == 409 and response.json()["detail"] == "no Uno"


def test_teleop_and_release(client: TestClient, service: FakeService) -> None:
    body = {"v_m_s": -0.2, "omega_rad_s": 1.5, "driver": "joystick", "take_over": True}
    response = client.post("/api/teleop", headers=AUTH, json=body)
    assert response.status_code == 200 and response.json()["state"] == "teleop"
    assert service.calls[-1] == ("teleop", "joystick", -0.2, 1.5, True)
    client.post("/api/teleop", headers=AUTH, json={"v_m_s": 0.1, "omega_rad_s": 0})
    assert service.calls[-1] == ("teleop", "api", 0.1, 0.0, False)
    client.post("/api/teleop/release", headers=AUTH, json={"driver": "joystick"})
    assert service.calls[-1] == ("release_teleop", "joystick")
    client.post("/api/teleop/release", headers=AUTH)
    assert service.calls[-1] == ("release_teleop", None)


@pytest.mark.parametrize(
    ("raw_body", "named"),
    [
        ('{"v_m_s": NaN, "omega_rad_s": 0}', "v_m_s"),
        ('{"v_m_s": Infinity, "omega_rad_s": 0}', "v_m_s"),
        ('{"v_m_s": 2.5, "omega_rad_s": 0}', "v_m_s"),
        ('{"v_m_s": 0, "omega_rad_s": -10.5}', "omega_rad_s"),
        ('{"v_m_s": "fast", "omega_rad_s": 0}', "v_m_s"),
        ('{"v_m_s": 0}', "omega_rad_s"),
        ('{"v_m_s": 0, "omega_rad_s": 0, "speed": 1}', "speed"),
        ('{"v_m_s": 0, "omega_rad_s": 0, "driver": ""}', "driver"),
        ("[1, 2]", "body"),
        ("{not json", "body"),
    ],
)
def test_bad_teleop_bodies_are_422_naming_the_field(
    client: TestClient, service: FakeService, raw_body: str, named: str
) -> None:
    response = client.post("/api/teleop", headers={**AUTH, **JSON}, content=raw_body)
    assert response.status_code == 422
    detail = response.json()["detail"]
    assert isinstance(detail, str) and named in detail
    assert service.calls == []


def test_config_get_hides_the_token(service: FakeService) -> None:
    from app.web import create_app

    service.config = service.config.model_copy(
        update={"web": service.config.web.model_copy(update={"token": TOKEN})}
    )
    with TestClient(create_app(service, token=TOKEN, static_dir=None)) as client:
        document = client.get("/api/config").json()
    assert document["config"]["web"]["token"] == "<set>"
    assert TOKEN not in json.dumps(document)
    assert "steering.*" in document["live_keys"]


def test_config_patch_of_live_keys(client: TestClient, service: FakeService) -> None:
    patch = {
        "steering": {"cruise_speed_m_s": 0.2},
        "drive": {"max_linear_speed_m_s": 0.25},
        "perception": {"method": "thesis", "safe_zone": {"top_y_frac": 0.7}},
        "safety": {"min_clearance_m": 0.3},
    }
    response = client.patch("/api/config", headers=AUTH, json=patch)
    assert response.status_code == 200
    config = response.json()["config"]
    assert config["steering"]["cruise_speed_m_s"] == 0.2
    assert config["perception"]["safe_zone"]["top_y_frac"] == 0.7
    assert config["steering"]["turn_speed_rad_s"] == 1.5  # untouched keys stay
    updates = [c[1] for c in service.calls if c[0] == "update_config"]
    assert len(updates) == 1
    new = updates[0]
    assert new.drive.max_linear_speed_m_s == 0.25 and new.perception.method == "thesis"
    assert service.config is new


@pytest.mark.parametrize(
    ("patch", "named"),
    [
        ({"camera": {"fps_hz": 15}}, "camera.fps_hz"),  # not live
        ({"drive": {"wheel_base_m": 0.3}}, "drive.wheel_base_m"),  # geometry: not live
        ({"web": {"token": "x" * 20}}, "web.token"),
        ({"steering": {"bogus": 1}}, "steering.bogus"),  # unknown
        ({"nosuchsection": {"a": 1}}, "nosuchsection"),
        ({"steering": {"cruise_speed_m_s": 50}}, "steering.cruise_speed_m_s"),  # bounds
        ({"steering": {"cruise_speed_m_s": "fast"}}, "steering.cruise_speed_m_s"),
        ({"steering": {"cruise_speed_m_s": None}}, "steering.cruise_speed_m_s"),
        ({"perception": {"method": "magic"}}, "perception.method"),
        ({"steering": 3}, "steering"),
    ],
)
def test_config_patch_rejections_name_the_key(
    client: TestClient, service: FakeService, patch: dict[str, Any], named: str
) -> None:
    response = client.patch("/api/config", headers=AUTH, json=patch)
    assert response.status_code == 422, response.text
    assert named in response.json()["detail"]
    assert service.calls == []


def test_values_that_conflict_with_the_running_configuration_get_409(
    client: TestClient, service: FakeService
) -> None:
    # Each value is within its bounds; together they turn the safe zone inside out.
    response = client.patch(
        "/api/config", headers=AUTH, json={"perception": {"safe_zone": {"top_y_frac": 1.0}}}
    )
    assert response.status_code == 409, response.text
    assert "top_y_frac" in response.json()["detail"]
    assert service.calls == []


def test_config_patch_body_must_be_an_object(client: TestClient) -> None:
    response = client.patch("/api/config", headers={**AUTH, **JSON}, content="[1]")
    assert response.status_code == 422 and response.json()["detail"]


def pairs(pixels: list[Any], ground: list[Any]) -> list[dict[str, Any]]:
    """The point-pair calibration body's ``pairs``."""
    return [{"image_px": u, "ground_m": g} for u, g in zip(pixels, ground, strict=True)]


def board_image() -> np.ndarray:
    return render_floor_board(camera_homography(), (0.45, -0.12))


def test_calibrate_with_a_chessboard(client: TestClient, service: FakeService) -> None:
    service.publish_frame(board_image())
    body = {"pattern": "7x5", "square_m": SQUARE_M, "board_x_m": 0.45, "board_y_m": -0.12}
    response = client.post("/api/calibrate", headers=AUTH, json=body)
    assert response.status_code == 200, response.text
    result = response.json()
    assert result["points"] == result["inliers"] == 35
    assert result["reprojection_rms_px"] < 0.3 and result["ground_rms_m"] < 0.001
    assert len(result["corners_px"]) == 35 and result["image_size"] == [WIDTH, HEIGHT]
    expected_origin = apply_homography(camera_homography(), np.array([[0.45, -0.12]]))[0]
    np.testing.assert_allclose(result["board_origin_px"], expected_origin, atol=0.3)
    saved = Path(service.config.mapping.floor_calibration_file)
    assert result["saved_to"] == str(saved)
    loaded = load_floor_calibration(saved, (WIDTH, HEIGHT))
    assert loaded.points == 35


def test_calibrate_with_point_pairs_without_saving(
    client: TestClient, service: FakeService
) -> None:
    service.publish_frame(board_image())
    pixels = apply_homography(camera_homography(), GROUND)
    body = {
        "pairs": pairs(pixels.tolist(), GROUND.tolist()),
        "save": False,
    }
    response = client.post("/api/calibrate", headers=AUTH, json=body)
    assert response.status_code == 200, response.text
    result = response.json()
    assert result["ground_rms_m"] < 1e-6 and result["corners_px"] is None
    assert result["saved_to"] is None
    assert not Path(service.config.mapping.floor_calibration_file).exists()


@pytest.mark.parametrize(
    "body",
    [
        {"pattern": "7x5", "square_m": -1},
        {"pattern": "seven", "square_m": 0.04},
        {"pattern": "2x2", "square_m": 0.04},  # OpenCV's detector raises below 3x3
        {"pattern": "7x5", "square_m": 0.04, "board_yaw_rad": float("nan")},
        {"pairs": pairs([[1, 2]] * 3, [[1, 2]] * 3)},  # too few
        {"pairs": [{"image_px": [1, 2]}] * 4},  # a pixel without its floor position
        {"image_points_px": [[1, 2]] * 4, "ground_points_m": [[1, 2]] * 4},  # old shape
        {},
    ],
)
def test_bad_calibration_bodies_are_422(
    client: TestClient, service: FakeService, body: dict[str, Any]
) -> None:
    service.publish_frame(board_image())
    raw = json.dumps(body)  # allows NaN, like a sloppy client
    response = client.post("/api/calibrate", headers={**AUTH, **JSON}, content=raw)
    assert response.status_code == 422 and response.json()["detail"]
    assert service.calls == []


def test_calibration_failures_are_409_with_the_reason(
    client: TestClient, service: FakeService
) -> None:
    service.publish_frame(np.full((HEIGHT, WIDTH, 3), 128, np.uint8))  # no board
    response = client.post(
        "/api/calibrate", headers=AUTH, json={"pattern": "7x5", "square_m": SQUARE_M}
    )
    assert response.status_code == 409
    assert "not found" in response.json()["detail"]
    # Degenerate pairs (all on a line) are refused by the fit, not by the schema.
    line = [[100.0 + 10 * i, 300.0] for i in range(4)]
    ground = [[0.5, 0.1 * i] for i in range(4)]
    response = client.post("/api/calibrate", headers=AUTH, json={"pairs": pairs(line, ground)})
    assert response.status_code == 409 and response.json()["detail"]


def test_calibration_without_a_frame_is_409(client: TestClient) -> None:
    response = client.post(
        "/api/calibrate", headers=AUTH, json={"pattern": "7x5", "square_m": SQUARE_M}
    )
    assert response.status_code == 409
    assert "frame" in response.json()["detail"]


def test_calibration_preview(client: TestClient, service: FakeService) -> None:
    assert client.get("/api/calibrate/preview").status_code == 409
    service.publish_frame(board_image())
    plain = client.get("/api/calibrate/preview")
    assert plain.status_code == 200 and plain.headers["content-type"] == "image/jpeg"
    assert plain.headers["x-chessboard-corners"] == "0"
    drawn = client.get("/api/calibrate/preview", params={"pattern": "7x5"})
    assert drawn.headers["x-chessboard-corners"] == str(PATTERN[0] * PATTERN[1])
    image = cv2.imdecode(np.frombuffer(drawn.content, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (HEIGHT, WIDTH, 3)
    for bad in ("x", "2x5"):
        assert client.get("/api/calibrate/preview", params={"pattern": bad}).status_code == 422


def test_unknown_paths_and_methods_are_json_errors(client: TestClient) -> None:
    missing = client.get("/api/nothing")
    assert missing.status_code == 404 and missing.json() == {"detail": "Not Found"}
    wrong = client.get("/api/start")
    assert wrong.status_code == 405 and wrong.json()["detail"]


def test_openapi_docs(client: TestClient) -> None:
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for path in ("/api/status", "/api/teleop", "/api/config", "/api/calibrate", "/metrics"):
        assert path in paths


def test_static_files_are_served_after_the_api(tmp_path: Path, service: FakeService) -> None:
    from fastapi import APIRouter

    from app.web import create_app

    (tmp_path / "index.html").write_text("<h1>floornav</h1>")
    (tmp_path / "api").mkdir()  # must not shadow the API
    extra = APIRouter()

    @extra.get("/viser/ping")
    async def ping() -> dict[str, bool]:
        return {"pong": True}

    app = create_app(service, token=TOKEN, static_dir=tmp_path, viser_router=extra)
    with TestClient(app) as client:
        assert "floornav" in client.get("/").text
        assert client.get("/api/status").json()["state"] == State.IDLE.value
        assert client.get("/viser/ping").json() == {"pong": True}


def test_create_app_refuses_an_empty_token(service: FakeService) -> None:
    from app.web import create_app

    with pytest.raises(ValueError, match="token"):
        create_app(service, token="", static_dir=None)
