"""The cost of an FMU plant and an FMU law beside the built-in ones, measured side by side in one process.

For each pair (built-in plant vs the reference plant FMU; the Python consensus law vs the reference law FMU) it
runs seed000 over CAN in virtual time, interleaved ``--repeat`` times (the fastest of each is kept: this machine's
speed drifts by about 40 %), and prints x real time, the ratio, and the cost of one plant step and one law step
timed in isolation.
    python bench/bench_fmi.py [--sim 20] [--repeat 3]
"""
from __future__ import annotations

import argparse
import time

from ecu_sim.view import LocalView, NeighbourView, ReferenceView
from hil.runtime.assembly import assemble
from hil.runtime.virtual import VirtualRig
from hil.scenario import load_scenario

PAIRS = [("plant", "seed000", "seed000-fmu-plant"), ("law", "seed000-consensus", "seed000-fmu-law")]


def run_wall_s(name: str, sim_s: float) -> float:
    """Wall seconds for seed000-style ``name`` over CAN for ``sim_s`` simulated seconds."""
    rig = VirtualRig(load_scenario(name))
    t0 = time.perf_counter()
    rig.run(sim_s)
    wall = time.perf_counter() - t0
    rig.parts.close()
    return wall


def plant_step_us(name: str, n: int = 20_000) -> float:
    parts = assemble(load_scenario(name))
    t0 = time.perf_counter()
    for _ in range(n):
        parts.plant.step()
    cost = (time.perf_counter() - t0) / n * 1e6
    parts.close()
    return cost


def law_step_us(name: str, n: int = 20_000) -> float:
    parts = assemble(load_scenario(name))
    u = parts.layout.index(0, 1)  # a middle unit: two coupled neighbours
    off = parts.layout.offset_m
    view = LocalView(t=0.0, dt=0.01, x=-float(off[u]), v=80.0, ref=ReferenceView(0.0, 80.0, valid=True),
                     neighbours=[NeighbourView("intra", "ahead", float(off[u - 1]), x=-float(off[u - 1]), v=80.0,
                                               valid=True),
                                 NeighbourView("intra", "behind", float(off[u + 1]), x=-float(off[u + 1]), v=80.0,
                                               valid=True)])
    law = parts.law(u)
    t0 = time.perf_counter()
    for k in range(n):
        view.t = k * 0.01
        law.step(view)
    cost = (time.perf_counter() - t0) / n * 1e6
    parts.close()
    return cost


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=20.0, help="simulated seconds per run (default 20)")
    ap.add_argument("--repeat", type=int, default=3, help="interleaved repetitions; the fastest is kept (default 3)")
    args = ap.parse_args()
    for what, builtin, fmu in PAIRS:
        best = {builtin: float("inf"), fmu: float("inf")}
        for _ in range(args.repeat):
            for name in (builtin, fmu):
                best[name] = min(best[name], run_wall_s(name, args.sim))
        step = plant_step_us if what == "plant" else law_step_us
        costs = {name: min(step(name) for _ in range(args.repeat)) for name in (builtin, fmu)}
        print(f"{what}: {builtin:20s} {args.sim / best[builtin]:6.1f}x real time, {costs[builtin]:6.1f} us per {what} step")
        print(f"{what}: {fmu:20s} {args.sim / best[fmu]:6.1f}x real time, {costs[fmu]:6.1f} us per {what} step")
        print(f"{what}: FMU / built-in wall time {best[fmu] / best[builtin]:.2f}x, per step "
              f"{costs[fmu] / costs[builtin]:.1f}x")


if __name__ == "__main__":
    main()
