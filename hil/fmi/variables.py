"""The variable tables of the two reference FMUs. One table per model is the single source of its value references:
build.py writes the C header (model_vars.h) and model_description.py the XML from it, so they cannot disagree."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Causality = Literal["independent", "parameter", "input", "output"]


@dataclass(frozen=True)
class VariableGroup:
    """``count`` scalar variables ``name[1..count]`` (or one ``name`` when not ``indexed``) with consecutive value
    references; ``macro`` names their first reference in C (``VR_<macro>``)."""

    name: str
    macro: str
    causality: Causality
    start: float | None
    description: str
    unit: str = ""
    count: int = 1
    indexed: bool = False

    def names(self) -> list[str]:
        """The scalar names, ``x[1]`` .. ``x[n]`` for an indexed group."""
        return [f"{self.name}[{i + 1}]" for i in range(self.count)] if self.indexed else [self.name]


@dataclass(frozen=True)
class ModelSpec:
    """One reference model: its identifier, the C file of its dynamics, C constants and the variable groups."""

    identifier: str
    source: str
    description: str
    constants: dict[str, int]
    groups: list[VariableGroup]
    step_s: float

    def scalars(self) -> list[tuple[int, str, VariableGroup]]:
        """(value reference, scalar name, group) in value-reference order."""
        named = [(name, group) for group in self.groups for name in group.names()]
        return [(vr, name, group) for vr, (name, group) in enumerate(named)]


TIME = VariableGroup("time", "TIME", "independent", None, "simulation time", "s")


def train_plant(n_trains: int, units_per_train: int) -> ModelSpec:
    """The coupled multi-unit plant for ``n_trains`` trains of ``units_per_train`` units (flat unit index 1..n,
    front to back, train by train; coupler j joins units j and j + 1 of one train, numbered train by train)."""
    n, couplers = n_trains * units_per_train, n_trains * (units_per_train - 1)

    def unit(name: str, macro: str, causality: Causality, start: float | None, description: str, unit: str) -> VariableGroup:
        return VariableGroup(name, macro, causality, start, description, unit, n, True)

    groups = [
        TIME,
        VariableGroup("k", "K", "parameter", 1.6e5, "coupler stiffness", "N/m"),
        VariableGroup("d", "D", "parameter", 600.0, "coupler damping", "N.s/m"),
        VariableGroup("substeps", "SUBSTEPS", "parameter", 1.0, "RK4 steps per communication step (a whole number)"),
        unit("m", "M", "parameter", 80_000.0, "mass", "kg"),
        unit("m_eff", "M_EFF", "parameter", 86_400.0, "effective mass (rotating masses included)", "kg"),
        unit("length", "LENGTH", "parameter", 25.0, "unit length (coupler rest length)", "m"),
        unit("c0", "C0", "parameter", 0.01176, "Davis c0", "N/kg"),
        unit("c1", "C1", "parameter", 0.00077616, "Davis c1", "N.s/(m.kg)"),
        unit("c2", "C2", "parameter", 1.6e-5, "Davis c2", "N.s2/(m2.kg)"),
        unit("x0", "X0", "parameter", 0.0, "initial front-end position", "m"),
        unit("v0", "V0", "parameter", 0.0, "initial speed", "m/s"),
        unit("F", "F", "input", 0.0, "applied traction (+) or brake (-) force", "N"),
        unit("grade", "GRADE", "input", 0.0, "grade force per kg, + uphill", "N/kg"),
        unit("curve", "CURVE", "input", 0.0, "curve resistance per kg (opposes motion)", "N/kg"),
        unit("dist", "DIST", "input", 0.0, "disturbance force", "N"),
        unit("x", "X", "output", None, "front-end position", "m"),
        unit("v", "V", "output", None, "speed", "m/s"),
        unit("a", "A", "output", None, "mean acceleration over the last step", "m/s2"),
    ]
    if couplers:
        groups.append(VariableGroup("e", "E", "output", None, "coupler displacement (+ stretched)", "m", couplers, True))
    constants = {"N_UNITS": n, "N_TRAINS": n_trains, "UNITS_PER_TRAIN": units_per_train, "N_COUPLERS": couplers}
    description = f"trainhil train plant: {n_trains} train(s) of {units_per_train} coupled units, RK4"
    return ModelSpec("train_plant", "train_plant.c", description, constants, groups, 0.001)


NEIGHBOUR_SLOTS = ("intra_ahead", "intra_behind", "inter_ahead", "inter_behind")


def consensus_law() -> ModelSpec:
    """Seed 000's ordinary consensus for one unit (the gains' defaults are ecu_sim/controllers/consensus.py's)."""
    groups = [
        TIME,
        VariableGroup("kx_intra", "KX_INTRA", "parameter", 20.0, "position gain to coupled units", "1/s2"),
        VariableGroup("kv_intra", "KV_INTRA", "parameter", 10.0, "speed gain to coupled units", "1/s"),
        VariableGroup("kx_inter", "KX_INTER", "parameter", 1e-4, "position gain to radio neighbours", "1/s2"),
        VariableGroup("kv_inter", "KV_INTER", "parameter", 1.0, "speed gain to radio neighbours", "1/s"),
        VariableGroup("kx_ref", "KX_REF", "parameter", 0.05, "pinning gain on the position error", "1/s2"),
        VariableGroup("kv_ref", "KV_REF", "parameter", 0.1, "pinning gain on the speed error", "1/s"),
        VariableGroup("k_hat", "K_HAT", "parameter", 0.0, "coupler stiffness per kg cancelled (0: none)", "1/s2"),
        VariableGroup("mass", "MASS", "parameter", 86_400.0, "effective mass of the unit", "kg"),
        VariableGroup("offset", "OFFSET", "parameter", 0.0, "own slot offset behind the reference", "m"),
        VariableGroup("has_reference", "HAS_REFERENCE", "parameter", 0.0, "1: pinned to the reference"),
        VariableGroup("c0", "C0", "parameter", 0.01176, "Davis c0 (nominal)", "N/kg"),
        VariableGroup("c1", "C1", "parameter", 0.00077616, "Davis c1 (nominal)", "N.s/(m.kg)"),
        VariableGroup("c2", "C2", "parameter", 1.6e-5, "Davis c2 (nominal)", "N.s2/(m2.kg)"),
        VariableGroup("radio_range", "RADIO_RANGE", "parameter", 1000.0, "radio range beta", "m"),
        VariableGroup("spacing", "SPACING", "parameter", 100.0, "desired gap between trains l_s", "m"),
        VariableGroup("x", "X", "input", 0.0, "own measured position", "m"),
        VariableGroup("v", "V", "input", 0.0, "own measured speed", "m/s"),
        VariableGroup("ref_x", "REF_X", "input", 0.0, "reference position", "m"),
        VariableGroup("ref_v", "REF_V", "input", 0.0, "reference speed", "m/s"),
        VariableGroup("ref_valid", "REF_VALID", "input", 0.0, "1: the reference is valid"),
    ]
    for slot in NEIGHBOUR_SLOTS:
        for field, unit, what in (("x", "m", "position"), ("v", "m/s", "speed"), ("valid", "", "1: valid"),
                                  ("weight", "", "degraded-mode weight"), ("offset", "m", "slot offset")):
            groups.append(VariableGroup(f"{slot}_{field}", f"{slot}_{field}".upper(), "input", 0.0,
                                        f"{slot.replace('_', ' ')} neighbour: {what}", unit))
    groups += [
        VariableGroup("force", "FORCE", "output", None, "commanded force", "N"),
        VariableGroup("accel", "ACCEL", "output", None, "commanded acceleration", "m/s2"),
    ]
    return ModelSpec("consensus_law", "consensus_law.c", "trainhil consensus law (seed 000 baseline), one unit",
                     {}, groups, 0.01)
