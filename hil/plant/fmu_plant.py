"""The plant with its dynamics from an FMU ([plant.fmu]): the FMU takes each unit's applied force (and grade,
curve and disturbance where mapped) and gives positions and speeds; everything around the dynamics is the built-in
plant's (hil/plant/dynamics.py): the actuator chain and its faults, sensor noise, the track lookup, events.

The FMU is stepped every ``plant.fmu.step_s`` (a whole multiple of plant.step_s; by default every plant step) with
the inputs of the step start held over the step, as the built-in plant holds its forces. Between communication
points the state is the last one the FMU gave. Parameters are set at instantiation from the scenario (per unit:
the true masses, lengths, Davis terms and initial state; for the group: the coupler's k and d), so the FMU and
the firmware's nominal data differ exactly as they do with the built-in plant.
"""
from __future__ import annotations

import numpy as np

from ecu_sim.fmu import FmuError, FmuVariable, load_fmu
from hil.plant.dynamics import Plant, PlantDiverged
from hil.scenario.layout import TrainLayout
from hil.scenario.model import PLANT_FMU_QUANTITIES, PlantConfig, PlantFmu, TrackConfig


class FmuPlantError(PlantDiverged):
    """The plant FMU failed a step or gave a non-finite output: the run stops there, its files stay readable."""


