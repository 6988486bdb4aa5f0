"""Seed 001: distributed super-twisting sliding-mode consensus (STSMCA) for one car of a train.

With the consensus errors e_x, e_v, the degree D = sum_j a_ij + b_i and the coupler acceleration f of
:mod:`ecu_sim.controllers.chain` (whose docstring fixes the signs):

    s   = c e_x + e_v                                                   (9)
    s'  = c e_v + D v'_i - sum_j a_ij v'_j - b a_r                       (10)
    a_i = ( -c e_v + sum_j a_ij a_j + b a_r + u1 ) / D                   (11), the car's demanded acceleration
    u^  = a_i - f + omega^(v)                                                the force per kg sent to the plant
    u1  = -k1 |s|^(1/2) sgn(s) + w,    w' = -k2 sgn(s)                   (12)

so that with v'_i = u^ + f - omega^ - d^ the sliding variable obeys s' = u1 - D d^ (13): the super-twisting
integrator w absorbs the (Lipschitz part of the) disturbance. Reconstructions of the garbled formulas:

- (11) as printed puts the disturbance d^ inside the compensation bracket. No controller can know it, and
  with it the disturbances would simply vanish: it is left out. (11) also lacks the c_i e_v,i term of (10)
  (printed: e_v alone); it is restored so that (13) follows from (10), as the seed's own proof needs.
- (12) lost the exponent 1/2 of |s| (the proof's zeta = [|s|^(1/2) sgn s, w] needs it): restored.
- Signs of (6)/(11) around the coupler and the spacing term are made physical (see chain.py).

Neighbours' accelerations v'_j are what each car received last over CAN: the AgentAux frame carries a_j,
the acceleration car j's law demanded (the net closed-loop acceleration a_i above, not the force per kg,
which also holds the coupler and resistance compensation). (11) is then a distributed solve of
(L + B) a = h (h_i = -c e_v + b a_r + u1) by one Jacobi sweep per control period, run one period late:
a(k) = D^-1 (A a(k-1) + h(k)). Its iteration matrix D^-1 A has eigenvalues +-0.966 (= cos(pi/12)) on this 6-car chain
(pinned at car 1, free at car 6): an alternating mode (sign flips every period) and a slow mode, each
decaying by only 3.4 % per period. Both lag the cancellation the proof assumes; the |s|^(1/2) term (infinite
gain at s = 0) turns the lag into a sustained oscillation whose size grows with the period. Options that
change how received values are used (defaults = the law as written):

- ``accel_exchange = "last"`` (as written): the last value received;
- ``"mean2"``: the mean of this and the previous cycle's values (a zero at the Nyquist frequency: removes
  the alternation, but makes the slow mode slower);
- ``"lowpass"``: a first-order low-pass with time constant ``accel_filter_s``;
- ``"none"``: no neighbour feed-forward at all (their accelerations become a perturbation of s');
- ``accel_gain`` kappa in [0, 1]: the used sum is kappa * sum_j a_j (under-relaxation). The sweep's
  iteration matrix becomes kappa D^-1 A (spectral radius 0.966 kappa): the exchange settles in fewer periods;
  the rest, (1 - kappa) sum_j a_j, is left to the super-twisting integrator as a perturbation of s'.

The exchange order is set by the ECU schedule, not the law: with the ECU phases staggered front to back by
more than one car's transmission time (``ecu.stagger_s``), car i's cycle already has car i-1's value of the
same period (a Gauss-Seidel sweep: iteration eigenvalues in [0, 0.933 kappa^2], no alternating mode).
The ideal loop always runs the Jacobi order (every agent decides on the same sampled state).

Our remedy for slow ECU periods (docs/seed001.md) is the front-to-back schedule with kappa = 0.8, chosen by a
rule, not by fitting: the sweep's slowest mode 0.933 * 0.8^2 = 0.60 per period cuts the exchange error 10x in
4.5 periods (45 ms at 10 ms), well inside the fastest sliding time constant 1 / max(c) = 0.33 s; kappa = 1 takes
33 periods. What kappa leaves out during a ramp, (1 - kappa) * 2 * a_r = 0.08 m/s^2 on an inner car, is far
below k2 (0.8 ... 0.91), which the super-twisting integrator can absorb.

The discrete integrator is forward Euler at the ECU period (w += -k2 sgn(s) dt after u1 is formed).
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo, register
from ecu_sim.controllers.chain import ChainErrors, chain_errors, per_car
from ecu_sim.view import AgentInfo, Command, LocalView

AccelExchange = Literal["last", "mean2", "lowpass", "none"]


class ExchangeParams(ControllerParams):
    """What every equivalent-control law of seed 001 shares: resistance compensation and the use of the
    neighbours' accelerations received over CAN."""

    compensate_resistance: bool = Field(default=True, description="add the nominal Davis resistance omega^(v) (the seed's omega^)")
    accel_exchange: AccelExchange = Field(default="last", description="use of neighbours' accelerations: last | mean2 | lowpass | none")
    accel_filter_s: float = Field(default=0.05, gt=0, description="time constant of the 'lowpass' exchange filter, s")
    accel_gain: float = Field(default=1.0, ge=0, le=1, description="kappa: weight of the neighbours' accelerations (1 = as written)")


