"""Seed 002's first comparison law: fixed-spacing cooperative cruise in the style of Bai et al. (2019).

Seed 002 compares with Bai, Lin, Dong et al., "Distributed cooperative cruise control of multiple
high-speed trains under a state-dependent information transmission topology" (IEEE T-ITS 2019) but
gives neither its formula nor its gains. Ours keeps that paper's two defining features and otherwise
the seed-002 law's structure, so the comparison isolates the spacing term:

    u^ = kx sum_j s_j g_j + kv sum_j (v_j - v) - kr (v - v_r) + R(v) + grade/curve(x)

- fixed spacing: a linear spring on every gap error g = d - d_r, s_j = +1 for the train ahead and -1
  for the train behind (the same pair force sign as the potential law), so every gap is driven to d_r
  exactly and stays there whatever v_r does;
- state-dependent topology: a neighbour counts only while the gap is within radio range (d - d_r <= beta - l_s),
  on top of the radio's own range cut.
Gains (ours): kx = 1/3000 s^-2 (1 m/s^2 at a 3 km gap error: the potential law's full-scale force at
its 3 km scale, but unbounded and linear), kv = kr = 0.05 1/s (the potential law's k2 and k2 alpha).
Same feed-forward and emergency rule as the potential law.
"""
from __future__ import annotations

import math

from pydantic import Field

from ecu_sim.controllers.base import PlantInfo, register
from ecu_sim.controllers.common import check_own_state, emergency_command, train_ahead_too_close
from ecu_sim.controllers.multi_train import MultiTrainLaw, MultiTrainParams, gap_terms
from ecu_sim.view import AgentInfo, Command, LocalView


class FixedSpacingParams(MultiTrainParams):
    """Gains of the fixed-spacing law (ours: the seed gives none)."""

    kx: float = Field(default=1.0 / 3000.0, ge=0, description="spring on the gap error (1/s^2)")
    kv: float = Field(default=0.05, ge=0, description="speed consensus with neighbours (1/s)")
    kr: float = Field(default=0.05, ge=0, description="own speed error to v_r (1/s)")


@register
class FixedSpacing(MultiTrainLaw):
    """Fixed-spacing cooperative cruise (Bai et al. 2019 style) for one train."""

    name = "fixed_spacing"
    Params = FixedSpacingParams

    def __init__(self, params: FixedSpacingParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self._in_range = plant_info.radio_range_m - plant_info.spacing_m  # g above this: beyond radio range

    def step(self, view: LocalView) -> Command:
        agent, p = self.agent, self.params
        check_own_state(view)
        if p.emergency_rule and train_ahead_too_close(view, agent, self.plant_info):
            return emergency_command(agent, self.plant_info)
        v, ref = view.v, view.ref
        u = self.feed_forward(view.x, v)
        for nb, g, dv in gap_terms(view, agent.offset_m):
            if g > self._in_range:
                continue
            spring = p.kx * g
            u += nb.weight * ((spring if nb.side == "ahead" else -spring) + p.kv * dv)
        if agent.has_reference and ref.valid:
            u -= p.kr * (v - ref.v)
        if not math.isfinite(u):
            raise ValueError(f"command is not finite (v = {v!r}, v_r = {ref.v!r})")
        return Command(force_n=agent.mass_kg * u, accel_mps2=u)
