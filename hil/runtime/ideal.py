"""The ideal reference loop: the same control laws on the same plant, with no network at all.

Every control period each agent reads the true states of its neighbours and of itself (age 0) and the
exact reference; its command acts on the plant at once (zero-order hold to the next period). This is
the oracle the networked run is compared with: any difference is the network's doing (latency,
quantisation, loss). Neighbours' accelerations are the accelerations they demanded in the previous
period, the same quantity the AgentAux frame carries on CAN.
"""
from __future__ import annotations

import math
import time
from typing import Callable

from ecu_sim.view import LocalView, NeighbourView, ReferenceView
from hil.record.runlog import RunLog
from hil.record.safety import record_violations
from hil.runtime.firmware import refuse_external_units
from hil.runtime.assembly import Assembly, assemble
from hil.runtime.kernel import to_ns
from hil.runtime.plant_step import plant_step
from hil.scenario.model import Scenario


class IdealLoop:
    """Network-free closed loop of one scenario."""

    def __init__(self, scenario: Scenario, seed: int | None = None, control_period_s: float | None = None) -> None:
        refuse_external_units(scenario, "the ideal loop")
        self.sc = scenario
        self.parts: Assembly = assemble(scenario, seed)
        self.layout = self.parts.layout
        period = scenario.ecu.cycle_s if control_period_s is None else control_period_s
        step = to_ns(scenario.plant.step_s)
        if to_ns(period) % step:
            raise ValueError(f"control period {period} s must be a whole multiple of plant.step_s = {scenario.plant.step_s}")
        self._control_every = to_ns(period) // step
        self._record_every = to_ns(scenario.recording.period_s) // step
        self._period = period
        self._neighbours = [self.layout.neighbours(u) for u in range(self.layout.n_units)]
        self._views = [
            LocalView(t=0.0, dt=period, x=math.nan, v=math.nan, ref=ReferenceView(),
                      neighbours=[NeighbourView(link, side, float(self.layout.offset_m[q]), age_s=0.0, valid=True)  # type: ignore[arg-type]
                                  for q, link, side in self._neighbours[u]])
            for u in range(self.layout.n_units)
        ]
        self._laws = [self.parts.law(u) for u in range(self.layout.n_units)]  # built before the run, each its own
        self._demanded = [0.0] * self.layout.n_units  # last demanded acceleration per unit
        self._applied = [0.0] * self.layout.n_units  # last commanded force per unit
        self.log = RunLog(self.layout)
        self.log.reference_change_times = self.parts.reference.change_times

    def _control(self, t: float) -> None:
        plant, ref = self.parts.plant, self.parts.reference
        x, v = plant.x.tolist(), plant.v.tolist()
        x_r, v_r, a_r = ref.state(t)
        commands = []
        for u, (view, nbrs) in enumerate(zip(self._views, self._neighbours)):
            view.t, view.x, view.v = t, x[u], v[u]
            view.ref.x, view.ref.v, view.ref.a, view.ref.age_s, view.ref.valid = x_r, v_r, a_r, 0.0, True
            for nv, (q, _, _) in zip(view.neighbours, nbrs):
                nv.x, nv.v, nv.a, nv.u = x[q], v[q], self._demanded[q], self._applied[q]
            commands.append(self._laws[u].step(view))
        for u, cmd in enumerate(commands):  # all agents decide on the same sampled state, then act
            mass = self.layout.effective_mass_kg[u]
            self._demanded[u] = cmd.accel_mps2 if math.isfinite(cmd.accel_mps2) else cmd.force_n / mass
            self._applied[u] = cmd.force_n
            plant.command(u, cmd.force_n, int(cmd.mode), t)

    def run(self, duration_s: float | None = None, progress: Callable[[float], None] | None = None,
            on_chunk: Callable[[RunLog], None] | None = None, chunk_s: float = 1.0) -> RunLog:
        """Run to ``duration_s``, calling ``on_chunk`` every ``chunk_s`` simulated seconds, as ``VirtualRig.run``
        does (incremental recording); Ctrl-C stops early and returns the log so far, ``log.interrupted`` set."""
        duration = self.sc.duration_s if duration_s is None else duration_s
        plant, ref, log = self.parts.plant, self.parts.reference, self.log
        step_ns = to_ns(self.sc.plant.step_s)
        n_steps, per_chunk = to_ns(duration) // step_ns, max(1, to_ns(chunk_s) // step_ns)
        wall0 = time.perf_counter()
        step_s = self.sc.plant.step_s
        try:
            for k in range(n_steps):
                t = k * step_s
                if k % self._control_every == 0:
                    self._control(t)
                plant_step(plant, ref, log, t, k % self._record_every == 0)
                if (k + 1) % per_chunk == 0 or k + 1 == n_steps:
                    if progress:
                        progress(plant.t)
                    if on_chunk:
                        on_chunk(log)
        except KeyboardInterrupt:
            log.interrupted = True
            log.event(plant.t, "WARN", "rig", "run interrupted (Ctrl-C)")
        log.sim_time_s = plant.t
        log.wall_time_s = time.perf_counter() - wall0
        record_violations(log, self.sc.plant.coupler_band_m)  # every safety violation on the timeline
        return log


def run_ideal(scenario: Scenario, duration_s: float | None = None, seed: int | None = None) -> RunLog:
    """Convenience: build and run the ideal loop of a scenario."""
    return IdealLoop(scenario, seed).run(duration_s)


__all__ = ["IdealLoop", "run_ideal"]
