"""The OpenAPI document says what the server answers: error statuses and bodies, and
the methods a 405 lists in ``Allow``."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.testclient import TestClient

from .conftest import AUTH


def test_a_405_lists_every_method_of_the_path(client: TestClient) -> None:
    response = client.request("OPTIONS", "/api/config", headers=AUTH)
    assert response.status_code == 405
    assert response.headers["allow"] == "GET, HEAD, PATCH"
    response = client.delete("/api/start", headers=AUTH)
    assert response.status_code == 405
    assert response.headers["allow"] == "POST"


def test_a_body_that_is_not_json_gets_a_documented_400(app: FastAPI, client: TestClient) -> None:
    response = client.post(
        "/api/teleop",
        content=b"\xff\xfe{not json",
        headers={**AUTH, "content-type": "application/json"},
    )
    assert response.status_code in (400, 422)
    documented = app.openapi()["paths"]["/api/teleop"]["post"]["responses"]
    assert str(response.status_code) in documented
    assert "detail" in response.json()


def test_every_422_is_documented_in_the_shape_it_is_sent(app: FastAPI) -> None:
    schema = app.openapi()
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            answer = operation["responses"].get("422")
            if answer is None:
                continue
            body = answer["content"]["application/json"]["schema"]
            assert body == {"$ref": "#/components/schemas/ErrorResponse"}, (method, path)
    assert "HTTPValidationError" not in schema["components"]["schemas"]


def test_beside_the_dashboard_files_a_wrong_method_still_gets_405(dashboard: TestClient) -> None:
    """The daemon serves static/ at ``/``; that mount must not answer API paths (schemathesis
    against the running daemon found GET /api/teleop/release answered 404 by the files)."""
    client = dashboard
    for path in ("/api/teleop/release", "/api/start", "/api/estop"):
        response = client.get(path, headers=AUTH)
        assert response.status_code == 405, path
        assert response.headers["allow"] == "POST"
    assert client.request("OPTIONS", "/api/config", headers=AUTH).headers["allow"] == (
        "GET, HEAD, PATCH"
    )
    # The files themselves are still there, and a missing one is still a 404.
    assert client.get("/").status_code == 200 and "<html" in client.get("/").text.lower()
    assert client.get("/app.js").status_code == 200
    assert client.get("/no-such-page").status_code == 404
    assert client.get("/api/status").status_code == 200
