"""``floornav run``: set up logging, print the banner, open the devices, run the
`Runtime`, write the report."""

from __future__ import annotations

import asyncio
import gc
import logging
from pathlib import Path
from typing import Any

from app.config import FloornavConfig
from app.devices import open_devices
from app.fileio import json_safe, write_bytes_atomic
from app.logs import setup_logging
from app.runtime import Runtime
from app.web.auth import resolve_token

log = logging.getLogger("floornav")


def banner(config: FloornavConfig, config_source: str, description: dict[str, str]) -> str:
    web = config.web
    lines = [
        "floornav daemon",
        f"  config   {config_source}",
        f"  camera   {description.get('camera', '?')}",
        f"  serial   {description.get('serial', '?')}",
        f"  world    {description['world']}" if "world" in description else "",
        f"  method   {config.perception.method}",
        f"  web      http://{web.host}:{web.port}/  (API /api, metrics /metrics)",
        f"  viser    port {config.viser.port} (localhost)" if config.viser.enabled else "",
        "  autonomy "
        + ("starts at once" if config.runtime.autostart else "waits for POST /api/start"),
    ]
    return "\n".join(line for line in lines if line)


def write_report(path: Path, report: dict[str, Any]) -> None:
    import json

    write_bytes_atomic(path, (json.dumps(json_safe(report), indent=2) + "\n").encode())


async def _serve(runtime: Runtime, duration_s: float | None, token: str) -> None:
    from app.web.server import WebService

    web = WebService(runtime, token=token)
    freezer = asyncio.create_task(_freeze_startup_objects(runtime))
    try:
        await runtime.run(duration_s=duration_s, services=[web])
    finally:
        freezer.cancel()


async def _freeze_startup_objects(runtime: Runtime) -> None:
    """Once the pipeline runs, move everything allocated so far (the imported libraries,
    compiled kernels, the app) out of the garbage collector's reach. A full collection
    otherwise walks those ~130k objects every time: 50-65 ms measured, during which every
    thread, the simulated Uno's included, waits."""
    while runtime.maps.peek() is None:
        await asyncio.sleep(0.1)
    gc.collect()
    gc.freeze()
    log.info(
        "garbage collector: %d start-up objects frozen",
        gc.get_freeze_count(),
        extra={"event": "gc_freeze"},
    )


def run_daemon(
    config: FloornavConfig,
    *,
    config_source: str,
    duration_s: float | None = None,
    report_path: Path | None = None,
) -> int:
    """Run until stopped (or ``duration_s``); 0 on a clean stop, 1 if a stage crashed."""
    setup_logging(config.runtime.log_level, json_lines=config.runtime.log_json)
    token, generated = resolve_token(config)
    with open_devices(config) as devices:
        print(banner(config, config_source, devices.description), flush=True)
        if generated:
            # Printed once, on the run that created it; it is kept 0600 in token_file.
            print(
                f"  token    {token}  (new; stored in {config.web.token_file}, "
                "give it to the dashboard once)",
                flush=True,
            )
        if devices.calibration is None:
            log.warning(
                "autonomy unavailable, teleop allowed: %s",
                devices.calibration_problem,
                extra={"event": "autonomy_refused"},
            )
        runtime = Runtime(config, devices)
        code = 0
        try:
            asyncio.run(_serve(runtime, duration_s, token))
        except KeyboardInterrupt:
            pass
        except Exception as exc:  # a stage crashed: motors are already stopped
            log.error("daemon stopped by an error: %s", exc, extra={"event": "crash"})
            code = 1
        report = runtime.report()
    if report_path is not None:
        write_report(report_path, report)
        log.info("report written to %s", report_path, extra={"event": "report"})
    return code
