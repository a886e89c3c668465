"""A witness to stalls of the whole machine, for timing tests.

The CI machine is a small VM whose host can stop it outright (CPU steal): a last
session saw the camera, the simulated Uno and every other process fall silent for 20 s
at once. A timing test must hold the daemon to what it answers for, not fail because
the machine did not run at all.

`StallWitness` starts a tiny process that sleeps in 5 ms steps and reports each
oversleep longer than `REPORT_GAP_S` on its own clock (CLOCK_MONOTONIC, which every
process shares). A process that only sleeps is woken promptly by the scheduler even on
busy cores (the daemon's own CPU load does not delay it by more than a few ms), so a
long gap in it means the machine as a whole was not running: time no process under test
can be blamed for.
"""

from __future__ import annotations

import atexit
import subprocess
import sys
import threading
import time

REPORT_GAP_S = 0.03
"""Oversleeps reported (shorter ones are a busy core's ordinary wake-up delay)."""

_WITNESS_SOURCE = f"""
import sys, time
step = 0.005
last = time.monotonic()
print("ready", flush=True)
while True:
    time.sleep(step)
    now = time.monotonic()
    if now - last - step > {REPORT_GAP_S}:
        print(f"{{last + step!r}} {{now!r}}", flush=True)
    last = now
"""


class StallWitness:
    """The machine's stalls while it runs (`gaps`, `stalled_s`)."""

    def __init__(self) -> None:
        self._gaps: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> StallWitness:
        # Not niced: it must wake whenever the daemon's processes could run.
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _WITNESS_SOURCE],
            stdout=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
        )
        assert self._proc.stdout is not None
        if self._proc.stdout.readline().strip() != "ready":
            raise RuntimeError("the stall witness did not start")
        self._reader = threading.Thread(target=self._read, name="stall-witness", daemon=True)
        self._reader.start()
        return self

    def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            start_s, end_s = (float(v) for v in line.split())
            with self._lock:
                self._gaps.append((start_s, end_s))

    def stop(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait(5)
            self._proc = None

    def __enter__(self) -> StallWitness:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        """The stalls overlapping ``start_s``..``end_s`` (time.monotonic()), clipped to it.

        A stall still going on at ``end_s`` is reported once the witness wakes: call this
        a little after ``end_s`` (`settled_gaps`)."""
        with self._lock:
            gaps = list(self._gaps)
        return [(max(a, start_s), min(b, end_s)) for a, b in gaps if b > start_s and a < end_s]

    def settled_gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        """`gaps`, once the witness has had 0.1 s past ``end_s`` (and past now) to report
        a stall that was still going on then."""
        time.sleep(max(0.1, end_s + 0.1 - time.monotonic()))
        return self.gaps(start_s, end_s)

    def stalled_s(self, start_s: float, end_s: float) -> float:
        """How long the machine did not run between ``start_s`` and ``end_s``."""
        return stalled_within(self.settled_gaps(start_s, end_s), start_s, end_s)


def stalled_within(gaps: list[tuple[float, float]], start_s: float, end_s: float) -> float:
    """Seconds of ``gaps`` (`StallWitness.gaps`) that lie between ``start_s`` and
    ``end_s``."""
    return sum(max(0.0, min(b, end_s) - max(a, start_s)) for a, b in gaps)


_shared: StallWitness | None = None


def shared_witness() -> StallWitness:
    """One witness for the whole test session (started on first use; a daemon thread
    reads it and the process ends with pytest's)."""
    global _shared
    if _shared is None:
        _shared = StallWitness().start()
        atexit.register(_shared.stop)
    return _shared
