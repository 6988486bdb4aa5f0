"""Baseline: ordinary (linear) consensus on position and speed errors plus resistance compensation.

The "ordinary consensus" of seed 000's comparison (Li, Yang, Gao 2015 style):

    u^ = sum_q a_q [kx (x~_q - x~_self) + kv (v_q - v_self)] - a_ref [kx0 x~ + kv0 v~] + R(v)

with separate (kx, kv) for coupled units (intra) and radio neighbours (inter). The paper gives
no gains. Defaults are the linear counterpart of the finite-time law's gains (the same numbers
with alpha = 1): intra kx = p1 = 20, kv = p3 = 10; inter kx = p2 = 1e-4, kv = p4 = 1; pinning
kx0 = mu1 = 0.05, kv0 = mu2 = 0.1. The settling time of this baseline depends entirely on these
gains, so any comparison of settling times is a comparison at these chosen gains.
"""
from __future__ import annotations

from math import isfinite

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo, register
from ecu_sim.controllers.common import (
    check_own_state,
    emergency_command,
    gap_error,
    train_ahead_too_close,
    usable_neighbours,
)
from ecu_sim.view import AgentInfo, Command, LocalView


class ConsensusParams(ControllerParams):
    """Gains of the linear consensus (ours: the paper gives none; see the module docstring)."""

    kx_intra: float = Field(default=20.0, ge=0, description="position gain to coupled units (1/s^2; = p1)")
    kv_intra: float = Field(default=10.0, ge=0, description="speed gain to coupled units (1/s; = p3)")
    kx_inter: float = Field(default=1e-4, ge=0, description="position gain to radio neighbours (1/s^2; = p2)")
    kv_inter: float = Field(default=1.0, ge=0, description="speed gain to radio neighbours (1/s; = p4)")
    kx_ref: float = Field(default=0.05, ge=0, description="pinning gain on the own position error x~ (1/s^2; = mu1)")
    kv_ref: float = Field(default=0.1, ge=0, description="pinning gain on the own speed error v~ (1/s; = mu2)")
    cancel_coupler: bool = Field(
        default=False,
        description="add -k^ e for each coupler (k^ = k/m), cancelling the physical coupler as the finite-time law does",
    )


@register
class OrdinaryConsensus(Controller):
    """Linear consensus for one power unit (seed 000's "ordinary consensus" baseline).

    Adjacency: a_q = 1 for a valid coupled unit; for a radio neighbour a_q = 1 while the gap is
    within radio range (s <= beta, i.e. gap error <= beta - l_s), else 0. Each neighbour's terms
    are multiplied by its degraded-mode ``weight``; invalid neighbours are left out. Pinning for
    units with ``has_reference`` while the reference is valid. The physical coupler is not cancelled
    unless ``cancel_coupler``. Same emergency rule as the finite-time law (gap ahead below l_e).
    """

    name = "consensus"
    Params = ConsensusParams

    def __init__(self, params: ConsensusParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self._k_hat = plant_info.coupler_stiffness / agent.mass_kg if params.cancel_coupler else 0.0
        self._beta_hat = plant_info.radio_range_m - plant_info.spacing_m

    def step(self, view: LocalView) -> Command:
        agent, plant, p = self.agent, self.plant_info, self.params
        check_own_state(view)
        if train_ahead_too_close(view, agent, plant):
            return emergency_command(agent, plant)
        x, v, off = view.x, view.v, agent.offset_m
        u = plant.resistance_per_kg(v)
        for nb, d, dv in usable_neighbours(view, off):
            if nb.link == "intra":
                u += nb.weight * ((p.kx_intra - self._k_hat) * d + p.kv_intra * dv)
            elif gap_error(nb, d) <= self._beta_hat:
                u += nb.weight * (p.kx_inter * d + p.kv_inter * dv)
        ref = view.ref
        if agent.has_reference and ref.valid:
            u -= p.kx_ref * (x - (ref.x - off)) + p.kv_ref * (v - ref.v)
        if not isfinite(u):
            raise ValueError(f"command is not finite (reference x_r = {ref.x!r}, v_r = {ref.v!r})")
        return Command(force_n=agent.mass_kg * u, accel_mps2=u)
