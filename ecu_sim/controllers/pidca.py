"""Seed 001 baseline PIDCA: PID consensus on the combined consensus error e = e_x + e_v (the seed's (26)).

    e  = e_x + e_v                        (e_x, e_v of :mod:`ecu_sim.controllers.chain`: > 0 when ahead of the slot / too fast)
    u^ = -(kP e + kI integral(e) dt + kD de/dt) + b a_r + omega^(v)

with the seed's kP = 10, kI = 15, kD = 0.1. The seed takes the law from its ref. [23] and does not print it;
our reading is the textbook PID on the consensus error, the physical couplers not cancelled, plus the nominal
Davis resistance and, for the pinned car, the reference acceleration a_r (both known to the firmware, as in
the other three laws; either can be switched off). Discretisation at the ECU period dt: the integral by
forward Euler (after the output), de/dt as the backward difference of e (0 on the first cycle and after a
reset), so the quantised speeds of the CAN frames (0.5 mm/s) reach the derivative term as
kD * 0.5e-3 / dt (0.01 m/s^2 at 5 ms).

The independent check in CONTROLLERS.md found this chain barely stable under these gains (a lightly damped
mode), and divergent with the couplers cancelled: hence no coupler cancellation here.
The AgentAux acceleration is the law's demand without the resistance term: -(PID) + b a_r.
"""
from __future__ import annotations

import math

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo, register
from ecu_sim.controllers.chain import ChainErrors, chain_errors, per_car
from ecu_sim.view import AgentInfo, Command, LocalView


class PidcaParams(ControllerParams):
    """The seed's PID gains (scalar or per car)."""

    kp: float | list[float] = Field(default=10.0, description="proportional gain on e = e_x + e_v (1/s^2 on e_x)")
    ki: float | list[float] = Field(default=15.0, description="integral gain")
    kd: float | list[float] = Field(default=0.1, description="derivative gain")
    compensate_resistance: bool = Field(default=True, description="add the nominal Davis resistance omega^(v)")
    feedforward_reference: bool = Field(default=True, description="pinned car adds the reference acceleration a_r")


@register
class PidConsensus(Controller):
    """PIDCA for one car (seed 001 baseline); state: the integral of e and the previous e."""

    name = "pidca"
    Params = PidcaParams

    def __init__(self, params: PidcaParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.kp, self.ki, self.kd = (per_car(getattr(params, n), agent, n) for n in ("kp", "ki", "kd"))
        for name in ("kp", "ki", "kd"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} of car {agent.unit + 1} must be >= 0, got {getattr(self, name)}")
        self._errors = ChainErrors()
        self.integral = 0.0
        self._prev: float | None = None

    def reset(self) -> None:
        self.integral, self._prev = 0.0, None

    def step(self, view: LocalView) -> Command:
        e = chain_errors(view, self.agent, self.plant_info, self._errors)
        err = e.e_x + e.e_v
        deriv = 0.0 if self._prev is None else (err - self._prev) / view.dt
        self._prev = err
        accel = -(self.kp * err + self.ki * self.integral + self.kd * deriv)
        if self.params.feedforward_reference:
            accel += e.ref_accel
        self.integral += err * view.dt
        u = accel + (self.plant_info.resistance_per_kg(view.v) if self.params.compensate_resistance else 0.0)
        if not math.isfinite(u):
            raise ValueError(f"pidca command is not finite (e = {err!r}, integral = {self.integral!r})")
        return Command(force_n=self.agent.mass_kg * u, accel_mps2=accel)
