#!/usr/bin/env python3
"""CPU per perceived frame of `floornav run` on the simulator without and with the MQTT
bridge (issue 14: at most 5 % more with a subscriber attached). Starts a Mosquitto on a
free port and a ``mosquitto_sub`` on ``floornav/#``, then runs the daemon alternately
off/on; each run is sampled ``--warmup-s`` after its API answered and again
``--window-s`` later: the daemon process's CPU time (all threads) over the frames it
perceived in between.

    .venv/bin/python scripts/measure_mqtt_cpu.py --rounds 2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import statistics
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S


def status(port: int) -> dict[str, object]:
    url = f"http://127.0.0.1:{port}/api/status"
    with urllib.request.urlopen(url, timeout=5) as response:
        data: dict[str, object] = json.load(response)
    return data


def frames(port: int) -> int:
    counters = status(port)["counters"]
    assert isinstance(counters, dict)
    return int(counters["frames_perceived"])


def daemon_cpu_per_frame(
    env_overrides: dict[str, str],
    warmup_s: float,
    window_s: float,
    label: str,
    attach: Callable[[], contextlib.AbstractContextManager[object]] | None = None,
) -> float:
    """Start `floornav run` on the simulator with ``env_overrides`` (its own web port,
    no viser), enter ``attach()`` (a subscriber) once its API answers, and return the
    daemon's CPU milliseconds per perceived frame over ``window_s`` after ``warmup_s``."""
    web = free_port()
    env = {
        **os.environ,
        "FLOORNAV_WEB__PORT": str(web),
        "FLOORNAV_VISER__ENABLED": "false",
        "FLOORNAV_TOKEN": "measure-bridge-cpu-0000000",
        **env_overrides,
    }
    proc = subprocess.Popen(
        [str(ROOT / ".venv" / "bin" / "floornav"), "run"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                status(web)
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("the daemon did not start") from None
                time.sleep(0.1)
        with attach() if attach is not None else contextlib.nullcontext():
            time.sleep(warmup_s)
            f0, c0, t0 = frames(web), cpu_s(proc.pid), time.monotonic()
            time.sleep(window_s)
            f1, c1, t1 = frames(web), cpu_s(proc.pid), time.monotonic()
        per_frame_ms = (c1 - c0) / max(1, f1 - f0) * 1000
        print(
            f"{label}: {f1 - f0} frames in {t1 - t0:.0f} s "
            f"({(f1 - f0) / (t1 - t0):.1f} fps), {c1 - c0:.1f} s CPU, "
            f"{per_frame_ms:.2f} ms/frame",
            flush=True,
        )
        return per_frame_ms
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # the simulated Uno's process too


def measure(broker_port: int, bridge: bool, warmup_s: float, window_s: float) -> float:
    overrides = (
        {
            "FLOORNAV_MQTT__URL": f"mqtt://127.0.0.1:{broker_port}",
            "FLOORNAV_MQTT__ROBOT_ID": "measure",
        }
        if bridge
        else {}
    )
    return daemon_cpu_per_frame(
        overrides, warmup_s, window_s, f"bridge {'on ' if bridge else 'off'}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--warmup-s", type=float, default=10.0)
    parser.add_argument("--window-s", type=float, default=30.0)
    args = parser.parse_args()
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        conf = Path(tmp) / "mosquitto.conf"
        conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        broker = subprocess.Popen(
            ["/usr/sbin/mosquitto", "-c", str(conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(0.5)
        subscriber = subprocess.Popen(
            ["mosquitto_sub", "-p", str(port), "-t", "floornav/#"], stdout=subprocess.DEVNULL
        )
        results: dict[bool, list[float]] = {False: [], True: []}
        try:
            for _ in range(args.rounds):
                for bridge in (False, True):
                    results[bridge].append(measure(port, bridge, args.warmup_s, args.window_s))
        finally:
            subscriber.terminate()
            broker.terminate()
            subscriber.wait(10)
            broker.wait(10)
    off, on = statistics.mean(results[False]), statistics.mean(results[True])
    print(f"CPU per frame: off {off:.2f} ms, on {on:.2f} ms ({(on / off - 1) * 100:+.1f} %)")


if __name__ == "__main__":
    main()
