"""``floornav run``: set up logging, print the banner, open the devices, run the
`Runtime`, write the report."""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import gc
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.config import FloornavConfig
from app.devices import Devices, open_devices
from app.fileio import json_safe, write_bytes_atomic
from app.jit import JitReport, compile_kernels
from app.logs import setup_logging
from app.mapping.map_files import MapFileError, export_ros_map, load_map, save_map
from app.mapping.occupancy import SavedMap
from app.recording.mcap_writer import McapRecorder
from app.recording.service import RecordingService, finish_recording, start_recording
from app.runtime import CommandRefusedError, Runtime
from app.runtime.core import Service
from app.web.auth import resolve_token

log = logging.getLogger("floornav")


def banner(
    config: FloornavConfig,
    config_source: str,
    description: dict[str, str],
    jit: JitReport | None = None,
) -> str:
    web = config.web
    lines = [
        "floornav daemon",
        f"  config   {config_source}",
        f"  camera   {description.get('camera', '?')}",
        f"  serial   {description.get('serial', '?')}",
        f"  world    {description['world']}" if "world" in description else "",
        f"  method   {config.perception.method}",
        jit.banner_line() if jit is not None else "",
        f"  web      http://{web.host}:{web.port}/  (API /api, metrics /metrics)",
        f"  viser    port {config.viser.port} (localhost)" if config.viser.enabled else "",
        "  autonomy "
        + ("starts at once" if config.autostarts() else "waits for a start (dashboard or API)"),
    ]
    return "\n".join(line for line in lines if line)


def write_report(path: Path, report: dict[str, Any]) -> None:
    import json

    write_bytes_atomic(path, (json.dumps(json_safe(report), indent=2) + "\n").encode())


async def _serve(
    runtime: Runtime, duration_s: float | None, token: str, recorder: McapRecorder | None = None
) -> None:
    from app.bridges import bridge_services
    from app.web.server import WebService

    web = WebService(runtime, token=token)
    services: list[Service] = [web, *bridge_services(runtime, token)]
    if recorder is not None:
        services.append(RecordingService(runtime, recorder))
    freezer = asyncio.create_task(_freeze_startup_objects(runtime))
    trimmer = asyncio.create_task(release_freed_memory_every(HEAP_TRIM_PERIOD_S))
    try:
        await runtime.run(duration_s=duration_s, services=services)
    finally:
        freezer.cancel()
        trimmer.cancel()


async def _freeze_startup_objects(runtime: Runtime) -> None:
    """Once the pipeline runs, move everything allocated so far (the imported libraries,
    compiled kernels, the app) out of the garbage collector's reach. A full collection
    otherwise walks those ~130k objects every time: 50-65 ms measured, during which every
    thread, the simulated Uno's included, waits."""
    while runtime.maps.peek() is None:
        await asyncio.sleep(0.1)
    # No gc.collect() here: a full collection on the loop stalled it for ~150 ms. The
    # imports were collected and frozen before the loop started (`run_daemon`); what
    # the start-up allocated since is frozen as it is.
    gc.freeze()
    log.info(
        "garbage collector: %d start-up objects frozen",
        gc.get_freeze_count(),
        extra={"event": "gc_freeze"},
    )


def continue_map(runtime: Runtime, devices: Devices, saved: SavedMap, map_path: Path) -> None:
    """Start from a saved map; the simulated robot is put where the map says it stood
    (a real one has not moved while the daemon was off)."""
    try:
        runtime.restore_map(saved)
    except (ValueError, CommandRefusedError) as exc:
        raise MapFileError(f"{map_path}: cannot continue this map: {exc}") from exc
    if devices.sim is not None:
        devices.sim.robot.teleport(devices.sim.T_plan_odom.compose(saved.T_world_robot))


def save_run_map(runtime: Runtime, map_path: Path, saved: SavedMap | None = None) -> str | None:
    """Save the map (``saved``, default: the runtime's at exit) as floornav's file and a
    ROS map_server copy; the path, or None when there is no map (no floor calibration)
    or it could not be written."""
    saved = runtime.saved_map() if saved is None else saved
    if saved is None:
        log.warning("no map to save (no floor calibration)", extra={"event": "map_not_saved"})
        return None
    try:
        save_map(map_path, saved)
        export_ros_map(map_path.with_suffix(".pgm"), map_path.with_suffix(".yaml"), saved)
    except OSError as exc:
        log.error("map not saved to %s: %s", map_path, exc, extra={"event": "map_not_saved"})
        return None
    log.info(
        "map saved to %s (+ ROS %s/.yaml)",
        map_path,
        map_path.with_suffix(".pgm").name,
        extra={"event": "map_saved"},
    )
    return str(map_path)


M_ARENA_MAX = -8
"""glibc's mallopt() parameter number for the malloc arena limit."""


def _libc() -> ctypes.CDLL:
    """The C library (OSError where there is none to load)."""
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def limit_malloc_arenas(arenas: int = 2) -> bool:
    """Cap glibc's malloc arenas before the daemon's threads start. glibc gives each
    busy thread its own arena (up to 8 per core) and rarely returns their memory: with
    ~14 threads the daemon kept ~20 MB more resident than with 2 arenas (measured: 378
    vs 357 MB), at no measurable cost in speed. False where there is no glibc."""
    try:
        return bool(_libc().mallopt(M_ARENA_MAX, arenas))
    except (OSError, AttributeError):
        return False


