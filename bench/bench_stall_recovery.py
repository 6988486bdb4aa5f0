"""Benchmark: how long after a stall of the machine the real-time rig is on time again.

On a virtual machine the host now and then holds a virtual CPU for milliseconds; every thread on it stops, and the
ECU cycles due meanwhile start late. This bench makes such stalls on purpose, at known instants, so that the rig's
own share can be told from the host's: a busy loop under SCHED_FIFO above every thread of the rig, kept to one CPU
(``bench/machine_stall.py``), takes that CPU for the stall's length. For each stall it prints the ECU cycles due
during it, the worst lateness of the cycles around it, and when the last of those overdue cycles started after the
stall's end (the rig's recovery: what a stall of the host costs beyond its own length), their misses, and the plant's
worst publication lateness; per run, the frames lost.

    python bench/bench_stall_recovery.py [--runs seed000 64] [--stall-ms 5 10 20] [--cpus all 0 1]

``--runs``: a packaged scenario by name, or an ECU count for seed000-consensus scaled to it as in
``bench/bench_realtime_scale.py``. Each run stalls every combination of ``--cpus`` (``all``: every CPU at once) and
``--stall-ms`` once, one stall every ``--every`` simulated seconds from 2 s, each starting 1 ms before the units'
first cycle of that period. The rig runs with its default settings at pace 1. Needs SCHED_FIFO (root or
CAP_SYS_NICE); exits 2 without it.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_realtime_scale import scenario_for  # noqa: E402
from hil.runtime.realtime.orchestrator import run_realtime  # noqa: E402
from hil.runtime.realtime.plant_node import publication_steps, tick_periods  # noqa: E402
from hil.runtime.realtime.scheduling import set_fifo_priority  # noqa: E402
from hil.runtime.realtime.streamed_series import read_series  # noqa: E402
from hil.scenario.loader import ScenarioError  # noqa: E402

FIRST_STALL_S = 2.0  # simulated s: the nodes are past their first, cold cycles


@dataclass(frozen=True)
class Stall:
    """One stall asked for: the CPUs it takes, from ``start_s`` (simulated) for ``length_s``."""

    cpus: tuple[int, ...]
    start_s: float
    length_s: float


def plan(cpu_sets: list[tuple[int, ...]], lengths_s: list[float], every_s: float, phase_s: float) -> list[Stall]:
    """Every CPU set with every length, one stall every ``every_s`` from FIRST_STALL_S, each 1 ms before the
    units' first cycle of its period (``phase_s``), so that cycles fall due during it."""
    combos = [(cpus, length) for cpus in cpu_sets for length in lengths_s]
    return [Stall(cpus, FIRST_STALL_S + k * every_s + max(phase_s - 0.001, 0.0), length)
            for k, (cpus, length) in enumerate(combos)]


def cpu_sets(names: list[str]) -> list[tuple[int, ...]]:
    """``all`` -> every CPU this process may use; ``N`` -> (N,)."""
    mine = tuple(sorted(os.sched_getaffinity(0)))
    out = []
    for name in names:
        if name != "all" and not name.isdigit():
            raise SystemExit(f"--cpus {name}: not 'all' or a CPU number")
        cpus = mine if name == "all" else (int(name),)
        if not set(cpus) <= set(mine):
            raise SystemExit(f"--cpus {name}: not a CPU this process may use ({', '.join(map(str, mine))})")
        out.append(cpus)
    return out


