"""What seed 004's per-car tracking laws share: the car's own desired state, its force share and units.

Every car's ECU tracks X_d(t) = x_r(t) - offset (offset = lengths of the cars ahead), from the wayside
Reference/ReferenceAux frames (x_r, v_r, a_r): E = x - X_d, dE = v - v_r. The paper's laws end in
F = -Lambda^T (...): the ECU multiplies by its own entry lambda_i of the traction/brake distribution
(a design constant it is configured with) and the plant applies lambda_i h_i rho_i F again.

Units (the paper gives none): ``force_unit = "N"`` reads the gains as written in newtons; ``"kN"``
multiplies every force by 1000 (CONTROLLERS.md, section 004: only this reading holds the bands).
``gain_scale`` (OURS) multiplies by any other factor, e.g. one chosen from the sampled-loop bound
lambda^2 c1 scale dt / M < 2 (seed004-ours.toml).

Feed-forward (``feedforward = true``) is OURS, not the paper's: m (a_r + R(v_r)) / lambda_i with the
firmware's one nominal mass (AgentInfo.mass_kg: effective mass from [trains]; using it for the resistance
too overestimates that by the rotating-mass factor, ~10 %) and nominal resistance (PlantInfo, from [plant]
davis_*; none at v_r = 0). It never sees the drawn masses, the per-car resistance or the health factors.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from ecu_sim.controllers.base import ControllerParams, PlantInfo
from ecu_sim.view import AgentInfo, LocalView

CRH5A_DISTRIBUTION = (0.5, 0.3, 0.5, 0.3, 0.6, 0.4, 0.6, 0.4)  # seed 004's Lambda (5 motor, 3 trailer cars)
FORCE_SCALE = {"N": 1.0, "kN": 1000.0}


class TrackingParams(ControllerParams):
    """Parameters common to seed 004's laws."""

    distribution: list[float] = Field(default=list(CRH5A_DISTRIBUTION), min_length=1,
                                      description="lambda per car of a train (the ECU uses its own)")
    force_unit: Literal["N", "kN"] = Field(default="N", description="unit the gains are read in")
    feedforward: bool = Field(default=False, description="OURS: add m (a_r + R(v_r)) / lambda (nominal model)")
    gain_scale: float | None = Field(default=None, gt=0, description="OURS: multiply the law's force by this "
                                     "instead of force_unit's 1 (N) or 1000 (kN)")

    @model_validator(mode="after")
    def _check_distribution(self) -> "TrackingParams":
        if not all(0.0 < lam <= 1.0 for lam in self.distribution):
            raise ValueError(f"distribution values must lie in (0, 1], got {self.distribution}")
        return self


class CarTracking:
    """One car's desired state and force conversion, built from the law's parameters and the agent info."""

    def __init__(self, law: str, params: TrackingParams, agent: AgentInfo, plant: PlantInfo) -> None:
        if not agent.has_reference:
            raise ValueError(f"law {law!r} needs the reference on every car: set trains.reference_units = \"all\" "
                             f"(train {agent.train + 1} unit {agent.unit + 1} does not receive it)")
        if agent.unit >= len(params.distribution):
            raise ValueError(f"law {law!r}: distribution has {len(params.distribution)} values, "
                             f"no entry for unit {agent.unit + 1}")
        self.lam = params.distribution[agent.unit]
        self.scale = FORCE_SCALE[params.force_unit] if params.gain_scale is None else params.gain_scale
        self.feedforward = params.feedforward
        self.offset = agent.offset_m
        self.mass = agent.mass_kg
        self.plant = plant

    def errors(self, view: LocalView) -> tuple[float, float]:
        """(E, dE) = (x - (x_r - offset), v - v_r) from the own sensor and the last reference."""
        ref = view.ref
        e, de = view.x - (ref.x - self.offset), view.v - ref.v
        if not (math.isfinite(e) and math.isfinite(de)):
            raise ValueError(f"tracking error is not finite: x = {view.x!r}, v = {view.v!r}, x_r = {ref.x!r}, v_r = {ref.v!r}")
        return e, de

    def force(self, control: float, view: LocalView) -> float:
        """-lambda * control in newtons (the law's bracket), plus our feed-forward when enabled."""
        f = -self.lam * control * self.scale
        if self.feedforward:
            v_r = view.ref.v
            resistance = self.plant.resistance_per_kg(v_r) if v_r > 0.0 else 0.0  # none at standstill
            f += self.mass * (view.ref.a + resistance) / self.lam
        return f
