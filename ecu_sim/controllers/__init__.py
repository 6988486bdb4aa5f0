"""Control laws, one module each. Importing this package registers every law."""
from ecu_sim.controllers import consensus, finite_time  # noqa: F401
from ecu_sim.controllers.base import Controller, build_controller, get_controller, known_controllers

__all__ = ["Controller", "build_controller", "get_controller", "known_controllers"]
