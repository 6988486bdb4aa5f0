"""Benchmark: how many ECUs at 100 Hz the real-time rig keeps on time on this machine.

Builds seed000-consensus with more trains and units (up to 16 per train bus at 1 Mbit/s), runs it in real time
for a few simulated seconds, one ECU per process and several ECUs per process, and reports per configuration:
ECU cycle lateness p50/p99 (wall), deadline misses and skipped cycles (a miss is a cycle started more than one
period late), plant publication lateness p99, sensor-to-actuator latency p99, frames lost, and the CPU time
the rig used per simulated second once every node was ready (all processes, to the end of the run and its merge;
psutil; the bench's own stall watch and CPU sampler not counted). A configuration "keeps up" when ECU
p99 lateness is below a tenth of the 10 ms cycle and fewer than 0.1 % of cycles miss.

    python bench/bench_realtime_scale.py [--ecus 12 24 48 64] [--per-process 0 1 8] [--duration 10] [--pace 1]
                                         [--plant-spin-us 0 200] [--scheduling auto normal] [--cpu-layout auto none]

Each configuration also prints the CPU per simulated second by role (ECU, plant and radio processes, the bus
servers' threads, the orchestrator), the profile the real-time cost is read from, and the host's steal time during
the run (a virtual machine's CPUs taken by its host: every node stalls at once). A stall watch
(``bench/stall_watch.py``, a process that only sleeps) runs beside the rig on each CPU: the bench prints each CPU's
stalls and how many ECU and plant deadline misses fell in one (a stall of the machine or of one of its virtual CPUs,
not of the rig). ``--keep DIR``
keeps each run's files (the nodes' timing series) under DIR instead of deleting them. ``--idle-latency-us host 0``
runs each configuration as the host idles and with idle CPUs kept polling (``hil run --idle-latency-us``; the
default, auto, polls where permitted), side by side. ``--scheduling auto normal``
runs each configuration under SCHED_FIFO where permitted and under the normal scheduler, side by side (the stall
watch sleeps under SCHED_FIFO above the rig where permitted, so the rig's own bursts are not counted as stalls).
``--cpu-layout auto none`` runs each configuration with the ECU processes on cores of their own (the default) and
with the kernel placing everything, side by side (``hil run --cpu-layout``). ``--turns on off`` runs each with the
nodes' turns (their frames at their instants, the bus waiting for them) and without, side by side (``hil run
--turns``; the default, auto, takes them faster than real time); each run also prints its loop (sensor-to-actuator p50, speed overshoot, coupler maximum),
to be read beside virtual time's (``hil run <scenario> --duration S``).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.runtime.realtime.bus_server import BusServerStats, turns_given_up, turns_let_go_text  # noqa: E402
from hil.runtime.realtime.orchestrator import default_ecus_per_process, run_realtime  # noqa: E402
from hil.runtime.realtime.turns import TURNS_MODES, TurnsMode  # noqa: E402
from hil.runtime.realtime.streamed_series import read_series  # noqa: E402
from hil.runtime.realtime.plant_node import publication_steps, tick_periods  # noqa: E402
from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.record.metrics import compute_metrics, dropped_by_node  # noqa: E402
from hil.record.safety import violated  # noqa: E402
from hil.runtime.realtime.idle_latency import IdleLatencySetting, latency_us  # noqa: E402
from hil.runtime.realtime.scheduling import SCHEDULING_MODES, SchedulingMode  # noqa: E402
from hil.runtime.realtime.cpu_layout import CPU_LAYOUT_MODES, CpuLayoutMode  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402
from bench.null_firmware import REFERENCE as NULL_FIRMWARE  # noqa: E402
from bench.stall_watch import LATE_S, SLEEP_S, read_stalls, steal_s  # noqa: E402

CYCLE_S = 0.01


FIRMWARES = {"standard": {}, "null": {"ecu.program": NULL_FIRMWARE}}  # --firmware: the scenario's overrides


def scenario_for(n_ecus: int, name: str | None, firmware: str = "standard"):
    """The packaged scenario ``name`` (its own ECU count), or seed000-consensus scaled to ``n_ecus``; with the
    ``firmware`` of ``FIRMWARES`` (standard: the scenario's own)."""
    overrides = FIRMWARES[firmware]
    return load_scenario(name, overrides) if name else scaled_scenario(n_ecus, overrides)


def scaled_scenario(n_ecus: int, overrides: dict | None = None):
    """seed000-consensus with n_ecus units: as few trains as fit 16 units per bus, 3 km apart, 1 Mbit/s buses (and
    ``overrides`` besides)."""
    trains = max(1, -(-n_ecus // 16))
    if n_ecus % trains:
        raise SystemExit(f"--ecus {n_ecus}: must split evenly into {trains} trains of at most 16 units")
    units = n_ecus // trains
    heads = [200_000.0 - i * (3000.0 + units * 80.0) for i in range(trains)]
    return load_scenario("seed000-consensus", {
        "trains.count": trains, "trains.units": units, "trains.head_positions_m": heads,
        "trains.speeds_kmh": [316.0] * trains, "reference.x0_m": 200_000.0, "can.bitrate": 1_000_000,
        "ecu.phase_s": 0.005, **(overrides or {}),
    })


def start_stall_watches(out: Path) -> list[subprocess.Popen]:
    """bench/stall_watch.py once per CPU this process may use, each kept to its CPU, writing that CPU's stalls to
    ``out/stalls_cpu<N>.bin``."""
    return [subprocess.Popen([sys.executable, str(ROOT / "bench" / "stall_watch.py"), str(out / f"stalls_cpu{c}.bin"),
                              str(c)]) for c in sorted(os.sched_getaffinity(0))]


def read_cpu_stalls(out: Path) -> np.ndarray:
    """Every CPU's stalls in time order: rows (wall epoch at the wake-up, lateness s, host steal s, CPU)."""
    parts = [np.column_stack([rows, np.full(len(rows), float(f.stem.removeprefix("stalls_cpu")))])
             for f in out.glob("stalls_cpu*.bin") if len(rows := read_stalls(f))]
    if not parts:
        return np.zeros((0, 4))
    rows = np.concatenate(parts)
    return rows[np.argsort(rows[:, 0])]


def misses_in_stalls(series: Iterable[Path], period_wall_s: float, t0: float, pace: float,
                     stalls: np.ndarray) -> tuple[int, int]:
    """(deadline misses in the nodes' timing ``series``, how many of them overlap a stall of any CPU's watch): a miss
    is a row late by more than ``period_wall_s``, the wall interval from its deadline to its start; each stall is a
    watch's late sleep."""
    stall_spans = [(w - late - SLEEP_S, w) for w, late, *_ in stalls]
    n = overlapped = 0
    for f in series:
        rows = read_series(f)
        for deadline, lateness in rows[rows[:, 1] > period_wall_s]:
            start = t0 + deadline / pace
            n += 1
            overlapped += any(a < start + lateness and start < b for a, b in stall_spans)
    return n, overlapped


def cpu_seconds() -> float:
    """User + system CPU of this process and every child it has reaped or still has."""
    me = psutil.Process()
    t = me.cpu_times()
    total = t.user + t.system + t.children_user + t.children_system
    for c in me.children(recursive=True):
        try:
            ct = c.cpu_times()
            total += ct.user + ct.system
        except psutil.Error:
            pass
    return total


ROLES = ("ecu_node", "plant_node", "radio_node")


def role_of(proc: psutil.Process) -> str:
    """A rig process's role from its command line (the node module it runs); the bench's stall watch is none."""
    try:
        cmd = " ".join(proc.cmdline())
    except psutil.Error:
        return "other"
    if "stall_watch" in cmd:
        return "sampler"
    return next((r.removesuffix("_node") for r in ROLES if r in cmd), "other")


def thread_times(pid: int) -> dict[int, tuple[str, int, int, int]]:
    """Every thread of process ``pid``: tid -> (name, CPU ns, time slices, ns runnable but waiting for a core), from
    /proc's schedstat (exact, unlike the tick-sampled utime/stime, which miss threads that wake briefly and often)."""
    out: dict[int, tuple[str, int, int, int]] = {}
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            name = (task / "comm").read_text().strip()
            ns, wait, slices = (task / "schedstat").read_text().split()
        except (OSError, ValueError):
            continue
        out[int(task.name)] = (name, int(ns), int(slices), int(wait))
    return out


class CpuByRole:
    """CPU seconds and wake-ups (time slices) per role once every node is ready: the ECU, plant and radio
    processes, and this process's threads: the bus servers' native threads and the orchestrator's Python, whose
    end of the run (the nodes' results, the merge) is taken whole by a last sample at ``stop``. Sampled every
    ``every_s`` (a node process's last second is missed). A sample reads every thread of the rig and holds the
    orchestrator's interpreter for 0.5 to 2.4 ms: taken every 0.25 s it doubled the misses of a pace-10 run."""

    def __init__(self, every_s: float = 1.0) -> None:
        self.every_s = every_s
        self.me = psutil.Process()
        self.roles: dict[int, str] = {}  # tid -> role
        self.now: dict[int, tuple[int, int, int]] = {}  # tid -> (CPU ns, slices, run-queue wait ns), latest sample
        self.first: dict[int, tuple[int, int, int]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self.sampler_s = 0.0  # this sampler's own CPU seconds (set by ``stop``)

    def _sample(self, initial: bool = False) -> None:
        """Read every thread's counters; a thread seen first after the start counts from its birth."""
        procs = [(self.me.pid, None)] + [(c.pid, c) for c in self.me.children(recursive=True)]
        for pid, proc in procs:
            for tid, (name, ns, slices, wait) in thread_times(pid).items():
                if tid not in self.roles:
                    self.roles[tid] = self._role(pid, tid, name, proc)
                    self.first[tid] = (ns, slices, wait) if initial else (0, 0, 0)
                self.now[tid] = (ns, slices, wait)

    def _role(self, pid: int, tid: int, name: str, proc: psutil.Process | None) -> str:
        if proc is not None:
            return role_of(proc)
        if name.startswith("bus-server"):
            return "bus servers"
        return "sampler" if tid == self._thread.native_id else "orchestrator"

    def start(self) -> None:
        self._sample(initial=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(self.every_s):
            self._sample()

    def stop(self) -> dict[str, tuple[float, int, float]]:
        """Role -> (CPU s, time slices, s its threads were runnable but waited for a core) since ``start``; the
        sampler's own CPU (this thread's, up to its last sample) goes to ``sampler_s``, as it is not the rig's."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._sample()  # this process's threads to the end: the end of the run (the merge) whole, not up to a second
        out: dict[str, tuple[float, int, float]] = {}
        for tid, (ns, slices, wait) in self.now.items():
            role = self.roles[tid]
            if role == "sampler":
                if tid == self._thread.native_id:
                    self.sampler_s = (ns - self.first[tid][0]) * 1e-9
                continue
            ns0, slices0, wait0 = self.first[tid]
            cpu, n, waited = out.get(role, (0.0, 0, 0.0))
            out[role] = (cpu + (ns - ns0) * 1e-9, n + slices - slices0, waited + (wait - wait0) * 1e-9)
        return out


def virtual_run(sc, duration: float) -> tuple[float, dict]:
    """The same scenario in virtual time (one process, no recording): its CPU seconds per simulated second, and
    its loop (``loop_figures``), the reference real time's is read against."""
    rig = VirtualRig(sc)
    c0 = time.process_time()
    log = rig.run(duration)
    cpu = (time.process_time() - c0) / duration
    return cpu, loop_figures(compute_metrics(log, sc.plant.coupler_band_m))


def loop_figures(m: dict) -> dict:
    """What says whether two runs had the same loop: speed overshoot, coupler maximum, settling time (None: not
    settled) and the safety verdicts violated, with how many times."""
    verdicts = {k: v["count"] for k, v in violated(m["safety"]).items()}
    return {"overshoot_mps": m["speed_overshoot_max_mps"], "coupler_max_m": m["coupler_max_abs_m"],
            "settling_s": m["settling_time_s"], "verdicts": verdicts}


def loop_comparison(real: dict, virtual: dict) -> str:
    """Real time's loop beside virtual time's: the figures, and the settling gap in per cent where both settled."""
    def settling(s: float | None) -> str:
        return "not settled" if s is None else f"settling {s:.1f} s"

    gap = ""
    if real["settling_s"] is not None and virtual["settling_s"] is not None:
        gap = f" ({100 * (real['settling_s'] / virtual['settling_s'] - 1):+.1f} %)"
    verdicts = "the same verdicts" if real["verdicts"].keys() == virtual["verdicts"].keys() else "other verdicts"
    return (f"virtual time's loop: speed overshoot {virtual['overshoot_mps']:.2f} m/s, coupler max "
            f"{virtual['coupler_max_m']:.3f} m, {settling(virtual['settling_s'])}; real time's "
            f"{settling(real['settling_s'])}{gap}; {verdicts} (real {real['verdicts']}, virtual {virtual['verdicts']})")


def one(sc, per_process: int | None, duration: float, pace: float, plant_spin_us: float = 200.0,
        radio: str = "servers", keep: Path | None = None, scheduling: SchedulingMode = "auto",
        idle_latency_us: IdleLatencySetting = "auto", cpu_layout: CpuLayoutMode = "auto", turns: TurnsMode = "auto") -> dict:
    """One real-time run of ``sc`` and its figures; its files go to ``keep`` (None: a temporary directory)."""
    n_ecus = sc.trains.count * sc.trains.units
    cpu0, t0 = [0.0], [0.0]
    by_role = CpuByRole()
    watcher: list[subprocess.Popen] = []

    def started(go: float) -> None:  # every node is ready: CPU spent on start-up (imports) is not counted
        cpu0[0], t0[0] = cpu_seconds(), go
        by_role.start()
        watcher.extend(start_stall_watches(out))

    steal0 = steal_s()
    with contextlib.ExitStack() as stack:
        out = keep if keep is not None else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        out.mkdir(parents=True, exist_ok=True)
        try:
            res = run_realtime(sc, out, pace=pace, duration_s=duration, ecus_per_process=per_process, record=False,
                               plant_spin_us=plant_spin_us, radio_in_servers=radio == "servers",
                               on_start=started, scheduling=scheduling, idle_latency_us=idle_latency_us,
                               cpu_layout=cpu_layout, turns=turns)
        finally:
            for w in watcher:
                with contextlib.suppress(psutil.Error):
                    t = psutil.Process(w.pid).cpu_times()
                    cpu0[0] += t.user + t.system  # the watch is not the rig
                w.terminate()
                w.wait()
        stalls = read_cpu_stalls(out)
        nodes = out / "nodes"
        ecu_in_stalls = misses_in_stalls(nodes.glob("timing_ecu_*.bin"), CYCLE_S / pace, t0[0], pace, stalls)
        publication_s = publication_steps(tick_periods(sc)) * sc.plant.step_s
        plant_in_stalls = misses_in_stalls([nodes / "timing_plant.bin"], publication_s / pace, t0[0], pace, stalls)
    roles = by_role.stop()
    steal = steal_s() - steal0
    m = res.metrics
    plant = m["realtime"]["plant"]
    ecus = m["realtime"]["ecus"].values()
    cycles = sum(e["cycles"] for e in ecus) or 1
    skipped = sum(e.get("cycles_skipped", 0) for e in ecus)
    p99 = m["cycle_lateness_p99_s"]
    misses = m["cycle_deadline_misses"]
    keeps_up = p99 is not None and p99 < CYCLE_S / 10 and misses + skipped < 1e-3 * cycles
    servers = [BusServerStats(**b) for b in m["realtime"]["bus_servers"].values()]
    return {"ecus": n_ecus, "per_process": per_process, "p50_ms": 1e3 * (m["cycle_lateness_p50_s"] or 0),
            "p99_ms": 1e3 * (p99 or 0), "misses": misses, "skipped": skipped, "cycles": cycles,
            "plant_p99_ms": 1e3 * (m["plant_lateness_p99_s"] or 0), "e2e_p99_ms": 1e3 * (m["e2e_latency_p99_s"] or 0),
            "lost": m["frames_lost"], "lost_on_buses": [b.frames_dropped for b in res.log.buses],
            "lost_by_node": dropped_by_node(m["per_bus"]),
            "bus_warnings": [f"t = {e.t:.1f} s {e.text}" for e in res.log.events
                             if e.level == "WARN" and e.source.startswith("bus")],  # a node's queue lost as it left
            "cpu_per_sim_s": (cpu_seconds() - cpu0[0] - by_role.sampler_s) / duration, "keeps_up": keeps_up,
            "sampler_per_sim_s": by_role.sampler_s / duration,
            "interrupted": m["interrupted"], "steal_s": steal, "stalls": stalls,
            "plant_misses": m["plant_deadline_misses"], "publications": plant["cycles"] + plant["cycles_skipped"],
            "publications_skipped": plant["cycles_skipped"],
            "misses_in_stalls": ecu_in_stalls, "plant_misses_in_stalls": plant_in_stalls,
            "cpu_by_role": {k: (cpu / duration, n / duration) for k, (cpu, n, _) in sorted(roles.items())},
            "waited_by_role": {k: waited / duration for k, (_, _, waited) in sorted(roles.items())},
            "scheduling": m["realtime"]["scheduling"]["policy"], "idle_latency_us": m["realtime"]["idle_latency_us"],
            "cpu_layout": m["realtime"]["cpu_layout"], "turns": m["realtime"]["turns"],
            "e2e_p50_ms": 1e3 * (m["e2e_latency_p50_s"] or 0), "overshoot_mps": m["speed_overshoot_max_mps"],
            "coupler_max_m": m["coupler_max_abs_m"], "loop": loop_figures(m),
            "turns_held": sum(b.turns_held for b in servers), "turn_overruns": sum(b.turn_overruns for b in servers),
            # metrics.json has the servers' times in simulated seconds already: T0 0, pace 1
            "let_go": turns_let_go_text(servers), "given_up": turns_given_up(servers, 0.0, 1.0)}


def held_text(limit_us: int | None) -> str:
    """What the run held of the CPUs' wake-up latency limit (metrics.json's realtime.idle_latency_us)."""
    return "idle latency: the host's" if limit_us is None else f"idle latency held at {limit_us} us"


def stall_line(stalls: np.ndarray, ecu: tuple[int, int], plant: tuple[int, int]) -> str:
    """What the stall watches saw (per CPU: a whole-machine stall shows on each), and how many ECU and plant
    deadline misses (of all) fell in a stall of any CPU."""
    misses = f"ECU misses {ecu[1]} of {ecu[0]}, plant misses {plant[1]} of {plant[0]}"
    if not len(stalls):
        return f"CPU stalls (a sleeping process kept to each CPU woke over {LATE_S * 1e3:g} ms late): none; {misses}"
    per_cpu = ", ".join(f"CPU {int(c)}: {int(n)} (longest {1e3 * late.max():.1f} ms, {1e3 * late.sum():.0f} ms in all)"
                        for c, n in zip(*np.unique(stalls[:, 3], return_counts=True))
                        for late in [stalls[stalls[:, 3] == c, 1]])
    with_steal = int((stalls[:, 2] > 0).sum())
    return (f"CPU stalls (a sleeping process kept to each CPU woke over {LATE_S * 1e3:g} ms late): {per_cpu}; "
            f"{with_steal} with host steal; during one: {misses}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ecus", type=int, nargs="+", default=[12, 24, 48, 64])
    ap.add_argument("--per-process", type=int, nargs="+", default=[0, 1],
                    help="ECUs per process; 0: the rig's default layout (default_ecus_per_process)")
    ap.add_argument("--plant-spin-us", type=float, nargs="+", default=[200.0],
                    help="the plant's polling before each publication, µs (several: side by side)")
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--pace", type=float, default=1.0)
    ap.add_argument("--radio", nargs="+", choices=("servers", "process"), default=["servers"],
                    help="the radio inside the bus servers (the rig's) or as a node process (before); several: side by side")
    ap.add_argument("--scheduling", nargs="+", choices=SCHEDULING_MODES, default=["auto"],
                    help="the rig's scheduling (hil run --scheduling); several: side by side, alternated")
    ap.add_argument("--idle-latency-us", type=latency_us, nargs="+", default=["auto"], metavar="US",
                    help="the CPUs' wake-up latency limit for each run (hil run --idle-latency-us): auto (the "
                         "default: 0 where permitted), host, or µs; several: side by side, alternated")
    ap.add_argument("--cpu-layout", nargs="+", choices=CPU_LAYOUT_MODES, default=["auto"],
                    help="the rig's CPU layout (hil run --cpu-layout): auto (ECU processes on cores of their own) "
                         "or none; several: side by side, alternated")
    ap.add_argument("--turns", nargs="+", choices=TURNS_MODES, default=["auto"],
                    help="the nodes' turns (hil run --turns): on (frames at their instants, the bus waiting for them), "
                         "off, or auto (the default: on faster than real time); several: side by side, alternated")
    ap.add_argument("--firmware", nargs="+", choices=tuple(FIRMWARES), default=["standard"],
                    help="the ECUs' firmware: standard (the scenario's), or null (bench/null_firmware.py: the same "
                         "frames, nothing read or run: what the rig around the firmware costs); several: side by side")
    ap.add_argument("--scenario", help="run this packaged scenario as it is (e.g. seed000) instead of the scaled ones")
    ap.add_argument("--keep", type=Path, help="keep each run's files under this directory (one folder per run)")
    args = ap.parse_args()
    if args.scenario:
        sc = load_scenario(args.scenario)
        args.ecus = [sc.trains.count * sc.trains.units]
    what = args.scenario or "seed000-consensus scaled: 1 Mbit/s buses of up to 16 units"
    print(f"{psutil.cpu_count()} CPUs, load average {psutil.getloadavg()[0]:.2f}; pace {args.pace:g}, "
          f"{args.duration:g} s per run, 100 Hz ECUs; {what}")
    head = f"{'ECUs':>5} {'per proc':>8} {'p50 ms':>7} {'p99 ms':>7} {'misses':>7} {'skipped':>7} {'plant p99':>9} " \
           f"{'e2e p99':>8} {'lost':>6} {'CPU s/sim s':>11}  keeps up"
    print(head)
    best = 0
    for n in args.ecus:
        for k, spin, radio, mode, idle, cpus, turns, fw in [
                (k, spin, radio, mode, idle, cpus, turns, fw) for k in args.per_process for spin in args.plant_spin_us
                for radio in args.radio for mode in args.scheduling for idle in args.idle_latency_us
                for cpus in args.cpu_layout for turns in args.turns for fw in args.firmware]:
            t = time.monotonic()
            sc = scenario_for(n, args.scenario, fw)
            run_name = f"{n}ecus-{k}perproc-spin{spin:g}-{radio}-{mode}-idle{idle}-cpus{cpus}-turns{turns}-{fw}"
            keep = args.keep / run_name if args.keep is not None else None
            r = one(sc, k or None, args.duration, args.pace, spin, radio, keep, mode, idle, cpus, turns)
            r["per_process"] = k or default_ecus_per_process(n, units_per_train=sc.trains.units, pace=args.pace)
            virtual, virtual_loop = virtual_run(sc, args.duration)
            print(f"{r['ecus']:5d} {r['per_process']:8d} {r['p50_ms']:7.2f} {r['p99_ms']:7.2f} {r['misses']:7d} "
                  f"{r['skipped']:7d} {r['plant_p99_ms']:9.2f} {r['e2e_p99_ms']:8.1f} {r['lost']:6d} "
                  f"{r['cpu_per_sim_s']:11.4f}  {'yes' if r['keeps_up'] else 'no'}"
                  f"{f'  (plant spin {spin:g} us)' if len(args.plant_spin_us) > 1 else ''}"
                  f"{f'  (radio: {radio})' if len(args.radio) > 1 else ''}"
                  f"{f'  (firmware: {fw})' if len(args.firmware) > 1 else ''}"
                  f"  ({r['scheduling']})"
                  f"  ({held_text(r['idle_latency_us'])})"
                  f"  (cpu layout: {'none' if r['cpu_layout'] is None else 'ECUs on ' + str(r['cpu_layout']['ecus'])})"
                  f"  (turns {'on' if r['turns'] else 'off'}: {r['turns_held']} held, {r['turn_overruns']} let go)"
                  f"{'  (interrupted)' if r['interrupted'] else ''}  [{time.monotonic() - t:.0f} s]", flush=True)
            print("      CPU s/sim s by role (times run per sim s: wake-ups and preemptions, CPU per run): " + ", ".join(
                f"{k} {cpu:.3f} ({n:.0f}, {1e6 * cpu / max(n, 1):.0f} us)" for k, (cpu, n) in r["cpu_by_role"].items())
                + f"; the bench's sampler {r['sampler_per_sim_s']:.4f}, not counted")
            print("      s per sim s each role was runnable but waited for a core (the cores' contention): " + ", ".join(
                f"{k} {waited:.3f}" for k, waited in r["waited_by_role"].items()))
            if r["let_go"]:
                print(f"      {r['let_go']}")
            if r["given_up"]:
                print(f"      {r['given_up'][1]}")
            if r["lost"]:
                on_buses = sum(r["lost_on_buses"])
                by_node = ", ".join(f"{name} {n}" for name, n in r["lost_by_node"].items())
                print(f"      lost: {on_buses} dropped from TX queues (by bus {r['lost_on_buses']}; by node: {by_node}), "
                      f"{r['lost'] - on_buses} offered to the radio and not delivered")
            for warning in r["bus_warnings"]:
                print(f"      bus warning: {warning}")
            print(f"      host steal time during the run: {r['steal_s']:.2f} s"
                  f"{f'; files in {keep}' if keep is not None else ''}")
            print(f"      plant: {r['plant_misses']} of {r['publications']} publications missed their deadline, "
                  f"{r['publications_skipped']} skipped (the latest due sent instead)")
            print(f"      the loop: sensor-to-actuator p50 {r['e2e_p50_ms']:.2f} ms, speed overshoot "
                  f"{r['overshoot_mps']:.2f} m/s, coupler max {r['coupler_max_m']:.3f} m")
            print("      " + loop_comparison(r["loop"], virtual_loop))
            print("      " + stall_line(r["stalls"], r["misses_in_stalls"], r["plant_misses_in_stalls"]))
            print(f"      virtual time, same scenario: {virtual:.4f} CPU s/sim s; real time costs "
                  f"{r['cpu_per_sim_s'] / virtual:.2f} x that   (target <= 4)")
            if r["keeps_up"]:
                best = max(best, n)
    print(f"largest ECU count that keeps up: {best or 'none'} (target 64)")


if __name__ == "__main__":
    main()
