"""Actuator faults: a unit's traction/brake actuator degraded to a health factor, or lost altogether.

Uses the plant's health API (``Plant.set_health``, hil/plant/actuators.py): the NORMAL-mode force becomes
h x the command; service and emergency brakes (fail-safe, train line) are pneumatic and keep working. At the
fault's end the unit is repaired (h = 1). The ECU is never told; only the motion shows it.
"""
from __future__ import annotations

from hil.plant.dynamics import Plant


class ActuatorFaults:
    def __init__(self, plant: Plant, layout) -> None:
        self._plant, self._layout = plant, layout

    def _unit(self, spec) -> int:
        return self._layout.index(spec.train - 1, spec.unit - 1)

    def start(self, spec, t: float) -> None:
        health = 0.0 if spec.kind == "traction_loss" else spec.health
        self._plant.set_health(self._unit(spec), health, t)

    def end(self, spec, t: float) -> None:
        self._plant.set_health(self._unit(spec), 1.0, t)
