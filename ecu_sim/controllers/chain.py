"""Seed 001's consensus errors for one car of a single-train chain, shared by STSMCA, SMCA, PIDCA and CCA.

Seed 001 (one train of n cars, chain topology a_ij = 1 for |i - j| = 1, only car 1 pinned, b_1 = 1):

    e_x,i = sum_j a_ij (x_i - x_j - l (j - i)) + b_i (x_i - x_0)      (8)
    e_v,i = sum_j a_ij (v_i - v_j)             + b_i (v_i - v_0)

Positions decrease along the train (car 1 in front, l = 81 m), so x_i - x_j - l (j - i) is zero at
81 m spacing for both neighbours (j = i + 1: x_i - x_{i+1} - l; j = i - 1: x_i - x_{i-1} + l); the
``+ l (j - i)`` of the seed's (6) is a garble. In slot errors x~ = x - (x_r - offset) this is
x~_i - x~_j = -Delta_j (Delta_j = x~_j - x~_i, as the ECU computes it), and x_i - x_0 = x~_i for the
head (x_0 = x_r, offset 0). The physical coupler acceleration on car i (the seed's f_i, with its sign
made physical: a stretched coupler pulls the front car back and the rear car forward) is

    f_i = k^ sum_j a_ij Delta_j + lambda^ sum_j a_ij (v_j - v_i),    k^ = k/m, lambda^ = d/m.

Only coupled neighbours of the same train count (seed 001 has one train; radio neighbours are ignored).
An invalid neighbour (timed out) drops out of the sums and of D_i = sum_j a_ij + b_i, and so does the
reference while it is stale. Neighbours' accelerations come from their AgentAux frames (NaN until the first
one arrives: then 0 is used).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ecu_sim.controllers.base import PlantInfo
from ecu_sim.controllers.common import check_neighbour, check_own_state
from ecu_sim.view import AgentInfo, LocalView


@dataclass(slots=True)
class ChainErrors:
    """One cycle's consensus quantities of one car (see the module docstring)."""

    e_x: float = 0.0  # position consensus error, m
    e_v: float = 0.0  # speed consensus error, m/s
    degree: float = 0.0  # D_i = sum_j a_ij + b_i over the neighbours/reference that are valid now
    coupler_accel: float = 0.0  # f_i, m/s^2 (estimated from neighbours' states)
    nbr_accels: list[float] | None = None  # a_j per entry of view.neighbours (as received); NaN where not used
    ref_accel: float = 0.0  # b_i a_r (0 when not pinned)
    pinned: bool = False  # the reference entered this cycle


def chain_errors(view: LocalView, agent: AgentInfo, plant: PlantInfo, out: ChainErrors) -> ChainErrors:
    """Fill ``out`` with e_x, e_v, D, f and the neighbours' accelerations of this cycle (no allocation but the list)."""
    check_own_state(view)
    k_hat, lam_hat = plant.coupler_stiffness / agent.mass_kg, plant.coupler_damping / agent.mass_kg
    e_x = e_v = f = 0.0
    degree = 0.0
    accels = out.nbr_accels
    if accels is None or len(accels) != len(view.neighbours):
        accels = [math.nan] * len(view.neighbours)
    x, v, offset = view.x, view.v, agent.offset_m
    for k, nb in enumerate(view.neighbours):
        accels[k] = math.nan
        if not nb.valid or nb.link != "intra":
            continue
        delta, dv = (nb.x - x) + (nb.offset_m - offset), nb.v - v
        check_neighbour(nb, delta, dv)
        e_x -= delta
        e_v -= dv
        f += k_hat * delta + lam_hat * dv
        degree += 1.0
        accels[k] = nb.a if math.isfinite(nb.a) else 0.0
    ref = view.ref
    out.pinned = agent.has_reference and ref.valid
    out.ref_accel = 0.0
    if out.pinned:
        e_x += view.x - (ref.x - agent.offset_m)
        e_v += view.v - ref.v
        degree += 1.0
        out.ref_accel = ref.a if math.isfinite(ref.a) else 0.0
    out.e_x, out.e_v, out.degree, out.coupler_accel, out.nbr_accels = e_x, e_v, degree, f, accels
    return out


def per_car(value: float | list[float], agent: AgentInfo, name: str) -> float:
    """A gain given for every car (a scalar) or per car (a list indexed by the car's position in the train)."""
    if isinstance(value, (int, float)):
        return float(value)
    if len(value) != agent.n_units:
        raise ValueError(f"{name} has {len(value)} values, but the train has {agent.n_units} cars")
    return float(value[agent.unit])
