"""Which firmware each unit runs, and building it: the one seam for user code in both runtimes.

The scenario says it all by name or reference (``controller.law``, ``ecu.program``, ``[[ecu.units]]`` overrides,
``ecu.external``); the virtual rig and every real-time ECU node resolve those strings themselves
(:mod:`ecu_sim.references`), so nothing is patched and no process needs to be told anything else.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from ecu_sim.codec import TrainDb
from ecu_sim.controllers.base import get_controller
from ecu_sim.programs import EcuSetup, get_program
from ecu_sim.references import FirmwareBuildError, ReferenceLoadError, is_import_reference, module_root, one_line
from ecu_sim.runtime import Ecu, NeighbourLink
from hil.layout import TrainLayout
from hil.scenario.model import Scenario


EcuFactory = Callable[[Any, TrainDb, int], Ecu]  # (assembly, db, flat unit) -> the unit's ECU


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


def import_roots(sc: Scenario) -> list[Path]:
    """The ``sys.path`` folders the scenario's ``module:QualName`` references are imported from here: the real-time
    node processes search them (``TRAINHIL_USER_PATH``) so that they import the same modules."""
    roots: list[Path] = []
    for f in firmware_plan(sc):
        for ref in (f.law, f.program):
            if is_import_reference(ref):
                root = module_root(ref)
                if root is not None and root not in roots:
                    roots.append(root)
    return roots


# ---------------------------------------------------------------------- building one unit's ECU
def neighbour_links(db: TrainDb, layout: TrainLayout, forward_aux: bool, u: int) -> list[NeighbourLink]:
    """Where unit u's neighbours' states arrive from: intra-train AgentState/AgentAux, or the radio IDs."""
    links = []
    state: int
    aux: int | None
    for q, link, side in layout.neighbours(u):
        if link == "intra":
            unit = layout.train_unit(q)[1]
            state, aux = db.agent_state(unit).frame_id, db.agent_aux(unit).frame_id
        elif side == "ahead":
            state, aux = db.radio_ahead_state.frame_id, db.radio_ahead_aux.frame_id if forward_aux else None
        else:
            state, aux = db.radio_behind_state.frame_id, db.radio_behind_aux.frame_id if forward_aux else None
        links.append(NeighbourLink(state, aux, link, side, float(layout.offset_m[q])))  # type: ignore[arg-type]
    return links


def ecu_setup(parts, db: TrainDb, u: int) -> EcuSetup:
    """What unit u's program is built from (``parts``: the run's :class:`~hil.runtime.assembly.Assembly`)."""
    sc, layout = parts.scenario, parts.layout
    return EcuSetup(f"{layout.unit_name(u)}/ecu", u, layout.agent_info(u), parts.controllers[u], db,
                    neighbour_links(db, layout, sc.radio.forward_aux, u), sc.ecu, sc.can.sensor_period_s)


def build_ecu(parts, db: TrainDb, u: int) -> Ecu:
    """The firmware of flat unit u, as the scenario names it (both runtimes build every ECU here)."""
    program = parts.firmware[u].program
    factory = get_program(program)
    try:
        ecu = factory(ecu_setup(parts, db, u))
    except Exception as exc:  # the user's program raised while being built: one line, not a traceback
        raise FirmwareBuildError(f"ECU program {program!r} for {parts.layout.unit_name(u)} could not be built: "
                                 f"{one_line(exc)}") from None
    if not isinstance(ecu, Ecu):
        raise ReferenceLoadError(f"ECU program {program!r} returned {type(ecu).__name__}, not an ecu_sim.runtime.Ecu")
    return ecu


def refuse_external_units(sc: Scenario, runtime: str) -> None:
    """External units exist only in real time: elsewhere there is no device to wait for. ScenarioError (exit 2)."""
    if sc.ecu.external:
        from hil.scenario.loader import ScenarioError

        raise ScenarioError(f"ecu.external = {sc.ecu.external}: an external unit needs a real-time run (hil run "
                            f"--realtime), not {runtime}; to run your own firmware in-process, name it in "
                            "ecu.program (or [[ecu.units]] program = ...)")