def release_freed_memory() -> bool:
    """Give the heap pages freed so far back to the system (glibc's ``malloc_trim``).

    The kernel warm-up runs every method and a mapper once on a full frame; glibc keeps
    what they freed, so a daemon started at 313 MB resident stayed about 35 MB higher
    than one trimmed after the warm-up (386 vs 324 MB at start, 388 vs 355 MB after
    45 s). Once, before the devices open: a trim walks the heap holding malloc's locks.
    False where there is no glibc."""
    try:
        _libc().malloc_trim(0)
    except (OSError, AttributeError):
        return False
    return True


MADV_PAGEOUT = 21
"""madvise(2) advice (Linux 5.4+): reclaim these pages now; their content is kept (a
file's pages are read back from the file when next touched)."""

COMPILER_LIBRARY = "libllvmlite"
"""The shared library that holds LLVM, numba's compiler."""


def release_compiler_code(library: str = COMPILER_LIBRARY) -> int:
    """Give back the resident pages of the compiler's own code, 68 of the daemon's
    ~360 MB: once the kernels are compiled or loaded (`compile_kernels`), calling them
    runs their machine code, not LLVM's. The pages are reclaimed with ``MADV_PAGEOUT``,
    which keeps their content, so should anything compile later (a live method change
    loading kernels from the cache) the kernel reads them back from the library file.
    Returns the bytes advised (0 where there is no such mapping, no /proc or no
    MADV_PAGEOUT)."""
    try:
        madvise = _libc().madvise
        with open("/proc/self/maps") as maps:
            lines = maps.readlines()
    except (OSError, AttributeError):
        return 0
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    advised = 0
    for line in lines:
        fields = line.split()
        if len(fields) < 6 or library not in fields[5]:
            continue
        start, end = (int(address, 16) for address in fields[0].split("-"))
        if madvise(start, end - start, MADV_PAGEOUT) == 0:
            advised += end - start
    return advised


def release_memory() -> bool:
    """`release_freed_memory` and `release_compiler_code`; False where there is no
    glibc."""
    release_compiler_code()
    return release_freed_memory()


HEAP_TRIM_PERIOD_S = 30.0
"""How often the running daemon gives freed memory back (`release_memory`)."""


async def release_freed_memory_every(
    period_s: float, release: Callable[[], bool] = release_memory
) -> None:
    """Trim the heap every ``period_s`` while the daemon runs, in a worker thread (the
    trim takes about a millisecond and ctypes lets go of the GIL). glibc keeps what the
    stages' per-frame arrays freed: trimmed every 30 s, simulator runs sat at 354-357 MB
    after their first minute against 374 MB untrimmed. (A fixed mmap threshold, which
    returns big arrays at once, got 330-343 MB but doubled perception's time in page
    faults.) The compiler's code goes too, in case something compiled since."""
    while True:
        await asyncio.sleep(period_s)
        if not await asyncio.to_thread(release):
            return  # no glibc: nothing to trim


def run_daemon(
    config: FloornavConfig,
    *,
    config_source: str,
    duration_s: float | None = None,
    report_path: Path | None = None,
    map_path: Path | None = None,
    record_path: Path | None = None,
) -> int:
    """Run until stopped (or ``duration_s``); 0 on a clean stop, 1 if a stage crashed.

    With ``map_path``, the run continues the map saved there (if the file exists) and
    saves the map there on exit, with a ROS map_server copy (``.pgm`` + ``.yaml``)
    beside it. A map file that cannot be used raises `MapFileError` before any device
    opens, and is never overwritten.

    With ``record_path``, the run is recorded there as MCAP (`app.recording`); the file
    is finished (summary and index) however the run ends."""
    limit_malloc_arenas()
    setup_logging(config.runtime.log_level, json_lines=config.runtime.log_json)
    token, generated = resolve_token(config)
    saved = load_map(map_path) if map_path is not None and map_path.exists() else None
    # Before the devices open: a compile holds the GIL for seconds, which the running
    # simulator, Uno link and event loop must never wait out.
    log.info("preparing numba kernels", extra={"event": "jit_start"})
    jit = compile_kernels(config)
    release_memory()
    log.info(
        "numba kernels ready: %s",
        jit.summary(),
        extra={
            "event": "jit",
            "compiled": jit.compiled,
            "loaded": jit.loaded,
            "cache_dir": jit.cache_dir or "__pycache__ beside the sources",
        },
    )
    with open_devices(config) as devices:
        print(banner(config, config_source, devices.description, jit), flush=True)
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
        gc.collect()  # before the loop runs: one full collection of the imports, then
        gc.freeze()  # keep them out of every later one
        if saved is not None and map_path is not None:
            continue_map(runtime, devices, saved, map_path)
        explored_path = map_path or Path(config.runtime.explored_map_file)

        async def save_explored_map() -> None:
            explored = await runtime.saved_map_while_running()
            await asyncio.to_thread(save_run_map, runtime, explored_path, explored)

        runtime.on_explored = save_explored_map
        code = 0
        recorder = (
            start_recording(record_path, {"config": config_source, **devices.description})
            if record_path is not None
            else None
        )
        try:
            asyncio.run(_serve(runtime, duration_s, token, recorder))
        except KeyboardInterrupt:
            pass
        except Exception as exc:  # a stage crashed: motors are already stopped
            log.error("daemon stopped by an error: %s", exc, extra={"event": "crash"})
            code = 1
        finally:
            recording = finish_recording(recorder) if recorder is not None else None
        report = runtime.report()
        if recording is not None:
            report["recording"] = recording
        if map_path is not None:
            report["map_file"] = save_run_map(runtime, map_path)
    if report_path is not None:
        write_report(report_path, report)
        log.info("report written to %s", report_path, extra={"event": "report"})
    return code
