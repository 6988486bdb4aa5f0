"""A process that only sleeps, to tell a stall of the machine (or of one of its CPUs) from a stall of the rig.

    python bench/stall_watch.py OUT [CPU]    (until SIGTERM; bench/bench_realtime_scale.py starts and stops it)

With CPU it keeps to that CPU (the bench starts one per CPU: a host that takes one virtual CPU stalls only the
threads on it, which a watch on the other CPU would not see). It sleeps ``SLEEP_S`` over and over and writes each
wake-up later than ``LATE_S`` to OUT as a row of float64 ``(wall epoch at the wake-up, lateness s, host steal s
since the last reading before it)``. It shares no lock, socket or thread with the rig, so where it is late at the
instant the rig's nodes all are, its CPU stalled (the host took it: steal time; or every core was busy),
not the rig's serving thread. Where the host permits it, it sleeps under SCHED_FIFO at WATCH_PRIORITY, above every
thread of the rig (hil/runtime/realtime/scheduling.py), so the rig's own bursts under SCHED_FIFO do not make it
late: what it sees is the machine's (the host, the kernel).
"""
from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from hil.runtime.realtime.scheduling import PRIORITIES, set_fifo_priority  # noqa: E402

SLEEP_S = 0.002
# a wake-up this much past its sleep counts: a host holds a virtual CPU in trains of 1.5-5.6 ms holds as well as in
# single stalls, and a train adds up to a miss (docs/realtime-performance.md, "How long after a stall");
# idle, the watches under SCHED_FIFO woke under 0.9 ms late (about 40,000 wake-ups on two CPUs in 40 s)
LATE_S = 0.001
READ_STEAL_EVERY = 5  # sleeps between readings of the steal counter (10 ms: its resolution)
WATCH_PRIORITY = max(PRIORITIES.values()) + 1  # above the rig's serving thread


def steal_s() -> float:
    """CPU time the host took from this virtual machine since boot (/proc/stat; 0 where there is none)."""
    try:
        with open("/proc/stat", "rb") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def watch(out: Path) -> None:
    """Sleep and record late wake-ups until SIGTERM; the steal counter is read every READ_STEAL_EVERY sleeps (its
    unit is a clock tick, 10 ms) and at each late wake-up."""
    stop: list[bool] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    with open(out, "wb", buffering=0) as f:
        steal, k = steal_s(), 0
        while not stop:
            before = time.monotonic()
            time.sleep(SLEEP_S)
            late = time.monotonic() - before - SLEEP_S
            k += 1
            if late > LATE_S:
                now_steal = steal_s()
                f.write(np.array([time.time(), late, now_steal - steal]).tobytes())
                steal = now_steal
            elif k % READ_STEAL_EVERY == 0:
                steal = steal_s()


def read_stalls(path: Path) -> np.ndarray:
    """The rows OUT holds: (n, 3)."""
    return np.fromfile(path).reshape(-1, 3) if path.exists() else np.zeros((0, 3))


if __name__ == "__main__":
    if len(sys.argv) > 2:
        os.sched_setaffinity(0, {int(sys.argv[2])})
    set_fifo_priority(WATCH_PRIORITY)  # where refused, an ordinary process (it then also sees the rig's bursts)
    watch(Path(sys.argv[1]))
