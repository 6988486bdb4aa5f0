"""Plant host process: the train-group Plant (sensor and actuator nodes) and the wayside, paced to the wall clock.

    python -m hil.runtime.realtime.plant_node --run RUN --scenario-json FILE --seed N --duration S --pace F --out DIR [--spin-us US]

Per train bus it joins as "Plant" (receives TractionCmd and AgentState of its units) and as "Wayside" (sends
Reference/ReferenceAux, receives nothing). Only what other nodes can observe is paced: the plant sleeps on its
buses until the next Sensor (every ``can.sensor_period_s``) or Reference (every ``reference.period_s``)
publication, the last ``--spin-us`` before it polling (the one spinning process of a rig), and integrates lazily:
before each publication, and before applying each TractionCmd (CRC and mode checked) it integrates up to the
command's simulated arrival time (the bus timestamp), so the command acts from the first step starting at or
after it, exactly as in the virtual rig, and the plant costs its steps instead of one wake-up per step (a 1 ms
step at pace 10 would need 10,000 wake-ups per second). Recording samples (every ``recording.period_s``) are
taken during integration. A command that reaches the plant after it already integrated past the command's
arrival (the plant was late) is applied at once and counted (``late_commands``). The integration never skips; the
publications do, by the ECUs' rule: a plant more than a publication period late (the machine stalled it) publishes
only the latest sample due, counted as skipped, instead of a burst of stale ones that would overflow its TX queues
(``late_publication``). With turns it skips only when also later than a turn's hold (``TURN_HOLD_MAX_S`` of wall
time): until then its buses wait for each publication, past it they went on without it, as an ECU's do.
If commands stop, the Plant's own fail-safe acts and logs it. The commands of external units (``ecu.external``)
are watched (hil/runtime/realtime/external.py): the node prints ``joined <unit> <t>`` on stdout at the first valid one.

No frame reaches Python one by one: each train bus's TractionCmd and AgentState frames go into an engine
``CommandInbox`` on receipt, which checks and decodes the commands (length, E2E CRC, Mode: the virtual network's
check on delivery) and closes the latencies; every kernel event first takes what came (``take_commands``).

Sensor-to-actuator latency (``e2e``): the ECU sends its AgentState numbered with the Sensor sample k it used,
in the same cycle as its TractionCmd (which has the lower ID, so it is on the bus first). When AgentState k of
unit u arrives, the latency is the arrival time of u's last valid TractionCmd minus the publication time of Sensor
sample k: sensor sampled -> command at the plant (applied at the next plant step, within ``plant.step_s``).

Every ``STREAM_EVERY_WALL_S`` of wall time the new signal rows are appended to ``DIR/signals.bin`` and let go (the
live view follows the file, the merge reads it: the plant's memory does not grow with its signals); at the end,
and every ``SAVE_EVERY_WALL_S``, ``DIR/plant.json`` (events, e2e latencies, lateness, counters) and the timing
series.
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path
from typing import Callable


import trainhil_engine as engine

from ecu_sim.codec import TrainDb
from hil.record.integrity import write_json_atomic
from hil.runtime.realtime.node import load_scenario_json, node_parser, open_bus
from hil.runtime.realtime.live_tail import SIGNAL_STREAM
from hil.runtime.realtime.external import JOIN_LINE, ExternalWatch, missing_after_s
from hil.runtime.realtime.frame_io import EngineFrames, PythonCanFrames, node_frames
from hil.runtime.kernel import to_ns
from hil.runtime.realtime.paced_kernel import PacedKernel
from hil.runtime.realtime.streamed_series import StreamedSeries
from hil.runtime.realtime.scheduling import enter_role
from hil.runtime.realtime.pacing import (Heartbeat, LatenessStats, SimClock, StopFlag, handshake, linger,
                                         periods_overrun, set_timer_slack, turn_waited)
from hil.plant.can_node import VALID_MODES, PlantCanNode
from hil.record.runlog import RunLog
from hil.runtime.assembly import assemble
from hil.runtime.plant_step import plant_step
from hil.runtime.train_db import bus_packing, load_train_db

SAVE_EVERY_WALL_S = 5.0  # the plant's data so far is saved this often (a plant killed mid-run leaves it)
STREAM_EVERY_WALL_S = 0.25  # new signal rows are appended to DIR/signals.bin this often (the live view reads it)


class PlantNode:
    """The plant and wayside of every train, driven by a SimClock."""

    def __init__(self, sc, seed: int, db: TrainDb, buses: list, wayside: list, out: Path | None = None,
                 turns: bool = False) -> None:
        """``out``: where the timing series go as they come (timing_plant.bin, timing_e2e.bin); None: memory.
        ``turns``: each publication is the plant's turn (``EngineFrames.read_every``): its frames go on the buses at
        its instant however long its work takes."""
        self.turns = turns
        self.sc, self.db = sc, db
        self.parts = assemble(sc, seed)
        self.plant, self.layout = self.parts.plant, self.parts.layout
        self.buses, self.wayside = buses, wayside
        self.packing = bus_packing(sc, db)  # CAN FD containers (can.dbc), packed on send and unpacked on receipt
        self.log = RunLog(self.layout)
        self.io = PlantCanNode(db, self.layout, self.plant, self.parts.reference, self.log)
        L = self.layout
        self.state_unit = [{db.agent_state(L.train_unit(u)[1]).frame_id: u for u in self.train_units(i)}
                           for i in range(L.n_trains)]
        # per train bus: its commands decoded and its sensor-to-actuator latencies closed in the engine, on receipt
        self.inboxes = [engine.CommandInbox(self.io.command_table(i), VALID_MODES, list(self.state_unit[i].items()),
                                            L.n_units) for i in range(L.n_trains)]
        self.out = out
        # sensor-to-actuator latencies (s), by the command arrival time they end at
        self.e2e = StreamedSeries(None if out is None else out / "timing_e2e.bin")
        self.extended = sc.can.extended_ids
        # set once the clock runs (``_schedule``): the clock, the node's frame I/O (frame_io.py), its scheduler
        self.clock: SimClock
        self.frames: EngineFrames | PythonCanFrames
        self.kernel: PacedKernel
        self.stats: LatenessStats | None = None  # publication lateness
        self.n_steps = self.publish_every = 0  # plant steps in the run; steps between publications
        self.save: Callable[[LatenessStats], None] | None = None
        self.stream: Callable[[], None] | None = None
        self.next_save = self.next_stream = 0.0  # time.monotonic() of the next save and stream
        self.tick = 0  # the plant's state is at simulated time tick * plant.step_s
        self.target = 0  # tick of the next publication
        self.scheduling = "normal"  # the policy the node runs under ("fifo": SCHED_FIFO), for its results
        self.every = tick_periods(sc)  # plant steps between Sensor and Reference publications and recording samples
        self.late_commands = 0  # commands that reached the plant after it had integrated past their arrival time
        self.faults = None  # the fault schedule's clock and the plant-side faults (hil/runtime/realtime/faults.py)
        if sc.faults:
            from hil.runtime.realtime.faults import PlantFaults

            self.faults = PlantFaults(sc, self.plant, self.layout, seed, self.log)
        self.late_command_max_s = 0.0
        external = [self.layout.unit_index(name) for name in sc.ecu.external]
        self.external = ExternalWatch(self.layout, external, missing_after_s(sc)) if external else None

    def train_units(self, i: int) -> range:
        first = self.layout.index(i, 0)
        return range(first, first + self.layout.units_per_train)

    def rx_ids(self, i: int) -> set[int]:
        return set(self.io.cmd_unit[i]) | set(self.state_unit[i])

    # ---- receiving
    def take_commands(self) -> None:
        """What the buses brought since the last event (every kernel event starts with it): the refused commands
        logged, the valid ones applied in arrival order across the buses, and the latencies they closed kept."""
        taken = [inbox.take() for inbox in self.inboxes]
        for train, (_, refused, _) in enumerate(taken):
            for frame_id, data, t in refused:
                self.io.refuse(train, frame_id, data, t)
        commands = [command for valid, _, _ in taken for command in valid]
        if len(taken) > 1:
            commands.sort(key=arrival)
        for command in commands:
            self.on_command(*command)
        for _, _, latencies in taken:
            self.e2e.extend(latencies)

    def on_command(self, u: int, force: float, mode: int, t: float, counter: int) -> None:
        """A valid TractionCmd of unit u that arrived at t: the plant integrated up to the first step starting at or
        after t (never past a pending publication: its sample must be taken at its own time; only a lagging plant
        receives commands stamped beyond it), then the command applied if it continues u's command stream."""
        step = self.sc.plant.step_s
        k = min(math.ceil(t / step - 1e-9), self.target)
        if k < self.tick:
            self.late_commands += 1
            self.late_command_max_s = max(self.late_command_max_s, (self.tick - k) * step)
        elif k > self.tick:
            self.advance_to(k)
        if self.io.apply(u, force, mode, t, counter) and self.external is not None and self.external.command(u, t):
            print(f"{JOIN_LINE} {u} {t!r}", flush=True)  # the orchestrator waits for it (JoinWait)

    # ---- sending
    def publish_sensors(self, t: float) -> None:
        """Every unit's Sensor frame, one engine call per train bus; each unit's sample number noted for the
        sensor-to-actuator latency."""
        for train, outputs in enumerate(self.io.sensor_outputs()):
            samples = [(u, counter) for u, (_, _, counter) in zip(self.train_units(train), outputs)]
            self.inboxes[train].published(t, samples)
            self.frames.send_outputs(train, outputs, end_turn=True)

    def publish_reference(self, t: float) -> None:
        frames = self.io.reference_frames(t)
        n = self.layout.n_trains
        for k in range(len(self.wayside)):
            self.frames.send(n + k, frames)  # the wayside's connections follow the plant's

    # ---- the paced loop
    def run(self, clock: SimClock, duration: float, stop: StopFlag, spin_s: float,
            save: Callable[[LatenessStats], None] | None = None,
            stream: Callable[[], None] | None = None) -> LatenessStats:
        """Run to ``duration``; ``save(stats)`` every SAVE_EVERY_WALL_S so a killed plant leaves its data so far, and
        ``stream()`` every STREAM_EVERY_WALL_S (the new signal rows, for the live view).

        Only publications are paced (events of the node's ``PacedKernel``): it sleeps to the next Sensor/Reference
        tick and integrates lazily in between (see :meth:`advance_to`), so the plant costs its steps and no per-step
        wake-ups."""
        self._schedule(clock, duration, stop, spin_s)
        self.save, self.stream = save, stream
        self.next_save = time.monotonic() + SAVE_EVERY_WALL_S
        self.next_stream = time.monotonic() + STREAM_EVERY_WALL_S
        end_ns = to_ns(self.n_steps * self.sc.plant.step_s)
        self.kernel.run(end_ns + 1)
        self.log.sim_time_s = self.tick * self.sc.plant.step_s
        self.log.interrupted = self.tick < self.n_steps
        if self.external is not None:
            self.log.events.extend(self.external.events(self.log.sim_time_s))
        self.log.wall_time_s = time.time() - clock.t0
        self.frames.end_turns_for_good()  # its last publication is over: lingering must not hold the buses
        if not stop:
            linger(clock)
        assert self.stats is not None  # set by _schedule
        return self.stats

    def _schedule(self, clock: SimClock, duration: float, stop: StopFlag, spin_s: float) -> None:
        """The node's paced kernel, with the first publication and the end of the run on it."""
        self.clock = clock
        self.frames = node_frames(clock, self.buses + self.wayside, self.sc.can, self.packing, lazy=True)
        for train, inbox in enumerate(self.inboxes):
            self.frames.route_commands(train, inbox)
            self.frames.sends_at_least(train, self.io.sensor_bytes(train))
        for k in range(len(self.wayside)):
            self.frames.sends_at_least(len(self.buses) + k, self.io.reference_bytes())
        self.kernel = PacedKernel(clock, self.frames, stop, None, spin_s,
                                  heartbeat=Heartbeat())  # silent when a step never returns: hung
        step = self.sc.plant.step_s
        self.publish_every = publication_steps(self.every)
        self.stats = LatenessStats(self.publish_every * step, clock.pace,
                                   None if self.out is None else self.out / "timing_plant.bin")
        self.n_steps = int(round(duration / step))
        self.target = 0
        if self.n_steps > 0:
            self.kernel.at(0, self.publish, 0)
            # a lazy reader: synced at each publication on the train buses (the wayside's connections hear nothing);
            # with turns, each publication is its turn on the wayside's connections too
            links = len(self.buses) + (len(self.wayside) if self.turns else 0)
            self.frames.read_every(0.0, self.publish_every * step, list(range(links)), turns=self.turns)
        self.kernel.at(to_ns(self.n_steps * step), self.finish)

    def publish(self, target: int) -> None:
        """A publication tick (kernel event): integrate to it, book its lateness, faults, Sensor and Reference
        frames, the live stream and the periodic save; then schedule the next one."""
        step, stats = self.sc.plant.step_s, self.stats
        assert stats is not None  # set by _schedule
        deadline = target * step
        now = self.clock.now()
        if not turn_waited(self.turns, now - deadline, self.clock.pace):  # no bus waits for it any more
            late = late_publication(target, self.publish_every, self.n_steps, now / step)
            stats.skipped += (late - target) // self.publish_every
            self.target = target = late  # commands that arrived meanwhile act at their own steps, up to it
        t = target * step
        self.take_commands()
        self.advance_to(target)
        stats.add(max(self.clock.now() - deadline, 0.0), deadline)  # synced early, it publishes as at t
        if self.faults is not None:
            self.faults.poll(t, self.plant.x)
        if target % self.every["sensor"] == 0:
            self.publish_sensors(t)
        if target % self.every["ref"] == 0:
            self.publish_reference(t)
        self.frames.end_turn()  # the publication is on the buses: they may go on past t
        if self.stream is not None and time.monotonic() > self.next_stream:
            self.stream()
            self.next_stream = time.monotonic() + STREAM_EVERY_WALL_S
        if self.save is not None and time.monotonic() > self.next_save:
            self.log.sim_time_s, self.log.interrupted = t, True  # as of this save
            self.log.wall_time_s = time.time() - self.clock.t0
            self.save(stats)
            self.next_save = time.monotonic() + SAVE_EVERY_WALL_S
        nxt = target + self.publish_every
        self.target = min(nxt, self.n_steps)  # commands that arrive meanwhile integrate at most up to it
        if nxt < self.n_steps:
            self.kernel.at(to_ns(nxt * step), self.publish, nxt)

    def finish(self, _=None) -> None:
        """The end of the run (kernel event): the commands that arrived until then applied, the last steps done."""
        self.take_commands()
        self.advance_to(self.n_steps)
        self.frames.end_turn()

    def advance_to(self, k: int) -> None:
        """Integrate steps tick..k-1 (a recording sample before each step that falls on the recording period).

        Called before each publication and before each command is applied, so a command that arrived (bus
        timestamp) at t acts from the first step starting at or after t, as in the virtual rig."""
        plant, log, every_record, step = self.plant, self.log, self.every["record"], self.sc.plant.step_s
        while self.tick < k:
            plant_step(plant, self.parts.reference, log, self.tick * step, self.tick % every_record == 0)
            self.tick += 1

    def results(self, stats: LatenessStats) -> dict:
        e2e = self.e2e
        return {"sim_time_s": self.log.sim_time_s, "wall_time_s": self.log.wall_time_s,
                "interrupted": self.log.interrupted, **stats.summary(), "scheduling": self.scheduling,
                "e2e_latency_n": e2e.n, "e2e_latency_p50_s": e2e.percentile(50), "e2e_latency_p99_s": e2e.percentile(99),
                "e2e_latency_max_s": e2e.max if e2e.n else None, "e2e_crc_errors": self.io.e2e_errors,
                "late_commands": self.late_commands, "late_command_max_s": self.late_command_max_s,
                "malformed_frames": self.io.malformed_frames, "command_rejects": self.io.command_rejects(),
                "events": [[e.t, e.level, e.source, e.text] for e in self.log.events],
                "codec_saturations": self.db.total_saturations(),
                **({"external_units": self.external.report(self.log.sim_time_s)} if self.external is not None else {})}


