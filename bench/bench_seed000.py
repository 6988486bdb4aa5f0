"""Virtual-time speed of seed000 (12 ECUs at 100 Hz, exact CAN timing) and its cost over the ideal loop.

Prints simulated seconds per wall second for the networked rig and for the ideal (network-free) loop of
the same scenario, and their ratio. Targets (issue 2): >= 30x real time on one core, network <= 2x ideal.
    python bench/bench_seed000.py [--sim 60] [--profile]
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time

from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario


def timed(build, sim_s: float) -> tuple[float, float]:
    """(wall seconds to build, wall seconds to run sim_s)."""
    t0 = time.perf_counter()
    runner = build()
    t1 = time.perf_counter()
    runner.run(sim_s)
    return t1 - t0, time.perf_counter() - t1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=60.0, help="simulated seconds per run")
    ap.add_argument("--scenario", default="seed000")
    ap.add_argument("--profile", action="store_true", help="print the top functions of the networked run")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    print(f"scenario {sc.name}: {sc.trains.count} trains x {sc.trains.units} units, ECU cycle {sc.ecu.cycle_s * 1e3:g} ms, "
          f"plant step {sc.plant.step_s * 1e3:g} ms, CAN {sc.can.bitrate // 1000} kbit/s, {args.sim:g} s simulated")
    _, ideal_wall = timed(lambda: IdealLoop(sc), args.sim)
    _, net_wall = timed(lambda: VirtualRig(sc), args.sim)
    rig = VirtualRig(sc)
    rig.run(1.0)
    frames_per_s = sum(b.frames_sent for b in rig.log.buses) / 1.0
    print(f"ideal loop      : {args.sim / ideal_wall:8.1f} x real time ({ideal_wall:.2f} s wall)")
    print(f"network (CAN)   : {args.sim / net_wall:8.1f} x real time ({net_wall:.2f} s wall), {frames_per_s:.0f} frames per simulated s")
    print(f"network / ideal : {net_wall / ideal_wall:8.2f} x the ideal loop's cost   (target <= 2)")
    print(f"per frame       : {net_wall / (frames_per_s * args.sim) * 1e6:8.1f} us of wall time per CAN frame (all costs included)")
    if args.profile:
        prof = cProfile.Profile()
        rig = VirtualRig(sc)
        prof.runcall(rig.run, min(args.sim, 20.0))
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(18)
        print(out.getvalue())


if __name__ == "__main__":
    main()
