"""Virtual-time speed of seed000 (12 ECUs at 100 Hz, exact CAN timing) and its cost over the ideal loop.

Runs, side by side in one process: the ideal (network-free) loop, the rig on the compiled frame engine, and
(with --python-model) the rig on the Python bus model. Prints simulated seconds per wall second, the ratios,
and the engine's own cost per frame: the wall time spent inside the engine's event loop and sends (bus model,
arbitration, frame timing, delivery into the mailboxes, radio), plus the codec and mailbox calls the firmware
makes per frame, timed in isolation.

Targets: network <= 2x the ideal loop, >= 40x real time on one core, engine cost <= 1 us per frame; a group of
3 trains x 8 units at 1 Mbit/s >= 20x real time (--units 8 --bitrate 1000000).
    python bench/bench_seed000.py [--sim 30] [--trains 3 --units 4 --bitrate 500000] [--python-model] [--profile]
                                  [--breakdown] [--floor]

``--floor`` also runs the rig with a bare firmware around each law (``bare_cycle``: the same reads, alignment, law
and outputs, none of the flags, stale handling, guard or monitors), a bound on what any Python firmware could cost,
and with each ECU's outputs replayed from a standard run (no firmware, no law: what the bus, the plant and the rig
around them cost), and says whether each loop is the standard firmware's.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import time
import timeit
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trainhil_engine as engine

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' oracles (the Python network)

from ecu_sim.runtime import Ecu, Output  # noqa: E402
from ecu_sim.view import BrakeMode  # noqa: E402
from hil.runtime.engine_net import EngineKernel  # noqa: E402
from hil.runtime.ideal import IdealLoop  # noqa: E402
from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402
from tests.oracle.python_rig import PythonNetworkRig  # noqa: E402


def timed(build, sim_s: float) -> tuple[object, float]:
    """(the runner, wall seconds to run sim_s)."""
    runner = build()
    t0 = time.perf_counter()
    runner.run(sim_s)
    return runner, time.perf_counter() - t0


def firmware_engine_calls_us(rig: VirtualRig) -> dict[str, float]:
    """Microseconds per call of the engine calls the firmware and plant make per frame, timed in isolation."""
    ecu = rig.ecus[0]
    codec = rig.db.agent_state(0)
    frame = codec.encode((1000.0, 80.0), 3)
    n = 20000
    mb = ecu.mailbox
    slot = ecu.slots[codec.frame_id].index if codec.frame_id in ecu.slots else 0
    fid = next(iter(ecu.slots))
    data = rig.db.by_id[fid].encode(tuple(0.0 for _ in rig.db.by_id[fid].signals), 1)

    def put_refresh_read() -> None:
        mb.put(fid, data, 1.0)
        mb.refresh()
        mb.read(slot, 1.0, 1.0)

    return {
        "encode": timeit.timeit(lambda: codec.encode((1000.0, 80.0), 3), number=n) / n * 1e6,
        "decode": timeit.timeit(lambda: codec.decode(frame), number=n) / n * 1e6,
        "mailbox put+refresh+read": timeit.timeit(put_refresh_read, number=n) / n * 1e6,
    }


class PartTimes:
    """Wall time spent in named parts of a run, by wrapping the callables that do them (about 0.1 us per call)."""

    def __init__(self) -> None:
        self.s: dict[str, float] = {}

    def wrap(self, name: str, fn):
        """``fn`` with its time added to part ``name``."""
        clock, s = time.perf_counter, self.s
        s.setdefault(name, 0.0)

        def timed_call(*args):
            t0 = clock()
            try:
                return fn(*args)
            finally:
                s[name] += clock() - t0
        return timed_call


def _time_laws_and_plant(parts: PartTimes, controllers, plant) -> None:
    """Time every law's ``step`` and the plant's integration step (instance attributes, so nothing else changes)."""
    for c in controllers:
        c.step = parts.wrap("law", c.step)
    plant.step = parts.wrap("plant integration", plant.step)


class TimedIdeal(IdealLoop):
    """The ideal loop with its control step timed."""

    def __init__(self, sc, parts: PartTimes) -> None:
        super().__init__(sc)
        self._control = parts.wrap("control step", self._control)  # type: ignore[method-assign]
        _time_laws_and_plant(parts, self.parts.controllers, self.parts.plant)


class TimedRig(VirtualRig):
    """The network rig with its tasks timed (the kernel holds the bound methods made here)."""

    def __init__(self, sc, parts: PartTimes) -> None:
        self._parts = parts
        super().__init__(sc)
        _time_laws_and_plant(parts, [e.controller for e in self.ecus], self.plant)
        for bus in self.buses:  # the engine calls that encode and queue (ECU and sensor outputs; wayside frames)
            bus.send_outputs = parts.wrap("send outputs", bus.send_outputs)  # type: ignore[method-assign]
            bus.send_frames = parts.wrap("send frames", bus.send_frames)  # type: ignore[method-assign]
        sample = parts.wrap("sensor sampling", self.plant_io.sensor_outputs)
        self.plant_io.sensor_outputs = sample  # type: ignore[method-assign]

    def _schedule(self) -> None:
        p = self._parts
        self._plant_tick = p.wrap("plant task", self._plant_tick)  # type: ignore[method-assign]
        self._apply_commands = p.wrap("commands", self._apply_commands)  # type: ignore[method-assign]
        self._publish_sensors = p.wrap("sensors", self._publish_sensors)  # type: ignore[method-assign]
        self._wayside_tick = p.wrap("wayside", self._wayside_tick)  # type: ignore[method-assign]
        self._ecu_tick = p.wrap("ECU task", self._ecu_tick)  # type: ignore[method-assign]
        super()._schedule()


def bare_cycle(ecu: Ecu) -> Callable[[float], list[Output]]:
    """Not firmware, a bound: the least an ECU's cycle does for the same loop. One read per input slot, the
    neighbours aligned to our own sample, the law, the three outputs; no flags, stale-data modes, guard around the
    law, monitors or counters. Reads the ECU's internals; a nominal run needs none of what it leaves out."""
    mb, view, law, mass = ecu.mailbox, ecu.view, ecu.controller, ecu.agent.mass_kg
    out_cmd, out_state, out_aux = ecu.sent_messages()
    sensor, samples, window, neighbours = ecu._sensor.index, ecu._samples, ecu._align_window_s, ecu._neighbour_io
    ref_slots = None if ecu._ref is None else (ecu._ref.index, ecu._ref_aux.index)  # type: ignore[union-attr]
    timeout, ref_timeout = ecu._timeouts[0], ecu._timeouts[1]
    read, counter = mb.read, [0]

    def cycle_outputs(t: float) -> list[Output]:
        view.t = t
        mb.refresh()
        counter[0] = c = (counter[0] + 1) & 0xF
        ok, _, values, k, t_good = read(sensor, t, timeout)
        if not ok:
            return [(out_cmd, (int(BrakeMode.SERVICE), 0.0), c)]
        x, v = view.x, view.v = values
        samples[k] = (x, v, t_good)
        for nv, state, aux in neighbours:
            nv.valid, nv.age_s, values, kn, tn = read(state, t, timeout)
            if nv.valid:
                nv.x, nv.v = values
                own = samples[kn]
                if own is not None and 0.0 <= tn - own[2] < window:
                    nv.x, nv.v = nv.x + x - own[0], nv.v + v - own[1]
                if aux >= 0 and (aux_read := read(aux, t, timeout))[0] and aux_read[2]:
                    nv.a, nv.u = aux_read[2]
        if ref_slots is not None:
            ref = view.ref
            ref.valid, ref.age_s, values, _, _ = read(ref_slots[0], t, ref_timeout)
            if ref.valid:
                ref.x, ref.v = values
                ref.a = (mb.values(ref_slots[1]) or (0.0,))[0]
        cmd = law.step(view)
        accel = cmd.accel_mps2 if cmd.accel_mps2 == cmd.accel_mps2 else cmd.force_n / mass
        return [(out_cmd, (int(cmd.mode), cmd.force_n), c), (out_state, (x, v), k), (out_aux, (accel, cmd.force_n), k)]
    return cycle_outputs