def start_stall_makers(cpus: set[int]) -> dict[int, subprocess.Popen]:
    """One bench/machine_stall.py per CPU, waiting for its intervals on stdin."""
    return {c: subprocess.Popen([sys.executable, str(ROOT / "bench" / "machine_stall.py"), str(c)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) for c in sorted(cpus)}


def send_plan(makers: dict[int, subprocess.Popen], stalls: list[Stall], t0: float) -> None:
    """Each maker's intervals in epoch time (simulated t = 0 at ``t0``, pace 1); stdin closed after them."""
    for cpu, maker in makers.items():
        assert maker.stdin is not None
        for s in stalls:
            if cpu in s.cpus:
                maker.stdin.write(f"{t0 + s.start_s!r} {s.length_s!r}\n")
        maker.stdin.close()


def held_intervals(makers: dict[int, subprocess.Popen]) -> dict[int, list[tuple[float, float]]]:
    """Per CPU, the (start, end) epoch intervals its maker held, in order."""
    held = {}
    for cpu, maker in makers.items():
        assert maker.stdout is not None
        out = maker.stdout.read()  # (its stdin is closed: communicate() would flush it)
        if maker.wait(timeout=30) != 0:
            raise SystemExit(f"bench/machine_stall.py {cpu} exited {maker.returncode}")
        held[cpu] = [(float(a), float(b)) for a, b in (line.split() for line in out.splitlines())]
    return held


def timing_rows(paths: list[Path]) -> np.ndarray:
    """Rows (deadline s, lateness s) of the nodes' timing series, all together."""
    parts = [read_series(p) for p in paths if p.exists()]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


@dataclass
class Recovery:
    """What one stall did to the rig (times in ms)."""

    due: int  # ECU cycles due during the stall
    worst_ms: float  # the worst lateness of a cycle due from a period before the stall to its end
    recovered_ms: float  # when the last of those cycles started, after the stall's end (0: all before it)
    misses: int  # of those cycles, late by more than their period
    plant_worst_ms: float  # the worst lateness of a publication due in the same span


def recovery(ecu: np.ndarray, plant: np.ndarray, start: float, end: float, cycle_s: float) -> Recovery:
    """The stall from ``start`` to ``end`` (simulated s, as held) against the ECU and plant timing rows."""
    around = ecu[(ecu[:, 0] >= start - cycle_s) & (ecu[:, 0] <= end)]
    due = int(((ecu[:, 0] >= start) & (ecu[:, 0] <= end)).sum())
    started = around[:, 0] + around[:, 1]
    near_plant = plant[(plant[:, 0] >= start - cycle_s) & (plant[:, 0] <= end)]
    return Recovery(due, 1e3 * float(around[:, 1].max(initial=0.0)),
                    1e3 * (float(started.max(initial=end)) - end), int((around[:, 1] > cycle_s).sum()),
                    1e3 * float(near_plant[:, 1].max(initial=0.0)))


def scenario(name: str):
    """A packaged scenario by name, or seed000-consensus scaled to an ECU count."""
    return scenario_for(int(name), None) if name.isdigit() else scenario_for(0, name)


def run(name: str, sc, stalls_asked: list[Stall], every_s: float) -> None:
    """One real-time run of ``sc`` (called ``name``) with the stalls; prints a line per stall."""
    duration = stalls_asked[-1].start_s + every_s + 1.0
    with tempfile.TemporaryDirectory() as d:
        metrics, t0, held = run_stalled(sc, Path(d) / "rt", duration, stalls_asked)
        nodes = Path(d) / "rt" / "nodes"
        ecu = timing_rows(sorted(nodes.glob("timing_ecu_*.bin")))
        plant = timing_rows([nodes / "timing_plant.bin"])
    print(f"\n{name} ({sc.trains.count * sc.trains.units} ECUs), pace 1, {duration:.1f} s: ECU misses "
          f"{metrics['cycle_deadline_misses']}, plant misses {metrics['plant_deadline_misses']}, frames lost "
          f"{metrics['frames_lost']}; publication period "
          f"{1e3 * publication_steps(tick_periods(sc)) * sc.plant.step_s:g} ms, ECU cycle {1e3 * sc.ecu.cycle_s:g} ms")
    print(f"  {'CPUs':>6} {'asked':>7} {'held':>7} {'cycles due':>10} {'worst late':>10} {'last late cycle started':>24} "
          f"{'misses':>6} {'plant worst':>11}")
    position = {cpu: 0 for cpu in held}
    for s in stalls_asked:
        spans = [held[c][position[c]] for c in s.cpus]
        for c in s.cpus:
            position[c] += 1
        start, end = min(a for a, _ in spans) - t0, max(b for _, b in spans) - t0
        r = recovery(ecu, plant, start, end, sc.ecu.cycle_s)
        cpus = "all" if len(s.cpus) > 1 else str(s.cpus[0])
        print(f"  {cpus:>6} {1e3 * s.length_s:5.1f}ms {1e3 * (end - start):5.1f}ms {r.due:10d} {r.worst_ms:8.2f}ms "
              f"{r.recovered_ms:+10.2f} ms after its end {r.misses:6d} {r.plant_worst_ms:9.2f}ms", flush=True)


def run_stalled(sc, out: Path, duration: float, stalls: list[Stall]) -> tuple[dict, float, dict[int, list]]:
    """Run ``sc`` in real time into ``out`` with the stall makers holding their CPUs as planned: (its metrics, the
    epoch of simulated t = 0, the intervals each CPU was held). A run that fails or is interrupted stops the makers
    first: none outlives the bench to stall the machine later."""
    makers = start_stall_makers({c for s in stalls for c in s.cpus})
    t0: list[float] = []

    def on_start(go: float) -> None:
        t0.append(go)
        send_plan(makers, stalls, go)

    try:
        res = run_realtime(sc, out, pace=1.0, duration_s=duration, record=False, on_start=on_start)
        if res.metrics["interrupted"]:  # Ctrl-C stops the rig cleanly: the bench stops too
            raise KeyboardInterrupt
    except BaseException:
        for maker in makers.values():
            maker.kill()
            maker.wait()
        raise
    return res.metrics, t0[0], held_intervals(makers)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=["seed000", "64"],
                    help="packaged scenarios by name, or ECU counts (seed000-consensus scaled)")
    ap.add_argument("--stall-ms", type=float, nargs="+", default=[5.0, 10.0, 20.0])
    ap.add_argument("--cpus", nargs="+", default=["all", "0", "1"], help="all, or a CPU number; several: each in turn")
    ap.add_argument("--every", type=float, default=0.5, help="simulated seconds between stalls")
    args = ap.parse_args()
    refused = set_fifo_priority(1, reset_on_fork=True)  # a probe only: this process then goes back to normal
    if refused is not None:
        print(f"bench_stall_recovery: SCHED_FIFO refused ({refused}); the stalls need it (root or CAP_SYS_NICE)",
              file=sys.stderr)
        raise SystemExit(2)
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if any(length <= 0 or length >= 1e3 * args.every - 50 for length in args.stall_ms):
        raise SystemExit(f"--stall-ms: each must be above 0 and at least 50 ms below --every ({args.every:g} s)")
    sets = cpu_sets(args.cpus)
    try:
        scenarios = [(name, scenario(name)) for name in args.runs]
    except ScenarioError as exc:
        raise SystemExit(f"--runs: {exc}") from None
    print(f"{os.cpu_count()} CPUs; stalls of {', '.join(f'{x:g}' for x in args.stall_ms)} ms on CPUs "
          f"{', '.join(args.cpus)}, every {args.every:g} s; the rig's default settings (at pace 1 on two CPUs or more: "
          "the serving thread and the plant on the first CPU the rig may use, the ECU processes on the others)")
    for name, sc in scenarios:
        run(name, sc, plan(sets, [x / 1e3 for x in args.stall_ms], args.every, sc.ecu.phase_s), args.every)


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("bench_stall_recovery: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