class SignalStream:
    """Appends the run log's new signal rows (native float64) to a file and lets them go: the live view follows it,
    the merge reads it, and it survives whatever happens to the processes."""

    def __init__(self, path: Path, log: RunLog) -> None:
        self.log, self.rows = log, 0
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o600)

    def write(self) -> None:
        n = len(self.log.signals)
        if n > self.rows:
            os.write(self.fd, self.log.signals.rows_bytes(self.rows))
            self.rows = n
            self.log.signals.release_before(n)

    def close(self) -> None:
        os.close(self.fd)


def arrival(command: tuple[int, float, int, float, int]) -> float:
    """A decoded command's arrival time (``CommandInbox.take``), to merge the buses' commands in arrival order."""
    return command[3]


def tick_periods(sc) -> dict[str, int]:
    """Plant steps (at least one) between Sensor publications, Reference publications and recording samples."""
    step = sc.plant.step_s
    return {name: max(1, round(period / step)) for name, period in
            (("sensor", sc.can.sensor_period_s), ("ref", sc.reference.period_s), ("record", sc.recording.period_s))}


def late_publication(target: int, every: int, n_steps: int, now_steps: float) -> int:
    """The publication (a plant tick) to run when the one at ``target`` is due: the latest one due by ``now_steps``
    (the clock, in plant steps), at most the run's last before ``n_steps``; ``target`` itself unless the plant is
    more than a period (``every`` steps) late. The ones between are skipped, as an ECU skips its cycles."""
    overrun = periods_overrun(now_steps - target, every)
    last = (n_steps - 1) // every * every
    return max(target, min(target + overrun * every, last))


