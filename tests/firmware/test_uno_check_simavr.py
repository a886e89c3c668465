"""The daemon's serial driver against the real firmware in simavr (`uno-check`)."""

from __future__ import annotations

import json

import pytest

from app.cli import main


@pytest.mark.firmware
def test_uno_check_on_the_firmware_in_simavr(
    firmware_build: object, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FLOORNAV_SERIAL__BACKEND", "simavr")
    assert main(["uno-check", "--json", "--pings", "20"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["firmware"].startswith("floornav-fw")
    assert report["rtt_median_ms"] < 10.0
