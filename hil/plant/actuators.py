"""Traction/brake actuators of every unit: held commands, envelope, rate limit, brake modes, fail-safe.

Commands are zero-order held. In ``NORMAL`` mode the commanded force is applied; with
``limits.enabled`` it is first clipped to the envelope ``-max_brake <= F <= min(max_traction,
max_power / v)`` and the applied force follows at most ``rate_limit`` N/s; the braking part
(F < 0) is then scaled by ``clip(v / V_STOP, -1, 1)`` because a friction brake opposes motion and
cannot drive a unit backwards from standstill. With limits disabled the command passes unchanged.

Actuator chain (seed 004's plant, off by default): before the envelope the NORMAL-mode command F becomes

    F_act = lambda (h rho Q(F) + nu)

lambda = ``plant.actuator.distribution`` (the unit's share of its commanded force), rho = the actuator slope,
Q = the input nonlinearity (F realised in notches of ``notch_step_n``: rho Q(F) = rho F + Delta(F) with
|Delta| <= rho notch / 2), h = the health factor (1 healthy, 0 no force) and nu = a bounded fault offset.
h and nu follow a per-unit schedule of steps and linear ramps, from ``[[plant.actuator_faults]]`` or from
:meth:`Actuators.set_health` / :meth:`Actuators.set_fault_offset` at run time. The ECU never sees h or nu:
only their effect on the motion. Service and emergency brakes (fail-safe, train line) bypass the chain.
With no chain configured the command goes to the envelope exactly as before (bit-identical runs).
The fade is viscous, not static friction: on a grade steeper than c0 / g a braked unit creeps
back at v = V_STOP (g grade - c0) / a_brake (1.5 cm/s at 20 permille under the emergency brake).

``SERVICE`` and ``EMERGENCY`` apply ``-m_eff * deceleration`` (times the same standstill factor)
and bypass the envelope and the rate limit. ``EMERGENCY`` commanded by any unit brakes every unit of
its train (train line). Per unit, commands older than ``failsafe.hold_s`` give the service brake
and older than ``failsafe.emergency_after_s`` the emergency brake (that unit only). Brake levels are
only re-evaluated when a command changes something or a fail-safe deadline passes, so the per-step
cost is a handful of vector operations.
"""
from __future__ import annotations

import math

import numpy as np

from ecu_sim.view import BrakeMode
from hil.scenario.layout import TrainLayout
from hil.plant.units import UnitParams, unit_params
from hil.scenario.model import PlantConfig

V_STOP = 0.1  # m/s: brake force fades linearly to zero below this speed (no driving backwards)
_clip = np.clip if not hasattr(np, "_core") else np._core.umath.clip  # the ufunc: 2.5x faster than np.clip
_LEVELS = {0: "normal", 1: "service brake", 2: "emergency brake"}


class _Schedule:
    """One unit's health or fault offset over time: pieces (start, value at start, slope), steps and ramps."""

    def __init__(self, base: float) -> None:
        self.pieces: list[tuple[float, float, float]] = [(-math.inf, base, 0.0)]

    def _piece(self, t: float) -> tuple[float, float, float]:
        for p in reversed(self.pieces):
            if p[0] <= t:
                return p
        return self.pieces[0]

    def value(self, t: float) -> float:
        start, v, slope = self._piece(t)
        return v if slope == 0.0 else v + slope * (t - start)

    def ramping(self, t: float) -> bool:
        return self._piece(t)[2] != 0.0

    def next_change(self, t: float) -> float:
        return min((p[0] for p in self.pieces if p[0] > t), default=math.inf)

    def add(self, start: float, target: float, ramp: float) -> float:
        """From ``start`` go to ``target`` (linearly over ``ramp`` s); later pieces are replaced. Returns the value at start."""
        v0 = self.value(start)
        self.pieces = [p for p in self.pieces if p[0] < start]
        if ramp > 0.0:
            self.pieces += [(start, v0, (target - v0) / ramp), (start + ramp, target, 0.0)]
        else:
            self.pieces.append((start, target, 0.0))
        return v0


