"""Seed 000: finite-time distributed cooperative cruise law (13) for an EMU group on moving block.

Every power unit is an agent. Law (13), with Delta_q = x~_q - x~_self and dv_q = v_q - v_self:

    u^ = p1 sum_intra a_q sig(Delta_q)^a1 + p3 sum_intra a_q sig(dv_q)^a2
       + p2 sum_inter a_q sig(Delta_q)^a1 + p4 sum_inter a_q sig(dv_q)^a2
       - a_ref [mu1 sig(x~)^a1 + mu2 sig(v~)^a2] + R(v),      a2 = 2 a1 / (a1 + 1),

and the ECU sends the force u = m u^. Readings of the paper (CONTROLLERS.md, section 000) are
written down where they are used: :func:`coupler_weight`, :func:`gap_weight` and the class.
"""
from __future__ import annotations

from math import isfinite

from pydantic import Field, model_validator

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo, register
from ecu_sim.controllers.common import (
    check_own_state,
    emergency_command,
    gap_error,
    sig,
    train_ahead_too_close,
    usable_neighbours,
)
from ecu_sim.view import AgentInfo, Command, LocalView


def coupler_weight(e: float, h1: float, h2: float, delta1: float, delta2: float, w_max: float) -> float:
    """Barrier part of the intra weight as a function of the coupler displacement e (> 0 stretched).

    - near full stretch, e >= h1 - delta1:       (2 h1 delta1 - delta1^2) / (h1^2 - e^2)
    - near full compression, e <= -(h2 - delta2): delta2^2 / (h2 - |e|)^2
    - otherwise 1.
    Both branches equal 1 at their switching point (continuous) and grow without bound toward the
    band edge. The paper leaves the weight undefined at and beyond |e| = h (singular, then of the
    wrong sign), so the weight is capped at ``w_max``: min(formula, w_max) inside the band and
    w_max at or beyond its edge. This is continuous and monotone in |e|; a coupler at the cap has
    left (or almost left) the band, which the runtime and the metrics record, not the law.
    Callers pass e = Delta for the unit ahead and e = -Delta for the unit behind, so both units of
    a coupled pair use the same weight (the paper's garbled compression clause read symmetrically).
    """
    if e >= h1 - delta1:
        if e >= h1:
            return w_max
        w = (2.0 * h1 * delta1 - delta1 * delta1) / (h1 * h1 - e * e)
        return w if w < w_max else w_max
    if e <= delta2 - h2:
        room = h2 + e  # h2 - |e| (e < 0 here)
        if room <= 0.0:
            return w_max
        w = (delta2 * delta2) / (room * room)
        return w if w < w_max else w_max
    return 1.0


def gap_weight(g: float, zeta: float, beta_hat: float, gamma1: float, gamma2: float, w_max: float) -> float:
    """Inter-train weight as a function of the gap error g = s - l_s (the paper's Delta seen from the follower).

    zeta = l_s - l_e, beta_hat = beta - l_s. The paper writes the cases for the train ahead
    (Delta = g) and for the train behind (Delta = -g); both read the same in g:
    - closing side, within gamma2 of the emergency gap (g <= gamma2 - zeta, i.e. s <= l_e + gamma2):
      (2 gamma2 zeta - gamma2^2) / (zeta^2 - g^2), equal to 1 at the switching point; singular at
      s = l_e, so capped at w_max there and beyond (s <= l_e: the follower is emergency braking);
    - beyond radio range (g > beta_hat, i.e. s > beta): 0. The paper's mirror clause Delta < -beta_hat
      would be a gap below 2 l_s - beta, not a range condition, and lies in the barrier case above
      whenever beta_hat > zeta (seed 000: 7000 m vs 1500 m): it is not used;
    - near the range limit (beta_hat - gamma1 < g <= beta_hat): (beta_hat - g)/gamma1, from 1 down to 0;
    - otherwise 1.
    """
    if g <= gamma2 - zeta:
        if g <= -zeta:
            return w_max
        w = (2.0 * gamma2 * zeta - gamma2 * gamma2) / (zeta * zeta - g * g)
        return w if w < w_max else w_max
    if g > beta_hat:
        return 0.0
    if g > beta_hat - gamma1:
        return (beta_hat - g) / gamma1
    return 1.0


