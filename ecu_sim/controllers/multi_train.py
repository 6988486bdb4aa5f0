"""What the single-mass multi-train laws (seeds 002 and 003) share: feed-forward, gap errors, parameters.

Each train is one agent (``trains.units = 1``); its neighbours are the trains ahead and behind, heard
over radio. With ``x~ = x - (x_r - offset)`` the slot error, a neighbour's ``Delta = x~_nbr - x~_self``
is the error of the gap between the two trains: for the train ahead Delta = d - d_r, for the train behind
Delta = -(d - d_r), where d is the head-to-head distance x_ahead - x_behind (the papers' point-mass
d_ij) and d_r = l_s + the length of the train ahead. :func:`gap_terms` yields that gap error g seen the
same way from both trains (g > 0: the gap is too long).
"""
from __future__ import annotations

from collections.abc import Iterator

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo
from ecu_sim.controllers.common import usable_neighbours
from ecu_sim.line_map import LineMap
from ecu_sim.view import AgentInfo, LocalView, NeighbourView
from ecu_sim.track import TrackConfig


class MultiTrainParams(ControllerParams):
    """Options every single-mass multi-train law has."""

    line_map: TrackConfig = Field(
        default=TrackConfig(),
        description="the firmware's line database (grades, curves) for grade/curve feed-forward; empty = flat line. "
        "Packaged scenarios copy their [track] here",
    )
    emergency_rule: bool = Field(default=True, description="emergency brake when the gap ahead falls below l_e (the rig's safety rule)")


class MultiTrainLaw(Controller):
    """Base of the single-mass train laws: feed-forward of running, grade and curve resistance."""

    def __init__(self, params: MultiTrainParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.line = LineMap(params.line_map)

    def feed_forward(self, x: float, v: float) -> float:
        """Davis resistance at v plus grade and curve resistance at x, per kg (cancels the nominal plant's)."""
        return self.plant_info.resistance_per_kg(v) + self.line.resistance_per_kg(x, v)


def gap_terms(view: LocalView, offset: float) -> Iterator[tuple[NeighbourView, float, float]]:
    """(neighbour, g, dv) for every valid neighbour: g = gap error d - d_r of the pair, dv = v_nbr - v_self."""
    for nb, delta, dv in usable_neighbours(view, offset):
        yield nb, (delta if nb.side == "ahead" else -delta), dv