class Actuators:
    """Per-unit actuator state; :meth:`apply` gives the force of the coming step."""

    def __init__(self, plant: PlantConfig, layout: TrainLayout, dt: float, t0: float = 0.0,
                 units: UnitParams | None = None) -> None:
        n = layout.n_units
        self._layout = layout
        lim, fs = plant.limits, plant.failsafe
        self._limited = lim.enabled
        self._power, self._max_brake = lim.max_power_w, lim.max_brake_n
        self._v_base = lim.max_power_w / lim.max_traction_n  # below it the traction cap is max_traction
        self._max_step = lim.rate_limit_n_per_s * dt
        self._hold, self._emergency_after = fs.hold_s, fs.emergency_after_s
        # brake force per level (0 normal, 1 service, 2 emergency) before the standstill factor
        self._brake_table = -np.outer([0.0, fs.service_brake_mps2, fs.emergency_brake_mps2], layout.effective_mass_kg)
        self.force_cmd = np.zeros(n)
        self.mode_cmd = np.zeros(n, dtype=int)
        self.last_cmd_t = np.full(n, float(t0))
        self.force_applied = np.zeros(n)
        self.level = np.zeros(n, dtype=int)  # effective brake level per unit
        self.events: list[tuple[float, str, str]] = []
        self._drive = np.zeros(n)  # rate-limited actuator force (limits enabled)
        self._failsafe = np.zeros(n, dtype=int)  # fail-safe level per unit
        self._train_emergency = np.zeros(layout.n_trains, dtype=bool)
        self._override = np.zeros(n, dtype=bool)  # unit under service/emergency brake
        self._any_override = False
        self._brake = np.zeros(n)  # brake force of the overridden units
        self._next_check = -math.inf  # next time a fail-safe level can change
        self._tmp = np.empty(n)
        self._scale = np.empty(n)
        self._init_chain(plant, units if units is not None else unit_params(layout, plant))

    # ------------------------------------------------------------------ actuator chain (lambda, rho, Q, h, nu)

    def _init_chain(self, plant: PlantConfig, units: UnitParams) -> None:
        n = self._layout.n_units
        self._lam, self._rho = units.distribution, units.slope
        self._notch = plant.actuator.notch_step_n
        self.health = np.ones(n)  # h per unit (a plant fault: never on CAN)
        self.fault_offset = np.zeros(n)  # nu per unit, N
        self._health_sched: dict[int, _Schedule] = {}
        self._offset_sched: dict[int, _Schedule] = {}
        self._notices: list[tuple[float, str]] = []  # (time, text) of scheduled fault changes, logged when reached
        self._chain = units.actuator_shaped or self._notch > 0.0
        self._chain_dirty = True
        self._next_fault_t = math.inf
        self._eff = np.zeros(n)  # shaped NORMAL-mode force
        for i, f in enumerate(plant.actuator_faults):
            u = self._layout.index(f.train - 1, f.unit - 1)
            if f.health is not None:
                self.set_health(u, f.health, f.start_s, f.ramp_s)
            if f.offset_n is not None:
                self.set_fault_offset(u, f.offset_n, f.start_s, f.ramp_s)

    def set_health(self, u: int, health: float, at_s: float, ramp_s: float = 0.0) -> None:
        """Unit u's actuator health goes to ``health`` at ``at_s`` (linearly over ``ramp_s`` from its value then).

        Later changes of the same unit replace what the schedule held after their start. Examples:
        degradation to 60 % over 10 s from t = 300 s: ``set_health(u, 0.6, 300.0, 10.0)``; total traction
        loss of a car at t = 500 s: ``set_health(u, 0.0, 500.0)``; repair: ``set_health(u, 1.0, t)``.
        A time already passed takes effect at the next step, as if the change had started at ``at_s``.
        """
        self._check_fault(u, "health", health, at_s, ramp_s)
        if not 0.0 <= health <= 1.0:
            raise ValueError(f"health {health!r} for {self.unit_name(u)} must lie in [0, 1] (1 = healthy)")
        v0 = self._health_sched.setdefault(u, _Schedule(1.0)).add(at_s, health, ramp_s)
        self._schedule_notice(at_s, f"{self.unit_name(u)}: actuator health {v0:.3g} -> {health:.3g}"
                              + (f" over {ramp_s:g} s" if ramp_s > 0 else ""))

    def set_fault_offset(self, u: int, offset_n: float, at_s: float, ramp_s: float = 0.0) -> None:
        """Unit u's bounded fault offset nu goes to ``offset_n`` N at ``at_s`` (linearly over ``ramp_s``)."""
        self._check_fault(u, "offset_n", offset_n, at_s, ramp_s)
        v0 = self._offset_sched.setdefault(u, _Schedule(0.0)).add(at_s, offset_n, ramp_s)
        self._schedule_notice(at_s, f"{self.unit_name(u)}: actuator fault offset {v0:.6g} -> {offset_n:.6g} N"
                              + (f" over {ramp_s:g} s" if ramp_s > 0 else ""))

    def _check_fault(self, u: int, what: str, value: float, at_s: float, ramp_s: float) -> None:
        if not 0 <= u < self._layout.n_units:
            raise IndexError(f"unit index {u} out of range 0..{self._layout.n_units - 1}")
        for name, x in ((what, value), ("at_s", at_s), ("ramp_s", ramp_s)):
            if not (isinstance(x, (int, float)) and math.isfinite(x)):
                raise ValueError(f"{name} = {x!r} for {self.unit_name(u)} must be a finite number")
        if at_s < 0 or ramp_s < 0:
            raise ValueError(f"at_s = {at_s} and ramp_s = {ramp_s} for {self.unit_name(u)} must be >= 0")

    def _schedule_notice(self, at_s: float, text: str) -> None:
        self._notices.append((at_s, text))
        self._notices.sort(key=lambda item: item[0])
        self._chain = True
        self._next_fault_t = -math.inf  # re-evaluate at the next step

    def _update_faults(self, t: float) -> None:
        """Health and offsets at t; the next time they can change (every step while one ramps)."""
        nxt = math.inf
        for sched, out in ((self._health_sched, self.health), (self._offset_sched, self.fault_offset)):
            for u, s in sched.items():
                out[u] = s.value(t)
                nxt = -math.inf if s.ramping(t) else min(nxt, s.next_change(t))
        while self._notices and self._notices[0][0] <= t:
            self.events.append((t, "WARN", self._notices.pop(0)[1]))
        if self._notices:
            nxt = min(nxt, self._notices[0][0])
        self._next_fault_t = nxt
        self._chain_dirty = True

    def _shaped_command(self, t: float) -> np.ndarray:
        """lambda (h rho Q(F) + nu) of the held commands, recomputed only when an input changed."""
        if t >= self._next_fault_t:
            self._update_faults(t)
        if self._chain_dirty:
            eff = self._eff
            if self._notch > 0.0:
                np.divide(self.force_cmd, self._notch, out=eff)
                np.round(eff, out=eff)
                np.multiply(eff, self._notch, out=eff)
            else:
                eff[:] = self.force_cmd
            np.multiply(eff, self._rho, out=eff)
            np.multiply(eff, self.health, out=eff)
            np.add(eff, self.fault_offset, out=eff)
            np.multiply(eff, self._lam, out=eff)
            self._chain_dirty = False
        return self._eff

    # ------------------------------------------------------------------ commands

    def command(self, u: int, force_n: float, mode: int, t: float) -> None:
        """Store the command of unit u (held until the next one) and its arrival time."""
        self._chain_dirty = True
        if mode == self.mode_cmd[u] and self._failsafe[u] == 0:
            self.force_cmd[u] = force_n
            self.last_cmd_t[u] = t
            return
        if mode not in _LEVELS:
            raise ValueError(f"mode {mode!r} for {self.unit_name(u)} is not a BrakeMode (0, 1, 2)")
        self.force_cmd[u] = force_n
        self.mode_cmd[u] = mode
        self.last_cmd_t[u] = t
        self._next_check = -math.inf  # re-evaluate the brake levels at the next step

    def unit_name(self, u: int) -> str:
        train, unit = self._layout.train_unit(u)
        return f"train {train + 1} unit {unit + 1} (#{u})"

    # ------------------------------------------------------------------ per step

    def apply(self, t: float, v: np.ndarray) -> np.ndarray:
        """Force (N) each unit's actuator applies over the step starting at t; returns ``force_applied``."""
        if t >= self._next_check:
            self._relevel(t)
        out = self.force_applied
        cmd = self._shaped_command(t) if self._chain else self.force_cmd
        if self._limited:
            self._limited_force(v, out, cmd)
        else:
            out[:] = cmd
        if self._any_override:
            s = self._standstill_factor(v)
            np.multiply(self._brake, s, out=s)
            np.copyto(out, s, where=self._override)
        return out

    def _limited_force(self, v: np.ndarray, out: np.ndarray, cmd: np.ndarray) -> None:
        """Envelope, rate limit and standstill fade of the NORMAL-mode force ``cmd``."""
        cap, drive = self._tmp, self._drive
        np.maximum(v, self._v_base, out=cap)
        np.divide(self._power, cap, out=cap)  # = min(max_traction, P / v)
        _clip(cmd, -self._max_brake, cap, out=cap)  # target force
        np.subtract(cap, drive, out=cap)
        _clip(cap, -self._max_step, self._max_step, out=cap)
        np.add(drive, cap, out=drive)
        out[:] = drive
        if v.min() < V_STOP:  # only near standstill: fade the braking part
            s = self._standstill_factor(v)
            np.minimum(drive, 0.0, out=cap)
            np.multiply(cap, s, out=cap)
            np.maximum(drive, 0.0, out=out)
            np.add(out, cap, out=out)

    def _standstill_factor(self, v: np.ndarray) -> np.ndarray:
        """clip(v / V_STOP, -1, 1): a brake opposes motion and vanishes at standstill."""
        s = self._scale
        np.multiply(v, 1.0 / V_STOP, out=s)
        return _clip(s, -1.0, 1.0, out=s)

    # ------------------------------------------------------------------ brake levels

    def _relevel(self, t: float) -> None:
        """Recompute fail-safe and train-line levels, log the transitions, schedule the next check."""
        lay = self._layout
        age = t - self.last_cmd_t
        failsafe = np.where(age > self._emergency_after, 2, np.where(age > self._hold, 1, 0))
        train_em = (self.mode_cmd == BrakeMode.EMERGENCY).reshape(lay.n_trains, lay.units_per_train).any(axis=1)
        self._log_failsafe(t, failsafe)
        self._log_train_line(t, train_em)
        level = np.maximum(self.mode_cmd, failsafe)
        level[np.repeat(train_em, lay.units_per_train)] = 2
        released = (self.level > 0) & (level == 0)
        self._drive[released] = self.force_applied[released]  # ramp on from the brake force
        self.level[:] = level
        self._failsafe[:] = failsafe
        self._train_emergency[:] = train_em
        self._override[:] = level > 0
        self._any_override = bool(self._override.any())
        self._brake[:] = self._brake_table[level, np.arange(len(level))]
        first = min(self._hold, self._emergency_after)
        deadline = np.where(failsafe == 0, first, np.where(failsafe == 1, self._emergency_after, np.inf))
        self._next_check = float(np.min(self.last_cmd_t + deadline))

    def _log_failsafe(self, t: float, failsafe: np.ndarray) -> None:
        for u in np.flatnonzero(failsafe != self._failsafe):
            old, new = int(self._failsafe[u]), int(failsafe[u])
            age = t - self.last_cmd_t[u]
            name = self.unit_name(int(u))
            if new == 0:
                self.events.append((t, "INFO", f"{name}: commands resumed, fail-safe {_LEVELS[old]} released"))
            elif new == 1:
                self.events.append((t, "WARN", f"{name}: no command for {age:.3f} s, fail-safe service brake"))
            else:
                self.events.append((t, "ERROR", f"{name}: no command for {age:.3f} s, fail-safe emergency brake"))

    def _log_train_line(self, t: float, train_em: np.ndarray) -> None:
        lay = self._layout
        for i in np.flatnonzero(train_em != self._train_emergency):
            if train_em[i]:
                first = lay.index(int(i), 0)
                block = self.mode_cmd[first : first + lay.units_per_train]
                who = ", ".join(self.unit_name(first + int(j)) for j in np.flatnonzero(block == BrakeMode.EMERGENCY))
                self.events.append((t, "ERROR", f"train {i + 1}: emergency brake on the train line (commanded by {who})"))
            else:
                self.events.append((t, "INFO", f"train {i + 1}: train-line emergency brake released"))