class BareFirmwareRig(VirtualRig):
    """The rig with ``bare_cycle`` in place of every ECU's standard cycle (their engine sends unchanged)."""

    def __init__(self, sc) -> None:
        super().__init__(sc)
        for ecu in self.ecus:
            ecu.cycle_outputs = bare_cycle(ecu)  # type: ignore[method-assign, assignment]


def recorded_outputs(sc, sim_s: float) -> dict[str, list[list[Output]]]:
    """Every ECU's outputs, cycle by cycle, in a standard run of ``sim_s``."""
    rig = VirtualRig(sc)
    tapes: dict[str, list[list[Output]]] = {}
    for ecu in rig.ecus:
        ecu.cycle_outputs = recording(ecu.cycle_outputs, tapes.setdefault(ecu.name, []))  # type: ignore
    rig.run(sim_s)
    return tapes


def recording(cycle_outputs: Callable[[float], list[Output]], tape: list[list[Output]]):
    """``cycle_outputs`` with each cycle's outputs also appended to ``tape``."""
    def recorded(t: float) -> list[Output]:
        tape.append(cycle_outputs(t))
        return tape[-1]
    return recorded


class ReplayedOutputsRig(VirtualRig):
    """The rig with every ECU's outputs replayed from a standard run (``recorded_outputs``): no firmware and no law,
    the same frames at the same instants, so what is left is the bus, the plant and the rig around them."""

    def __init__(self, sc, tapes: dict[str, list[list[Output]]]) -> None:
        super().__init__(sc)
        for ecu in self.ecus:
            ecu.cycle_outputs = lambda t, tape=iter(tapes[ecu.name]): next(tape)  # type: ignore


