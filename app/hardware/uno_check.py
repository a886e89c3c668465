"""``floornav uno-check``: connect to the Uno the way the daemon does, and report the
banner, round-trip times, telemetry and a short optional drive. The caller starts the
configured Uno (`app.devices.open_uno`) and passes its port."""

from __future__ import annotations

import asyncio
import statistics
import time

from app.config import SerialConfig
from app.hardware.link_settings import link_config
from app.hardware.serial_link import LinkError, UnoLink


async def run_uno_check(
    port: str,
    serial: SerialConfig,
    *,
    pings: int = 50,
    drive_pwm: int = 0,
    drive_s: float = 0.0,
) -> dict[str, object]:
    """Check the Uno at ``port`` with the driver settings of ``serial``.

    Returns a JSON-ready report; ``connected`` is False (with ``error``) on failure.
    The motors are commanded to zero before returning, whatever happened."""
    report: dict[str, object] = {"backend": serial.backend, "connected": False, "port": port}
    link = UnoLink(port, config=link_config(serial))
    await link.start()
    try:
        await link.wait_connected(serial.handshake_timeout_s + 1.0)
        report["connected"] = True
        if link.banner is not None:
            report["firmware"] = link.banner.firmware
            report["protocol_version"] = link.banner.protocol_version
        rtts_ms = [await link.ping() * 1e3 for _ in range(max(0, pings))]
        if rtts_ms:
            rtts_ms.sort()
            report["rtt_median_ms"] = round(statistics.median(rtts_ms), 3)
            report["rtt_p95_ms"] = round(rtts_ms[int(0.95 * (len(rtts_ms) - 1))], 3)
        if drive_pwm and drive_s > 0:
            await link.drive(drive_pwm, drive_pwm)
            await asyncio.sleep(drive_s)
            await link.stop_motors()
        await asyncio.sleep(0.12)  # let a telemetry frame arrive
        telemetry = link.latest_telemetry(1.0)
        if telemetry is not None:
            data = telemetry.data
            report["encoders"] = [data.encoder_left, data.encoder_right]
            report["device_crc_errors"] = data.crc_errors
            report["device_garbage_bytes"] = data.garbage_bytes
    except (LinkError, TimeoutError) as exc:
        report["error"] = str(exc)
    finally:
        start = time.monotonic()
        await link.stop()  # sends STOP before closing
        report["stop_ms"] = round((time.monotonic() - start) * 1e3, 1)
    return report
