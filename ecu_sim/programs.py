"""ECU programs: the firmware a unit runs around its control law, chosen by name or reference.

A program is either a subclass of :class:`ecu_sim.runtime.Ecu` (built with the standard wiring) or a factory
``(setup: EcuSetup) -> Ecu``; :func:`standard_program` builds the shipped firmware, for a factory to wrap or adjust.
The scenario's ``ecu.program`` (and ``[[ecu.units]] program``) names one: ``"standard"``, a name registered with
:func:`register_program`, a name an installed package publishes in the entry-point group ``trainhil.ecu_programs``,
or a ``"package.module:QualName"`` reference (:mod:`ecu_sim.references`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ecu_sim.codec import TrainDb
from ecu_sim.controllers.base import Controller
from ecu_sim.references import PROGRAM_GROUP, ReferenceLoadError, known_names, resolve
from ecu_sim.runtime import Ecu, NeighbourLink
from ecu_sim.view import AgentInfo

STANDARD = "standard"


@dataclass(frozen=True)
class EcuSetup:
    """What the rig hands a program to build one unit's ECU: its name, agent, law, DBC, neighbours and settings."""

    name: str  # "train1/unit2/ecu": the ECU's name in events and reports
    unit: int  # flat unit index, front to back, 0-based
    agent: AgentInfo
    controller: Controller
    db: TrainDb
    links: list[NeighbourLink]
    config: Any  # the scenario's ecu section (cycle, timeouts)
    sample_period_s: float


EcuProgram = Callable[[EcuSetup], Ecu]


def wire(cls: type[Ecu], setup: EcuSetup) -> Ecu:
    """Build an ``Ecu`` (sub)class with the standard wiring."""
    return cls(setup.name, setup.agent, setup.controller, setup.db, setup.links, setup.config,
               sample_period_s=setup.sample_period_s)


def standard_program(setup: EcuSetup) -> Ecu:
    """The shipped firmware."""
    return wire(Ecu, setup)


_PROGRAMS: dict[str, EcuProgram] = {STANDARD: standard_program}
_REGISTERED: dict[str, Any] = {STANDARD: standard_program}  # what each name was registered with


def as_program(obj: Any, reference: str) -> EcuProgram:
    """An Ecu subclass or a factory as a program; anything else is an error naming the reference."""
    if isinstance(obj, type):
        if not issubclass(obj, Ecu):
            raise ReferenceLoadError(f"{reference!r} is the class {obj.__qualname__}, not a subclass of "
                                     "ecu_sim.runtime.Ecu (or a factory (setup) -> Ecu)")
        return lambda setup, cls=obj: wire(cls, setup)
    if callable(obj):
        return obj
    raise ReferenceLoadError(f"{reference!r} is {obj!r}: expected a subclass of ecu_sim.runtime.Ecu or a factory "
                             "(setup) -> Ecu")


def register_program(name: str, program: Any) -> None:
    """Make an Ecu subclass or factory available under ``name`` in this process (e.g. a program defined in a test)."""
    if _REGISTERED.get(name, program) is not program:
        raise ValueError(f"ECU program {name!r} is already registered as {_REGISTERED[name]!r}")
    _PROGRAMS[name], _REGISTERED[name] = as_program(program, name), program


def get_program(name: str) -> EcuProgram:
    """A program by registered name, published name or ``module:QualName`` reference."""
    return resolve(name, _PROGRAMS, PROGRAM_GROUP, as_program, "ECU program", "ClassOrFactory")


def known_programs() -> list[str]:
    """Registered and published program names."""
    return known_names(_PROGRAMS, PROGRAM_GROUP)