def same_loop(a: VirtualRig, b: VirtualRig) -> bool:
    """Whether two runs of one scenario left the plant in the same state to the last bit."""
    return bool(np.array_equal(a.plant.x, b.plant.x) and np.array_equal(a.plant.v, b.plant.v))


def floor(sc, sim_s: float, repeat: int) -> None:
    """The network run with the standard firmware, with ``bare_cycle``, and with its outputs replayed (no firmware,
    no law), against the ideal loop (interleaved, the fastest of ``repeat`` runs of each)."""
    tapes = recorded_outputs(sc, sim_s)
    builds: dict[str, Callable[[], object]] = {
        "ideal loop": lambda: IdealLoop(sc), "network, standard firmware": lambda: VirtualRig(sc),
        "network, bare firmware": lambda: BareFirmwareRig(sc),
        "network, outputs replayed": lambda: ReplayedOutputsRig(sc, tapes)}
    walls = dict.fromkeys(builds, float("inf"))
    runs: dict[str, object] = {}
    for _ in range(repeat):
        for name, build in builds.items():
            runs[name], wall = timed(build, sim_s)
            walls[name] = min(walls[name], wall)
    print("the firmware's floor (bounds, not firmware): a bare cycle around each law (bare_cycle), and the ECUs'")
    print("outputs replayed from a standard run (no firmware, no law: the bus, the plant and the rig around them):")
    for name, wall in walls.items():
        print(f"  {name:28s} {sim_s / wall:6.1f} x real time   {wall / walls['ideal loop']:5.2f} x the ideal loop")
    standard = runs["network, standard firmware"]
    for name in ("network, bare firmware", "network, outputs replayed"):
        same = same_loop(standard, runs[name])  # type: ignore[arg-type]
        print(f"  {name}: its loop is the standard one's (plant state at the end): {'yes' if same else 'NO'}")


def timed_parts(build, sim_s: float) -> tuple[object, float, dict[str, float]]:
    """(runner, wall seconds to run sim_s, the wall seconds of its timed parts) of ``build(parts)``."""
    parts = PartTimes()
    runner, wall = timed(lambda: build(parts), sim_s)
    return runner, wall, parts.s


