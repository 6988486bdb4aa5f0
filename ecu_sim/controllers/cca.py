"""Seed 001 baseline CCA: common (linear) consensus on seed 001's consensus errors.

    u^ = -(kx e_x + kv e_v) + b a_r + omega^(v)

i.e. u^ = sum_j a_ij [kx (x~_j - x~_i) + kv (v_j - v_i)] - b [kx x~ + kv v~] + b a_r + omega^(v), with e_x, e_v of
:mod:`ecu_sim.controllers.chain`. The seed says its CCA parameters are "the same as ref. [22]" and prints
none; ours are kx = 1 1/s^2, kv = 2 1/s (per mode lambda of L + B the loop is s^2 + kv lambda s + kx lambda,
critically damped at lambda = 1; the slowest, collective mode of this chain, lambda_min = 0.058, then has
omega = 0.24 rad/s and damping 0.24). The physical couplers are not cancelled (a plain consensus); the Davis
resistance and, for the pinned car, a_r are fed forward as in the other seed-001 laws. Any worst-error
comparison with this baseline is a comparison at these chosen gains.
The AgentAux acceleration is the law's demand without the resistance term.
"""
from __future__ import annotations

import math

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo, register
from ecu_sim.controllers.chain import ChainErrors, chain_errors, per_car
from ecu_sim.view import AgentInfo, Command, LocalView


class CcaParams(ControllerParams):
    """Linear consensus gains (ours: the seed prints none)."""

    kx: float | list[float] = Field(default=1.0, ge=0, description="gain on the position consensus error e_x (1/s^2)")
    kv: float | list[float] = Field(default=2.0, ge=0, description="gain on the speed consensus error e_v (1/s)")
    compensate_resistance: bool = Field(default=True, description="add the nominal Davis resistance omega^(v)")
    feedforward_reference: bool = Field(default=True, description="pinned car adds the reference acceleration a_r")


@register
class CommonConsensus(Controller):
    """CCA for one car (seed 001 baseline); stateless."""

    name = "cca"
    Params = CcaParams

    def __init__(self, params: CcaParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.kx, self.kv = per_car(params.kx, agent, "kx"), per_car(params.kv, agent, "kv")
        self._errors = ChainErrors()

    def step(self, view: LocalView) -> Command:
        e = chain_errors(view, self.agent, self.plant_info, self._errors)
        accel = -(self.kx * e.e_x + self.kv * e.e_v)
        if self.params.feedforward_reference:
            accel += e.ref_accel
        u = accel + (self.plant_info.resistance_per_kg(view.v) if self.params.compensate_resistance else 0.0)
        if not math.isfinite(u):
            raise ValueError(f"cca command is not finite (e_x = {e.e_x!r}, e_v = {e.e_v!r})")
        return Command(force_n=self.agent.mass_kg * u, accel_mps2=accel)
