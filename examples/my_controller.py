"""My cruise law: the firmware under test (a simple law to copy and change).

Each power unit runs one instance. It sees only what arrived over CAN (its LocalView) and returns a force:

    head units (pinned to the wayside reference):  a = a_r - kx (x - x*) - kv (v - v_r),   x* = x_r - offset
    other units (follow the unit ahead):           a = a_ahead + kc e + kd (v_ahead - v)
    every unit:                                    F = m (a + R(v))

e is the coupler displacement to the unit ahead (> 0 stretched), a_ahead the acceleration the unit ahead
demanded (its AgentAux frame), R(v) the Davis resistance per kg. A unit whose train ahead is closer than l_e
brakes at the emergency rate. Registering the class (``@register``) makes it usable in scenario files as
``[controller] law = "my_cruise"``; the tests pass the class itself to the rig instead.
"""
from __future__ import annotations

from math import isfinite

from pydantic import Field

from ecu_sim.controllers.base import Controller, ControllerParams, register
from ecu_sim.controllers.common import check_own_state, emergency_command, train_ahead_too_close
from ecu_sim.view import Command, LocalView


class MyCruiseParams(ControllerParams):
    """Gains (SI units). The defaults settle the example scenario (cruise.toml) in about 15 s."""

    kx: float = Field(default=0.25, ge=0, description="head: position gain on x - x* (1/s^2)")
    kv: float = Field(default=1.0, ge=0, description="head: speed gain on v - v_r (1/s)")
    kc: float = Field(default=1.0, ge=0, description="follower: gain on the coupler displacement (1/s^2)")
    kd: float = Field(default=2.0, ge=0, description="follower: gain on the speed difference to the unit ahead (1/s)")


@register
class MyCruise(Controller):
    """Heads track their slot on the reference; followers track the unit ahead with acceleration feedforward."""

    name = "my_cruise"
    Params = MyCruiseParams

    def step(self, view: LocalView) -> Command:
        p, agent, plant = self.params, self.agent, self.plant_info
        check_own_state(view)
        if train_ahead_too_close(view, agent, plant):
            return emergency_command(agent, plant)
        a = 0.0
        ref = view.ref
        if agent.has_reference and ref.valid:
            a = ref.a - p.kx * (view.x - (ref.x - agent.offset_m)) - p.kv * (view.v - ref.v)
        else:
            for nb in view.neighbours:
                if nb.valid and nb.link == "intra" and nb.side == "ahead":
                    e = nb.position_error_from(view.x, agent.offset_m)  # coupler displacement
                    a_ahead = nb.a if isfinite(nb.a) else 0.0
                    a = a_ahead + p.kc * e + p.kd * (nb.v - view.v)
        force = agent.mass_kg * (a + plant.resistance_per_kg(view.v))
        return Command(force_n=force, accel_mps2=a)
