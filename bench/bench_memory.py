"""Peak memory (RSS) of `hil run seed000` against its simulated length: 100, 1000 and 10000 s by default.

Each run is a fresh `hil run` process (with its recording, as a user runs it); the figure is its peak resident set
size (getrusage of the child). The bus statistics are kept as the frames come (hil/can/frame_stats.py), the
metrics' figures of the sampled signals too (hil/record/signal_summary.py), and `hil run` lets the per-frame rows,
the load windows and the signal samples go once they are recorded, so the peak should not grow with the length.
    python bench/bench_memory.py [--sims 100,1000,10000] [--scenario seed000] [--realtime]

With ``--realtime`` the runs are real-time runs at pace 1, and wait4's peak is that of the rig's largest process
(the orchestrator or one of its nodes).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time


def peak_rss_mb(argv: list[str]) -> tuple[float, float]:
    """(peak RSS of the child in MB, its wall time in s)."""
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # a fresh child per run: its getrusage peak is its own
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)  # its summary is not the bench's output
        os.execvp(argv[0], argv)
    _, status, usage = os.wait4(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(argv)} failed with {os.waitstatus_to_exitcode(status)}")
    return usage.ru_maxrss / 1024.0, time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sims", default="100,1000,10000", help="simulated seconds, comma-separated")
    p.add_argument("--scenario", default="seed000")
    p.add_argument("--realtime", action="store_true", help="real-time runs (pace 1: each takes its simulated length); "
                   "the figure is the largest process of the rig (orchestrator or a node)")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, sim in enumerate(float(s) for s in args.sims.split(",")):
            argv = [sys.executable, "-m", "hil", "run", args.scenario, "--duration", repr(sim), "--quiet",
                    "--out", os.path.join(tmp, f"r{k}")] + (["--realtime"] if args.realtime else [])
            rss, wall = peak_rss_mb(argv)
            rows.append((sim, rss, wall))
            print(f"{args.scenario} {sim:8.0f} s simulated: peak RSS {rss:7.1f} MB   ({wall:6.1f} s wall)", flush=True)
    (s0, r0, _), (s1, r1, _) = rows[0], rows[-1]
    if s1 > s0:
        print(f"growth: {(r1 - r0) * 1024 / (s1 - s0):.1f} kB per simulated second")


if __name__ == "__main__":
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    main()