def expand(template: str, layout: TrainLayout, per: str = "unit") -> list[str]:
    """Variable names of a template: one per unit (``{unit}``, ``{train}``, ``{car}``, 1-based), one per coupler
    (``{coupler}``), or the name itself for the group."""
    if per == "coupler":
        return [template.format(coupler=j + 1) for j in range(len(layout.coupler_pairs()))]
    u = layout.units_per_train
    return [template.format(unit=i + 1, train=i // u + 1, car=i % u + 1) for i in range(layout.n_units)]


def unit_quantity(plant: "FmuPlant", name: str) -> np.ndarray | float:
    """A scenario quantity named in [plant.fmu.parameters]: per unit (an array) or for the group (a float)."""
    layout, units = plant.layout, plant.units
    per_unit = {
        "mass_kg": layout.mass_kg, "effective_mass_kg": layout.effective_mass_kg, "length_m": layout.length_m,
        "davis_c0": units.c0, "davis_c1": units.c1, "davis_c2": units.c2,
        "initial_position_m": plant.x0, "initial_speed_mps": plant.v0,
    }
    if name in per_unit:
        return np.broadcast_to(np.asarray(per_unit[name], dtype=float), (layout.n_units,))
    group = {"coupler_stiffness_n_per_m": plant.config.coupler_stiffness_n_per_m,
             "coupler_damping_ns_per_m": plant.config.coupler_damping_ns_per_m, "step_s": plant.fmu_step_s}
    return float(group[name])


class FmuPlant(Plant):
    """:class:`~hil.plant.dynamics.Plant` whose :meth:`step` advances an FMU instead of the exact linear map."""

    def __init__(self, plant: PlantConfig, track: TrackConfig, layout: TrainLayout, x0: np.ndarray, v0: np.ndarray,
                 rng: np.random.Generator, dt: float | None = None) -> None:
        assert plant.fmu is not None
        self.x0, self.v0 = np.array(x0, dtype=float), np.array(v0, dtype=float)
        self._fmu_ready, self._track_config = False, track
        super().__init__(plant, track, layout, x0, v0, rng, dt)
        mapping = plant.fmu
        self.fmu_step_s = mapping.step_s or self.dt
        self._every = max(1, round(self.fmu_step_s / self.dt))
        self.fmu = load_fmu(mapping.path)
        self._refuse_unmapped(mapping)
        ports = self._ports(mapping)
        self.instance, self._give_back = self.fmu.acquire(self, f"plant:{self.fmu.name}")
        self.instance.initialize(self._parameters(mapping))
        self._inputs, self._outputs = (self.instance.port(p) for p in ports)
        self._read_outputs(0.0)
        self._fmu_ready = True

    def close(self) -> None:
        """The run is over: the FMU instance back to this process's pool (a sweep's next run reuses it)."""
        self._give_back()

    # ------------------------------------------------------------------ mapping

    def _refuse_unmapped(self, mapping: PlantFmu) -> None:
        """What the scenario asks of the plant must reach the FMU: grades, curves, disturbances."""
        needs = [("grade", "the track has grades", bool(self._track_config.grades)),
                 ("curve", "the track has curves", bool(self._track_config.curves)),
                 ("disturbance", "plant.disturbances has force disturbances", bool(self._dist)),
                 (None, "plant.disturbances has a position-channel disturbance", self._d2 is not None)]
        for field, why, needed in needs:
            if needed and (field is None or getattr(mapping.inputs, field) is None):
                where = f"plant.fmu.inputs.{field} maps no FMU input" if field else "the FMU plant cannot take it"
                raise FmuError(f"{self.fmu.path}: {why}, but {where}")

    def _ports(self, mapping: PlantFmu) -> tuple[list[FmuVariable], list[FmuVariable]]:
        """The FMU variables written before and read after each step, checked for presence, type and causality."""
        layout, fmu = self.layout, self.fmu
        self._input_roles = [r for r in ("force", "grade", "curve", "disturbance") if getattr(mapping.inputs, r)]
        inputs = [fmu.variable(name, ("input",), f"plant.fmu.inputs.{role}")
                  for role in self._input_roles for name in expand(getattr(mapping.inputs, role), layout)]
        self._output_roles = [r for r in ("position", "speed", "acceleration", "coupler") if getattr(mapping.outputs, r)]
        outputs: list[FmuVariable] = []
        self._slices: dict[str, slice] = {}  # each output role's place in the output port
        for role in self._output_roles:
            names = expand(getattr(mapping.outputs, role), layout, "coupler" if role == "coupler" else "unit")
            self._slices[role] = slice(len(outputs), len(outputs) + len(names))
            outputs += [fmu.variable(name, ("output",), f"plant.fmu.outputs.{role}") for name in names]
        return inputs, outputs

    def _parameters(self, mapping: PlantFmu) -> dict[FmuVariable, float]:
        """[plant.fmu.parameters] resolved: each FMU variable with its value (checked: a parameter, or an input)."""
        values: dict[FmuVariable, float] = {}
        for template, source in mapping.parameters.items():
            per_unit = isinstance(source, str) and PLANT_FMU_QUANTITIES[source] == "unit"
            names = expand(template, self.layout) if per_unit else [template]
            quantity = unit_quantity(self, source) if isinstance(source, str) else float(source)
            for i, name in enumerate(names):
                var = self.fmu.variable(name, ("parameter", "input"), f"plant.fmu.parameters[{template!r}]")
                values[var] = float(quantity[i]) if isinstance(quantity, np.ndarray) else float(quantity)
        return values

    # ------------------------------------------------------------------ state

    @property
    def x(self) -> np.ndarray:
        """True front-end positions (m): the FMU's, refreshed in place after each communication step."""
        return self._x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        if getattr(self, "_fmu_ready", False):
            raise FmuError(f"{self.fmu.path}: the FMU plant's state is the FMU's; positions are set only at the start "
                           "(trains.initial_unit_positions, mapped to an FMU parameter)")
        self._x[:] = value

    def coupler_displacements(self) -> np.ndarray:
        """e (m, > 0 stretched) of every coupler: the FMU's output where mapped, else from positions and lengths."""
        if "coupler" in self._output_roles:
            return self._coupler.copy()
        p = self.layout.coupler_pairs()
        if len(p) == 0:
            return np.zeros(0)
        return self._x[p[:, 0]] - self._x[p[:, 1]] - self.layout.length_m[p[:, 0]]

    # ------------------------------------------------------------------ integration

    def step(self) -> None:
        """Advance by dt: the actuator chain at t, then (every ``fmu.step_s``) one FMU step with the inputs held."""
        t = self.t
        force = self._act.apply(t, self._v)
        if self._steps % self._every == 0:
            self._inputs.write(self._input_values(t, force))
            try:
                self.instance.do_step(t, self.fmu_step_s)
            except FmuError as exc:
                raise FmuPlantError(f"plant FMU at t = {t:.6f} s: {exc}") from None
            self._read_outputs(t + self.fmu_step_s)
        self._steps += 1
        self.t = self._steps * self.dt

    def _input_values(self, t: float, force: np.ndarray) -> np.ndarray:
        """The mapped inputs in port order: force, then grade and curve (N/kg) and disturbance (N) where mapped."""
        if len(self._input_roles) == 1:
            values = force
        else:
            parts = [force]
            if "grade" in self._input_roles or "curve" in self._input_roles:
                self._track.lookup(self._x, self._grade, self._curve)
                parts += [arr for role, arr in (("grade", self._grade), ("curve", self._curve)) if role in self._input_roles]
            if "disturbance" in self._input_roles:
                w = np.zeros(self.layout.n_units)
                self._dist.add(t, w)
                parts.append(w)
            values = np.concatenate(parts)
        if not np.isfinite(values).all():
            raise FmuPlantError(f"plant diverged at t = {t:.6f} s: non-finite FMU input "
                                f"{self._inputs.first_non_finite(values)}")
        return values

    def _read_outputs(self, t: float) -> None:
        """Positions, speeds, accelerations and coupler displacements from the FMU, checked finite."""
        values = self._outputs.read()
        if not np.isfinite(values).all():
            raise FmuPlantError(f"plant diverged at t = {t:.6f} s: the FMU {self.fmu.name} gives "
                                f"{self._outputs.first_non_finite(values)}")
        if "acceleration" not in self._output_roles and t > 0:
            np.subtract(values[self._slices["speed"]], self._v, out=self.a)
            self.a /= self.fmu_step_s
        self._x[:] = values[self._slices["position"]]
        self._v[:] = values[self._slices["speed"]]
        if "acceleration" in self._slices:
            self.a[:] = values[self._slices["acceleration"]]
        if "coupler" in self._slices:
            self._coupler = values[self._slices["coupler"]].copy()
