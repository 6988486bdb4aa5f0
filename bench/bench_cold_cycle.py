"""What a cold cache costs the Python a real-time node runs per wake-up: seed000's ECU cycle and plant step, warm,
after a sleep, and after the caches were evicted.

Real time pays for the same firmware cycle several times what virtual time pays (docs/realtime-performance.md,
"What real time still costs"). A real-time node sleeps between its cycles, and on a virtual machine the host runs
other work on the core meanwhile (or moves the virtual CPU), so the node's code and data may be out of the caches
when it wakes.
This bench measures that in isolation, in virtual time: it runs seed000 and times one ECU cycle
(``cycle_and_send``: the firmware and the engine's encode-and-queue) and one plant step in every TIMED_EVERY by the
thread's CPU clock, with before each timed one:

* nothing (warm, as virtual time runs);
* a 10 ms sleep, as a real-time node sleeps between its 100 Hz cycles, or a 1 ms sleep;
* a 10 ms sleep with the CPUs' wake-up latency limit held at 0 µs (``hil run --realtime --idle-latency-us 0``): an
  idle CPU then polls instead of halting (only where this user may hold ``/dev/cpu_dma_latency``);
* a 10 ms busy wait: the same gap with the CPU kept busy (the sleep, not the time, is what matters if these two
  differ);
* a touch of a buffer twice one core's L2 cache (the cycle's lines then come from L3), or twice the last-level
  cache (they come from memory).

The modes run interleaved, a simulated second each in turn, so the machine's drift hits them alike. It prints the
mean CPU per timed call and its ratio to warm.

    python bench/bench_cold_cycle.py [--sim 8] [--scenario seed000]
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.runtime.realtime.idle_latency import CPU_LATENCY_FILE, IdleLatencyHold, may_hold  # noqa: E402
from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402

CACHE_DIR = Path("/sys/devices/system/cpu/cpu0/cache")
TIMED_EVERY = 20  # one call in this many is timed (and prepared): the sleeps would take too long for all
GAP_S = 0.01  # a 100 Hz node's sleep between cycles
SHORT_GAP_S = 0.001  # a sleep ten times shorter: whether the cold comes with the length of the sleep


def cache_bytes(level: int) -> int | None:
    """The size of this machine's level-``level`` data or unified cache (bytes), None where sysfs does not say."""
    for index in sorted(CACHE_DIR.glob("index*")):
        try:
            if int((index / "level").read_text()) == level and (index / "type").read_text().strip() != "Instruction":
                size = (index / "size").read_text().strip()
                return int(size[:-1]) * 1024 if size.endswith("K") else int(size)
        except (OSError, ValueError):
            continue
    return None


def touch(buffer: np.ndarray) -> None:
    """Write every cache line of ``buffer``, pushing other data out of the caches."""
    np.add(buffer, 1.0, out=buffer)


def busy_wait(seconds: float) -> None:
    """Keep the CPU busy for ``seconds`` (no sleep: the core is not given up)."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


class TimedRig(VirtualRig):
    """The virtual rig, one ECU cycle and one plant step in every TIMED_EVERY timed (thread CPU) after ``prepare``."""

    def __init__(self, scenario, prepare: Callable[[], None]) -> None:
        super().__init__(scenario)
        self.prepare = prepare
        self.calls = {"ecu": 0, "plant": 0}
        self.ns = {"ecu": 0, "plant": 0}

    def _timed(self, kind: str, call: Callable[[], None]) -> None:
        self.calls[kind] += 1
        if self.calls[kind] % TIMED_EVERY:
            call()
            return
        self.prepare()
        t0 = time.thread_time_ns()
        call()
        self.ns[kind] += time.thread_time_ns() - t0

    def mean_us(self, kind: str) -> float:
        return self.ns[kind] / (self.calls[kind] // TIMED_EVERY) / 1e3

    def _ecu_tick(self, u: int, t_ns: int) -> None:
        self._timed("ecu", lambda: super(TimedRig, self)._ecu_tick(u, t_ns))

    def _plant_step(self, t_ns: int) -> None:
        self._timed("plant", lambda: super(TimedRig, self)._plant_step(t_ns))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=8.0, help="simulated seconds per mode")
    ap.add_argument("--scenario", default="seed000")
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    l2, llc = cache_bytes(2), cache_bytes(3) or cache_bytes(2)
    if l2 is None or llc is None:
        raise SystemExit(f"{CACHE_DIR}: no cache sizes on this machine; the bench needs them")
    l2_buffer, llc_buffer = np.zeros(2 * l2 // 8), np.zeros(2 * llc // 8)
    held = f"after a {GAP_S * 1e3:g} ms sleep, latency held"  # run with the limit held at 0 µs
    modes: dict[str, Callable[[], None]] = {
        "warm (virtual time)": lambda: None,
        f"after a {GAP_S * 1e3:g} ms sleep": lambda: time.sleep(GAP_S),
        f"after a {SHORT_GAP_S * 1e3:g} ms sleep": lambda: time.sleep(SHORT_GAP_S),
        held: lambda: time.sleep(GAP_S),
        f"after a {GAP_S * 1e3:g} ms busy wait": lambda: busy_wait(GAP_S),
        f"L2 evicted ({2 * l2 >> 20} MiB touched)": lambda: touch(l2_buffer),
        f"all caches evicted ({2 * llc >> 20} MiB touched)": lambda: touch(llc_buffer)}
    if not may_hold():
        print(f"(not permitted to hold {CPU_LATENCY_FILE}: the held mode is left out)")
        del modes[held]
    rigs = {name: TimedRig(sc, prepare) for name, prepare in modes.items()}
    for second in range(1, int(args.sim) + 1):  # interleaved, a simulated second each
        for name, rig in rigs.items():
            with IdleLatencyHold(0) if name == held else contextlib.nullcontext():
                rig.kernel.run(second * 1_000_000_000)
    print(f"scenario {sc.name}: {args.sim:g} simulated s per mode, interleaved; one call in {TIMED_EVERY} timed; "
          f"L2 {l2 >> 10} KiB per core, last level {llc >> 20} MiB; CPU time per call (thread clock)")
    warm = next(iter(rigs.values()))
    for name, rig in rigs.items():
        ecu, plant = rig.mean_us("ecu"), rig.mean_us("plant")
        print(f"  {name:44s} ECU cycle {ecu:6.1f} us ({ecu / warm.mean_us('ecu'):4.1f}x)   "
              f"plant step {plant:6.1f} us ({plant / warm.mean_us('plant'):4.1f}x)")


if __name__ == "__main__":
    main()
