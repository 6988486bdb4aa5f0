"""The virtual-time rig: plant, ECUs, wayside, CAN buses and radio on one discrete-event queue.

Data path (docs/architecture.md): plant --Sensor frames--> train bus --> ECU --TractionCmd--> bus --> plant;
ECUs exchange AgentState/AgentAux on their bus; the radio gateway forwards the tail's state to the
next train's bus and the head's state back; the wayside sends Reference frames to every bus.
Nothing crosses between these nodes except encoded CAN frames. Same seed, same run, bit for bit.

The network is the compiled frame engine (``trainhil_engine``): no Python runs per frame, CAN error confinement and
the bus faults included. The Python bus model it is checked against lives with the tests
(``tests/oracle/python_rig.py``, a subclass that overrides the network hooks below: ``_make_network``,
``_make_bus``, ``_attach_plant``, ``_ecu_node``, ``_attach_radio``, ``_plant_tick``, ``_before_run``, ``_collect``,
``_finish_network``, ``_make_faults``).
"""
from __future__ import annotations

import time
from functools import partial
from typing import Callable

import trainhil_engine as engine

from ecu_sim.codec import TrainDb
from ecu_sim.runtime import Ecu, cycle_and_send, os_exit_stops_the_firmware
from hil.runtime.plant_step import plant_step
from hil.radio.gateway import RadioGateway, RadioIds, build_links
from hil.plant.can_node import VALID_MODES, PlantCanNode
from hil.record.runlog import BusLog, RunLog
from hil.record.safety import record_violations
from hil.runtime.assembly import Assembly, assemble
from hil.faults.schedule import needs_fault_machinery
from hil.runtime.firmware import EcuFactory, build_ecu, refuse_external_units
from hil.runtime.engine_net import EngineBus, EngineKernel, attach_radio, copy_link_stats
from hil.runtime.kernel import to_ns
from hil.runtime.train_db import bus_packing, check_train_db, load_train_db
from hil.scenario.model import Scenario

ProgressFn = Callable[[float], None]  # called with the simulated time reached (s)


