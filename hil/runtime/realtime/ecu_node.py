"""ECU host process: one or several units' firmware (the same ``ecu_sim.runtime.Ecu`` as the virtual rig) on python-can.

    python -m hil.runtime.realtime.ecu_node --run RUN --scenario-json FILE --seed N --duration S --pace F --out DIR --unit U [--unit U2 ...]

``--unit`` is a flat unit index (front to back, 0-based). Each unit cycles at ``ecu.cycle_s`` with the phase
``ecu.phase_s + unit_in_train * ecu.stagger_s`` as in virtual time. Between deadlines the process sleeps on its
buses (one per train it hosts, acceptance filters = the units' rx ids, applied by the server); every frame goes
into the firmware's mailboxes stamped with its simulated arrival time (the end of its transmission); at a
deadline the unit's ``cycle`` runs and its frames are sent. Never spins. A unit more than one cycle late counts a
deadline miss and skips to its next future deadline. At exit it writes ``DIR/ecu_<train>_<unit>.json`` per unit.

On the emulated buses the frames never pass through Python: python-can opens the connection (handshake,
filters), then the engine reads the socket straight into the mailboxes and writes the outputs
(``hil.runtime.realtime.frame_io``). On SocketCAN the frames come through python-can.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Iterable

from ecu_sim.runtime import cycle_and_send, encodes_in_engine
from hil.faults.schedule import needs_fault_machinery
from hil.faults.watchdog import Watchdog, restart_text
from hil.runtime.realtime.frame_io import EngineFrames, PythonCanFrames, node_frames
from hil.record.integrity import write_json_atomic
from hil.runtime.realtime.node import load_scenario_json, node_parser, open_bus
from hil.runtime.kernel import to_ns
from hil.runtime.realtime.paced_kernel import PacedKernel
from hil.runtime.realtime.scheduling import enter_role
from hil.runtime.realtime.pacing import (Heartbeat, LatenessStats, SimClock, StopFlag, handshake, linger,
                                         set_timer_slack, turn_waited)
from hil.runtime.firmware import assemble_firmware, build_ecu
from hil.runtime.train_db import bus_packing, load_train_db


def main(argv: list[str] | None = None) -> int:
    p = node_parser("python -m hil.runtime.realtime.ecu_node", "Run ECU firmware on the real-time rig's buses.")
    p.add_argument("--unit", type=int, action="append", required=True, help="flat unit index (repeatable)")
    p.add_argument("--join-late", action="store_true", help="a restarted ECU: start at the first cycle after 'go'")
    args = p.parse_args(argv)
    stop = StopFlag()
    set_timer_slack(1)
    scheduling = enter_role("ecu", args.fifo, args.cpus)
    sc = load_scenario_json(args.scenario_json)
    parts = assemble_firmware(sc)  # no plant: not this process's
    layout, db = parts.layout, load_train_db(sc)
    for u in args.unit:
        if not 0 <= u < layout.n_units:
            raise SystemExit(f"--unit {u}: out of range 0..{layout.n_units - 1}")
    ecus = {u: build_ecu(parts, db, u) for u in args.unit}
    if needs_fault_machinery(sc):  # diagnostics as in virtual time (hil/runtime/virtual_faults.py)
        from ecu_sim.diagnostics import EcuDiagnostics, neighbour_names

        for u, ecu in ecus.items():
            ecu.monitors.append(EcuDiagnostics(ecu, sc.can.sensor_period_s, neighbour_names(layout, u), parts.plant_info))
    trains = sorted({layout.train_unit(u)[0] for u in ecus})
    packing = bus_packing(sc, db)
    buses, routes = [], []  # per bus: frame id -> the hosted ECUs that listen to it
    for train in trains:
        mine = [e for u, e in ecus.items() if layout.train_unit(u)[0] == train]
        ids = set().union(*(e.rx_ids for e in mine))
        first = min(layout.train_unit(u)[1] for u in ecus if layout.train_unit(u)[0] == train)
        buses.append(open_bus(args.run, train, ids, sc.can, f"ECU_T{train + 1}_U{first + 1:02d}x{len(mine)}",
                              receive_own=len(mine) > 1, packing=packing, lazy=True))
        routes.append({i: [e for e in mine if i in e.rx_ids] for i in ids})
    bus_of = {u: trains.index(layout.train_unit(u)[0]) for u in ecus}
    try:
        clock = SimClock(handshake(stop), args.pace)
        io = node_frames(clock, buses, sc.can, packing, lazy=True)
        for i, table in enumerate(routes):
            for frame_id, listeners in table.items():
                for ecu in listeners:
                    io.route(i, frame_id, ecu.mailbox)
            if (least := least_sent_bytes([e for u, e in ecus.items() if bus_of[u] == i])) is not None:
                io.sends_at_least(i, least)
        for u, sender in senders(ecus, bus_of).items():  # each unit's TX queue named as virtual time names its node
            io.name_sender(bus_of[u], sender, layout.ecu_node_name(u))
        stats = run(clock, sc, layout, ecus, io, bus_of, args.duration, stop, args.join_late, Path(args.out),
                    args.turns)
    finally:
        for b in buses:
            b.shutdown()
    out = Path(args.out)
    first = min(ecus)  # the ECUs of this process share its codecs: their saturation counts go into one file
    for u, ecu in ecus.items():
        train, unit = layout.train_unit(u)
        stats[u].series.close()  # its rows are in timing_ecu_<train>_<unit>.bin
        write_json_atomic(out / f"ecu_{train + 1}_{unit + 1}.json", {
            "name": ecu.name, "unit": u, **stats[u].summary(), "scheduling": scheduling, "e2e": ecu.e2e_summary(),
            "controller_errors": ecu.counters.controller_errors, "events": [list(e) for e in ecu.events],
            "codec_saturations": db.total_saturations() if u == first else {}})
    return 0


def run(clock: SimClock, sc, layout, ecus: dict, io: EngineFrames | PythonCanFrames, bus_of: dict, duration: float,
        stop: StopFlag, join_late: bool = False, out: Path | None = None, turns: bool = False) -> dict[int, LatenessStats]:
    """Cycle every hosted unit on the paced kernel to ``duration`` (``join_late``: from the first cycle after now);
    each unit's cycle lateness goes to ``out/timing_ecu_<train>_<unit>.bin`` (kept in memory without ``out``).
    ``turns``: each cycle is the unit's turn (``EngineFrames.read_every``): the firmware runs as at its cycle start
    and its frames go on the bus at that instant however late it is; its lateness is still the wall clock's.

    With ``ecu.restart_after_s``, a unit whose controller stopped it (exception, NaN) is restarted in place after
    that long, as the virtual rig's watchdog does."""
    kernel = PacedKernel(clock, io, stop, heartbeat=Heartbeat())  # silent when a cycle never returns: hung
    cycles = UnitCycles(kernel, sc, layout, ecus, io, bus_of, out, turns)
    start = clock.now() if join_late else 0.0
    for u in ecus:
        phase = sc.ecu.phase_s + layout.train_unit(u)[1] * sc.ecu.stagger_s
        first = phase + max(0, math.ceil((start - phase) / sc.ecu.cycle_s)) * sc.ecu.cycle_s
        io.read_every(first, sc.ecu.cycle_s, [bus_of[u]], turns)  # a lazy reader: its bus syncs us at each cycle start
        cycles.schedule(u, first)
    try:
        kernel.run(to_ns(duration))
    except (ConnectionError, OSError) as exc:  # the bus server went away (its rig died): keep what we have
        for ecu in ecus.values():
            ecu.events.append((clock.now(), "ERROR", f"the bus went away, the ECU stopped: {exc}"))
        return cycles.stats
    io.end_turns_for_good()  # its last cycle is over: lingering must not hold the bus
    if not stop:
        linger(clock)
    return cycles.stats