class StsmcaParams(ExchangeParams):
    """Seed 001's STSMCA gains (per car where the seed gives per-car values)."""

    c: float | list[float] = Field(default=[3.0, 1.5, 2.0, 3.0, 1.0, 1.5], description="sliding-surface slope c_i (1/s), per car")
    k1: float | list[float] = Field(default=2.0, description="super-twisting gain k1_i on |s|^(1/2), per car")
    k2: float | list[float] = Field(default=[0.8, 0.91, 0.9, 0.9, 0.88, 0.91], description="super-twisting integral gain k2_i")


def sign(z: float) -> float:
    return 1.0 if z > 0.0 else (-1.0 if z < 0.0 else 0.0)


class NeighbourAccelFilter:
    """Per-neighbour memory that turns received accelerations into the values the law uses."""

    def __init__(self, mode: AccelExchange, tau: float) -> None:
        self.mode, self.tau = mode, tau
        self._prev: list[float] = []

    def reset(self) -> None:
        self._prev = []

    def apply(self, received: list[float], dt: float) -> float:
        """Sum over neighbours of the used acceleration; NaN entries (neighbour not used) are skipped and forgotten."""
        if self.mode == "none":
            return 0.0
        if self.mode == "last":
            return sum(a for a in received if a == a)
        prev = self._prev
        if len(prev) != len(received):
            prev[:] = [math.nan] * len(received)
        total = 0.0
        alpha = dt / (self.tau + dt)
        for k, a in enumerate(received):
            if a != a:
                prev[k] = math.nan
                continue
            p = prev[k]
            if self.mode == "mean2":
                used = a if p != p else 0.5 * (a + p)
                prev[k] = a
            else:
                used = a if p != p else p + alpha * (a - p)
                prev[k] = used
            total += used
        return total


class EquivalentControlLaw(Controller):
    """The equivalent control (11) around a reaching law u1(s): shared by STSMCA and SMCA.

    Subclasses set ``self.c`` and implement :meth:`reaching`. Params must carry ``compensate_resistance``,
    ``accel_exchange``, ``accel_filter_s`` and ``accel_gain``.
    """

    def __init__(self, params: ControllerParams, agent: AgentInfo, plant_info: PlantInfo, c: float) -> None:
        super().__init__(params, agent, plant_info)
        if not c > 0:
            raise ValueError(f"c of car {agent.unit + 1} must be > 0, got {c}")
        self.c = c
        self.w = 0.0  # integral state of the reaching law (0 for laws without one)
        self.s = 0.0  # last sliding variable (for inspection and tests)
        self._errors = ChainErrors()
        self._filter = NeighbourAccelFilter(params.accel_exchange, params.accel_filter_s)  # type: ignore[attr-defined]
        self._kappa = float(params.accel_gain)  # type: ignore[attr-defined]
        self._resist = bool(params.compensate_resistance)  # type: ignore[attr-defined]

    def reset(self) -> None:
        self.w = 0.0
        self._filter.reset()

    def reaching(self, s: float, dt: float) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, view: LocalView) -> Command:
        e = chain_errors(view, self.agent, self.plant_info, self._errors)
        resist = self.plant_info.resistance_per_kg(view.v) if self._resist else 0.0
        if e.degree == 0.0:  # isolated (every input lost): hold the resistance only, leave the state alone
            return Command(force_n=self.agent.mass_kg * resist, accel_mps2=0.0)
        s = self.c * e.e_x + e.e_v
        self.s = s
        u1 = self.reaching(s, view.dt)
        a_nbrs = self._kappa * self._filter.apply(e.nbr_accels or [], view.dt)
        accel = (-self.c * e.e_v + a_nbrs + e.ref_accel + u1) / e.degree
        u = accel - e.coupler_accel + resist
        if not math.isfinite(u):
            raise ValueError(f"{self.name} command is not finite (s = {s!r}, w = {self.w!r})")
        return Command(force_n=self.agent.mass_kg * u, accel_mps2=accel)


@register
class SuperTwistingConsensus(EquivalentControlLaw):
    """STSMCA for one car (seed 001); state: the super-twisting integrator w and the exchange filter."""

    name = "stsmca"
    Params = StsmcaParams

    def __init__(self, params: StsmcaParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info, per_car(params.c, agent, "c"))
        self.k1 = per_car(params.k1, agent, "k1")
        self.k2 = per_car(params.k2, agent, "k2")
        for name, value in (("k1", self.k1), ("k2", self.k2)):
            if not value > 0:
                raise ValueError(f"{name} of car {agent.unit + 1} must be > 0, got {value}")

    def reaching(self, s: float, dt: float) -> float:
        """u1 of (12): -k1 |s|^(1/2) sgn(s) + w, then w += -k2 sgn(s) dt (forward Euler)."""
        u1 = -self.k1 * math.copysign(math.sqrt(abs(s)), s) + self.w
        self.w -= self.k2 * sign(s) * dt
        return u1
