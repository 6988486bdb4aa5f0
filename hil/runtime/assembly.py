"""Parts both runtimes build the same way from a scenario: layout, plant, reference, controllers.

Keeping this in one place is what makes the ideal loop and the networked rig differ only by the network.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.plant import Plant
from hil.reference_profile import ReferenceProfile
from hil.runtime.firmware import FirmwareParts, assemble_firmware
from hil.scenario.model import Scenario


@dataclass
class Assembly(FirmwareParts):
    """The network-independent parts of a run: the firmware's (layout, laws) and the plant's side."""

    plant: Plant
    reference: ReferenceProfile
    seed: int
    streams: dict[str, np.random.Generator]

    def close(self) -> None:
        """The run is over: the plant and the laws give back what they hold (FMU instances, to the pool)."""
        self.plant.close()
        self.close_laws()


def random_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent, named random streams: adding a consumer never shifts another's draws."""
    names = ("plant", "radio", "faults")
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {name: np.random.default_rng(child) for name, child in zip(names, children)}


def build_plant(scenario: Scenario, layout: TrainLayout, x0: np.ndarray, v0: np.ndarray,
                rng: np.random.Generator) -> Plant:
    """The built-in plant, or the FMU plant of [plant.fmu]; an FMU that does not load or fit its mapping is a
    ScenarioError naming it (exit 2 before a run writes anything)."""
    if scenario.plant.fmu is None:
        return Plant(scenario.plant, scenario.track, layout, x0, v0, rng)
    from ecu_sim.fmu import FmuError
    from hil.plant.fmu_plant import FmuPlant
    from hil.scenario import ScenarioError

    try:
        return FmuPlant(scenario.plant, scenario.track, layout, x0, v0, rng)
    except FmuError as exc:
        raise ScenarioError(f"{scenario.name}: plant.fmu: {exc}") from None


def assemble(scenario: Scenario, seed: int | None = None) -> Assembly:
    """Build layout, plant (at its initial state), reference and one controller per unit (its own law)."""
    seed = scenario.seed if seed is None else seed
    streams = random_streams(seed)
    fw = assemble_firmware(scenario)
    layout = fw.layout
    given = scenario.trains.initial_unit_positions  # per-unit start (uneven couplers), else couplers at rest
    x0 = np.array(given, dtype=float) if given is not None else layout.initial_positions(scenario.trains.head_positions_m)
    v0 = np.repeat(scenario.trains.initial_speeds_mps, layout.units_per_train).astype(float)
    plant = build_plant(scenario, layout, x0, v0, streams["plant"])
    return Assembly(scenario, layout, fw.firmware, fw.plant_info, plant,
                    ReferenceProfile.from_config(scenario.reference), seed, streams)


def check_firmware(scenario: Scenario, *, ecus: bool = True, processes: list[list[int]] | None = None) -> None:
    """Build every law (and, with ``ecus``, every rig ECU; an external unit has neither here) once, so a law or
    program that cannot be built is one line (ReferenceLoadError, exit 2) before a run writes anything, in either
    runtime. ``processes``: the units each process of the run will run (default: all in one, as virtual time
    does); each group's laws are built together and given back before the next's, as their processes would."""
    from hil.runtime.firmware import build_ecu
    from hil.runtime.train_db import load_train_db

    parts = assemble(scenario)
    db = load_train_db(scenario) if ecus else None
    try:
        for units in processes if processes is not None else [list(range(parts.layout.n_units))]:
            for u in units:
                if db is None:
                    parts.law(u)
                elif not parts.firmware[u].external:
                    build_ecu(parts, db, u)
            parts.close_laws()
    finally:
        parts.close()
