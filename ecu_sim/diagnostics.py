"""ECU diagnostics: what the firmware reports about its inputs, and the sensor plausibility check.

``EcuDiagnostics`` is a monitor (``ecu.monitors``) run after every cycle. It writes diagnostic events (the
firmware's trouble codes) into ``ecu.events``, each when a condition starts and when it clears:

* a neighbour whose data went stale (age above ``ecu.neighbour_timeout_s``) and is left out of the law;
* E2E anomalies of an input stream: CRC errors, wrong sequences, repeated frames, lost frames (alive-counter
  gaps). One event opens an episode; further anomalies within ``E2E_EPISODE_S`` extend it; its summary closes it;
* an implausible own sensor (``SensorPlausibility``): the ECU then commands the service brake and stops sending
  its AgentState (``ecu.sensor_fault``), as it does with a stale sensor, until the sensor is plausible again.

Plausibility rules (per new sensor sample k, sample period T, d samples since the last one):

* stuck: position and speed bit-identical for ``STUCK_SAMPLES`` samples in a row while |v| > 1 m/s. A moving
  unit's position changes by at least 10 mm per 10 ms sample, ten times the DBC's 1 mm resolution, so a
  healthy sensor never repeats, with or without noise;
* inconsistent: |x_k - x_{k-d} - (v_k + v_{k-d}) d T / 2| > ``JUMP_TOLERANCE_M`` in ``JUMP_COUNT`` of the last
  ``JUMP_WINDOW`` samples. The trapezoid rule is exact to (dT)^3/12 x jerk: 1 mm even for the 1e4 m/s^3 of the
  seed-000 barrier chatter, and a healthy sensor with 0.1 m noise exceeds 0.5 m once in 2500 samples.

The diagnostics are installed by ``hil.faults`` when a scenario schedules faults, so runs without faults keep
their event log as it was.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from ecu_sim.e2e import E2EStatus
from ecu_sim.runtime import Ecu

STUCK_SAMPLES = 3
STUCK_MIN_SPEED_MPS = 1.0
JUMP_TOLERANCE_M = 0.5
JUMP_COUNT, JUMP_WINDOW = 3, 10
CLEAR_SAMPLES = 100  # plausible samples in a row before a sensor fault clears (1 s at 100 Hz)
E2E_EPISODE_S = 1.0
_CRC, _WRONG, _REPEATED = E2EStatus.CRC_ERROR, E2EStatus.WRONG_SEQUENCE, E2EStatus.REPEATED
_ANOMALIES = (("CRC_ERROR", "CRC errors"), ("WRONG_SEQUENCE", "wrong sequences"), ("REPEATED", "repeated frames"),
              ("LOST", "lost frames"))


class SensorPlausibility:
    """Stuck and inconsistent-sensor checks on one unit's (x, v) samples (see the module docstring)."""

    def __init__(self, sample_period_s: float) -> None:
        self.period = sample_period_s
        self.last: tuple[int, float, float] | None = None  # counter, x, v
        self.repeats = 0
        self.jumps: deque[bool] = deque(maxlen=JUMP_WINDOW)
        self.good_run = 0
        self.fault: str | None = None  # "stuck" | "inconsistent" while the sensor is judged implausible

    def update(self, counter: int, x: float, v: float) -> str | None:
        """Take a new sample; returns the fault now in effect (None: plausible)."""
        last, self.last = self.last, (counter, x, v)
        if last is None:
            return self.fault
        c0, x0, v0 = last
        d = (counter - c0) % 16 or 16
        stuck = x == x0 and v == v0 and abs(v) > STUCK_MIN_SPEED_MPS
        self.repeats = self.repeats + 1 if stuck else 0
        residual = x - x0 - 0.5 * (v + v0) * d * self.period
        self.jumps.append(abs(residual) > JUMP_TOLERANCE_M and not stuck)
        if self.repeats >= STUCK_SAMPLES - 1:
            found = "stuck"
        elif sum(self.jumps) >= JUMP_COUNT:
            found = "inconsistent"
        else:
            found = None
        if found is not None:
            self.fault, self.good_run = found, 0
        elif self.fault is not None and not stuck and not self.jumps[-1]:
            self.good_run += 1
            if self.good_run >= CLEAR_SAMPLES:
                self.fault = None
                self.jumps.clear()
        return self.fault


@dataclass
class _Episode:
    start: float
    last: float
    base: dict[str, int]
    counts: dict[str, int] = field(default_factory=dict)