def publication_steps(ticks: dict[str, int]) -> int:
    """Plant steps between the plant's publications: each Sensor and each Reference tick is one."""
    return math.gcd(ticks["sensor"], ticks["ref"])


def main(argv: list[str] | None = None) -> int:
    p = node_parser("python -m hil.runtime.realtime.plant_node", "Run the plant and the wayside on the real-time rig's buses.")
    p.add_argument("--spin-us", type=float, default=200.0, help="on SocketCAN, poll the last microseconds before a publication (0: sleep only); "
                        "on the emulated buses the plant waits for its bus servers' SYNC instead")
    args = p.parse_args(argv)
    stop = StopFlag()
    set_timer_slack(1)
    scheduling = enter_role("plant", args.fifo, args.cpus)
    sc = load_scenario_json(args.scenario_json)
    db = load_train_db(sc)
    n = sc.trains.count
    out = Path(args.out)
    node = PlantNode(sc, args.seed, db, [], [], out, turns=args.turns)
    node.scheduling = scheduling
    try:
        for i in range(n):
            node.buses.append(open_bus(args.run, i, node.rx_ids(i), sc.can, "Plant", packing=node.packing, lazy=True))
            node.wayside.append(open_bus(args.run, i, (), sc.can, "Wayside", lazy=True))
        clock = SimClock(handshake(stop), args.pace)
        stats = LatenessStats(sc.plant.step_s, args.pace)

        def save(st: LatenessStats) -> None:
            st.series.flush()
            node.e2e.flush()
            write_json_atomic(out / "plant.json", node.results(st))

        rows = SignalStream(out / SIGNAL_STREAM, node.log)
        try:
            stats = node.run(clock, args.duration, stop, args.spin_us * 1e-6, save, rows.write)
        finally:
            rows.write()
            rows.close()
            final = node.stats if node.stats is not None else stats  # a run that failed early: its own so far
            save(final)
            final.series.close()
            node.e2e.close()
    finally:
        for b in node.buses + node.wayside:
            b.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
