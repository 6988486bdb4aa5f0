"""Seed 004: fractional-order finite-time tracking law with an RBF-network adaptive gain, one car per ECU.

Per car i (scalars; the paper writes the vector form), E = x - X_d, dE = v - v_r (tracking.py):

    S0 = dE + g1 E + g2 phi(E),   phi(E) = sig(E)^nu if |E| >= eps, else E^2 sign(E)          (2)
    S  = S0 + g3 I^r[S0] + g4 I^r[sig(S0)^nu]       (Riemann-Liouville integral from the ECU's start) (8)
    F  = -lambda_i (k S + eta sig(S)^nu)                                                       (19)
    k  = c1 + c2 rho^ (1 + Phi)^2                                                                 (20)
    d rho^/dt = -c3 rho^ + c2 (1 + Phi)^2 S^2,    rho^(0) = 0                                     (21)
    Phi = || [phi_1 .. phi_10] ||,  phi_j = exp(-sum_q (z_q - c_j)^2 / (2 b^2)),  z = [x, X_d]

Readings (the paper is silent or garbled here; CONTROLLERS.md section 004):
- (2)'s small-error branch "E^T E sign(E)" is read per car as E^2 sign(E); eps is not given: 1 mm by default
  (the sensor's resolution on CAN). phi jumps at |E| = eps (eps^nu vs eps^2), as written.
- ||S||^2 in (21) couples all cars; each ECU only has its own S, so each car adapts its own rho^ with S_i^2.
- z = [x, X_d] in metres as written (``rbf_origin = "absolute"``): with the centres in [-0.4, 0.5] m every
  phi_j is 0 away from the track's origin, so Phi = 0 and k = c1 + c2 rho^. ``rbf_origin = "start"`` measures
  both from the car's first measured position instead (then Phi is ~2.6 at the start and 0 after a few metres).
- I^r is :class:`ecu_sim.fractional.FractionalIntegral` at the ECU period (product trapezoid, bounded memory).
  A missed cycle (the runtime braked on a stale sensor) holds the last S0 for the missing samples.
- rho^ is integrated exactly for the held input over each period: rho^ <- e^{-c3 dt} rho^ + (1 - e^{-c3 dt}) u / c3.
- Gains as written are in N (``force_unit = "N"``) or kN (``"kN"``); feed-forward is ours (tracking.py).
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from ecu_sim.controllers.base import Controller, PlantInfo, register
from ecu_sim.controllers.common import check_own_state, sig
from ecu_sim.controllers.tracking import CarTracking, TrackingParams
from ecu_sim.fractional import FractionalIntegral
from ecu_sim.view import AgentInfo, Command, LocalView

PAPER_CENTRES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, -0.1, -0.2, -0.3, -0.4)


class FractionalParams(TrackingParams):
    """Law (19)-(21) parameters; defaults are the paper's (seed 004, section 3) unless marked ours."""

    r: float = Field(default=4.0 / 9.0, gt=0, lt=1, description="order of the fractional integral")
    nu: float = Field(default=0.8, gt=0, lt=1, description="power of sig()")
    c1: float = Field(default=2e5, gt=0)
    c2: float = Field(default=10.0, ge=0, description="adaptive part of k (0 switches the RBF/adaptive term off)")
    c3: float = Field(default=0.01, gt=0, description="leakage of rho^")
    eta: float = Field(default=2e5, ge=0)
    gamma1: float = Field(default=0.1, gt=0)
    gamma2: float = Field(default=0.1, gt=0)
    gamma3: float = Field(default=1.0, ge=0)
    gamma4: float = Field(default=1.0, ge=0)
    epsilon: float = Field(default=1e-3, gt=0, description="ours (not given): |E| below which phi(E) = E^2 sign(E), m")
    rbf_centres: list[float] = Field(default=list(PAPER_CENTRES), min_length=1)
    rbf_width: float = Field(default=math.sqrt(2.0) / 2.0, gt=0, description="b of every Gaussian")
    rbf_origin: Literal["absolute", "start"] = Field(default="absolute", description="z = [x, X_d] as written, or both measured from the car's first position")
    memory_window: int = Field(default=16, ge=1, description="exact local steps of the fractional integral")


