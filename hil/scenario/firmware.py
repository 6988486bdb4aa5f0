"""Which firmware each unit runs, as the scenario says it: its law (name or reference) and parameters, its ECU
program, or nothing (an external unit); and the check that every one of them loads and validates, which the
loader runs so that a bad one is an error of the scenario file. Building them is the runtimes' (hil/runtime/firmware.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from ecu_sim.controllers.base import get_controller
from ecu_sim.programs import get_program
from ecu_sim.references import ReferenceLoadError
from hil.scenario.layout import TrainLayout
from hil.scenario.model import Scenario


@dataclass(frozen=True)
class UnitFirmware:
    """What one unit runs: its law (name or reference) and parameters, its ECU program, or nothing (external)."""

    law: str
    params: dict[str, Any]
    program: str
    external: bool = False


def firmware_plan(sc: Scenario) -> list[UnitFirmware]:
    """Per flat unit index: the scenario's law and program, with the ``[[ecu.units]]`` overrides applied.

    An override with another law and no ``params`` gets that law's defaults, not the scenario law's parameters."""
    layout = TrainLayout.from_config(sc.trains)
    plan = [UnitFirmware(sc.controller.law, dict(sc.controller.params), sc.ecu.program)] * layout.n_units
    for o in sc.ecu.units:
        law = o.law or sc.controller.law
        params = o.params if o.params is not None else (dict(sc.controller.params) if law == sc.controller.law else {})
        plan[layout.unit_index(o.unit)] = UnitFirmware(law, dict(params), o.program or sc.ecu.program)
    for name in sc.ecu.external:
        u = layout.unit_index(name)
        plan[u] = UnitFirmware(plan[u].law, plan[u].params, plan[u].program, external=True)
    return plan


def firmware_errors(sc: Scenario) -> list[str]:
    """``field: why`` for every law, parameter set and program of the scenario that does not load or validate
    (each distinct one is checked once, under the first field that names it)."""
    fields = [("controller.law", "controller.params", sc.controller.law, sc.controller.params, "ecu.program",
               sc.ecu.program)]
    for i, (o, f) in enumerate(zip(sc.ecu.units, _override_plans(sc))):
        fields.append((f"ecu.units.{i}.law", f"ecu.units.{i}.params", f.law, f.params, f"ecu.units.{i}.program",
                       f.program))
    errors: list[str] = []
    programs_seen: set[str] = set()
    for law_field, params_field, law, params, program_field, program in fields:
        try:
            cls = get_controller(law)
        except LookupError as exc:
            errors.append(f"{law_field}: {exc.args[0]}")
        else:
            try:
                cls.Params(**params)
            except ValidationError as exc:
                errors += [f"{params_field}.{'.'.join(str(p) for p in e['loc'])}: {e['msg']} (got {e.get('input')!r})"
                           for e in exc.errors()]
        if program not in programs_seen:
            programs_seen.add(program)
            try:
                get_program(program)
            except ReferenceLoadError as exc:
                errors.append(f"{program_field}: {exc.args[0]}")
    return errors


def _override_plans(sc: Scenario) -> list[UnitFirmware]:
    """The firmware of each ``[[ecu.units]]`` entry, in order."""
    plan = firmware_plan(sc)
    layout = TrainLayout.from_config(sc.trains)
    return [plan[layout.unit_index(o.unit)] for o in sc.ecu.units]
