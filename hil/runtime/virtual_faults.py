"""The fault schedule of a virtual-time run: triggers on the event kernel, injectors on the rig's parts.

``VirtualFaults(rig)`` is built by ``VirtualRig`` when the scenario has ``[[faults]]`` or ``ecu.restart_after_s``.
It installs the monitors (ECU diagnostics on every ECU, error confinement and a guardian on every bus), schedules
time triggers and ends as kernel events at their exact times and checks position triggers every sensor period.
At the end of the run (``finish``) it matches detections to faults, adds the safety violations to the timeline,
and leaves the ``faults`` block of metrics.json on the log (``log.fault_report``).
"""
from __future__ import annotations

from ecu_sim.diagnostics import EcuDiagnostics, neighbour_names
from hil.faults.actuator import ActuatorFaults
from hil.faults.bus import EngineBusFaults, describe_bus_event, e2e_checker
from hil.runtime.ecu_faults import EcuFaults
from hil.faults.radio import RadioFaults
from hil.faults.report import fault_report
from hil.faults.schedule import BUS_KINDS, RADIO_KINDS, SOURCE, FaultSchedule, ScheduledFault, fault_rng
from hil.faults.sensor import SensorFaults
from hil.record.runlog import RunLog
from hil.runtime.engine_net import engine_impairments
from hil.runtime.kernel import to_ns



class VirtualFaults:
    """The fault machinery of one virtual rig (built by ``VirtualRig._make_faults``)."""

    def __init__(self, rig) -> None:
        self.rig = rig
        sc, layout, log = rig.sc, rig.layout, rig.log
        self.schedule = FaultSchedule(sc, layout)
        seed = rig.parts.seed
        for u, ecu in enumerate(rig.ecus):
            ecu.monitors.append(EcuDiagnostics(ecu, sc.can.sensor_period_s, neighbour_names(layout, u),
                                               rig.parts.plant_info))
        self.ecus = EcuFaults(rig, sc.ecu.restart_after_s, log.event)
        self.sensors = SensorFaults(rig.plant, layout, fault_rng(seed, 2000))
        self.actuators = ActuatorFaults(rig.plant, layout)
        self.buses = self._bus_faults(seed, rig.db.cycle_times(), e2e_checker(rig.db))
        self.radio = None
        if rig.gateway:
            rng = fault_rng(seed, 3000)
            self.radio = RadioFaults(rig.gateway.links, layout.n_trains, rng, self._radio_impairments(rng))
        k = rig.kernel
        for f in self.schedule.faults:
            if f.spec.at_s is not None:
                k.at(to_ns(f.spec.at_s), self._start, f)
        if any(f.spec.at_position_m is not None for f in self.schedule.faults):
            k.every(0, to_ns(sc.can.sensor_period_s), self._poll)

    # ---- on the network (the oracle's subclass overrides these)
    def _bus_faults(self, seed: int, periods: dict[int, float], e2e_ok) -> list:
        """Error confinement and the guardian on every bus, in the engine; its events taken whenever it hands back
        control, so the timeline keeps their order."""
        rig = self.rig
        buses = [EngineBusFaults(bus, i, seed, periods, e2e_ok=e2e_ok, packing=bus.packing)
                 for i, bus in enumerate(rig.buses)]
        rig.kernel.after_advance = self._take_bus_events
        for bus in rig.buses:
            bus.after_send = self._take_bus_events
        return buses

    def _radio_impairments(self, rng):
        """The radio faults' effects on the engine's links."""
        return engine_impairments(self.rig.net, list(self.rig.gateway.links), rng)

    def _take_bus_events(self) -> None:
        """The engine's bus error and guardian events since the last call, onto the timeline in their order."""
        net = self.rig.net
        if net.has_bus_events:
            log, buses = self.rig.log, self.rig.buses
            for bus, t_ns, kind, fields in net.take_bus_events():
                what, level, text = describe_bus_event(kind, fields)
                log.event(t_ns * 1e-9, level, f"{buses[bus].name}/{what}", text)
                self.rig.bus_event(bus, t_ns, kind, fields)

    # ---- triggers
    def _poll(self, t_ns: int) -> None:
        for f, _ in self.schedule.poll(t_ns * 1e-9, self.rig.plant.x, timed=False):
            self._start(f)

    def _start(self, f: ScheduledFault) -> None:
        rig = self.rig
        t = rig.kernel.now * 1e-9
        self.schedule.start(f, t)
        rig.log.event(t, "WARN", SOURCE, self.schedule.start_text(f))
        self._inject(f, t, True)
        if f.spec.duration_s is not None:
            rig.kernel.at(rig.kernel.now + to_ns(f.spec.duration_s), self._end, f)

    def _end(self, f: ScheduledFault) -> None:
        t = self.rig.kernel.now * 1e-9
        self.schedule.end(f, t)
        self.rig.log.event(t, "INFO", SOURCE, f"{f.label}: over after {t - f.start_s:.3f} s")
        self._inject(f, t, False)

    def _inject(self, f: ScheduledFault, t: float, on: bool) -> None:
        spec, kind = f.spec, f.kind
        if kind in ("ecu_crash", "ecu_hang"):
            if on:
                (self.ecus.crash if kind == "ecu_crash" else self.ecus.hang)(spec, t)
            else:
                self.ecus.end(spec, t)
        elif kind in ("sensor_stuck", "sensor_noise"):
            (self.sensors.start if on else self.sensors.end)(spec)
        elif kind in ("actuator_degradation", "traction_loss"):
            (self.actuators.start if on else self.actuators.end)(spec, t)
        elif kind in BUS_KINDS:
            bus = self.buses[spec.train - 1]
            if on:
                bus.start(spec, f.index, self.rig.kernel.now)
            else:
                bus.end(spec, f.index)
        elif kind in RADIO_KINDS and self.radio is not None:
            (self.radio.start if on else self.radio.end)(spec, f.index)

    # ---- the end
    def finish(self, log: RunLog) -> None:
        """Detections matched to faults and ``log.fault_report`` for the metrics."""
        sc = self.rig.sc
        self._take_bus_events()  # those of the buses' finish
        can = {bus.name: bf.summary() for bus, bf in zip(self.rig.buses, self.buses)}
        log.fault_report = fault_report(list(sc.faults), self.rig.layout, log, can,
                                        {"ecu_restarts": self.ecus.restarts})
