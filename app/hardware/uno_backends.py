"""The Uno a configuration selects: the simulated one, the real firmware in simavr, or a
real board on a serial port. Each yields a port path for `app.hardware.serial_link.UnoLink`,
so the same driver code runs against all three."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from app.config import SerialConfig
from app.hardware.interfaces import MotorPlant
from app.hardware.serial_link import UnoLinkConfig
from app.hardware.simavr import SimavrUno
from app.sim.sim_uno import SimulatedUno


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


@contextmanager
def uno_device(serial: SerialConfig, plant: MotorPlant | None = None) -> Iterator[str]:
    """Start the configured Uno (simulated ones only) and yield the port to open.

    ``plant`` receives the simulated motor outputs (ignored for a real board).
    """
    if serial.backend == "sim":
        with SimulatedUno(plant) as uno:
            yield uno.port
    elif serial.backend == "simavr":
        with SimavrUno(plant) as firmware:
            yield firmware.port
    else:
        yield serial.port