class EcuDiagnostics:
    """Diagnostic events of one ECU (see the module docstring); call it as ``monitor(ecu, t)``."""

    def __init__(self, ecu: Ecu, sample_period_s: float, neighbour_names: list[str] | None = None,
                 plant_info=None) -> None:
        self.plausibility = SensorPlausibility(sample_period_s)
        self.traction = TractionPlausibility(ecu, plant_info, sample_period_s) if plant_info is not None else None
        self.ratios: list[tuple[float, float]] = []  # (t, delivered / commanded) of every judged window
        self._sensor_counter = -1
        names = neighbour_names or [f"{nl.link} {nl.side}" for nl, _, _ in ecu._links]
        self._neighbours = list(zip(names, [False] * len(names)))
        self._had = [False] * len(names)
        self._episodes: dict[int, _Episode] = {}
        self._last_counts = {fid: self._counts(slot) for fid, slot in ecu.slots.items()}
        self._sig = {fid: sum(c.values()) for fid, c in self._last_counts.items()}

    @staticmethod
    def _counts(slot) -> dict[str, int]:
        c = slot.checker
        return {"CRC_ERROR": c.counts[E2EStatus.CRC_ERROR], "WRONG_SEQUENCE": c.counts[E2EStatus.WRONG_SEQUENCE],
                "REPEATED": c.counts[E2EStatus.REPEATED], "LOST": c.lost}

    def __call__(self, ecu: Ecu, t: float) -> None:
        self._sensor(ecu, t)
        self._stale_neighbours(ecu, t)
        self._e2e(ecu, t)
        if self.traction is not None:
            self._traction(ecu, t)

    # ---- own actuator
    def _traction(self, ecu: Ecu, t: float) -> None:
        tp = self.traction
        before = tp.ratio
        verdict = tp.update(ecu)
        if tp.ratio is not before and tp.ratio is not None:
            self.ratios.append((t, tp.ratio))
        if verdict is True:
            ecu.events.append((t, "ERROR", f"traction implausible: the unit delivered {round(tp.ratio, 2) + 0.0:.0%} of its command "
                                           f"(force balance over 2 x {tp.WINDOW_S:g} s)"))
        elif verdict is False:
            ecu.events.append((t, "INFO", f"cleared: traction implausible ({tp.ratio:.0%} delivered)"))

    # ---- own sensor
    def _sensor(self, ecu: Ecu, t: float) -> None:
        slot = ecu._sensor
        if slot.counter < 0 or slot.counter == self._sensor_counter or not slot.values:
            return
        self._sensor_counter = slot.counter
        before = self.plausibility.fault
        x, v = slot.values
        fault = self.plausibility.update(slot.counter, x, v)
        ecu.sensor_fault = fault is not None
        if fault != before:
            if fault is not None:
                what = ("frozen: position and speed repeat while moving" if fault == "stuck"
                        else "inconsistent: position steps disagree with the speed")
                ecu.events.append((t, "ERROR", f"own sensor implausible ({fault}, {what}): service brake"))
            else:
                ecu.events.append((t, "INFO", f"cleared: own sensor implausible ({before})"))

    # ---- neighbours
    def _stale_neighbours(self, ecu: Ecu, t: float) -> None:
        for k, nv in enumerate(ecu.view.neighbours):
            name, was_stale = self._neighbours[k]
            if nv.valid:
                self._had[k] = True
            stale = self._had[k] and not nv.valid
            if stale != was_stale:
                self._neighbours[k] = (name, stale)
                if stale:
                    ecu.events.append((t, "WARN", f"neighbour {name} stale (no good frame for {nv.age_s:.3f} s): "
                                                  "left out of the law"))
                else:
                    ecu.events.append((t, "INFO", f"cleared: neighbour {name} stale"))

    # ---- E2E
    def _e2e(self, ecu: Ecu, t: float) -> None:
        """Anomaly counts per stream (a cheap sum per cycle; the details only when it moved)."""
        for fid, slot in ecu.slots.items():
            c = slot.checker.counts
            sig = c[_CRC] + c[_WRONG] + c[_REPEATED] + slot.checker.lost
            if sig == self._sig[fid]:
                continue
            self._sig[fid] = sig
            now, last = self._counts(slot), self._last_counts[fid]
            ep = self._episodes.get(fid)
            if ep is None:
                grew = {k: now[k] - last[k] for k in now if now[k] > last[k]}
                ep = self._episodes[fid] = _Episode(t, t, dict(last))
                found = ", ".join(f"{n} {label}" for key, label in _ANOMALIES if (n := grew.get(key)))
                ecu.events.append((t, "WARN", f"E2E {slot.codec.name}: {found}"))
            ep.last = t
            self._last_counts[fid] = now
        for fid, ep in list(self._episodes.items()):
            if t - ep.last > E2E_EPISODE_S:
                self._close(ecu, ecu.slots[fid].codec.name, fid, ep)

    def _close(self, ecu: Ecu, stream: str, fid: int, ep: _Episode) -> None:
        del self._episodes[fid]
        now = self._last_counts[fid]
        found = ", ".join(f"{now[key] - ep.base[key]} {label}" for key, label in _ANOMALIES if now[key] > ep.base[key])
        ecu.events.append((ep.last, "INFO", f"E2E {stream}: episode over: {found} from t = {ep.start:.3f} s"))


