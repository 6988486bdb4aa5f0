"""Seed 002's second comparison law: safe-range potential cruise in the style of Li, Yang and Gao (2015).

Li, Yang, Gao, "Coordinated cruise control for high-speed train movements based on a multi-agent model"
(Transp. Res. C 2015) write the control as u_i = u_bar_i + u1 + u2 + u3 with u_bar_i = m (c0 + c1 v_r + c2 v_r^2)
the nominal force at the reference speed, u1 = m alpha sum a_ij (v_j - v_i) (speed consensus),
u2 = -m beta sum a_ij grad U_ij (a potential on the distance) and u3 = -m k (v_i - v_r) (pinning; the
sign that makes it stable). Seed 002 describes their spacing as held inside "uniformly set safety
distance bounds", with no distance regulation inside them ("即便期望速度发生切换,相邻列车之间仍无需进行
距离调节操作"). Neither the potential nor the gains are given; ours (per kg):

    u^ = R(v_r) + grade/curve(x) + alpha sum_j (v_j - v) - k (v - v_r) + sum_j s_j F(d_j)
    F(d) = beta (d - d_hi) above d_hi, beta (d - d_lo) below d_lo, 0 inside [d_lo, d_hi]

- a flat-bottomed potential: no force while the head-to-head distance d is inside the safe range
  [d_lo, d_hi] = [d_r, d_r + ``band_m``], linear walls outside (s_j = +1 ahead, -1 behind);
- ``band_m`` = 1500 m (ours: half the potential law's 3 km scale; the seed gives no bounds);
- beta = 1/3000 s^-2 (the fixed-spacing law's spring), alpha = k = 0.05 1/s (the potential law's speed gains);
- resistance compensated at v_r as in Li et al.'s u_bar (the own-speed difference is left to feedback).
"""
from __future__ import annotations

import math

from pydantic import Field

from ecu_sim.controllers.base import register
from ecu_sim.controllers.common import check_own_state, emergency_command, train_ahead_too_close
from ecu_sim.controllers.multi_train import MultiTrainLaw, MultiTrainParams, gap_terms
from ecu_sim.view import Command, LocalView


def wall_force(g: float, band_m: float, beta: float) -> float:
    """Gradient force of the flat-bottomed potential for a gap error g = d - d_r: 0 on [0, band], linear outside."""
    if g > band_m:
        return beta * (g - band_m)
    if g < 0.0:
        return beta * g
    return 0.0


class SafeRangeParams(MultiTrainParams):
    """Gains and safe range of the Li/Yang/Gao-style law (ours: the seed gives none)."""

    alpha: float = Field(default=0.05, ge=0, description="speed consensus with neighbours (1/s)")
    k: float = Field(default=0.05, ge=0, description="own speed error to v_r (1/s)")
    beta: float = Field(default=1.0 / 3000.0, ge=0, description="stiffness of the potential's walls (1/s^2)")
    band_m: float = Field(default=1500.0, gt=0, description="width of the safe range above d_r (m)")


@register
class SafeRange(MultiTrainLaw):
    """Safe-range potential cruise (Li/Yang/Gao 2015 style) for one train."""

    name = "safe_range"
    Params = SafeRangeParams

    def step(self, view: LocalView) -> Command:
        agent, p = self.agent, self.params
        check_own_state(view)
        if p.emergency_rule and train_ahead_too_close(view, agent, self.plant_info):
            return emergency_command(agent, self.plant_info)
        v, ref = view.v, view.ref
        pinned = agent.has_reference and ref.valid
        v_nominal = ref.v if pinned else v
        u = self.plant_info.resistance_per_kg(v_nominal) + self.line.resistance_per_kg(view.x, v)
        for nb, g, dv in gap_terms(view, agent.offset_m):
            f = wall_force(g, p.band_m, p.beta)
            u += nb.weight * ((f if nb.side == "ahead" else -f) + p.alpha * dv)
        if pinned:
            u -= p.k * (v - ref.v)
        if not math.isfinite(u):
            raise ValueError(f"command is not finite (v = {v!r}, v_r = {ref.v!r})")
        return Command(force_n=agent.mass_kg * u, accel_mps2=u)
