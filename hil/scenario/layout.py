"""Where every unit sits: flat unit indices, train membership, slot offsets and agent info.

Units are numbered 0..n_total-1 front to back across the whole group (train 0's head first).
Every other module (plant, ECUs, recording, metrics) uses this one numbering.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ecu_sim.view import AgentInfo
from hil.scenario.checks import UNIT_NAME, unit_name_error
from hil.scenario.model import TrainsConfig

@dataclass(frozen=True)
class TrainLayout:
    """Static geometry of the train group."""

    n_trains: int
    units_per_train: int
    mass_kg: np.ndarray  # (n,) physical mass per unit
    effective_mass_kg: np.ndarray  # (n,) mass x (1 + rotating-mass factor)
    length_m: np.ndarray  # (n,)
    offset_m: np.ndarray  # (n,) x*_u = x_r - offset_m[u]
    spacing_m: float
    emergency_gap_m: float
    reference_all: bool = False  # every unit's ECU receives the reference (else only train heads)

    @classmethod
    def from_config(cls, trains: TrainsConfig) -> "TrainLayout":
        n = trains.count * trains.units
        length = np.full(n, trains.unit_length_m)
        mass = np.full(n, trains.unit_mass_kg)
        train_of = np.repeat(np.arange(trains.count), trains.units)
        ahead = np.concatenate(([0.0], np.cumsum(length)[:-1]))  # lengths of all units ahead
        offset = ahead + train_of * trains.spacing_m
        return cls(
            n_trains=trains.count,
            units_per_train=trains.units,
            mass_kg=mass,
            effective_mass_kg=mass * (1.0 + trains.rotating_mass_factor),
            length_m=length,
            offset_m=offset,
            spacing_m=trains.spacing_m,
            emergency_gap_m=trains.emergency_gap_m,
            reference_all=trains.reference_units == "all",
        )

    def with_masses(self, mass_kg: np.ndarray, effective_mass_kg: np.ndarray) -> "TrainLayout":
        """The same layout with per-unit masses (hil/plant/units.py: drawn or listed per unit)."""
        n = self.n_units
        for name, a in (("mass_kg", mass_kg), ("effective_mass_kg", effective_mass_kg)):
            if np.shape(a) != (n,) or not np.all(np.isfinite(a)) or not np.all(np.asarray(a) > 0):
                raise ValueError(f"{name} must be {n} finite positive values, got {a!r}")
        return replace(self, mass_kg=np.asarray(mass_kg, dtype=float), effective_mass_kg=np.asarray(effective_mass_kg, dtype=float))

    @property
    def n_units(self) -> int:
        return self.n_trains * self.units_per_train

    def index(self, train: int, unit: int) -> int:
        """Flat index of (train, unit), both 0-based."""
        return train * self.units_per_train + unit

    def train_unit(self, u: int) -> tuple[int, int]:
        return divmod(u, self.units_per_train)

    def ecu_node_name(self, u: int) -> str:
        """Unit u's ECU's node on its train's bus (``ECU_U03``), in both runtimes: its TX queue, drops and error
        state go by it."""
        return f"ECU_U{self.train_unit(u)[1] + 1:02d}"

    def unit_name(self, u: int) -> str:
        """``train<t>/unit<k>`` (1-based) of flat unit u: the name in scenarios, events and node lists."""
        return self.name_of(*self.train_unit(u))

    @staticmethod
    def name_of(train: int, unit: int) -> str:
        """``train<t>/unit<k>`` of (train, unit), both 0-based: the one place a unit's name is formatted."""
        return f"train{train + 1}/unit{unit + 1}"

    def unit_index(self, name: str) -> int:
        """Flat index of a ``train<t>/unit<k>`` name; ValueError says what is wrong with it."""
        why = unit_name_error(name, self.n_trains, self.units_per_train)
        if why is not None:
            raise ValueError(why)
        train, unit = UNIT_NAME.fullmatch(name.strip()).groups()  # type: ignore[union-attr]
        return self.index(int(train) - 1, int(unit) - 1)

    def heads(self) -> np.ndarray:
        return np.arange(self.n_trains) * self.units_per_train

    def tails(self) -> np.ndarray:
        return self.heads() + self.units_per_train - 1

    def coupler_pairs(self) -> np.ndarray:
        """(n_couplers, 2) flat indices (front unit, rear unit) of every coupler."""
        pairs = [(self.index(i, j), self.index(i, j + 1)) for i in range(self.n_trains) for j in range(self.units_per_train - 1)]
        return np.array(pairs, dtype=int).reshape(-1, 2)

    def initial_positions(self, head_positions_m: list[float]) -> np.ndarray:
        """Unit front-end positions with every coupler at rest (e = 0)."""
        x = np.empty(self.n_units)
        for i, head in enumerate(head_positions_m):
            u0 = self.index(i, 0)
            lengths = self.length_m[u0 : u0 + self.units_per_train]
            x[u0 : u0 + self.units_per_train] = head - np.concatenate(([0.0], np.cumsum(lengths)[:-1]))
        return x

    def agent_info(self, u: int) -> AgentInfo:
        train, unit = self.train_unit(u)
        return AgentInfo(
            train=train,
            unit=unit,
            n_trains=self.n_trains,
            n_units=self.units_per_train,
            mass_kg=float(self.effective_mass_kg[u]),
            length_m=float(self.length_m[u]),
            offset_m=float(self.offset_m[u]),
            has_reference=(unit == 0 or self.reference_all),
        )

    def neighbours(self, u: int) -> list[tuple[int, str, str]]:
        """(neighbour index, link, side) of unit u: adjacent units, and across trains for head/tail."""
        train, unit = self.train_unit(u)
        out: list[tuple[int, str, str]] = []
        if unit > 0:
            out.append((u - 1, "intra", "ahead"))
        if unit < self.units_per_train - 1:
            out.append((u + 1, "intra", "behind"))
        if unit == 0 and train > 0:
            out.append((self.index(train - 1, self.units_per_train - 1), "inter", "ahead"))
        if unit == self.units_per_train - 1 and train < self.n_trains - 1:
            out.append((self.index(train + 1, 0), "inter", "behind"))
        return out

    def gaps(self, x: np.ndarray) -> np.ndarray:
        """Gap s_i = rear end of train i - front end of train i+1, for each adjacent pair."""
        tails, heads = self.tails(), self.heads()
        return (x[tails[:-1]] - self.length_m[tails[:-1]]) - x[heads[1:]]

    def coupler_displacements(self, x: np.ndarray) -> np.ndarray:
        """e = x_front - x_rear - l_front for every coupler (> 0 stretched)."""
        p = self.coupler_pairs()
        if len(p) == 0:
            return np.zeros(0)
        return x[p[:, 0]] - x[p[:, 1]] - self.length_m[p[:, 0]]
