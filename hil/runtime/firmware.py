"""Building each unit's firmware: the one seam for user code in both runtimes (which firmware each unit runs is the
scenario's: hil/scenario/firmware.py).

The scenario says it all by name or reference (``controller.law``, ``ecu.program``, ``[[ecu.units]]`` overrides,
``ecu.external``); the virtual rig and every real-time ECU node resolve those strings themselves
(:mod:`ecu_sim.references`), so nothing is patched and no process needs to be told anything else.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ecu_sim.codec import TrainDb
from ecu_sim.controllers.base import Controller, PlantInfo, build_controller
from ecu_sim.programs import EcuSetup, get_program
from ecu_sim.references import FirmwareBuildError, ReferenceLoadError, is_import_reference, module_root, one_line
from ecu_sim.runtime import Ecu, NeighbourLink
from hil.scenario.layout import TrainLayout
from hil.scenario.firmware import UnitFirmware, firmware_plan
from hil.scenario.model import Scenario


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


# ---------------------------------------------------------------------- what every unit's firmware is built from
@dataclass
class FirmwareParts:
    """The parts of a run its ECUs are built from: the laws and the configuration, no plant. A real-time ECU node
    builds only these, so it neither imports nor builds the plant (scipy, an FMU). Each unit's law is built when it
    is first asked for (``law``), so a process builds the laws of the units it runs and no other."""

    scenario: Scenario
    layout: TrainLayout
    firmware: list[UnitFirmware]  # per unit: law, params, ECU program, external
    plant_info: PlantInfo
    _laws: dict[int, Controller] = field(default_factory=dict, init=False, repr=False, compare=False)

    def law(self, u: int) -> Controller:
        """Flat unit u's own law, built on first use."""
        law = self._laws.get(u)
        if law is None:
            f = self.firmware[u]
            law = self._laws[u] = build_controller(f.law, f.params, self.layout.agent_info(u), self.plant_info)
        return law

    def close_laws(self) -> None:
        """Give back what the laws built so far hold (an FMU's instances, to its pool) and forget them."""
        laws, self._laws = self._laws, {}
        for law in laws.values():
            law.close()


EcuFactory = Callable[[FirmwareParts, TrainDb, int], Ecu]  # (the parts, or the whole assembly; db; flat unit) -> ECU


def plant_info(scenario: Scenario) -> PlantInfo:
    """The nominal model knowledge a firmware is configured with."""
    p = scenario.plant
    return PlantInfo(
        davis_c0=p.davis_c0, davis_c1=p.davis_c1, davis_c2=p.davis_c2,
        coupler_stiffness=p.coupler_stiffness_n_per_m, coupler_damping=p.coupler_damping_ns_per_m,
        spacing_m=scenario.trains.spacing_m, emergency_gap_m=scenario.trains.emergency_gap_m,
        radio_range_m=scenario.radio.range_m, emergency_brake_mps2=p.failsafe.emergency_brake_mps2,
    )


def assemble_firmware(scenario: Scenario) -> FirmwareParts:
    """The layout, the firmware plan and what the laws are configured with (each law is built when first asked for)."""
    return FirmwareParts(scenario, TrainLayout.from_config(scenario.trains), firmware_plan(scenario),
                         plant_info(scenario))


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


def ecu_setup(parts: FirmwareParts, db: TrainDb, u: int) -> EcuSetup:
    """What unit u's program is built from."""
    sc, layout = parts.scenario, parts.layout
    return EcuSetup(f"{layout.unit_name(u)}/ecu", u, layout.agent_info(u), parts.law(u), db,
                    neighbour_links(db, layout, sc.radio.forward_aux, u), sc.ecu, sc.can.sensor_period_s)


def build_ecu(parts: FirmwareParts, db: TrainDb, u: int) -> Ecu:
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
