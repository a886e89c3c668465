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
import os
import subprocess
import sys
import threading
import time
from typing import Self

REPORT_GAP_S = 0.03
"""Oversleeps reported (shorter ones are a busy core's ordinary wake-up delay)."""

_WITNESS_SOURCE = f"""
import os, sys, time
if len(sys.argv) > 1:
    os.sched_setaffinity(0, {{int(sys.argv[1])}})
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


class _Witness:
    """What both witnesses share: ``start``/``stop`` as a context, and `settled_gaps`."""

    def start(self) -> Self:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError

    def gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def settled_gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        """`gaps`, once the witness has had 0.1 s past ``end_s`` (and past now) to report
        a stall that was still going on then."""
        time.sleep(max(0.1, end_s + 0.1 - time.monotonic()))
        return self.gaps(start_s, end_s)


class StallWitness(_Witness):
    """The machine's stalls while it runs (`gaps`, `stalled_s`); with ``cpu``, the stalls
    of that one CPU (the witness pinned to it: `CpuStallWitnesses`)."""

    def __init__(self, cpu: int | None = None) -> None:
        self.cpu = cpu
        self._gaps: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> Self:
        # Not niced: it must wake whenever the daemon's processes could run.
        pin = [] if self.cpu is None else [str(self.cpu)]
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _WITNESS_SOURCE, *pin],
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

    def gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        """The stalls overlapping ``start_s``..``end_s`` (time.monotonic()), clipped to it.

        A stall still going on at ``end_s`` is reported once the witness wakes: call this
        a little after ``end_s`` (`settled_gaps`)."""
        with self._lock:
            gaps = list(self._gaps)
        return [(max(a, start_s), min(b, end_s)) for a, b in gaps if b > start_s and a < end_s]

    def stalled_s(self, start_s: float, end_s: float) -> float:
        """How long the machine did not run between ``start_s`` and ``end_s``."""
        return stalled_within(self.settled_gaps(start_s, end_s), start_s, end_s)


def stalled_within(gaps: list[tuple[float, float]], start_s: float, end_s: float) -> float:
    """Seconds of ``gaps`` (`StallWitness.gaps`) that lie between ``start_s`` and
    ``end_s``, overlapping gaps counted once."""
    return sum(max(0.0, min(b, end_s) - max(a, start_s)) for a, b in merged(gaps))


def merged(gaps: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The union of ``gaps`` as sorted, disjoint intervals.

    >>> merged([(3.0, 4.0), (0.0, 1.0), (0.5, 2.0)])
    [(0.0, 2.0), (3.0, 4.0)]
    """
    out: list[tuple[float, float]] = []
    for a, b in sorted(gaps):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


class CpuStallWitnesses(_Witness):
    """A witness pinned to each CPU: when any one CPU stops running ordinary tasks.

    On the CI VM one CPU at a time can stop running its tasks for hundreds of ms (a
    witness pinned to it saw up to 1.2 s while the browser tests ran) although the
    machine as a whole runs on: the unpinned `StallWitness` moves to the other CPU and
    sees nothing, while a thread of the daemon, or the simulated Uno's process, sitting
    on the stalled one waits. Ordinary CPU load does not do this: beside two busy-loop
    processes on both CPUs the pinned witnesses saw no gap over 30 ms in 20 s. Which CPU
    a thread sat on is not known, so `gaps` is the union over the CPUs: time during
    which some thread may have been frozen by nothing the process did."""

    def __init__(self) -> None:
        cpus = sorted(os.sched_getaffinity(0))
        self.witnesses = [StallWitness(cpu) for cpu in cpus]

    def start(self) -> Self:
        for witness in self.witnesses:
            witness.start()
        return self

    def stop(self) -> None:
        for witness in self.witnesses:
            witness.stop()

    def gaps(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        """The union of every CPU's stalls overlapping ``start_s``..``end_s``, clipped."""
        return merged([gap for w in self.witnesses for gap in w.gaps(start_s, end_s)])


_shared: StallWitness | None = None


_shared_cpus: CpuStallWitnesses | None = None


def shared_cpu_witnesses() -> CpuStallWitnesses:
    """One `CpuStallWitnesses` for the whole test session (started on first use)."""
    global _shared_cpus
    if _shared_cpus is None:
        _shared_cpus = CpuStallWitnesses().start()
        atexit.register(_shared_cpus.stop)
    return _shared_cpus


def shared_witness() -> StallWitness:
    """One witness for the whole test session (started on first use; a daemon thread
    reads it and the process ends with pytest's)."""
    global _shared
    if _shared is None:
        _shared = StallWitness().start()
        atexit.register(_shared.stop)
    return _shared
