"""Shared fixtures of the control-law tests: seed-000 plant numbers and small views built by hand."""
from __future__ import annotations

from ecu_sim.controllers.base import PlantInfo, get_controller
from ecu_sim.view import AgentInfo, LocalView, NeighbourView, ReferenceView

M = 80e3  # unit mass, kg
L = 80.0  # unit length, m
PLANT = PlantInfo(
    davis_c0=0.01176, davis_c1=0.00077616, davis_c2=1.6e-5,
    coupler_stiffness=1.6e5, coupler_damping=600.0,
    spacing_m=3000.0, emergency_gap_m=1500.0, radio_range_m=10_000.0, emergency_brake_mps2=1.2,
)


def R(v: float) -> float:
    """Davis resistance per kg, written out: c0 + c1 v + c2 v^2."""
    return 0.01176 + 0.00077616 * v + 1.6e-5 * v * v


def agent(unit: int = 0, train: int = 0, offset: float = 0.0, ref: bool | None = None, n_units: int = 4) -> AgentInfo:
    return AgentInfo(train=train, unit=unit, n_trains=3, n_units=n_units, mass_kg=M, length_m=L,
                     offset_m=offset, has_reference=(unit == 0) if ref is None else ref)


def nb(link, side, offset, x, v, valid=True, weight=1.0) -> NeighbourView:
    return NeighbourView(link=link, side=side, offset_m=offset, x=x, v=v, age_s=0.0, valid=valid, weight=weight)


def view(x, v, neighbours=(), ref=None) -> LocalView:
    return LocalView(t=0.0, dt=0.01, x=x, v=v, neighbours=list(neighbours), ref=ref or ReferenceView())


def law_params(law, **given) -> dict:
    """A law's parameters as a resolved scenario holds them: its defaults, with ``given`` on top."""
    cls = get_controller(law) if isinstance(law, str) else law
    return cls.Params(**given).model_dump(mode="json")
