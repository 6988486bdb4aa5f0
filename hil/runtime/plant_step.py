"""One step of the plant as every runtime takes it: the recording sample (the state at the step's start) when it
is due, the integration step, then the plant's events into the run log.

The virtual rig, the ideal loop and the real-time plant node all call this, so the three loops record and log
the plant alike."""
from __future__ import annotations

from hil.plant.dynamics import Plant
from hil.reference_profile import ReferenceProfile
from hil.record.runlog import RunLog


def plant_step(plant: Plant, reference: ReferenceProfile, log: RunLog, t: float, record: bool) -> None:
    """Integrate ``plant`` from ``t`` by one step; first add a recording sample at ``t`` if ``record``."""
    if record:
        x_r, v_r = reference.at(t)
        log.add_sample(t, x_r, v_r, plant.x, plant.v, plant.a, plant.force_cmd, plant.force_applied)
    plant.step()
    if plant.events:
        for te, level, text in plant.events:
            log.event(te, level, "plant", text)
        plant.events.clear()
