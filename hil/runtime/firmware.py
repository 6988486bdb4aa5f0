"""Building each unit's firmware: the one seam for user code in both runtimes (which firmware each unit runs is the
scenario's: hil/scenario/firmware.py).

The scenario says it all by name or reference (``controller.law``, ``ecu.program``, ``[[ecu.units]]`` overrides,
``ecu.external``); the virtual rig and every real-time ECU node resolve those strings themselves
(:mod:`ecu_sim.references`), so nothing is patched and no process needs to be told anything else.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ecu_sim.codec import TrainDb
from ecu_sim.programs import EcuSetup, get_program
from ecu_sim.references import FirmwareBuildError, ReferenceLoadError, is_import_reference, module_root, one_line
from ecu_sim.runtime import Ecu, NeighbourLink
from hil.scenario.layout import TrainLayout
from hil.scenario.firmware import firmware_plan
from hil.scenario.model import Scenario


EcuFactory = Callable[[Any, TrainDb, int], Ecu]  # (assembly, db, flat unit) -> the unit's ECU


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
