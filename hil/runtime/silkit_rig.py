"""The virtual rig as a Vector SIL Kit participant (``hil run SCENARIO --silkit [URI]``): plant, wayside, radio and
the rig's own ECUs run in the engine as always, in lockstep with SIL Kit's virtual time, and the rig is SIL Kit's
network simulator for each of its buses (``bus1`` ...): a SIL Kit CAN controller on such a network is a node of
that engine bus, so its frames meet the rig's on one bus model, and every frame of the bus reaches it with its
end-of-frame timestamp (hil/silkit/network_simulator.py says when).

Units named in ``ecu.external`` are left to SIL Kit participants named after them (``train1/unit2``); the rig is
the system controller and the simulation starts when all of them have joined, or stops with an error naming them
after ``ecu.join_timeout_s`` of wall time. The rig steps at half of ``step_ns`` (the participants' step, 1 ms by
default) and does its work at the half steps: run the engine to kΔ, queue what the participants sent in step kΔ,
run to (k + 1)Δ and hand every ended frame to SIL Kit.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ecu_sim.runtime import ECU_STOPPED, os_exit_stops_the_firmware
from hil.can.transmission import Transmission
from hil.record.runlog import RunLog
from hil.runtime.errors import RigDidNotStart
from hil.runtime.firmware import EcuFactory, build_ecu
from hil.runtime.train_db import TrainDb
from hil.runtime.virtual import ProgressFn, VirtualRig, to_ns
from hil.scenario.model import Scenario
from hil.silkit import capi
from hil.silkit.capi import Library, SilKitError
from hil.silkit.options import SilKitOptions
from hil.silkit.network_simulator import CanNetworkSimulator, create_simulator, start_simulator
from hil.silkit.participant import Participant
from hil.silkit.registry import Registry
from hil.silkit.runtime import find_runtime

PARTICIPANT = "trainhil"
# How long a lost participant may go unnamed after SIL Kit's system state turned Error: the disconnect comes on
# SIL Kit's own thread and may come after the state change; without it a lost ECU is recorded as an unnamed loss.
NAME_LOST_WAIT_S = 1.0


def _forwarder(network: CanNetworkSimulator) -> Callable[[Transmission], None]:
    """A bus listener handing each ended frame to the SIL Kit network simulating that bus."""
    def forward(tx: Transmission) -> None:
        network.frame_ended(tx.node, tx.frame_id, tx.data, tx.extended, tx.t_end, tx.fd, tx.brs)
    return forward


class JoinTimeout(RigDidNotStart):
    """External participants did not join in time; the message names them."""


class RegistryUnreachable(RigDidNotStart):
    """``--silkit URI``: no registry there; the message names the URI."""


class SilKitRig(VirtualRig):
    """:class:`VirtualRig` stepped by SIL Kit, its buses simulated for SIL Kit's CAN controllers."""

    runs_external_units = True

    def __init__(self, scenario: Scenario, seed: int | None = None, db: TrainDb | None = None,
                 ecu_factory: EcuFactory = build_ecu, options: SilKitOptions = SilKitOptions()) -> None:
        self._external: set[int] = set()
        super().__init__(scenario, seed, db, ecu_factory)
        self.external_names = list(scenario.ecu.external)
        self.options = options
        options.check_buses([bus.name for bus in self.buses])  # before anything connects to SIL Kit
        self.step_ns = step_ns = round(options.step_s * 1e9)
        runtime = find_runtime()
        self.lib = Library(str(runtime.library))
        self.registry = Registry(runtime) if not options.uri else None
        self.registry_uri = options.uri or self.registry.uri  # type: ignore[union-attr]
        try:
            self.participant = Participant(self.lib, PARTICIPANT, self.registry_uri,
                                           config=options.participant_config())
        except SilKitError as exc:
            self.close()
            raise RegistryUnreachable(f"no SIL Kit registry answers at {self.registry_uri} ({exc}); start one there "
                                      "(sil-kit-registry --listen-uri URI) or give --silkit without a URI for a "
                                      "registry of the run's own") from None
        if options.system_controller:
            self.participant.require([PARTICIPANT, *self.external_names])
        simulator = create_simulator(self.lib, self.participant.handle)
        self.networks, self._forwarders = [], []
        for bus in self.buses:
            network = CanNetworkSimulator(self.lib, self.participant.handle, options.network_of(bus.name), step_ns,
                                          self.sc.can.bitrate,
                                          self.sc.can.tx_queue_depth, bus=(self.net, bus.index), simulator=simulator,
                                          fd=self.sc.can.fd)
            self._forwarders.append(_forwarder(network))
            bus.frame_listeners.append(self._forwarders[-1])
            self.networks.append(network)
        start_simulator(self.lib, simulator)
        self.participant.on_step(self._step, step_ns // 2)
        self._failure: BaseException | None = None
        self._started = threading.Event()
        self._end_ns = self._at_ns = 0  # the run's end, and the time of SIL Kit's latest step
        self._gone: list[tuple[str, int]] = []  # participants that disconnected mid-run, and when
        self._lost: list[tuple[str, int]] = []  # those of them lost (SIL Kit's system state Error), and when
        self._leaving = False
        self._error_seen: float | None = None  # when SIL Kit's system state was first seen in Error (monotonic s)
        self._reached_end = False
        self._step_offsets_s: list[float] = []  # paced: each step's wall-clock start minus its scheduled one
        self.participant.on_disconnected(self._on_disconnected)

    # ------------------------------------------------------------------ external units have no ECU here
    def _attach_ecu(self, u: int, ecu_factory: EcuFactory) -> None:
        if self.layout.unit_name(u) in self.sc.ecu.external:
            self._external.add(u)
            self.ecus.append(ecu_factory(self.parts, self.db, u))  # kept for the lists' sake, never run
            self._ecu_nodes.append(None)
            return
        super()._attach_ecu(u, ecu_factory)

    def bus_event(self, bus: int, t_ns: int, kind: str, fields: dict) -> None:
        """An error-state change of a SIL Kit controller's node goes to that controller."""
        if bus < len(self.networks):  # the fault machinery is made before the networks
            self.networks[bus].error_state_changed(str(fields.get("node", "")), kind, t_ns)

    def _ecu_tick(self, u: int, t_ns: int) -> None:
        if u not in self._external:
            super()._ecu_tick(u, t_ns)

    # ------------------------------------------------------------------ running in SIL Kit's time
    def run(self, duration_s: float | None = None, progress: ProgressFn | None = None,
            on_chunk: Callable[[RunLog], None] | None = None, chunk_s: float = 1.0) -> RunLog:
        """Run the SIL Kit lifecycle until ``duration_s`` of virtual time; the log as :meth:`VirtualRig.run`'s.

        Ctrl-C stops the lifecycle and returns what was run, as in virtual time. An external participant that
        disconnects mid-run (killed, crashed) is recorded as its ECU's failure (any other lost participant as an
        error); SIL Kit's coordinated time cannot advance past a lost participant, so the rig leaves SIL Kit and
        runs on to ``duration_s`` in virtual time, every external unit sending nothing: the plant's fail-safe then
        holds them."""
        duration = self.sc.duration_s if duration_s is None else duration_s
        self._end_ns, self._chunk_ns, self._next_chunk = to_ns(duration), to_ns(chunk_s), to_ns(chunk_s)
        self._progress, self._on_chunk = progress, on_chunk
        wall0 = time.perf_counter()
        self._before_run()
        watchdog = threading.Timer(self.sc.ecu.join_timeout_s, self._join_timed_out)
        watchdog.daemon = True
        if self.external_names:
            watchdog.start()
        try:
            with os_exit_stops_the_firmware():  # the firmware runs in this process, on SIL Kit's step thread
                self.participant.run(poll=self._leave_if_lost)
                if self._lost and self._failure is None:
                    self._run_on_without_silkit(progress, on_chunk)
                elif not self._reached_end and self._failure is None:
                    self._stopped_by_another()
        except KeyboardInterrupt:
            self.log.interrupted = True
            self.log.event(self.kernel.now * 1e-9, "WARN", "rig", "run interrupted (Ctrl-C)")
        finally:
            watchdog.cancel()
            self._finish(time.perf_counter() - wall0)
            self.log.silkit_report = self._report()
            self.close()
        if self._failure is not None:
            raise self._failure
        return self.log

    def _report(self) -> dict:
        """The ``silkit`` block of metrics.json: who took part, what SIL Kit controllers did, and when paced, how
        late the rig's steps began against the wall clock's schedule of virtual time (SIL Kit never starts one early;
        the schedule is anchored at the step that began earliest against it, so this is the pacing's jitter)."""
        report: dict = {
            "registry": self.registry_uri, "participant": PARTICIPANT, "step_s": self.step_ns * 1e-9,
            "system_controller": self.options.system_controller, "external": self.external_names,
            "lost": [{"participant": name, "t_s": t * 1e-9} for name, t in self._lost],
            "networks": [n.network for n in self.networks],
            # the controllers that took part, also those whose participant left before the report
            "controllers": {n.network: n.controllers_seen for n in self.networks},
            "tx_queue_full": sum(n.queue_full for n in self.networks),
            "format_refused": sum(n.format_refused for n in self.networks),
            "bitrate_mismatches": sum(n.bitrate_mismatches for n in self.networks)}
        if self.options.pace is not None:  # anchored at the step that began earliest against the schedule
            offsets = np.asarray(self._step_offsets_s)
            late = (offsets - offsets.min()) * 1e3 if offsets.size else offsets
            report["pace"] = self.options.pace
            report["step_lateness_ms"] = ({"p50": float(np.percentile(late, 50)), "p99": float(np.percentile(late, 99)),
                                           "max": float(late.max()), "steps": int(late.size)} if late.size else None)
        return report

    def _on_disconnected(self, name: str) -> None:
        """SIL Kit's thread: a participant left before the run's end (gracefully or not: the system state says)."""
        if self._started.is_set() and not self._reached_end:
            self._gone.append((name, self._at_ns))

    def _leave_if_lost(self) -> None:
        """The main thread, while SIL Kit runs: once SIL Kit's system state is Error (a participant, external unit or
        not, left without shutting down: coordinated time cannot advance), the participants that left are lost;
        stop the lifecycle."""
        if self._leaving or not self._started.is_set() or self._reached_end:
            return
        if self.participant.system_state() == capi.STATE_ERROR:
            self._error_seen = self._error_seen or time.monotonic()
            if not self._gone and time.monotonic() - self._error_seen < NAME_LOST_WAIT_S:
                return  # SIL Kit's thread may not have said who left yet: it names the lost ECU
            self._leaving = True
            self._lost = list(self._gone) or [("(a participant)", self._at_ns)]
            names = ", ".join(name for name, _ in self._lost)
            self.participant.halt(f"trainhil: SIL Kit participant(s) {names} lost")

    def _stopped_by_another(self) -> None:
        """The lifecycle ended before the run's end and no participant was lost: another one stopped SIL Kit."""
        self.log.interrupted = True
        self.log.event(self.kernel.now * 1e-9, "WARN", "rig",
                       "the SIL Kit simulation was stopped by another participant before the run's end")

    def _run_on_without_silkit(self, progress: ProgressFn | None, on_chunk: Callable[[RunLog], None] | None) -> None:
        """Record each lost participant as its ECU's failure and run on to the end in virtual time alone."""
        for name, at_ns in self._lost:
            lost = f"SIL Kit participant {name} disconnected without shutting down (killed or crashed)"
            if name in self.external_names:
                self.log.event(at_ns * 1e-9, "ERROR", name, f"{lost}; its unit receives no command from now: "
                                                            f"{ECU_STOPPED}")
            else:
                self.log.event(at_ns * 1e-9, "ERROR", "rig", lost)
        t = self.kernel.now * 1e-9
        self.log.event(t, "WARN", "rig", f"left SIL Kit at t = {t:.3f} s: its coordinated time cannot advance "
                                         "past a lost participant; the run goes on in virtual time, the external "
                                         "units silent")
        for bus, forward in zip(self.buses, self._forwarders):
            bus.frame_listeners.remove(forward)
        self._run_chunks(self._end_ns, self._chunk_ns, progress, on_chunk)

    def _step(self, now_ns: int, duration_ns: int) -> None:
        """SIL Kit's step (every Δ/2, on its thread); an error stops the simulation and is raised by :meth:`run`."""
        self._started.set()
        self._at_ns = now_ns
        if self.options.pace is not None:  # when this step began against the wall clock's schedule
            self._step_offsets_s.append(time.perf_counter() - now_ns * 1e-9 / self.options.pace)
        try:
            if now_ns % self.step_ns != self.step_ns // 2 or self._failure is not None:
                return
            sent_at = now_ns - self.step_ns // 2
            self.kernel.run(min(sent_at, self._end_ns))
            for network in self.networks:
                network.inject(sent_at)
            horizon = min(sent_at + self.step_ns, self._end_ns)
            self.kernel.run(horizon)
            for bus in self.buses:
                bus.collect_frames()  # every ended frame to SIL Kit now; the statistics once per chunk
            if horizon >= self._next_chunk or horizon >= self._end_ns:
                self._collect()
                self._next_chunk += self._chunk_ns
                if self._progress:
                    self._progress(horizon * 1e-9)
                if self._on_chunk:
                    self._on_chunk(self.log)
            if horizon >= self._end_ns:
                self._reached_end = True
                self.participant.stop("trainhil: the run reached its duration")
        except BaseException as exc:  # ctypes would print and drop it: keep it for run() and stop the simulation
            self._failure = exc
            self.participant.stop(f"trainhil failed: {exc}")

    def _join_timed_out(self) -> None:
        """No step after ecu.join_timeout_s: the participants that were to join did not; abort."""
        if not self._started.is_set():
            self._failure = JoinTimeout(f"SIL Kit participant(s) {', '.join(self.external_names)} did not join "
                                        f"{self.registry_uri} within ecu.join_timeout_s = {self.sc.ecu.join_timeout_s} s")
            self.participant.abort()

    def close(self) -> None:
        """Leave SIL Kit and stop the registry this rig started."""
        if hasattr(self, "participant"):
            self.participant.close()
        if self.registry is not None:
            self.registry.close()
