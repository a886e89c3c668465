"""The timing tests' witness to stalls of the whole machine (`tests.stall_witness`)."""

from __future__ import annotations

import os
import signal
import time

from tests.stall_witness import StallWitness


def test_a_witness_that_was_not_run_reports_the_time_it_lost() -> None:
    # Stopping the witness's process is what a stalled machine does to every process.
    with StallWitness() as witness:
        assert witness._proc is not None
        start = time.monotonic()
        os.kill(witness._proc.pid, signal.SIGSTOP)
        time.sleep(0.3)
        os.kill(witness._proc.pid, signal.SIGCONT)
        end = time.monotonic()
        gaps = witness.settled_gaps(start, end)
        assert gaps, "the witness reported nothing"
        # At least the 0.3 s it was stopped; never more than the window asked about.
        assert witness.stalled_s(start, end) >= 0.29
        assert all(start <= a < b <= end for a, b in gaps)
        # A window before the stop holds none of it.
        assert witness.stalled_s(start - 5.0, start) == 0.0
