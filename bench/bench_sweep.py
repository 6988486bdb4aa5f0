"""Sweep throughput: runs per minute of seed000 with 1 and 2 local worker processes, and the speed-up.

Every run is a distinct grid point (a seed), timed end to end through ``run_sweep`` (pool start-up, runs,
files, results.csv). With ``--sim`` below 600 the figure "per 600 s run" is scaled by sim/600, which assumes
the cost grows linearly with simulated time (it does, up to a constant start-up per run of about 0.1 s), and
says so. Target: speed-up >= 1.7 with 2 workers on 2 cores.
    python bench/bench_sweep.py [--sim 600] [--runs 4] [--workers 1,2]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from hil.sweep.runner import run_sweep
from hil.sweep.spec import sweep_from_dict


def timed_sweep(sim_s: float, runs: int, workers: int) -> float:
    """Wall seconds of a sweep of `runs` seed000 runs of sim_s simulated seconds on `workers` processes."""
    spec = sweep_from_dict({"name": f"bench-w{workers}", "base": "seed000", "duration_s": sim_s,
                            "seeds": list(range(runs))}, "<bench>")
    with tempfile.TemporaryDirectory(prefix="bench-sweep-") as out:
        t0 = time.perf_counter()
        result = run_sweep(spec, Path(out), workers=workers, progress=False)
        wall = time.perf_counter() - t0
    if result.ok != runs:
        raise SystemExit(f"{result.failed} runs failed: {result.failures}")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=600.0, help="simulated seconds per run (the figure is per 600 s run)")
    ap.add_argument("--runs", type=int, default=4, help="runs per sweep (a multiple of every worker count is fairest)")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    args = ap.parse_args()
    counts = [int(w) for w in args.workers.split(",")]
    scale = args.sim / 600.0
    print(f"seed000, {args.runs} runs of {args.sim:g} simulated s per sweep, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f} before start")
    if scale != 1.0:
        print(f"runs per minute are scaled to 600 s runs: measured x {scale:g} (cost linear in simulated time)")
    rates = {}
    for w in counts:
        wall = timed_sweep(args.sim, args.runs, w)
        rates[w] = args.runs / wall * 60.0 * scale
        print(f"{w} worker{'s' if w > 1 else ' '}: {wall:7.1f} s wall, {rates[w]:6.2f} runs/min of 600 s "
              f"({args.sim * args.runs / wall:.1f} simulated s per wall s)")
    if len(counts) > 1:
        lo, hi = min(counts), max(counts)
        print(f"speed-up {hi} vs {lo} worker(s): {rates[hi] / rates[lo]:.2f}x   (target >= 1.7 for 2 vs 1 on 2 cores)")


if __name__ == "__main__":
    main()