@register
class FractionalFiniteTime(Controller):
    """Fractional-order finite-time tracking of the car's own X_d(t) (seed 004), see the module docstring."""

    name = "fractional_finite_time"
    Params = FractionalParams

    def __init__(self, params: FractionalParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.car = CarTracking(self.name, params, agent, plant_info)
        self._centres = np.asarray(params.rbf_centres, dtype=float)
        self._inv_2b2 = 1.0 / (2.0 * params.rbf_width**2)
        self._span = (float(self._centres.min()), float(self._centres.max()))
        self.reset()

    def reset(self) -> None:
        self._integral: FractionalIntegral | None = None  # built at the first cycle (needs the period)
        self._pair = np.zeros(2)  # [S0, sig(S0)^nu] fed to the integral
        self._t_last = math.nan
        self.rho_hat = 0.0
        self._origin = math.nan
        self.stats = {"phi_max": 0.0, "k_over_c1_max": 1.0, "s_abs_max": 0.0}  # for reports (RBF term's effect)

    def phi(self, x: float, x_d: float) -> float:
        """Phi = || RBF layer || at z = [x, X_d] (relative to the origin chosen by ``rbf_origin``)."""
        z1, z2 = x - self._origin, x_d - self._origin
        lo, hi = self._span
        for z in (z1, z2):  # far from every centre each exp(-...) underflows to 0.0: skip the vector work
            gap = lo - z if z < lo else z - hi
            if gap > 0.0 and 2.0 * self._inv_2b2 * gap * gap > 746.0:
                return 0.0
        d2 = (z1 - self._centres) ** 2 + (z2 - self._centres) ** 2
        return float(np.sqrt(np.sum(np.exp(-2.0 * self._inv_2b2 * d2))))  # sqrt(sum phi_j^2)

    def s0(self, e: float, de: float) -> float:
        """Filtered error (2)."""
        p = self.params
        small = abs(e) < p.epsilon
        return de + p.gamma1 * e + p.gamma2 * (e * e * math.copysign(1.0, e) if small else sig(e, p.nu))

    def _integrate(self, s0: float, t: float, dt: float) -> np.ndarray:
        """I^r of [S0, sig(S0)^nu] at t; missed cycles hold the last sample."""
        p = self.params
        if self._integral is None:
            self._integral = FractionalIntegral(p.r, dt, window=p.memory_window, channels=2)
        else:
            missed = round((t - self._t_last) / dt) - 1
            for _ in range(min(max(missed, 0), 10_000)):
                self._integral.update(self._pair)
        self._t_last = t
        self._pair[0], self._pair[1] = s0, sig(s0, p.nu)
        return self._integral.update(self._pair)

    def step(self, view: LocalView) -> Command:
        p = self.params
        check_own_state(view)
        if not view.ref.valid:  # the runtime brakes on a stale reference; nothing to track meanwhile
            return Command(force_n=0.0, accel_mps2=0.0)
        e, de = self.car.errors(view)
        if math.isnan(self._origin):
            self._origin = view.x if p.rbf_origin == "start" else 0.0
        s0 = self.s0(e, de)
        i_s0, i_sig = self._integrate(s0, view.t, view.dt).tolist()
        s = s0 + p.gamma3 * i_s0 + p.gamma4 * i_sig
        ph = self.phi(view.x, view.ref.x - self.car.offset)
        w = (1.0 + ph) ** 2
        k = p.c1 + p.c2 * self.rho_hat * w
        force = self.car.force(k * s + p.eta * sig(s, p.nu), view)
        decay = math.exp(-p.c3 * view.dt)
        self.rho_hat = decay * self.rho_hat + (1.0 - decay) / p.c3 * p.c2 * w * s * s
        st = self.stats
        if ph > st["phi_max"]:
            st["phi_max"] = ph
        if k > st["k_over_c1_max"] * p.c1:
            st["k_over_c1_max"] = k / p.c1
        if abs(s) > st["s_abs_max"]:
            st["s_abs_max"] = abs(s)
        if not math.isfinite(force):
            raise ValueError(f"command is not finite (S = {s!r}, k = {k!r})")
        return Command(force_n=force, accel_mps2=force / self.agent.mass_kg)
