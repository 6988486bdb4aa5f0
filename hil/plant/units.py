"""Per-unit plant parameters (masses, rotating-mass factors, Davis resistance, actuator share and slope).

A scenario's ``[plant.units]`` and ``[plant.actuator]`` give each quantity per unit as an explicit list
or as a uniform range. Ranges are drawn here, once, from the section's own seed (``plant.units.seed``),
one independent stream per quantity (so adding a quantity never changes another's draw), and the values
in effect are returned with the arrays so the plant can log them. With nothing configured every array
is the scenario's scalar (``trains.unit_mass_kg``, ``plant.davis_c*``), and the Davis coefficients stay
Python floats, so existing scenarios run bit for bit as before.

Resistance in the Chinese specific form (seed 004) is w0 [N/kN] = 1e-2 a0 + 1e-4 a1 V + 1e-4 a2 V^2 with
V in km/h, per kN of the unit's weight m g. Per kg of physical mass, with V = 3.6 v (v in m/s):

    c0 = 1e-5 g a0            [N/kg]
    c1 = 3.6e-7 g a1          [N s/(m kg)]
    c2 = 1.296e-6 g a2        [N s^2/(m^2 kg)]      (g = 9.81 m/s^2, as the track's grade force)

The real CRH5 formula w0 = 0.69 + 0.0063 V + 0.00015 V^2 N/kN (a0 = 69, a1 = 63, a2 = 1.5) lies inside
seed 004's ranges a0 in [50, 85], a1 in [30, 100], a2 in [0.1, 6.5]; at 300 km/h it is 16.0 N/kN, i.e.
8.6 kN on a 55 t car.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from hil.scenario.layout import TrainLayout
from ecu_sim.track import G
from hil.scenario.model import PlantConfig, UnitValues

KMH_PER_MPS = 3.6


def specific_to_per_kg(a0: np.ndarray, a1: np.ndarray, a2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chinese specific resistance coefficients (N/kN, V in km/h) -> Davis c0, c1, c2 per kg (v in m/s)."""
    to_per_kg = G / 1000.0  # N/kN of weight -> N per kg of mass
    return (1e-2 * a0 * to_per_kg, 1e-4 * a1 * KMH_PER_MPS * to_per_kg, 1e-4 * a2 * KMH_PER_MPS**2 * to_per_kg)


def draw_stream(seed: int, name: str) -> np.random.Generator:
    """The random stream of one quantity: independent of every other quantity's and of the run seed."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())]))


def per_unit(uv: UnitValues, name: str, layout: TrainLayout, seed: int) -> np.ndarray:
    """(n,) values of one quantity: the list (per train, repeated, or per unit) or a uniform draw."""
    n, u = layout.n_units, layout.units_per_train
    if uv.uniform is not None:
        lo, hi = uv.uniform
        return draw_stream(seed, name).uniform(lo, hi, n)
    values = np.asarray(uv.values, dtype=float)
    if len(values) == u:
        return np.tile(values, layout.n_trains)
    if len(values) == n:
        return values.copy()
    raise ValueError(f"plant.{name}.values has {len(values)} values: give {u} (per unit of a train) or {n} (every unit)")


@dataclass(frozen=True)
class UnitParams:
    """Per-unit parameters in effect. Davis coefficients are floats unless given per unit."""

    layout: TrainLayout  # with the per-unit masses
    c0: float | np.ndarray
    c1: float | np.ndarray
    c2: float | np.ndarray
    distribution: np.ndarray  # lambda, share of the commanded force the unit delivers
    slope: np.ndarray  # rho
    configured: dict[str, list[float]] = field(default_factory=dict)  # per-unit values that were given or drawn

    @property
    def actuator_shaped(self) -> bool:
        """True when the actuator chain changes the commanded force (lambda or rho not all 1)."""
        return bool(np.any(self.distribution != 1.0) or np.any(self.slope != 1.0))

    def describe(self, seed: int) -> str:
        """One line for the run's event log: every configured per-unit value (the record of a draw)."""
        parts = [f"{k} = [{', '.join(f'{v:.6g}' for v in vals)}]" for k, vals in self.configured.items()]
        return f"per-unit plant parameters (draw seed {seed}): " + "; ".join(parts)


def unit_params(layout: TrainLayout, plant: PlantConfig) -> UnitParams:
    """Per-unit arrays from the scenario's plant section (nominal values where nothing is configured)."""
    cfg, act, seed = plant.units, plant.actuator, plant.units.seed
    n = layout.n_units
    configured: dict[str, list[float]] = {}

    def get(uv: UnitValues | None, name: str) -> np.ndarray | None:
        if uv is None:
            return None
        arr = per_unit(uv, name, layout, seed)
        configured[name] = arr.tolist()
        return arr

    mass = get(cfg.mass_kg, "units.mass_kg")
    rot = get(cfg.rotating_mass_factor, "units.rotating_mass_factor")
    if mass is not None or rot is not None:
        m = layout.mass_kg if mass is None else mass
        factor = layout.effective_mass_kg / layout.mass_kg if rot is None else 1.0 + rot
        layout = layout.with_masses(m, m * factor)
    c0: float | np.ndarray = plant.davis_c0
    c1: float | np.ndarray = plant.davis_c1
    c2: float | np.ndarray = plant.davis_c2
    res = cfg.resistance
    if res is not None:
        names = ("c0", "c1", "c2") if res.form == "per_kg" else ("a0", "a1", "a2")
        k0, k1, k2 = (get(getattr(res, k), f"units.resistance.{k}") for k in names)
        assert k0 is not None and k1 is not None and k2 is not None  # the schema requires all three
        c0, c1, c2 = (k0, k1, k2) if res.form == "per_kg" else specific_to_per_kg(k0, k1, k2)
        if res.form == "specific_kmh":
            configured.update({"davis_c0": list(c0), "davis_c1": list(c1), "davis_c2": list(c2)})
    lam = get(act.distribution, "actuator.distribution")
    rho = get(act.slope, "actuator.slope")
    return UnitParams(layout, c0, c1, c2,
                      np.ones(n) if lam is None else lam, np.ones(n) if rho is None else rho, configured)
