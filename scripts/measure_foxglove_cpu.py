#!/usr/bin/env python3
"""CPU per perceived frame of `floornav run` on the simulator without and with the
Foxglove live view and a client subscribed to every channel (issue 14: at most 5 % more).
Runs the daemon alternately off/on; each run is sampled ``--warmup-s`` after its API
answered and again ``--window-s`` later: the daemon process's CPU time (all threads)
over the frames it perceived in between. The subscriber runs in its own process, so
its decoding is not counted.

    .venv/bin/python scripts/measure_foxglove_cpu.py --rounds 2
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

from measure_mqtt_cpu import cpu_s, frames, free_port, status  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"


async def subscribe_everything(port: int) -> None:
    """A Foxglove protocol client: subscribe to every advertised channel, read forever."""
    import websockets

    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
    ) as ws:
        subscribed: set[int] = set()
        received = 0
        while True:
            frame = await ws.recv()
            if isinstance(frame, bytes):
                received += 1
                continue
            message = json.loads(frame)
            if message.get("op") == "advertise":
                subs = [
                    {"id": channel["id"], "channelId": channel["id"]}
                    for channel in message["channels"]
                    if channel["id"] not in subscribed
                ]
                subscribed.update(s["channelId"] for s in subs)
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


def measure(view: bool, warmup_s: float, window_s: float) -> float:
    web, fox = free_port(), free_port()
    env = {
        **os.environ,
        "FLOORNAV_WEB__PORT": str(web),
        "FLOORNAV_VISER__ENABLED": "false",
        "FLOORNAV_TOKEN": "measure-foxglove-cpu-00000",
    }
    if view:
        env["FLOORNAV_FOXGLOVE__PORT"] = str(fox)
    proc = subprocess.Popen(
        [str(ROOT / ".venv" / "bin" / "floornav"), "run"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    client: subprocess.Popen[bytes] | None = None
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
        if view:
            client = subprocess.Popen(
                [sys.executable, __file__, "--subscriber", str(fox)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        time.sleep(warmup_s)
        f0, c0, t0 = frames(web), cpu_s(proc.pid), time.monotonic()
        time.sleep(window_s)
        f1, c1, t1 = frames(web), cpu_s(proc.pid), time.monotonic()
        if client is not None and client.poll() is not None:
            raise RuntimeError("the Foxglove subscriber ended early")
        per_frame_ms = (c1 - c0) / max(1, f1 - f0) * 1000
        print(
            f"view {'on ' if view else 'off'}: {f1 - f0} frames in {t1 - t0:.0f} s "
            f"({(f1 - f0) / (t1 - t0):.1f} fps), {c1 - c0:.1f} s CPU, "
            f"{per_frame_ms:.2f} ms/frame",
            flush=True,
        )
        return per_frame_ms
    finally:
        if client is not None:
            client.terminate()
            client.wait(10)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # the simulated Uno's process too


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--warmup-s", type=float, default=10.0)
    parser.add_argument("--window-s", type=float, default=30.0)
    parser.add_argument("--subscriber", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.subscriber is not None:
        asyncio.run(subscribe_everything(args.subscriber))
        return
    results: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(args.rounds):
        for view in (False, True):
            results[view].append(measure(view, args.warmup_s, args.window_s))
    off, on = statistics.mean(results[False]), statistics.mean(results[True])
    print(f"CPU per frame: off {off:.2f} ms, on {on:.2f} ms ({(on / off - 1) * 100:+.1f} %)")


if __name__ == "__main__":
    main()
