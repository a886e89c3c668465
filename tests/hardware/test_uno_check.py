"""`floornav uno-check` against the simulated Uno and the firmware in simavr: the same
driver code path the daemon uses for a real board."""

from __future__ import annotations

import json

import pytest

from app.cli import main
from app.config import SerialConfig
from app.hardware.link_settings import link_config


def test_link_config_follows_the_serial_section() -> None:
    config = link_config(SerialConfig(ack_timeout_ms=20, heartbeat_period_ms=80))
    assert config.ack_timeout_s == pytest.approx(0.02)
    assert config.heartbeat_period_s == pytest.approx(0.08)


def test_uno_check_on_the_simulated_uno(capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(["uno-check", "--json", "--pings", "20", "--drive-pwm", "100", "--drive-s", "0.2"])
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["connected"] and report["protocol_version"] == 1
    assert report["rtt_median_ms"] < 5.0
    left, right = report["encoders"]
    assert left > 0 and right > 0  # the simulated wheels turned while driving


def test_uno_check_on_a_missing_port_fails_clearly(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FLOORNAV_SERIAL__BACKEND", "port")
    monkeypatch.setenv("FLOORNAV_SERIAL__PORT", "/dev/serial/by-id/no-such-uno")
    monkeypatch.setenv("FLOORNAV_SERIAL__HANDSHAKE_TIMEOUT_S", "0.3")
    assert main(["uno-check", "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert not report["connected"]
    assert "no-such-uno" in report["error"]
