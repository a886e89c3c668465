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
import statistics
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

from measure_mqtt_cpu import daemon_cpu_per_frame, free_port  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"


async def subscribe_everything(port: int) -> None:
    """A Foxglove protocol client: subscribe to every advertised channel, read forever."""
    import websockets
    from websockets.typing import Subprotocol

    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(SUBPROTOCOL)], max_size=None
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


@contextlib.contextmanager
def subscriber(port: int) -> Iterator[None]:
    """A client subscribed to every channel, in its own process (its decoding is not
    the daemon's CPU)."""
    client = subprocess.Popen(
        [sys.executable, __file__, "--subscriber", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        yield
        if client.poll() is not None:
            raise RuntimeError("the Foxglove subscriber ended early")
    finally:
        client.terminate()
        client.wait(10)


def measure(view: bool, warmup_s: float, window_s: float) -> float:
    if not view:
        return daemon_cpu_per_frame({}, warmup_s, window_s, "view off")
    fox = free_port()
    return daemon_cpu_per_frame(
        {"FLOORNAV_FOXGLOVE__PORT": str(fox)},
        warmup_s,
        window_s,
        "view on ",
        attach=lambda: subscriber(fox),
    )


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
