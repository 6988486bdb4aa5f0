"""A control law from an FMU: ``controller.law = "fmu:PATH"`` (FMI 2 or 3 co-simulation), one instance per ECU.

Each cycle the law sets the FMU's mapped inputs from the LocalView, steps the FMU from its time to the end of the
cycle (``view.t + view.dt``) and reads the force (and, where mapped, the acceleration) as the cycle's Command. The
firmware around it is the same as for every law: freshness, E2E and degraded modes are the ECU runtime's, and the
input check and emergency rule (gap ahead below l_e) are applied here before the FMU is asked, as the packaged laws
apply them. A neighbour that is absent or invalid gives ``valid`` 0 and 0.0 for its numbers (never NaN).

``[controller.params]`` holds the mapping (docs/fmi.md): ``inputs`` (FMU variable -> view quantity),
``outputs.force`` / ``outputs.accel`` and ``parameters`` (FMU variable -> a number or a quantity of the unit or of
the plant, set at instantiation). ``[[ecu.units]]`` params give a unit its own mapping or numbers.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import Any, ClassVar

from pydantic import Field, field_validator

from ecu_sim.controllers.base import Controller, ControllerParams, PlantInfo
from ecu_sim.controllers.common import check_own_state, emergency_command, train_ahead_too_close
from ecu_sim.fmu import Fmu, FmuError, FmuInstance, FmuVariable, load_fmu
from ecu_sim.references import ReferenceLoadError
from ecu_sim.view import AgentInfo, Command, LocalView, NeighbourView

PREFIX = "fmu:"
SLOTS = ("intra_ahead", "intra_behind", "inter_ahead", "inter_behind")
NEIGHBOUR_FIELDS = ("x", "v", "a", "u", "valid", "weight", "offset_m", "age_s")

ViewQuantity = Callable[[LocalView, dict[str, NeighbourView]], float]


def _finite(value: float) -> float:
    return value if math.isfinite(value) else 0.0


def _neighbour_quantity(slot: str, field: str) -> ViewQuantity:
    def read(view: LocalView, slots: dict[str, NeighbourView]) -> float:
        nb = slots.get(slot)
        if nb is None or not nb.valid:
            return 0.0
        return 1.0 if field == "valid" else _finite(float(getattr(nb, field)))
    return read


VIEW_QUANTITIES: dict[str, ViewQuantity] = {
    "t": lambda view, _: view.t,
    "x": lambda view, _: view.x,
    "v": lambda view, _: view.v,
    "ref.x": lambda view, _: _finite(view.ref.x) if view.ref.valid else 0.0,
    "ref.v": lambda view, _: _finite(view.ref.v) if view.ref.valid else 0.0,
    "ref.a": lambda view, _: _finite(view.ref.a) if view.ref.valid else 0.0,
    "ref.valid": lambda view, _: 1.0 if view.ref.valid else 0.0,
    **{f"{slot}.{field}": _neighbour_quantity(slot, field) for slot in SLOTS for field in NEIGHBOUR_FIELDS},
}

def _plant_quantity(name: str) -> Callable[[AgentInfo, PlantInfo], float]:
    return lambda agent, plant: float(getattr(plant, name))


UNIT_QUANTITIES: dict[str, Callable[[AgentInfo, PlantInfo], float]] = {
    "mass_kg": lambda a, _: a.mass_kg,
    "length_m": lambda a, _: a.length_m,
    "offset_m": lambda a, _: a.offset_m,
    "has_reference": lambda a, _: float(a.has_reference),
    "train": lambda a, _: float(a.train + 1),
    "unit": lambda a, _: float(a.unit + 1),
    **{name: _plant_quantity(name) for name in PlantInfo.model_fields},
}


class FmuLawOutputs(ControllerParams):
    """FMU output variables the Command is read from."""

    force: str = Field(description="the commanded force, N (+ traction)")
    accel: str | None = Field(default=None, description="the demanded acceleration, m/s^2 (default: force / mass)")


class FmuLawParams(ControllerParams):
    """The mapping between the firmware and the FMU (docs/fmi.md)."""

    inputs: dict[str, str] = Field(default={}, description="FMU input variable -> view quantity: "
                                   + ", ".join(VIEW_QUANTITIES))
    outputs: FmuLawOutputs
    parameters: dict[str, float | str] = Field(default={}, description="FMU variable -> a number, or a quantity of "
                                               "the unit or plant: " + ", ".join(UNIT_QUANTITIES))

    @field_validator("inputs")
    @classmethod
    def _known_inputs(cls, value: dict[str, str]) -> dict[str, str]:
        for name, source in value.items():
            if source not in VIEW_QUANTITIES:
                raise ValueError(f"{name} = {source!r}: not a view quantity (known: {', '.join(VIEW_QUANTITIES)})")
        return value

    @field_validator("parameters")
    @classmethod
    def _known_parameters(cls, value: dict[str, float | str]) -> dict[str, float | str]:
        for name, source in value.items():
            if isinstance(source, str) and source not in UNIT_QUANTITIES:
                raise ValueError(f"{name} = {source!r}: not a unit or plant quantity (known: {', '.join(UNIT_QUANTITIES)})")
        return value


class FmuLaw(Controller):
    """One ECU's law stepped in an FMU instance (see the module docstring)."""

    name: ClassVar[str] = "fmu"
    Params = FmuLawParams
    fmu_path: ClassVar[str] = ""

    def __init__(self, params: FmuLawParams, agent: AgentInfo, plant_info: PlantInfo) -> None:
        super().__init__(params, agent, plant_info)
        self.fmu: Fmu = load_fmu(self.fmu_path)
        fmu, where = self.fmu, f"train {agent.train + 1} unit {agent.unit + 1}"
        self._sources = [VIEW_QUANTITIES[q] for q in params.inputs.values()]
        inputs = [fmu.variable(n, ("input",), f"controller.params.inputs ({where})") for n in params.inputs]
        outputs = [fmu.variable(params.outputs.force, ("output",), "controller.params.outputs.force")]
        if params.outputs.accel:
            outputs.append(fmu.variable(params.outputs.accel, ("output",), "controller.params.outputs.accel"))
        self._parameters: dict[FmuVariable, float] = {}
        for name, source in params.parameters.items():
            var = fmu.variable(name, ("parameter", "input"), f"controller.params.parameters ({where})")
            self._parameters[var] = UNIT_QUANTITIES[source](agent, plant_info) if isinstance(source, str) else float(source)
        self.instance: FmuInstance
        self.instance, self._give_back = fmu.acquire(self, f"law:t{agent.train + 1}u{agent.unit + 1}")
        self._in, self._out = self.instance.port(inputs), self.instance.port(outputs)
        self._started = False
        self.instance.initialize(self._parameters)  # fail at build time, not in the first cycle
        self.instance.reset()

    def step(self, view: LocalView) -> Command:
        agent = self.agent
        check_own_state(view)
        if train_ahead_too_close(view, agent, self.plant_info):
            return emergency_command(agent, self.plant_info)
        slots = {f"{nb.link}_{nb.side}": nb for nb in view.neighbours}
        self._in.write([source(view, slots) for source in self._sources])
        if not self._started:
            self.instance.initialize(self._parameters, view.t)
            self._started = True
        t = self.instance.time
        end = view.t + view.dt
        self.instance.do_step(t, end - t if end - t > 1e-12 else view.dt)
        out = self._out.read()
        bad = self._out.first_non_finite(out)
        if bad is not None:
            raise FmuError(f"{self.fmu.name}: the law's output {bad} at t = {view.t:.6f} s")
        force = float(out[0])
        accel = float(out[1]) if len(out) > 1 else force / agent.mass_kg
        return Command(force_n=force, accel_mps2=accel)

    def close(self) -> None:
        """The run is over: the FMU instance back to this process's pool (a sweep's next run reuses it)."""
        self._give_back()

    def reset(self) -> None:
        """ECU restart: the FMU instance back to its start, initialized again at the next cycle."""
        self.instance.reset()
        self._started = False


@lru_cache(maxsize=None)
def fmu_law_class(path: str) -> type[FmuLaw]:
    """The law class of the FMU at ``path`` (one class per FMU; the FMU's description is checked here)."""
    try:
        fmu = load_fmu(path)
    except FmuError as exc:
        raise ReferenceLoadError(f"{PREFIX}{path}: {exc}") from None
    attrs: dict[str, Any] = {"fmu_path": str(fmu.path), "__doc__": f"The control law of FMU {fmu.path}."}
    return type(f"FmuLaw[{fmu.name}]", (FmuLaw,), attrs)
