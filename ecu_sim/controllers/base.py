"""The controller contract: one small interface for every control law.

A controller is built once per agent with its parameters and the agent's static info; each
cycle it gets a :class:`~ecu_sim.view.LocalView` and returns a :class:`~ecu_sim.view.Command`.
State (integrators, observers, fractional memories) lives inside the controller object.
"""
from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict

from ecu_sim.references import LAW_GROUP, FirmwareBuildError, ReferenceLoadError, known_names, one_line, resolve
from ecu_sim.view import AgentInfo, Command, LocalView


class ControllerParams(BaseModel):
    """Base of every law's parameter model: unknown keys are errors, and so are values of the wrong kind
    (strict: ``p1 = true`` or ``p1 = "20"`` is not read as a number; an integer is a float)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class Controller(ABC):
    """A control law for one agent."""

    #: name used in scenario files (``[controller] law = "..."``)
    name: ClassVar[str]
    #: pydantic model of the law's parameters
    Params: ClassVar[type[ControllerParams]]

    def __init__(self, params: ControllerParams, agent: AgentInfo, plant_info: "PlantInfo") -> None:
        self.params = params
        self.agent = agent
        self.plant_info = plant_info

    @abstractmethod
    def step(self, view: LocalView) -> Command:
        """Compute this cycle's command from the local view."""

    def reset(self) -> None:
        """Forget internal state (ECU restart). Stateless laws need not override."""

    def close(self) -> None:
        """The run is over: give back what the law holds outside Python (an FMU instance). Most laws hold nothing."""


class PlantInfo(BaseModel):
    """Model knowledge a law may use (nominal values, as the firmware would be configured)."""

    model_config = ConfigDict(frozen=True)

    davis_c0: float  # N/kg
    davis_c1: float  # N*s/(m*kg)
    davis_c2: float  # N*s^2/(m^2*kg)
    coupler_stiffness: float  # N/m
    coupler_damping: float  # N*s/m
    spacing_m: float  # l_s, desired gap between trains
    emergency_gap_m: float  # l_e
    radio_range_m: float  # beta
    emergency_brake_mps2: float

    def resistance_per_kg(self, v: float) -> float:
        """Davis running resistance per kg at speed v (m/s), opposing motion for v >= 0."""
        return self.davis_c0 + self.davis_c1 * v + self.davis_c2 * v * v


_REGISTRY: dict[str, type[Controller]] = {}


def register(cls: type[Controller]) -> type[Controller]:
    """Class decorator: make a law available to scenarios under ``cls.name``."""
    if cls.name in _REGISTRY:
        raise ValueError(f"controller {cls.name!r} registered twice")
    _REGISTRY[cls.name] = cls
    return cls


def get_controller(name: str) -> type[Controller]:
    """A law by registered name, by a name an installed package publishes (entry-point group
    ``trainhil.controllers``), by a ``"package.module:QualName"`` reference, or an FMU's (``"fmu:PATH"``). The error
    lists the known names or says why the reference does not load."""
    import ecu_sim.controllers  # noqa: F401  (imports every law module, filling the registry)

    if name.startswith("fmu:"):
        from ecu_sim.controllers.fmu_law import fmu_law_class

        return fmu_law_class(name.removeprefix("fmu:"))

    return resolve(name, _REGISTRY, LAW_GROUP, _check_law, "controller law", "ClassName")


def _check_law(obj: object, reference: str) -> type[Controller]:
    """A loaded object is a law: a Controller subclass with its Params model."""
    if not (isinstance(obj, type) and issubclass(obj, Controller)):
        raise ReferenceLoadError(f"{reference!r} is {obj!r}, not a subclass of ecu_sim.controllers.base.Controller")
    if inspect.isabstract(obj):
        missing = ", ".join(sorted(obj.__abstractmethods__))
        raise ReferenceLoadError(f"{reference!r}: {obj.__qualname__} does not define {missing} (a law needs "
                                 "step(view) -> Command)")
    params = getattr(obj, "Params", None)
    if not (isinstance(params, type) and issubclass(params, BaseModel)):
        raise ReferenceLoadError(f"{reference!r}: {obj.__qualname__} has no `Params` (its ControllerParams model)")
    return obj


def known_controllers() -> list[str]:
    """Registered and published law names."""
    import ecu_sim.controllers  # noqa: F401

    return known_names(_REGISTRY, LAW_GROUP)


def build_controller(name: str, params: dict[str, Any], agent: AgentInfo, plant_info: PlantInfo) -> Controller:
    """Validate ``params`` against the law's model and build one controller."""
    cls = get_controller(name)
    p = cls.Params(**params)
    try:
        return cls(p, agent, plant_info)
    except Exception as exc:  # the user's __init__ raised: one line naming the law, not a traceback
        raise FirmwareBuildError(f"{name!r}: building the law for train {agent.train + 1} unit {agent.unit + 1} failed: {one_line(exc)}") from None