class FiniteTimeParams(ControllerParams):
    """Law (13) parameters; defaults are the paper's (seed 000, section 4)."""

    p1: float = Field(default=20.0, gt=0, description="intra position gain")
    p2: float = Field(default=1e-4, ge=0, description="inter (radio) position gain")
    p3: float = Field(default=10.0, ge=0, description="intra speed gain")
    p4: float = Field(default=1.0, ge=0, description="inter (radio) speed gain")
    mu1: float = Field(default=0.05, ge=0, description="pinning gain on the own position error x~")
    mu2: float = Field(default=0.1, ge=0, description="pinning gain on the own speed error v~")
    alpha1: float = Field(default=0.9, gt=0, le=1, description="position exponent (paper: 0 < a1 < 1; 1 = linear law)")
    h1: float = Field(default=0.1, gt=0, description="max coupler stretch, m")
    h2: float = Field(default=0.1, gt=0, description="max coupler compression, m")
    delta1: float = Field(default=0.05, gt=0, description="width of the stretch barrier zone, m (0 < delta1 < h1)")
    delta2: float = Field(default=0.03, gt=0, description="width of the compression barrier zone, m (0 < delta2 < h2)")
    gamma1: float = Field(default=1000.0, gt=0, description="width of the radio-range fade zone, m (0 < gamma1 < beta - l_s)")
    gamma2: float = Field(default=600.0, gt=0, description="width of the emergency-gap barrier zone, m (0 < gamma2 < l_s - l_e)")
    coupler_weight_max: float = Field(
        default=100.0, ge=1,
        description="cap of the coupler barrier weight (ours: the paper's is singular at |e| = h). "
        "100 is reached at e = 0.0996 m (stretch) and e = -0.097 m (compression) with the paper's numbers",
    )
    gap_weight_max: float = Field(
        default=100.0, ge=1,
        description="cap of the emergency-gap barrier weight (ours: the paper's is singular at s = l_e). "
        "100 is reached 4.8 m above l_e with the paper's numbers",
    )
    cancel_coupler: bool = Field(default=True, description="subtract k^/p1 from every intra weight, as the paper does")

    @model_validator(mode="after")
    def _check_bands(self) -> "FiniteTimeParams":
        if not self.delta1 < self.h1:
            raise ValueError(f"delta1 = {self.delta1} must be below h1 = {self.h1}")
        if not self.delta2 < self.h2:
            raise ValueError(f"delta2 = {self.delta2} must be below h2 = {self.h2}")
        return self


