"""The timing tests' witnesses to stalls of the whole machine and of single CPUs
(`tests.stall_witness`)."""

from __future__ import annotations

import os
import signal
import time

from tests.stall_witness import CpuStallWitnesses, StallWitness, merged, stalled_within


def stopped_for(pid: int, seconds: float) -> tuple[float, float]:
    """Stop the process ``pid`` for ``seconds``; when that began and ended."""
    start = time.monotonic()
    os.kill(pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(pid, signal.SIGCONT)
    return start, time.monotonic()


def test_a_witness_that_was_not_run_reports_the_time_it_lost() -> None:
    # Stopping the witness's process is what a stalled machine does to every process.
    with StallWitness() as witness:
        assert witness._proc is not None
        start, end = stopped_for(witness._proc.pid, 0.3)
        gaps = witness.settled_gaps(start, end)
        assert gaps, "the witness reported nothing"
        # At least the 0.3 s it was stopped; never more than the window asked about.
        assert witness.stalled_s(start, end) >= 0.29
        assert all(start <= a < b <= end for a, b in gaps)
        # A window before the stop holds none of it.
        assert witness.stalled_s(start - 5.0, start) == 0.0


def test_overlapping_gaps_count_once() -> None:
    assert merged([(3.0, 4.0), (0.0, 1.0), (0.5, 2.0), (2.0, 2.5)]) == [(0.0, 2.5), (3.0, 4.0)]
    assert stalled_within([(0.0, 1.0), (0.5, 2.0)], 0.0, 10.0) == 2.0
    assert stalled_within([(0.0, 1.0), (0.5, 2.0)], 1.5, 10.0) == 0.5


def test_one_stalled_cpu_is_seen_by_its_pinned_witness() -> None:
    # Stopping one pinned witness is what a CPU that stops running its tasks does to it;
    # the others run on, so the union holds that one CPU's stall.
    with CpuStallWitnesses() as witnesses:
        stopped = witnesses.witnesses[-1]
        assert stopped._proc is not None
        assert os.sched_getaffinity(stopped._proc.pid) == {stopped.cpu}
        start, end = stopped_for(stopped._proc.pid, 0.3)
        gaps = witnesses.settled_gaps(start, end)
        assert stalled_within(gaps, start, end) >= 0.29
        assert all(start <= a < b <= end for a, b in gaps)
