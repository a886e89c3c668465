#!/usr/bin/env python3
"""Run `floornav run` for a while with video clients streaming from /ws/video, then
print the daemon's capture-to-command latency (from its report) and what the clients
measured (capture-to-client latency, frames). Reproduces the API milestone's
"latency while a dashboard streams" figure, and with ``--status-rate`` issue 11's
"5 video clients and 100 status requests/s":

    .venv/bin/python scripts/measure_streaming.py --duration-s 40 --clients 1
    .venv/bin/python scripts/measure_streaming.py --duration-s 120 --clients 5 --status-rate 100
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from websockets.asyncio.client import connect

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def stream(url: str, until_s: float, latencies: list[float], ack: bool) -> int:
    frames = 0
    async with connect(url + ("?ack=2" if ack else ""), max_size=None) as ws:
        while time.time() < until_s:
            try:
                message = await asyncio.wait_for(ws.recv(), timeout=2.0)
            except TimeoutError:
                continue
            if isinstance(message, str):
                header = json.loads(message)
                latencies.append(time.time() - header["capture_wall_s"])
                continue
            frames += 1
            if ack:
                await ws.send(json.dumps({"type": "ack"}))
    return frames


async def poll_status(url: str, until_s: float, rate_hz: float) -> tuple[int, int]:
    """GET ``url`` at ``rate_hz`` (on a fixed schedule, not back to back) until
    ``until_s``; returns (answered, failed)."""
    answered = failed = 0
    period = 1.0 / rate_hz
    async with httpx.AsyncClient(timeout=2.0) as client:
        next_s = time.monotonic()
        while time.time() < until_s:
            try:
                response = await client.get(url)
                answered += response.status_code == 200
                failed += response.status_code != 200
            except httpx.HTTPError:
                failed += 1
            next_s += period
            await asyncio.sleep(max(0.0, next_s - time.monotonic()))
    return answered, failed


async def main_async(args: argparse.Namespace) -> int:
    port, viser_port = free_port(), free_port()
    report = args.report or Path(tempfile.mkdtemp()) / "report.json"
    env = {
        **os.environ,
        "FLOORNAV_WEB__PORT": str(port),
        "FLOORNAV_VISER__PORT": str(viser_port),
        "FLOORNAV_TOKEN": "measure-streaming-token-000",
    }
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "app",
            "run",
            "--duration-s",
            str(args.duration_s),
            "--report",
            str(report),
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"ws://127.0.0.1:{port}/ws/video"
    deadline = time.monotonic() + 60
    while True:  # wait for the server
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
        except OSError:
            if time.monotonic() > deadline or proc.poll() is not None:
                print("daemon did not start", file=sys.stderr)
                return 1
            await asyncio.sleep(0.2)
    until = time.time() + args.duration_s - 3
    per_client: list[list[float]] = [[] for _ in range(args.clients)]
    polls = (
        [poll_status(f"http://127.0.0.1:{port}/api/status", until, args.status_rate)]
        if args.status_rate > 0
        else []
    )
    results = await asyncio.gather(
        *(stream(url, until, per_client[i], ack=True) for i in range(args.clients)), *polls
    )
    frames = results[: args.clients]
    proc.wait(timeout=args.duration_s + 60)
    data = json.loads(report.read_text())
    print(f"daemon: fps {data['fps']}, capture->command latency ms {data['latency_ms']}")
    print(f"daemon: event-loop lag ms {data['loop_lag_ms']}, faults {data['faults']}")
    stages = ", ".join(f"{k} {v['p50']}/{v['p95']}" for k, v in data["stage_ms"].items())
    print(f"daemon: stage ms p50/p95: {stages}")
    if polls:
        answered, failed = results[-1]  # type: ignore[misc]
        rate = answered / max(1e-9, args.duration_s - 3)
        print(f"status: {answered} answered ({rate:.0f}/s), {failed} failed")
    for i, lat in enumerate(per_client):
        ms = sorted(v * 1000 for v in lat)
        p95 = ms[int(0.95 * (len(ms) - 1))] if ms else float("nan")
        print(
            f"client {i}: {frames[i]} frames, capture->client median "
            f"{statistics.median(ms):.1f} ms, p95 {p95:.1f} ms"
        )
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=40.0)
    parser.add_argument("--clients", type=int, default=1)
    parser.add_argument(
        "--status-rate", type=float, default=0.0, help="GET /api/status this often (per s)"
    )
    parser.add_argument(
        "--report", type=Path, default=None, help="keep the daemon's run report here"
    )
    return asyncio.run(main_async(parser.parse_args()))


if __name__ == "__main__":
    raise SystemExit(main())
