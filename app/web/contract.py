"""Keeping the OpenAPI document true to what the server answers.

Every error the app can give has its status and body schema in the document: 400 (a
body that is not JSON), 422 (our `ErrorResponse`, not FastAPI's default schema, since
`app.web.app` answers validation errors in its own shape), and a 405 lists in ``Allow``
every method the path has (Starlette names only those of the first route it matched).
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI

from app.web.schemas import ErrorResponse

HTTP_METHODS = {"GET", "PUT", "POST", "DELETE", "OPTIONS", "HEAD", "PATCH", "TRACE"}
ERROR_REF = {"$ref": "#/components/schemas/ErrorResponse"}


def _error(description: str) -> dict[str, Any]:
    return {"description": description, "content": {"application/json": {"schema": ERROR_REF}}}


def document_error_responses(app: FastAPI) -> None:
    """Make ``app.openapi()`` document 400 on every operation with a body, and our
    `ErrorResponse` for every 422 (FastAPI adds its own validation schema otherwise)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components["ErrorResponse"] = ErrorResponse.model_json_schema(
            ref_template="#/components/schemas/{model}"
        )
        for path_item in schema.get("paths", {}).values():
            for operation in path_item.values():
                responses = operation.setdefault("responses", {})
                if "requestBody" in operation:
                    responses.setdefault("400", _error("the body is not valid JSON"))
                if "422" in responses:
                    responses["422"] = _error(
                        responses["422"].get("description") or "malformed request or rejected value"
                    )
        for unused in ("HTTPValidationError", "ValidationError"):
            components.pop(unused, None)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def allowed_methods(app: FastAPI, path: str) -> list[str]:
    """Every method the OpenAPI document lists for ``path`` (templates such as
    ``/api/x/{id}`` match one segment per parameter), for a 405's ``Allow``."""
    methods: set[str] = set()
    for template, item in app.openapi().get("paths", {}).items():
        pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template))
        if re.fullmatch(pattern, path):
            methods.update(m.upper() for m in item if m.upper() in HTTP_METHODS)
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods)
