"""Seed 004's baseline: PID tracking of each car's own X_d(t), with the same force share as the fractional law.

    F = -lambda_i (kP E + kD dE + kI int E dt)        (gains kP = 2e5, kD = 2e5, kI = 2e6, as given)

The paper names the gains only. Reading: the same per-car errors and the same Lambda^T as law (19), so both
laws command through the same distribution; the integral starts at the ECU's first cycle (trapezoid rule).
Per car, ignoring couplers and resistance, the closed loop is M s^3 + lambda^2 h rho (kD s^2 + kP s + kI) = 0
(:func:`closed_loop_poles`); :func:`sampled_spectral_radius` is the same loop sampled at the ECU period with
a zero-order hold (stable when < 1). With gains in N (SI) the continuous loop is unstable for every car of
seed 004 (Routh: kD kP lambda^2 h rho < M kI); in kN it is stable but its fast pole (~ -lambda^2 kD / M) needs
a period below ~2 M / (lambda^2 kD) once sampled (1.4 ms for seed 004's car 5, before any latency).
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from ecu_sim.controllers.base import Controller, PlantInfo, register
from ecu_sim.controllers.common import check_own_state
from ecu_sim.controllers.tracking import CarTracking, TrackingParams
from ecu_sim.view import AgentInfo, Command, LocalView


class PidParams(TrackingParams):
    """PID gains (seed 004, section 3)."""

    kp: float = Field(default=2e5, ge=0)
    kd: float = Field(default=2e5, ge=0)
    ki: float = Field(default=2e6, ge=0)


def closed_loop_poles(m_eff: float, gain: float, kp: float, kd: float, ki: float) -> np.ndarray:
    """Roots of m s^3 + gain (kd s^2 + kp s + ki), gain = lambda^2 h rho (force scale included in k*)."""
    return np.roots([m_eff, gain * kd, gain * kp, gain * ki])


def sampled_spectral_radius(m_eff: float, gain: float, kp: float, kd: float, ki: float, dt: float) -> float:
    """Largest |eigenvalue| of the per-car loop sampled every dt (ZOH force, forward-Euler integral of E)."""
    b = gain / m_eff
    u = -b * np.array([kp, kd, ki])  # acceleration per unit of [E, dE, I]
    a = np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [dt, 0.0, 1.0]])
    a[0] += 0.5 * dt * dt * u
    a[1] += dt * u
    return float(np.max(np.abs(np.linalg.eigvals(a))))


@register
class PidTracking(Controller):
    """PID on the car's own tracking error (seed 004's baseline), see the module docstring."""

    name = "pid_tracking"
    Params = PidParams

    def __init__(self, params: PidParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.car = CarTracking(self.name, params, agent, plant_info)
        self.reset()

    def reset(self) -> None:
        self.integral = 0.0
        self._e_last = math.nan
        self._t_last = math.nan

    def step(self, view: LocalView) -> Command:
        p = self.params
        check_own_state(view)
        if not view.ref.valid:
            return Command(force_n=0.0, accel_mps2=0.0)
        e, de = self.car.errors(view)
        if not math.isnan(self._e_last):
            self.integral += 0.5 * (e + self._e_last) * (view.t - self._t_last)
        self._e_last, self._t_last = e, view.t
        force = self.car.force(p.kp * e + p.kd * de + p.ki * self.integral, view)
        if not math.isfinite(force):
            raise ValueError(f"command is not finite (E = {e!r}, dE = {de!r}, integral = {self.integral!r})")
        return Command(force_n=force, accel_mps2=force / self.agent.mass_kg)
