"""Schemathesis over the OpenAPI schema: generated requests (valid and not) never make
the server fail (no 5xx), with the token and without."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from app.config import FloornavConfig
from app.web import create_app

from ..conftest import room_scene
from .conftest import AUTH, TOKEN, serve_in_thread
from .fakes import FakeService, floor_msg

# The schema is loaded at import (schemathesis parametrizes at collection), so the app
# is built here; a calibration that happens to fit is saved into a throwaway folder.
_CALIBRATION_DIR = Path(tempfile.mkdtemp(prefix="floornav-fuzz-"))
_base = FloornavConfig()
_service = FakeService(
    _base.model_copy(
        update={
            "mapping": _base.mapping.model_copy(
                update={"floor_calibration_file": str(_CALIBRATION_DIR / "floor.json")}
            )
        }
    )
)
_service.publish_frame(room_scene(320, 240)[0])
_service.floors.publish(floor_msg(1))
_app = create_app(_service, token=TOKEN, static_dir=None)
schema = schemathesis.openapi.from_asgi("/openapi.json", _app)


@pytest.mark.slow  # about 10 s: chessboard searches on generated calibration requests
@schema.parametrize()
@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors_with_the_token(case: schemathesis.Case) -> None:
    case.call_and_validate(headers=dict(AUTH), checks=[not_a_server_error])


@schema.parametrize()
@settings(max_examples=5, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors_without_the_token(case: schemathesis.Case) -> None:
    case.call_and_validate(checks=[not_a_server_error])


@pytest.mark.slow  # about a minute: every check, every phase, 25 examples per operation
def test_the_whole_contract_holds(tmp_path: Path) -> None:
    """schemathesis's CLI with every check (status codes, bodies against their schemas,
    schema-valid requests accepted and invalid ones refused, ``Allow`` on 405s, auth
    honoured) over every operation, against the app served by uvicorn."""
    served = serve_in_thread(_app, log_level="error")
    try:
        result = subprocess.run(
            [
                str(Path(sys.executable).with_name("st")),
                "run",
                f"http://127.0.0.1:{served.port}/openapi.json",
                "--header",
                f"Authorization: {AUTH['Authorization']}",
                "--checks",
                "all",
                "--max-examples",
                "25",
                "--seed",
                "1",
                "--workers",
                "1",
                "--generation-database",
                "none",
                "--no-color",
            ],
            capture_output=True,
            text=True,
            timeout=600,
            cwd=tmp_path,  # its report folder stays out of the checkout
            check=False,
        )
    finally:
        served.stop()
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
