"""Small helpers shared by the control laws: sig(z)^a, input checks and the emergency-gap rule.

Everything here is plain float math (``math`` module): the laws call it every cycle, so it must
cost well under a microsecond per call and allocate nothing.
"""
from __future__ import annotations

import math
from collections.abc import Iterator

from ecu_sim.controllers.base import PlantInfo
from ecu_sim.view import AgentInfo, BrakeMode, Command, LocalView, NeighbourView

_isfinite = math.isfinite
_copysign = math.copysign


def sig(z: float, a: float) -> float:
    """sig(z)^a = |z|^a sign(z) (0 at z = 0); a = 1 gives z itself."""
    return _copysign(abs(z) ** a, z) if z != 0.0 else 0.0


def check_own_state(view: LocalView) -> None:
    """Raise a clear error when the own measurement is not a finite number."""
    if not (_isfinite(view.x) and _isfinite(view.v)):
        raise ValueError(f"own measured state is not finite: x = {view.x!r}, v = {view.v!r}")


def check_neighbour(nb: NeighbourView, delta: float, dv: float) -> None:
    """Raise a clear error when a neighbour marked valid carries a non-finite position or speed."""
    if not (_isfinite(delta) and _isfinite(dv)):
        raise ValueError(f"valid {nb.link} neighbour {nb.side} has a non-finite state: x = {nb.x!r}, v = {nb.v!r}")


def usable_neighbours(view: LocalView, offset: float) -> Iterator[tuple[NeighbourView, float, float]]:
    """(neighbour, Delta = x~_q - x~_self, dv = v_q - v_self) for every valid neighbour, checked finite."""
    x, v = view.x, view.v
    for nb in view.neighbours:
        if nb.valid:
            delta, dv = (nb.x - x) + (nb.offset_m - offset), nb.v - v
            check_neighbour(nb, delta, dv)
            yield nb, delta, dv


def gap_error(nb: NeighbourView, delta: float) -> float:
    """Signed gap error s - l_s of the gap between us and an inter-train neighbour.

    ``delta`` = x~_nbr - x~_self. For the train ahead it is s - l_s; for the train behind it is
    -(s - l_s), the same gap seen from the other side.
    """
    return delta if nb.side == "ahead" else -delta


def train_ahead_too_close(view: LocalView, agent: AgentInfo, plant: PlantInfo) -> bool:
    """True when a valid radio neighbour ahead shows a gap s = l_s + (x~_q - x~_self) below l_e.

    Only the follower decides (the unit whose neighbour is ahead); its emergency brake acts
    train-wide through the train line, so the unit ahead needs no rule of its own.
    """
    limit = plant.emergency_gap_m - plant.spacing_m  # s < l_e  <=>  delta < l_e - l_s
    for nb in view.neighbours:
        if nb.valid and nb.link == "inter" and nb.side == "ahead":
            if nb.position_error_from(view.x, agent.offset_m) < limit:
                return True
    return False


def emergency_command(agent: AgentInfo, plant: PlantInfo) -> Command:
    """Emergency-brake command; the force carries the emergency deceleration for the record."""
    a = -plant.emergency_brake_mps2
    return Command(force_n=agent.mass_kg * a, mode=BrakeMode.EMERGENCY, accel_mps2=a)