def timing_name(layout, u: int) -> str:
    """The file of unit ``u``'s cycle lateness (hil/runtime/realtime/merge.py records it)."""
    train, unit = layout.train_unit(u)
    return f"timing_ecu_{train + 1}_{unit + 1}.bin"


def least_sent_bytes(ecus: list) -> int | None:
    """The fewest data bytes of any frame these ECUs send, or None when one's program replaces the standard cycle
    (it may send any frame)."""
    if not ecus or not all(encodes_in_engine(ecu) for ecu in ecus):
        return None
    return min(codec.dlc for ecu in ecus for codec in ecu.sent_messages())


class UnitCycles:
    """Each hosted unit's cycle as a kernel event: cycle the firmware, send its frames, book its lateness, and
    schedule the next deadline (a unit more than one cycle late skips to its next future deadline). Each unit
    sends as its own sender on its bus (its own TX queue there, as its own CAN controller would have).

    With ``turns`` a unit ends its turn with its frames, unless another hosted unit cycles on the same bus at the
    same instant: that turn ends when the node next waits (``LinkGroup.begin_wait``), after both. A unit late by
    less than ``TURN_HOLD_MAX_S`` of wall time then runs its next cycle rather than skip to a future one: its bus
    waited for it, so the cycles after it still find the bus at their instants."""

    def __init__(self, kernel: PacedKernel, sc, layout, ecus: dict, io, bus_of: dict, out: Path | None,
                 turns: bool = False) -> None:
        self.kernel, self.ecus, self.io, self.bus_of, self.turns = kernel, ecus, io, bus_of, turns
        phase = {u: layout.train_unit(u)[1] * sc.ecu.stagger_s for u in ecus}
        self.ends_turn = {u: turns and not any(v != u and bus_of[v] == bus_of[u] and phase[v] == phase[u] for v in ecus)
                          for u in ecus}
        self.sender = senders(ecus, bus_of)
        self.cycle_s = sc.ecu.cycle_s
        self.stats = {u: LatenessStats(self.cycle_s, kernel.clock.pace, None if out is None else out / timing_name(layout, u))
                      for u in ecus}
        self.watchdog = Watchdog(sc.ecu.restart_after_s) if sc.ecu.restart_after_s is not None else None

    def schedule(self, u: int, deadline: float) -> None:
        self.kernel.at(to_ns(deadline), self.run_cycle, (u, deadline))

    def run_cycle(self, item: tuple[int, float]) -> None:
        u, deadline = item
        now = max(self.kernel.clock.now(), deadline)  # synced early, the cycle runs as at its deadline
        at = deadline if self.turns else now  # in a turn, as at its deadline however late
        ecu = self.ecus[u]
        cycle_and_send(ecu, at, u, self._send_outputs, self._send)
        if self.ends_turn[u]:
            self.io.end_turn([self.bus_of[u]])  # nothing when its frames ended it
        if self.watchdog is not None:
            _watch(self.watchdog, self.ecus, u, at)
        overrun = self.stats[u].add(now - deadline, deadline)
        if turn_waited(self.turns, now - deadline, self.kernel.clock.pace):
            overrun = 0  # its bus still waits for this turn: the next one follows, as in virtual time
        self.stats[u].skipped += overrun
        self.schedule(u, deadline + (1 + overrun) * self.cycle_s)

    def _send_outputs(self, u: int, outputs: list) -> None:
        self.io.send_outputs(self.bus_of[u], outputs, self.sender[u], self.ends_turn[u])

    def _send(self, u: int, frames: list[tuple[int, bytes]]) -> None:
        self.io.send(self.bus_of[u], frames, self.sender[u], self.ends_turn[u])


def senders(units: Iterable[int], bus_of: dict[int, int]) -> dict[int, int]:
    """Each hosted unit's sender on its bus: its rank among the units this process hosts on that bus."""
    count: dict[int, int] = {}
    sender = {}
    for u in sorted(units):
        sender[u] = count.get(bus_of[u], 0)
        count[bus_of[u]] = sender[u] + 1
    return sender


def _watch(watchdog: Watchdog, ecus: dict, u: int, now: float) -> None:
    """A unit its controller stopped (exception, NaN) is restarted in place when the watchdog says so."""
    if not ecus[u].alive and not watchdog.is_down(u):
        watchdog.stopped(u, "error", now)
    for v, why in watchdog.due(now):
        ecus[v].restart()
        ecus[v].events.append((now, "INFO", restart_text("watchdog", why)))


if __name__ == "__main__":
    sys.exit(main())
