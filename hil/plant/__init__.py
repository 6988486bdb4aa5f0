"""The plant: longitudinal dynamics of the train group (couplers, resistance, track, actuators)."""
from hil.plant.dynamics import Plant, PlantDiverged

__all__ = ["Plant", "PlantDiverged"]