class VirtualRig:
    """One scenario wired up over emulated CAN, ready to run in virtual time."""

    runs_external_units = False  # a subclass that lets another simulator run them (hil/runtime/silkit_rig.py)

    def __init__(self, scenario: Scenario, seed: int | None = None, db: TrainDb | None = None,
                 ecu_factory: EcuFactory = build_ecu) -> None:
        """``ecu_factory`` builds each unit's ECU (default: the program the scenario names,
        :func:`hil.runtime.firmware.build_ecu`)."""
        if not self.runs_external_units:
            refuse_external_units(scenario, "virtual time")
        self.sc = scenario
        self.parts: Assembly = assemble(scenario, seed)
        self.layout = self.parts.layout
        self.plant = self.parts.plant
        if db is None:
            db = load_train_db(scenario)  # checked against the scenario as it loads
        else:
            check_train_db(scenario, db)
        self.db = db
        packing = bus_packing(scenario, self.db)
        self._make_network()
        self.log = RunLog(self.layout)
        self.log.reference_change_times = self.parts.reference.change_times
        self.buses = [self._make_bus(i, self._bus_log(i)) for i in range(self.layout.n_trains)]
        if packing is not None:
            for bus in self.buses:
                bus.set_packing(packing)
        self.plant_io = PlantCanNode(self.db, self.layout, self.plant, self.parts.reference, self.log)
        self._command_train: dict[int, int] = {}  # the engine's command table -> train (bus) index
        self._plant_nodes = [self._attach_plant(i) for i in range(self.layout.n_trains)]
        self._wayside_nodes = [bus.attach("Wayside") for bus in self.buses]
        self.ecus: list[Ecu] = []
        self._train_of = [self.layout.train_unit(u)[0] for u in range(self.layout.n_units)]
        self._ecu_nodes: list = []  # each unit's node on its bus
        for u in range(self.layout.n_units):
            self._attach_ecu(u, ecu_factory)
        self.gateway, self._gw_nodes = self._attach_radio()
        self._schedule()
        self.faults = self._make_faults() if needs_fault_machinery(scenario) else None  # hil/faults, if any

    # ------------------------------------------------------------------ the network (the oracle overrides these)
    def _make_network(self) -> None:
        """The engine's network and its event kernel."""
        self.net = engine.Network()
        self.kernel = EngineKernel(self.net)

    def _bus_log(self, i: int) -> BusLog:
        log = BusLog(f"bus{i + 1}", self.sc.can.bitrate)
        self.log.buses.append(log)
        return log

    def _make_bus(self, i: int, log: BusLog) -> EngineBus:
        return EngineBus(self.net, f"bus{i + 1}", self.sc.can, log)

    def _make_faults(self):
        """The fault schedule, its injectors and monitors (hil/runtime/virtual_faults.py)."""
        from hil.runtime.virtual_faults import VirtualFaults

        return VirtualFaults(self)

    def _attach_plant(self, i: int) -> int:
        """The plant's node on train i's bus. The engine checks and decodes its TractionCmd frames on delivery and
        queues them; they are applied at the next plant step (a command acts from the first step after its
        arrival, as with a per-frame callback)."""
        node, table = self.net.attach_commands(self.buses[i].index, "Plant", self.plant_io.command_table(i), VALID_MODES)
        self._command_train[table] = i
        return node

    def _attach_ecu(self, u: int, ecu_factory: EcuFactory) -> None:
        ecu = ecu_factory(self.parts, self.db, u)
        self.ecus.append(ecu)
        self._ecu_nodes.append(self._ecu_node(u, ecu))

    def _ecu_node(self, u: int, ecu: Ecu) -> int:
        """Unit u's ECU node on its train's bus, delivering into the ECU's mailboxes."""
        train, _ = self.layout.train_unit(u)
        return self.buses[train].attach_ecu(self.layout.ecu_node_name(u), ecu)

    def disconnect_ecu(self, u: int) -> None:
        """Unit u's ECU leaves its bus (a crash): its queued frames are dropped and counted, and a WARN event from
        the bus says how many when there were some (as a real-time bus server says a node's leave)."""
        node, bus = self._ecu_nodes[u], self.buses[self._train_of[u]]
        if bus.attached(node) and (lost := bus.detach(node)):
            self.log.event(self.kernel.now * 1e-9, "WARN", bus.name,
                           f"node {self.layout.ecu_node_name(u)} left (crashed); {lost} queued frames dropped")

    def reconnect_ecu(self, u: int) -> None:
        """Unit u's ECU joins its bus again (a restart after a crash), as a new node."""
        self._ecu_nodes[u] = self._ecu_node(u, self.ecus[u])

    def _attach_radio(self) -> tuple[RadioGateway | None, list]:
        """The radio between adjacent trains, in the engine: its links carry the statistics."""
        n = self.layout.n_trains
        if n < 2:
            return None, []
        links = build_links(self.sc.radio, n, self.parts.streams["radio"])
        position_codecs = [self.db.agent_state(k) for k in range(self.layout.units_per_train)]
        attach_radio(self.net, self.buses, links, self.layout.units_per_train, self.sc.radio.forward_aux,
                     position_codecs, RadioIds.from_db(self.db))
        return RadioGateway([], links, lambda fid, data: None), []

    # ------------------------------------------------------------------ periodic tasks
    def _schedule(self) -> None:
        sc, k = self.sc, self.kernel
        self._step_ns = to_ns(sc.plant.step_s)
        self._sensor_every = to_ns(sc.can.sensor_period_s) // self._step_ns
        self._record_every = to_ns(sc.recording.period_s) // self._step_ns
        self._tick = 0
        k.every(0, self._step_ns, self._plant_tick)
        k.every(0, to_ns(sc.reference.period_s), self._wayside_tick)
        cycle = to_ns(sc.ecu.cycle_s)
        for u, ecu in enumerate(self.ecus):
            unit = self.layout.train_unit(u)[1]
            phase = to_ns(sc.ecu.phase_s + unit * sc.ecu.stagger_s)
            k.every(phase, cycle, partial(self._ecu_tick, u))

    def _plant_tick(self, t_ns: int) -> None:
        """Apply the commands that arrived, then the plant's step."""
        if self.net.has_commands:
            self._apply_commands()
        self._plant_step(t_ns)

    def _plant_step(self, t_ns: int) -> None:
        """Publish sensors and record at their periods (state at t), then integrate to t + step."""
        tick, plant = self._tick, self.plant
        self._tick += 1
        if tick % self._sensor_every == 0:
            self._publish_sensors()
        plant_step(plant, self.parts.reference, self.log, t_ns * 1e-9, tick % self._record_every == 0)

    def _apply_commands(self) -> None:
        """The TractionCmd frames the engine delivered to the plant since the last step, in arrival order: checked
        and decoded in the engine; the plant node applies them, and logs why the rejected ones were."""
        commands, rejected = self.net.drain_commands()
        apply = self.plant_io.apply
        for command in commands:
            apply(*command)
        for table, frame_id, data, t_ns in rejected:
            self.plant_io.refuse(self._command_train[table], frame_id, data, t_ns * 1e-9)

    def _publish_sensors(self) -> None:
        for bus, node, outputs in zip(self.buses, self._plant_nodes, self.plant_io.sensor_outputs()):
            bus.send_outputs(node, outputs)

    def _wayside_tick(self, t_ns: int) -> None:
        frames = self.plant_io.reference_frames(t_ns * 1e-9)
        for bus, node in zip(self.buses, self._wayside_nodes):
            bus.send_frames(node, frames)

    def _ecu_tick(self, u: int, t_ns: int) -> None:
        ecu = self.ecus[u]
        bus = self.buses[self._train_of[u]]
        cycle_and_send(ecu, t_ns * 1e-9, self._ecu_nodes[u], bus.send_outputs, bus.send_frames)
        if ecu.events:
            for t, level, text in ecu.events:
                self.log.event(t, level, ecu.name, text)
            ecu.events.clear()

    # ------------------------------------------------------------------ running
    def run(self, duration_s: float | None = None, progress: ProgressFn | None = None,
            on_chunk: Callable[[RunLog], None] | None = None, chunk_s: float = 1.0) -> RunLog:
        """Run to ``duration_s`` (scenario duration by default), calling ``on_chunk`` every ``chunk_s``
        simulated seconds (incremental recording). Ctrl-C stops the run early and returns the log of
        everything up to that point with ``log.interrupted`` set, so callers can still write it out."""
        duration = self.sc.duration_s if duration_s is None else duration_s
        end_ns, chunk_ns = to_ns(duration), to_ns(chunk_s)
        wall0 = time.perf_counter()
        self._before_run()
        try:
            self._run_chunks(end_ns, chunk_ns, progress, on_chunk)
        except KeyboardInterrupt:
            self.log.interrupted = True
            self.log.event(self.kernel.now * 1e-9, "WARN", "rig", "run interrupted (Ctrl-C)")
        finally:
            self._finish(time.perf_counter() - wall0)
        return self.log

    def _run_chunks(self, end_ns: int, chunk_ns: int, progress: ProgressFn | None,
                    on_chunk: Callable[[RunLog], None] | None) -> None:
        """Run from now to ``end_ns`` a chunk at a time, collecting, reporting progress and recording after each."""
        t = self.kernel.now
        while t < end_ns:
            t = min(t + chunk_ns, end_ns)
            with os_exit_stops_the_firmware():  # the firmware runs in this process
                self.kernel.run(t)
            self._collect()
            if progress:
                progress(t * 1e-9)
            if on_chunk:
                on_chunk(self.log)

    def bus_event(self, bus: int, t_ns: int, kind: str, fields: dict) -> None:
        """An error-model or guardian event of the engine bus ``bus`` (already on the timeline); for subclasses
        that hand error states on (the SIL Kit rig does, to its controllers)."""

    def _before_run(self) -> None:
        """Keep the completed frames in the engine for the buses someone listens to."""
        for bus in self.buses:
            bus.trace_if_listened()

    def _collect(self) -> None:
        """Bring the engine's bus statistics and traced frames into the log and the frame listeners, and apply the
        commands that arrived since the last plant step (at the end of a chunk, as a per-frame callback would have:
        no plant step lies between their arrival and now)."""
        self._apply_commands()
        for bus in self.buses:
            bus.collect()
        self._log_refusals()

    def _log_refusals(self) -> None:
        """Each node's first frame refused (a full TX queue, bus-off) as a WARN event from its bus at its time: where
        and when a loss began (the rest are counted only, in ``frames_dropped_by_node``)."""
        for bus in self.buses:
            for t_ns, text in bus.take_refusals():
                self.log.event(t_ns * 1e-9, "WARN", bus.name, text)

    def _finish_network(self, now: int) -> None:
        """The network's last events to ``now`` and its statistics into the log."""
        self.net.finish(now)
        self._collect()
        if self.gateway is not None:
            copy_link_stats(self.net, self.gateway.links)

    def _finish(self, wall_s: float) -> None:
        log, now = self.log, self.kernel.now
        self._finish_network(now)
        radio = {name: dict(link.stats) for name, link in (self.gateway.links.items() if self.gateway else [])}
        log.radio_stats = radio
        log.tally_frames_lost()
        log.codec_saturations = self.db.total_saturations()
        log.e2e = {ecu.name: ecu.e2e_summary() for ecu in self.ecus}
        log.plant_command_rejects = self.plant_io.command_rejects()
        log.sim_time_s = now * 1e-9
        log.wall_time_s = wall_s
        if self.faults is not None:
            self.faults.finish(log)
        record_violations(log, self.sc.plant.coupler_band_m)  # every safety violation on the timeline


def run_virtual(scenario: Scenario, duration_s: float | None = None, seed: int | None = None,
                progress: ProgressFn | None = None) -> RunLog:
    """Convenience: build and run a scenario in virtual time."""
    return VirtualRig(scenario, seed).run(duration_s, progress)
