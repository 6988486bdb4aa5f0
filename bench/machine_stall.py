"""A process that takes one CPU from everything else on it for given intervals: a stall of the machine, on purpose.

    python bench/machine_stall.py CPU    (bench/bench_stall_recovery.py starts one per CPU it stalls)

It keeps to CPU and reads intervals from stdin, one ``START_EPOCH DURATION_S`` per line, until EOF. It sleeps to each
start under the normal scheduler, then busy-loops for the duration under SCHED_FIFO above every thread of the rig
(the stall watch's priority, bench/stall_watch.py), so nothing of the rig runs on that CPU meanwhile: what a host
that holds a virtual CPU does to it. It drops back to the normal scheduler before it does anything else (a process
under SCHED_FIFO that writes or exits holds its CPU for milliseconds more than asked). It prints each interval as
it held it, ``START END`` (epoch), once stdin is closed and every interval is over.

Exits 2 where the host does not permit SCHED_FIFO: a busy loop under the normal scheduler shares its CPU and is no
stall.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.stall_watch import WATCH_PRIORITY  # noqa: E402
from hil.runtime.realtime.scheduling import set_fifo_priority  # noqa: E402


def hold(start: float, duration_s: float) -> tuple[float, float]:
    """Sleep to ``start`` (epoch), then hold this CPU for ``duration_s``; (start, end) as held."""
    time.sleep(max(start - time.time(), 0.0))
    refused = set_fifo_priority(WATCH_PRIORITY, reset_on_fork=True)
    if refused is not None:
        raise SystemExit(f"machine_stall: SCHED_FIFO refused ({refused}): a busy loop under the normal scheduler "
                         "is no stall (run as root or with CAP_SYS_NICE)")
    began = time.time()
    end = began + duration_s
    while time.time() < end:
        pass
    held_to = time.time()
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return began, held_to


def main(cpu: int) -> None:
    os.sched_setaffinity(0, {cpu})
    held = [hold(float(start), float(duration)) for start, duration in (line.split() for line in sys.stdin)]
    for began, end in held:
        print(f"{began!r} {end!r}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python bench/machine_stall.py CPU")
    try:
        main(int(sys.argv[1]))
    except SystemExit as exc:
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
            raise SystemExit(2) from None
        raise
