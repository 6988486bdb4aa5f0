"""Virtual time's sensor-to-actuator latency, to set beside the real-time plant's (``e2e_latency_*`` in a real-time
run's metrics): each TractionCmd's arrival at the plant minus the publication of the Sensor sample its cycle read.

In virtual time an ECU's cycle runs at its deadline and every Sensor frame of a publication has ended before the
first cycle after it (``ecu.phase_s``), so the sample a command answers is the last publication at or before its
cycle. Prints the count, p50, p99 and max in ms.
    python bench/bench_e2e_virtual.py [--scenario seed000] [--sim 60]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402


class LatencyTap(VirtualRig):
    """The rig, with each command's sensor-to-actuator latency taken as the plant applies it."""

    def __init__(self, sc) -> None:
        super().__init__(sc)
        self.latencies: list[float] = []
        real_apply = self.plant_io.apply
        cycle, period = sc.ecu.cycle_s, sc.can.sensor_period_s

        def apply(u: int, force: float, mode: int, t: float, counter: int) -> bool:
            phase = sc.ecu.phase_s + self.layout.train_unit(u)[1] * sc.ecu.stagger_s
            cycle_t = phase + math.floor((t - phase) / cycle + 1e-9) * cycle  # the cycle that sent it
            self.latencies.append(t - math.floor(cycle_t / period + 1e-9) * period)
            return real_apply(u, force, mode, t, counter)

        self.plant_io.apply = apply  # type: ignore[method-assign]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="seed000")
    ap.add_argument("--sim", type=float, default=60.0, help="simulated seconds")
    args = ap.parse_args()
    rig = LatencyTap(load_scenario(args.scenario))
    rig.run(args.sim)
    ms = np.array(rig.latencies) * 1e3
    print(f"{args.scenario}, virtual time, {args.sim:g} s: {len(ms)} commands; sensor-to-actuator latency "
          f"p50 {np.percentile(ms, 50):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, max {ms.max():.3f} ms")


if __name__ == "__main__":
    main()
