"""Security headers on every response, /docs without a CDN, the bearer scheme in OpenAPI."""

from __future__ import annotations

import re

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.web.body_limit import MAX_REQUEST_BODY_BYTES
from app.web.headers import DASHBOARD_CSP
from app.web.server import PROJECT_STATIC

from .conftest import AUTH


@pytest.mark.parametrize(
    ("method", "path", "status"),
    [
        ("GET", "/", 200),
        ("GET", "/app.js", 200),
        ("GET", "/api/status", 200),
        ("POST", "/api/start", 401),
        ("GET", "/no-such-page", 404),
        ("GET", "/docs", 200),
        ("GET", "/openapi.json", 200),
    ],
)
def test_every_response_carries_the_security_headers(
    dashboard: TestClient, method: str, path: str, status: int
) -> None:
    response = dashboard.request(method, path)
    assert response.status_code == status
    csp = response.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "frame-ancestors 'none'" in csp
    assert response.headers["x-frame-options"] == "DENY"
    assert response.headers["x-content-type-options"] == "nosniff"
    assert response.headers["referrer-policy"] == "no-referrer"


def test_a_refused_oversized_body_carries_them_too(client: TestClient) -> None:
    response = client.post(
        "/api/teleop",
        content=b"x" * (MAX_REQUEST_BODY_BYTES + 1),
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 413
    assert response.headers["content-security-policy"] == DASHBOARD_CSP


def test_the_dashboard_has_no_inline_script_or_style() -> None:
    # The CSP forbids them; a regression would only show as a dead page in a browser.
    html = (PROJECT_STATIC / "index.html").read_text()
    assert "<style" not in html and " style=" not in html
    assert not re.search(r"\son[a-z]+\s*=", html), "inline event handlers are refused"
    for tag in html.split("<script")[1:]:
        assert "src=" in tag.split(">")[0], "inline <script> blocks are refused by the CSP"


def test_docs_are_served_from_local_files(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200
    assert "http" not in page.text  # no CDN address
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "docs-init.js"):
        response = client.get(f"/docs-assets/{asset}")
        assert response.status_code == 200, asset
        assert len(response.content) > 100
    assert client.get("/docs-assets/../../config.py").status_code == 404
    assert client.get("/docs-assets/__init__.py").status_code == 404


def test_openapi_declares_the_bearer_scheme_where_it_is_needed(app: FastAPI) -> None:
    schema = app.openapi()
    assert schema["components"]["securitySchemes"]["bearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": schema["components"]["securitySchemes"]["bearer"]["description"],
    }
    paths = schema["paths"]
    assert paths["/api/start"]["post"]["security"] == [{"bearer": []}]
    assert paths["/api/teleop"]["post"]["security"] == [{"bearer": []}]
    # Stopping needs no token, and says so.
    for path in ("/api/stop", "/api/estop"):
        assert "security" not in paths[path]["post"]
        assert "401" not in paths[path]["post"]["responses"]


def test_docs_try_it_works_with_the_token(client: TestClient) -> None:
    # What Swagger UI sends once the token is entered under "Authorize".
    assert client.get("/api/auth", headers=AUTH).status_code == 204
