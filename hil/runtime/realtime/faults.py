"""The fault schedule of a real-time run: who triggers, who injects, and how it comes back together.

* The plant node owns the schedule's clock (``PlantFaults``): it knows the positions, so it resolves time and
  position triggers alike, at every publication. It logs each start and end (source ``faults``), injects the
  faults that live in the plant (stuck/noisy sensors, actuator health) itself, and announces the others on its
  stdout (``fault <k> start|end <t>``).
* The orchestrator (``RealtimeFaults``) reads those lines and acts: an ECU crash is the ECU's process killed
  (SIGKILL), a hang is SIGSTOP and SIGCONT, a restart is a new process for the unit that joins the running rig
  (a reset controller); bus faults go to the bus servers' models (``hil.faults.bus.BusFaults``, under each
  server's lock); radio faults set the impairments of the engine's radio links in the bus servers (on SocketCAN,
  they go to the radio node's stdin: ``RadioNodeFaults``). Units with an ECU fault get
  their own process. The watchdog (``ecu.restart_after_s``) restarts crashed and hung ECU processes;
  controller errors are restarted inside the ECU process (``hil.runtime.realtime.ecu_node``).
* At the end, the bus servers' events are moved to simulated time, detections are matched (``report``), the
  safety violations are added to the timeline and ``log.fault_report`` is left for the metrics, as in virtual
  time.

A restarted ECU process needs its imports (1-3 s on a loaded 2-core machine) before it is back: the down time
of a crash in real time is its duration plus that boot time, logged when the new process joins.
"""
from __future__ import annotations

import os
import queue
import signal
import time
from collections.abc import Callable
from typing import Any

from ecu_sim.runtime import RESTARTED
from hil.faults.actuator import ActuatorFaults
from hil.faults.bus import EngineBusFaults, describe_bus_event, e2e_checker
from hil.faults.radio import RadioFaults
from hil.faults.report import fault_report
from hil.faults.schedule import BUS_KINDS, RADIO_KINDS, SOURCE, FaultSchedule, fault_rng
from hil.faults.sensor import SensorFaults
from hil.faults.watchdog import Watchdog
from hil.record.runlog import Event, RunLog
from hil.runtime.train_db import bus_packing

ECU_KINDS = ("ecu_crash", "ecu_hang")
PLANT_KINDS = ("sensor_stuck", "sensor_noise", "actuator_degradation", "traction_loss")


def solo_units(scenario, layout) -> set[int]:
    """The flat units an ECU fault kills or stops: each runs in an ECU process of its own."""
    return {layout.index(f.train - 1, f.unit - 1) for f in scenario.faults if f.kind in ECU_KINDS}


# --------------------------------------------------------------------------- plant node


class PlantFaults:
    """In the plant node: the schedule's clock, plant-side injection, announcements to the orchestrator."""

    def __init__(self, scenario, plant, layout, seed: int, log: RunLog, announce=None) -> None:
        self.schedule = FaultSchedule(scenario, layout)
        self.log = log
        self.sensors = SensorFaults(plant, layout, fault_rng(seed, 2000))
        self.actuators = ActuatorFaults(plant, layout)
        self._announce = announce or (lambda line: print(line, flush=True))

    def poll(self, t: float, x) -> None:
        for f, what in self.schedule.poll(t, x):
            spec = f.spec
            if what == "start":
                self.log.event(t, "WARN", SOURCE, self.schedule.start_text(f))
            else:
                self.log.event(t, "INFO", SOURCE, f"{f.label}: over after {t - (f.start_s or 0.0):.3f} s")
            if spec.kind in ("sensor_stuck", "sensor_noise"):
                (self.sensors.start if what == "start" else self.sensors.end)(spec)
            elif spec.kind in ("actuator_degradation", "traction_loss"):
                (self.actuators.start if what == "start" else self.actuators.end)(spec, t)
            else:
                self._announce(f"fault {f.index} {what} {t!r}")


# --------------------------------------------------------------------------- radio node

RADIO_FAULT_STREAM = 3000  # fault_rng key of the radio faults' draws (burst losses)


