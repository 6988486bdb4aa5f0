"""Control laws, one module each. Importing this package registers every law."""
from ecu_sim.controllers import consensus, finite_time  # noqa: F401
from ecu_sim.controllers import cca, pidca, smca, stsmca  # noqa: F401  (seed 001)
from ecu_sim.controllers import fixed_spacing, potential, safe_range  # noqa: F401  (seed 002)
from ecu_sim.controllers import chain_ism  # noqa: F401  (seed 003)
from ecu_sim.controllers import fractional_ftc, pid_tracking  # noqa: F401  (seed 004)
from ecu_sim.controllers.base import Controller, build_controller, get_controller, known_controllers

__all__ = ["Controller", "build_controller", "get_controller", "known_controllers"]
