"""Hold processes of a real-time run still for a while, as a host that takes their CPU does
(bench/bench_server_hold.py).

    python bench/process_hold.py <orchestrator pid> <serving|plant|ecus>[,...] <hold ms> <go epoch s> <offset s>...

At each offset (wall seconds after ``go``) it stops the processes asked for (SIGSTOP), waits the hold, and lets
them go on (SIGCONT); it prints one line per hold, ``<start epoch s> <end epoch s>``, as measured. ``serving``: the
orchestrator, whose native thread serves every bus; ``plant`` and ``ecus``: its node processes of that kind;
several, comma-separated: all of them at once, as when they share the held CPU. Unlike
``bench/machine_stall.py``'s busy loop, which the rig's other threads can leave for another CPU, a stopped process
does nothing at all until it is let go, as on a CPU the host holds.
"""
from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

NODE_MODULES = {"plant": "hil.runtime.realtime.plant_node", "ecus": "hil.runtime.realtime.ecu_node"}
KINDS = ("serving", *NODE_MODULES)  # what it can hold: the orchestrator, or the node processes of one kind


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (from /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass  # the thread ended meanwhile
    return found


def targets(orchestrator: int, which: str) -> list[int]:
    """The processes ``which`` (one of KINDS) names: the orchestrator itself, or its node processes of one kind."""
    if which == "serving":
        return [orchestrator]
    module = NODE_MODULES[which].encode()
    pids = []
    for pid in children(orchestrator):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue  # it ended meanwhile
        if module in argv:
            pids.append(pid)
    return pids


def hold(pids: list[int], length_s: float) -> tuple[float, float]:
    """Stop ``pids`` for ``length_s``; returns when (epoch s) they were stopped and let go."""
    start = time.time()
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(length_s)
    finally:
        for pid in pids:
            os.kill(pid, signal.SIGCONT)
    return start, time.time()


def main() -> None:
    orchestrator, which, length_ms, go = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
    kinds = which.split(",")
    if not set(kinds) <= set(KINDS):
        raise SystemExit(f"process_hold: {which!r} is not a comma-separated list of {', '.join(KINDS)}")
    for offset in (float(a) for a in sys.argv[5:]):
        time.sleep(max(0.0, go + offset - time.time()))
        start, end = hold([pid for kind in kinds for pid in targets(orchestrator, kind)], length_ms / 1e3)
        print(f"{start!r} {end!r}", flush=True)


def _exit(signum: int, _frame: object) -> None:
    """Ended (the bench's run is over): leave through ``hold``'s ``finally``, which lets the processes go on."""
    raise SystemExit(128 + signum)


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the terminal's Ctrl-C is the bench's: it ends us with SIGTERM
    signal.signal(signal.SIGTERM, _exit)
    main()
