"""Seed 001 baseline SMCA: first-order sliding-mode consensus, "derived from (11)" in the seed.

The same sliding variable s = c e_x + e_v and the same equivalent control as STSMCA
(:class:`~ecu_sim.controllers.stsmca.EquivalentControlLaw`, whose docstring gives the reconstruction of
(11)), with the reaching law replaced by the classical discontinuous one:

    u1 = -k sgn(s),      so that  s' = -k sgn(s) - D d^.

The seed gives c = diag{1, ..., 1} and b = diag{1, 0, ..., 0} but no switching gain k: ours is k = 2 m/s^2
(per unit of s'), STSMCA's k1, so both laws have the same nominal authority. It rejects any matched
disturbance with D |d^| < k exactly (in continuous time); in discrete time at the ECU period dt the sign
term chatters: s jumps by about k dt / D every cycle.
"""
from __future__ import annotations

from pydantic import Field

from ecu_sim.controllers.base import PlantInfo, register
from ecu_sim.controllers.chain import per_car
from ecu_sim.controllers.stsmca import EquivalentControlLaw, ExchangeParams, sign
from ecu_sim.view import AgentInfo


class SmcaParams(ExchangeParams):
    """SMCA gains: the seed's c = 1; k is ours (see the module docstring)."""

    c: float | list[float] = Field(default=1.0, description="sliding-surface slope c_i (1/s), scalar or per car")
    k: float | list[float] = Field(default=2.0, description="switching gain k_i (ours: the seed gives none)")


@register
class SlidingModeConsensus(EquivalentControlLaw):
    """SMCA for one car (seed 001 baseline): stateless reaching law, the exchange filter's memory only."""

    name = "smca"
    Params = SmcaParams

    def __init__(self, params: SmcaParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info, per_car(params.c, agent, "c"))
        self.k = per_car(params.k, agent, "k")
        if not self.k > 0:
            raise ValueError(f"k of car {agent.unit + 1} must be > 0, got {self.k}")

    def reaching(self, s: float, dt: float) -> float:
        """u1 = -k sgn(s)."""
        return -self.k * sign(s)
