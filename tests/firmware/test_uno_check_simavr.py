"""The daemon's serial driver against the real firmware in simavr (`uno-check`)."""

from __future__ import annotations

import asyncio
import json
import random

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


@pytest.mark.firmware
async def test_simulated_wheels_feed_the_firmware_encoders(firmware_build: object) -> None:
    from app.hardware.serial_link import UnoLink
    from app.hardware.simavr import SimavrUno
    from app.sim.sim_uno import IntegratingPlant

    plant = IntegratingPlant()
    with SimavrUno(plant, build=False) as firmware:
        async with UnoLink(firmware.port) as link:
            await link.wait_connected(5.0)
            await link.drive(100, -100)
            await asyncio.sleep(0.5)
            assert firmware.pwm == (100, -100)
            telemetry = link.latest_telemetry(0.5)
            assert telemetry is not None
            # About 2 counts per PWM-second from the plant, fed back as pulses.
            assert telemetry.data.encoder_left > 20 and telemetry.data.encoder_right < -20
            await link.stop_motors()


@pytest.mark.firmware
async def test_the_firmware_counts_every_tick_the_wheels_made_while_commands_arrive(
    firmware_build: object,
) -> None:
    """The daemon's odometry with our firmware is only as good as this: with DRIVE
    frames at the daemon's 30 Hz, each changing the speeds and the right wheel's
    direction, the firmware's encoder counts end equal to the simulated wheels'. They
    were 5-8 % short while simavr's pull-ups made false edges on every PORTD write, and
    a few counts off while the firmware counted only A's rising edges (each reversal
    between two of them gained one)."""
    from app.hardware.serial_link import UnoLink
    from app.hardware.simavr import SimavrUno
    from app.sim.sim_uno import IntegratingPlant

    plant = IntegratingPlant()
    rng = random.Random(0)
    with SimavrUno(plant, build=False) as firmware:
        async with UnoLink(firmware.port) as link:
            await link.wait_connected(5.0)
            for _ in range(60):
                await link.drive(rng.randint(60, 200), rng.randint(-200, 200))
                await asyncio.sleep(1 / 30)
            await link.stop_motors()
            wheels = plant.read_encoders()
            counted: tuple[int, int] | None = None
            for _ in range(40):  # the last ticks reach the firmware within ~0.1 s
                await asyncio.sleep(0.05)
                telemetry = link.latest_telemetry(0.5)
                assert telemetry is not None
                counted = (telemetry.data.encoder_left, telemetry.data.encoder_right)
                if counted == wheels:
                    break
            assert abs(wheels[0]) > 100 and abs(wheels[1]) > 20
            assert counted == wheels