def breakdown(sc, sim_s: float, repeat: int) -> None:
    """Where the ideal loop's and the network rig's time goes, in ms per simulated second, side by side (the
    fastest of ``repeat`` runs of each, alternated, as the machine's speed drifts)."""
    ideal_wall = net_wall = float("inf")
    for _ in range(repeat):
        _, wall, parts = timed_parts(lambda p: TimedIdeal(sc, p), sim_s)
        if wall < ideal_wall:
            ideal_wall, i = wall, parts
        run, wall, parts = timed_parts(lambda p: TimedRig(sc, p), sim_s)
        if wall < net_wall:
            rig, net_wall, n = run, wall, parts
    engine_s = rig.net.busy_s  # type: ignore[attr-defined]
    sensor_sends = n["sensors"] - n["sensor sampling"]  # the sensors' send_outputs calls
    ecu_sends = n["send outputs"] - sensor_sends
    rows = [
        ("plant integration", i["plant integration"], n["plant integration"]),
        ("laws", i["law"], n["law"]),
        ("the loop's view building and commands", i["control step"] - i["law"], 0.0),
        ("ECU firmware around the law (inputs, E2E, outputs)", 0.0, n["ECU task"] - n["law"] - ecu_sends),
        ("engine: ECU outputs encoded and queued", 0.0, ecu_sends),
        ("engine: sensor and wayside frames encoded and queued", 0.0, sensor_sends + n["send frames"]),
        ("engine: event loop (arbitration, delivery, radio)", 0.0, engine_s - n["send outputs"] - n["send frames"]),
        ("commands applied to the plant", 0.0, n["commands"]),
        ("sensor sampling, wayside sampling and encoding", 0.0, n["sensor sampling"] + n["wayside"] - n["send frames"]),
        ("plant task: the rest (recording)", 0.0,
         n["plant task"] - n["plant integration"] - n["commands"] - n["sensors"]),
    ]
    rows.append(("the rest (loop, dispatch, timers)", ideal_wall - sum(r[1] for r in rows),
                 net_wall - sum(r[2] for r in rows)))
    ms = 1e3 / sim_s
    print(f"where the time goes (ms per simulated second; timers add about 0.1 us per timed call):")
    print(f"  {'':52s} {'ideal':>7s} {'network':>8s}")
    for name, a, b in rows:
        print(f"  {name:52s} {a * ms:7.2f} {b * ms:8.2f}")
    print(f"  {'total':52s} {ideal_wall * ms:7.2f} {net_wall * ms:8.2f}   ({net_wall / ideal_wall:.2f} x)")
    per_event, events = kernel_dispatch_us(), task_events_per_s(sc)
    print(f"  of the rest, the event kernel's dispatch alone (a no-op task): {per_event:.2f} us per task event, "
          f"{events:.0f} task events per simulated second: {per_event * events * 1e-3:.2f} ms")


def kernel_dispatch_us(events: int = 20_000, repeat: int = 3) -> float:
    """Microseconds per task event that the engine's event kernel costs by itself: a no-op periodic task, best of
    ``repeat`` runs (what batching tasks into fewer returns to Python could save at most)."""
    best = float("inf")
    for _ in range(repeat):
        kernel = EngineKernel(engine.Network())
        kernel.every(0, 1_000_000, lambda t: None)
        t0 = time.perf_counter()
        kernel.run(events * 1_000_000)
        best = min(best, time.perf_counter() - t0)
    return best / events * 1e6