def neighbour_names(layout, u: int) -> list[str]:
    """Readable names of unit u's neighbours, in the order of its NeighbourViews (``trainT/unitU``, as the rig's
    layout names its units)."""
    return [layout.unit_name(q) for q, _, _ in layout.neighbours(u)]


__all__ = ["EcuDiagnostics", "SensorPlausibility", "neighbour_names"]


class TractionPlausibility:
    """Force balance of one unit over windows of ``WINDOW_S``: the force its actuator delivered, estimated from
    its own speed change, the coupler forces of its intra-train neighbours (their aligned AgentState) and the
    nominal running resistance, against the mean force it commanded.

        F_est = m_eff (v_end - v_start) / W - mean(coupler forces on the unit) + mean(m_eff r(v))

    ``ratio`` = F_est / mean(F_cmd) is the actuator's apparent health; two windows in a row below ``LOW`` flag the
    actuator, one above ``HIGH`` clears it. The commanded force is taken as the TractionCmd frame carried it
    (saturated to its range). The command reaches the actuator up to ``TAU_S`` later, which moves the window's
    mean by up to |F_end - F_start| TAU_S / W (the seed-000 law flips between +-5 MN: 25 kN); windows where that
    bound exceeds a third of |mean F_cmd|, or where |mean F_cmd| < ``MIN_FORCE_N``, a brake mode was on, a
    neighbour was stale or the sensor implausible, are not judged. Assumes a flat track and no actuator envelope
    (a grade of 1 permille is 0.8 kN on 80 t; the envelope and rate limit would read as a lost force): the check
    is for scenarios like seed 000, and its event says what it estimated.
    """

    WINDOW_S = 2.0
    TAU_S = 0.01  # command-to-actuator delay bound (one ECU cycle)
    MIN_FORCE_N = 5e3
    LOW, HIGH = 0.5, 0.8  # flag below (twice in a row), clear above

    def __init__(self, ecu: Ecu, info, sample_period_s: float) -> None:
        self.m = ecu.agent.mass_kg
        self.info = info
        self.n_max = max(1, round(self.WINDOW_S / sample_period_s))
        self.k, self.d = info.coupler_stiffness, info.coupler_damping
        self.fault = False
        self.ratio: float | None = None
        self.low = 0  # judged windows in a row below LOW
        codec = ecu._out_cmd
        self.f_lo, self.f_hi = codec.limits[codec.index("Force")]  # what the TractionCmd frame can carry
        self._reset()

    def _reset(self, v: float | None = None) -> None:
        self.n, self.sum_f, self.sum_cmd, self.sum_r, self.v0 = 0, 0.0, 0.0, 0.0, v
        self.first = self.last = 0.0

    def _coupler_force(self, ecu: Ecu) -> float | None:
        """Sum of the intra-train coupler forces on the unit (None if a neighbour's state is not valid)."""
        total, view, own = 0.0, ecu.view, ecu.agent.offset_m
        for nv in view.neighbours:
            if nv.link != "intra":
                continue
            if not nv.valid:
                return None
            if nv.side == "ahead":  # e = x_front - x_rear - l_front; pulls the rear unit (us) forward
                e, de = (nv.x - view.x) - (own - nv.offset_m), nv.v - view.v
                total += self.k * e + self.d * de
            else:
                e, de = (view.x - nv.x) - (nv.offset_m - own), view.v - nv.v
                total -= self.k * e + self.d * de
        return total

    def update(self, ecu: Ecu) -> bool | None:
        """Take one cycle; returns the new verdict when it changes (True: implausible), else None."""
        cmd, v = ecu.last_command, ecu.view.v
        f = self._coupler_force(ecu) if cmd is not None and not ecu.sensor_fault else None
        if f is None or int(cmd.mode) != 0 or not math.isfinite(v):
            self._reset()
            return None
        if self.v0 is None:
            self._reset(v)
            return None
        self.n += 1
        self.sum_f += f
        self.last = min(max(cmd.force_n, self.f_lo), self.f_hi)  # the force the plant received
        if self.n == 1:
            self.first = self.last
        self.sum_cmd += self.last
        self.sum_r += self.m * self.info.resistance_per_kg(v)
        if self.n < self.n_max:
            return None
        n, window = self.n, self.n * self.WINDOW_S / self.n_max
        f_est = self.m * (v - self.v0) / window - self.sum_f / n + self.sum_r / n
        f_cmd = self.sum_cmd / n
        skew = abs(self.last - self.first) * self.TAU_S / window
        self._reset(v)
        if abs(f_cmd) < max(self.MIN_FORCE_N, 3.0 * skew):
            self.low = 0
            return None
        self.ratio = f_est / f_cmd
        self.low = self.low + 1 if self.ratio < self.LOW else 0
        if not self.fault and self.low >= 2:
            self.fault = True
            return True
        if self.fault and self.ratio > self.HIGH:
            self.fault = False
            return False
        return None