class RadioNodeFaults:
    """In the radio node: fault lines from stdin (any thread) queued, applied by the node's loop."""

    def __init__(self, scenario, gateway, seed: int) -> None:
        self.specs = list(scenario.faults)
        self.radio = RadioFaults(gateway.links, scenario.trains.count, fault_rng(seed, RADIO_FAULT_STREAM))
        self.lines: queue.Queue[str] = queue.Queue()

    def on_line(self, line: str) -> None:
        if line.startswith("fault "):
            self.lines.put(line)

    def apply_pending(self) -> None:
        while not self.lines.empty():
            _, k, what, *_ = self.lines.get().split()
            spec = self.specs[int(k)]
            (self.radio.start if what == "start" else self.radio.end)(spec, int(k))


# --------------------------------------------------------------------------- orchestrator


class RealtimeFaults:
    """In the orchestrator: bus faults on the servers, radio faults on the engine's radio (``radio``, an
    ``EngineRadio``; without one, on SocketCAN, they go to the radio node), ECU processes killed, stopped and
    restarted."""

    def __init__(self, scenario, layout, servers: list, seed: int, db, radio=None) -> None:
        self.sc, self.layout, self.seed = scenario, layout, seed
        self.specs = list(scenario.faults)
        self.watchdog = Watchdog(scenario.ecu.restart_after_s)
        self.servers = servers
        periods = db.cycle_times()
        ok, packing = e2e_checker(db), bus_packing(scenario, db)
        # error confinement and the guardian on every bus, in the engine's native bus servers
        self.buses = [EngineBusFaults(server, i, seed, periods, e2e_ok=ok, packing=packing)
                      for i, server in enumerate(servers)]
        self.radio = None  # RadioFaults on the engine's radio links (the same fault stream as the radio node's)
        if radio is not None:
            rng = fault_rng(seed, RADIO_FAULT_STREAM)
            self.radio = RadioFaults(radio.links, scenario.trains.count, rng, radio.impairment_setter(rng))
        self.events: list[Event] = []
        self.nodes: list[Any] = []  # the orchestrator's Nodes
        self.spawn: Callable[[int], Any] | None = None
        self.t0 = 0.0
        self.pace = 1.0
        self._hung: dict[int, Any] = {}  # unit -> its stopped node
        self._pending: list[tuple[Any, int, float]] = []  # (new node, unit, sim time asked) not yet ready
        self.restarts = 0

    def go(self, t0: float, pace: float, nodes: list, spawn) -> None:
        """The run started: ``nodes`` is the orchestrator's live list, ``spawn(unit)`` starts a late-joining ECU."""
        self.t0, self.pace, self.nodes, self.spawn = t0, pace, nodes, spawn

    def _node(self, kind: str, name: str | None = None) -> Any:
        return next((n for n in self.nodes if n.kind == kind and (name is None or n.name == name)
                     and n.proc.poll() is None), None)

    def _unit_name(self, u: int) -> str:
        return self.layout.unit_name(u)

    def _event(self, t: float, level: str, text: str) -> None:
        self.events.append(Event(t, level, "rig", text))

    # ---- called by the supervising loop
    def tick(self, sim_now: float) -> None:
        plant = self._node("plant")
        if plant is not None:
            while not plant.lines.empty():
                line = plant.lines.get()
                if line.startswith("fault "):
                    _, k, what, t = line.split()
                    self._dispatch(int(k), what, sim_now)
        for u, why in self.watchdog.due(sim_now):
            self._restart(u, sim_now, "watchdog", why)
        for item in list(self._pending):
            node, u, asked = item
            while not node.lines.empty():
                if node.lines.get() == "ready":
                    node.ready = True
            if node.ready:
                self._pending.remove(item)
                node.tell(f"go {self.t0!r}")
                self._event(sim_now, "INFO", f"ECU process {node.name} {RESTARTED} (a new process), "
                                             f"{sim_now - asked:.2f} s after the restart was asked")

    def _dispatch(self, k: int, what: str, sim_now: float) -> None:
        spec = self.specs[k]
        kind = spec.kind
        if kind in ECU_KINDS:
            u = self.layout.index(spec.train - 1, spec.unit - 1)
            if what == "start":
                (self._crash if kind == "ecu_crash" else self._hang)(u, spec, sim_now)
            elif self.watchdog.is_down(u, "crash" if kind == "ecu_crash" else "hang"):
                if kind == "ecu_crash":
                    self._restart(u, sim_now, "the crash ended", self.watchdog.up(u))
                else:
                    self._continue(u, sim_now)
        elif kind in BUS_KINDS:
            bf = self.buses[spec.train - 1]  # the engine's server takes its lock itself
            bf.start(spec, k) if what == "start" else bf.end(spec, k)
        elif kind in RADIO_KINDS and self.radio is not None:
            (self.radio.start if what == "start" else self.radio.end)(spec, k)
        elif kind in RADIO_KINDS:
            radio = self._node("radio")
            if radio is not None:
                radio.tell(f"fault {k} {what}")

    def _crash(self, u: int, spec, t: float) -> None:
        node = self._node("ecu", self._unit_name(u))
        if node is None:
            return
        node.reported = True  # not an unexpected exit: we killed it
        if u in self._hung:
            del self._hung[u]
        node.proc.kill()
        self._event(t, "WARN", f"ECU process {node.name} killed (SIGKILL): crash")
        self.watchdog.stopped(u, "crash", t, spec.duration_s)

    def _hang(self, u: int, spec, t: float) -> None:
        node = self._node("ecu", self._unit_name(u))
        if node is None:
            return
        os.kill(node.proc.pid, signal.SIGSTOP)
        node.held = True  # the orchestrator's hang watch leaves an injected hang to us
        self._hung[u] = node
        self._event(t, "WARN", f"ECU process {node.name} stopped (SIGSTOP): hang, still connected")
        self.watchdog.stopped(u, "hang", t, spec.duration_s)

    def _continue(self, u: int, t: float) -> None:
        node = self._hung.pop(u, None)
        self.watchdog.up(u)
        if node is not None and node.proc.poll() is None:
            os.kill(node.proc.pid, signal.SIGCONT)
            node.held, node.last_alive = False, time.time()  # watched again from now
            self._event(t, "INFO", f"ECU process {node.name} continued (SIGCONT): the hang is over, no reset")

    def _restart(self, u: int, t: float, by: str, why: str | None) -> None:
        """A new process for unit ``u`` (down for ``why``); a hung one is killed first."""
        old = self._hung.pop(u, None)
        if old is not None and old.proc.poll() is None:  # a hung process is replaced by the watchdog
            old.reported = True
            old.proc.kill()
        assert self.spawn is not None  # set by go() before any fault starts
        node = self.spawn(u)
        self.nodes.append(node)
        self._pending.append((node, u, t))
        self.restarts += 1
        self._event(t, "INFO", f"ECU process {self._unit_name(u)}: restart asked ({by}, after a {why})")

    def release(self) -> None:
        """Before the nodes are told to stop: a stopped (hung) process must run again to hear it."""
        for node in self._hung.values():
            if node.proc.poll() is None:
                os.kill(node.proc.pid, signal.SIGCONT)
        self._hung.clear()

    # ---- the end
    def finish(self, log: RunLog, t0: float | None, pace: float) -> None:
        """Bus events in simulated time, detections matched, ``log.fault_report``."""
        for i, server in enumerate(self.servers):
            shift = 0.0 if t0 is None else (t0 - server.epoch0) * pace
            for t_ns, kind, fields in server.take_bus_events():
                what, level, text = describe_bus_event(kind, fields)
                log.events.append(Event(t_ns * 1e-9 - shift, level, f"bus{i + 1}/{what}", text))
        log.events.extend(self.events)
        log.events.sort(key=lambda e: e.t)
        can = {f"bus{i + 1}": bf.summary() for i, bf in enumerate(self.buses)}
        log.fault_report = fault_report(self.specs, self.layout, log, can, {"ecu_restarts": self.restarts})