def task_events_per_s(sc) -> float:
    """The rig's task events per simulated second: plant steps, ECU cycles and wayside ticks."""
    return 1 / sc.plant.step_s + sc.trains.count * sc.trains.units / sc.ecu.cycle_s + 1 / sc.reference.period_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=float, default=30.0, help="simulated seconds per run")
    ap.add_argument("--scenario", default="seed000")
    ap.add_argument("--trains", type=int, help="override trains.count")
    ap.add_argument("--units", type=int, help="override trains.units (units per train)")
    ap.add_argument("--bitrate", type=int, help="override can.bitrate")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each, interleaved; the fastest of each counts")
    ap.add_argument("--python-model", action="store_true", help="also run the rig on the Python bus model")
    ap.add_argument("--profile", action="store_true", help="print the top Python functions of the engine run")
    ap.add_argument("--breakdown", action="store_true",
                    help="print where the ideal loop's and the network run's time goes, part by part")
    ap.add_argument("--floor", action="store_true",
                    help="also run the rig with a bare firmware around each law: a bound on any Python firmware's cost")
    args = ap.parse_args()
    overrides: dict[str, object] = {}
    if args.trains or args.units:  # the trains then start one slot apart at seed000's first speed
        count = args.trains or 3
        units = args.units or 4
        overrides["trains.count"], overrides["trains.units"] = count, units
        overrides["trains.speeds_kmh"] = [295.0] * count
        overrides["trains.head_positions_m"] = [108_800.0 - (3000.0 + 80.0 * units) * i for i in range(count)]
    if args.bitrate:
        overrides["can.bitrate"] = args.bitrate
    sc = load_scenario(args.scenario, overrides)
    print(f"scenario {sc.name}: {sc.trains.count} trains x {sc.trains.units} units, ECU cycle {sc.ecu.cycle_s * 1e3:g} ms, "
          f"plant step {sc.plant.step_s * 1e3:g} ms, CAN {sc.can.bitrate // 1000} kbit/s, {args.sim:g} s simulated")
    # interleaved repeats, best of each: this machine's speed drifts by tens of percent within minutes
    ideal_wall = net_wall = py_wall = float("inf")
    for _ in range(max(1, args.repeat)):
        ideal_wall = min(ideal_wall, timed(lambda: IdealLoop(sc), args.sim)[1])
        run, wall = timed(lambda: VirtualRig(sc), args.sim)
        if wall < net_wall:
            rig, net_wall = run, wall
        if args.python_model:
            py_wall = min(py_wall, timed(lambda: PythonNetworkRig(sc), args.sim)[1])
    print(f"best of {max(1, args.repeat)} interleaved runs each")
    frames = sum(b.frames_sent for b in rig.log.buses)  # type: ignore[attr-defined]
    engine_s = rig.net.busy_s  # type: ignore[attr-defined]
    print(f"ideal loop      : {args.sim / ideal_wall:8.1f} x real time ({ideal_wall:.2f} s wall)")
    print(f"network (engine): {args.sim / net_wall:8.1f} x real time ({net_wall:.2f} s wall), "
          f"{frames / args.sim:.0f} frames per simulated s   (target >= 40)")
    print(f"network / ideal : {net_wall / ideal_wall:8.2f} x the ideal loop's cost   (target <= 2)")
    print(f"per frame       : {net_wall / frames * 1e6:8.2f} us of wall time per CAN frame, all costs included")
    print(f"engine per frame: {engine_s / frames * 1e6:8.2f} us inside the engine's event loop and sends "
          f"({engine_s / net_wall:.0%} of the run)")
    calls = firmware_engine_calls_us(rig)  # type: ignore[arg-type]
    print("firmware calls  : " + ", ".join(f"{k} {v:.2f} us" for k, v in calls.items()))
    # per frame: one encode at its sender, one mailbox put at each receiver and one refresh+read per cycle (about
    # one decoded frame per receiver); the bus, arbitration and delivery are inside the event loop
    total = engine_s / frames * 1e6 + calls["encode"] + calls["mailbox put+refresh+read"]
    print(f"engine cost     : {total:8.2f} us per frame: event loop + encode + one mailbox put/refresh/read   (target <= 1)")
    if args.python_model:
        print(f"python bus model: {args.sim / py_wall:8.1f} x real time ({py_wall:.2f} s wall), "
              f"{py_wall / net_wall:.2f} x the engine run's cost")
    if args.breakdown:
        breakdown(sc, args.sim, max(1, args.repeat))
    if args.floor:
        floor(sc, args.sim, max(1, args.repeat))
    if args.profile:
        prof = cProfile.Profile()
        rig = VirtualRig(sc)
        prof.runcall(rig.run, min(args.sim, 20.0))
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(18)
        print(out.getvalue())


if __name__ == "__main__":
    main()