@register
class FiniteTimeCruise(Controller):
    """Finite-time distributed cruise law (13) of seed 000 for one power unit.

    Readings (see CONTROLLERS.md, section 000):
    - intra weight a = coupler_weight(e) - k^/p1 with k^ = k/m (own mass), e the coupler displacement
      of the pair (Delta for the unit ahead, -Delta for the unit behind): both units of a coupled pair
      use the same weight (same e, equal masses). The weight multiplies both the p1 and the p3 term,
      as in (13). The -k^/p1 part cancels the physical coupler k e exactly only for alpha1 = 1;
      for alpha1 < 1 it subtracts k^ sig(e)^alpha1 (as written in the paper).
    - inter weight a = gap_weight(g) with g = s - l_s (train ahead: g = Delta; train behind: g = -Delta).
    - pinning on the reference for units with ``has_reference`` (every train's head in seed 000),
      x~ = x - (x_r - offset), v~ = v - v_r; left out while the reference is not valid (the ECU
      runtime applies the service brake on a reference timeout).
    - + R(v): Davis resistance per kg (c0 + c1 v + c2 v^2) as feed-forward.
    - neighbours with ``valid = False`` are left out; ``weight`` (degraded-mode weight in [0, 1])
      multiplies all of that neighbour's terms.
    - safety: a valid radio neighbour ahead with gap s = l_s + Delta < l_e -> emergency brake.
    - sampled-time caveat (ours, measured): the weight also multiplies the p3 speed term, and a coupled
      pair's relative-speed loop has gain 2 p3 a, so a loop sampled every dt needs roughly a < 1/(p3 dt)
      (10 at dt = 10 ms, reached at e = 0.096 m stretch / -0.0905 m compression). A pair loaded by an
      extreme external force (60 m/s^2 on one unit) diverged at dt = 10 ms with the cap at 100 or 20
      and stayed bounded (outside the band) with the cap at 10. The default cap stays 100 (closest to
      the paper); lower ``coupler_weight_max`` for a guard that holds at the ECU period.
    Positions in the view are used as given: they must refer to one instant (aligning sample times
    is the runtime's job; at 90 m/s a 1 ms mismatch is 9 cm, comparable to the coupler band).
    No traction limit is applied here (the plant applies its envelope).
    """

    name = "finite_time"
    Params = FiniteTimeParams

    def __init__(self, params: FiniteTimeParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        p = params
        self._zeta = plant_info.spacing_m - plant_info.emergency_gap_m
        self._beta_hat = plant_info.radio_range_m - plant_info.spacing_m
        if not 0.0 < p.gamma1 < self._beta_hat:
            raise ValueError(f"gamma1 = {p.gamma1} must lie in (0, beta - l_s) = (0, {self._beta_hat})")
        if not 0.0 < p.gamma2 < self._zeta:
            raise ValueError(f"gamma2 = {p.gamma2} must lie in (0, l_s - l_e) = (0, {self._zeta})")
        self._a1 = p.alpha1
        self._a2 = 2.0 * p.alpha1 / (p.alpha1 + 1.0)
        self._k_over_p1 = plant_info.coupler_stiffness / agent.mass_kg / p.p1 if p.cancel_coupler else 0.0

    def intra_weight(self, e: float) -> float:
        """Full intra weight a(e) = barrier(e) - k^/p1 for a coupler displacement e."""
        p = self.params
        return coupler_weight(e, p.h1, p.h2, p.delta1, p.delta2, p.coupler_weight_max) - self._k_over_p1

    def inter_weight(self, g: float) -> float:
        """Inter weight for a gap error g = s - l_s."""
        p = self.params
        return gap_weight(g, self._zeta, self._beta_hat, p.gamma1, p.gamma2, p.gap_weight_max)

    def step(self, view: LocalView) -> Command:
        agent, plant, p = self.agent, self.plant_info, self.params
        check_own_state(view)
        if train_ahead_too_close(view, agent, plant):
            return emergency_command(agent, plant)
        a1, a2 = self._a1, self._a2
        x, v, off = view.x, view.v, agent.offset_m
        u = plant.resistance_per_kg(v)
        for nb, d, dv in usable_neighbours(view, off):
            if nb.link == "intra":
                e = d if nb.side == "ahead" else -d
                w = nb.weight * self.intra_weight(e)
                u += w * (p.p1 * sig(d, a1) + p.p3 * sig(dv, a2))
            else:
                w = nb.weight * self.inter_weight(gap_error(nb, d))
                u += w * (p.p2 * sig(d, a1) + p.p4 * sig(dv, a2))
        ref = view.ref
        if agent.has_reference and ref.valid:
            xt = x - (ref.x - off)
            vt = v - ref.v
            u -= p.mu1 * sig(xt, a1) + p.mu2 * sig(vt, a2)
        if not isfinite(u):
            raise ValueError(f"command is not finite (reference x_r = {ref.x!r}, v_r = {ref.v!r})")
        return Command(force_n=agent.mass_kg * u, accel_mps2=u)
