"""The serial driver's settings from the configuration's ``[serial]`` section."""

from __future__ import annotations

from app.config import SerialConfig
from app.hardware.serial_link import UnoLinkConfig


def link_config(serial: SerialConfig) -> UnoLinkConfig:
    """The driver's timing from the ``[serial]`` section."""
    return UnoLinkConfig(
        handshake_timeout_s=serial.handshake_timeout_s,
        ack_timeout_s=serial.ack_timeout_ms / 1000.0,
        heartbeat_period_s=serial.heartbeat_period_ms / 1000.0,
        telemetry_period_ms=serial.telemetry_period_ms,
        silence_timeout_s=serial.silence_timeout_ms / 1000.0,
        backoff_initial_s=serial.backoff_initial_s,
        backoff_max_s=serial.backoff_max_s,
    )
