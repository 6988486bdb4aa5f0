"""Additive disturbance forces (pulse, step, sine, random) on selected units over time windows.

Each disturbance acts on the units selected by its 1-based ``train``/``unit`` (None = all) while
``start_s <= t < end_s``. ``pulse`` and ``step`` are both a constant ``amplitude_n`` inside the
window (the names only describe the intent: short bump vs sustained load). ``random`` is an
Ornstein-Uhlenbeck force per selected unit with stationary standard deviation ``amplitude_n`` and
correlation time ``correlation_s``, discretised exactly at the plant step and drawn from the
plant's generator, so a seeded run is reproducible.

``channel = "position"`` disturbances (seed 003's mismatched d2, in m/s) are kept apart: :meth:`add`
never sees them, :meth:`add_position` sums them into a speed the plant adds to dx/dt only (the
step's position gains d2 dt after the exact linear step; v is unchanged). With none configured the
force path and its random draws are exactly as before.
"""
from __future__ import annotations

import math

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.scenario.model import Disturbance


def unit_mask(d: Disturbance, layout: TrainLayout, where: str) -> np.ndarray:
    """0/1 float mask (n,) of the units a disturbance acts on; bad train/unit numbers are errors."""
    if d.train is not None and d.train > layout.n_trains:
        raise ValueError(f"{where}.train = {d.train}, but there are only {layout.n_trains} trains")
    if d.unit is not None and d.unit > layout.units_per_train:
        raise ValueError(f"{where}.unit = {d.unit}, but trains have only {layout.units_per_train} units")
    train_of, unit_of = np.divmod(np.arange(layout.n_units), layout.units_per_train)
    sel = np.ones(layout.n_units, dtype=bool)
    if d.train is not None:
        sel &= train_of == d.train - 1
    if d.unit is not None:
        sel &= unit_of == d.unit - 1
    return sel.astype(float)


class _Active:
    """One disturbance, precomputed: window, mask, and the OU state for ``random``."""

    def __init__(self, d: Disturbance, mask: np.ndarray, dt: float) -> None:
        self.kind, self.start, self.end = d.kind, d.start_s, d.end_s
        self.mask = mask
        amplitude = d.amplitude  # N (force channel) or m/s (position channel)
        self.const = amplitude * mask  # pulse / step vector
        self.amplitude, self.omega = amplitude, 2.0 * math.pi * d.frequency_hz
        self.phi = math.exp(-dt / d.correlation_s)  # OU decay per step
        self.kick = amplitude * math.sqrt(1.0 - self.phi * self.phi)  # keeps the variance at amplitude^2
        self.state: np.ndarray | None = None  # OU force, drawn stationary on the first step in the window


class Disturbances:
    """All configured disturbances; :meth:`add` accumulates the active ones into a force vector."""

    def __init__(self, configs: list[Disturbance], layout: TrainLayout, rng: np.random.Generator, dt: float) -> None:
        self._rng = rng
        items = [(d.channel, _Active(d, unit_mask(d, layout, f"plant.disturbances[{i}]"), dt)) for i, d in enumerate(configs)]
        self._items = [a for channel, a in items if channel == "force"]
        self._position_items = [a for channel, a in items if channel == "position"]
        self._tmp = np.empty(layout.n_units)

    def __bool__(self) -> bool:
        """True when a force-channel disturbance is configured (position-channel ones: :attr:`has_position`)."""
        return bool(self._items)

    @property
    def has_position(self) -> bool:
        """True when a position-channel (mismatched) disturbance is configured."""
        return bool(self._position_items)

    def add(self, t: float, out: np.ndarray) -> None:
        """Add the disturbance force at time t (N, per unit) into ``out`` in place."""
        self._accumulate(self._items, t, out)

    def add_position(self, t: float, out: np.ndarray) -> None:
        """Add the position-channel disturbance at time t (m/s added to dx/dt, per unit) into ``out`` in place."""
        self._accumulate(self._position_items, t, out)

    def _accumulate(self, items: list[_Active], t: float, out: np.ndarray) -> None:
        tmp = self._tmp
        for d in items:
            if not d.start <= t < d.end:
                continue
            if d.kind == "sine":
                np.multiply(d.mask, d.amplitude * math.sin(d.omega * (t - d.start)), out=tmp)
                np.add(out, tmp, out=out)
            elif d.kind == "random":
                np.add(out, self._ou_step(d), out=out)
            else:  # pulse, step
                np.add(out, d.const, out=out)

    def _ou_step(self, d: _Active) -> np.ndarray:
        """Advance one OU process by a step (exact discretisation) and return its force vector."""
        noise = self._rng.standard_normal(out=self._tmp)
        if d.state is None:
            d.state = d.amplitude * noise * d.mask
            return d.state
        np.multiply(noise, d.kick, out=noise)
        np.multiply(noise, d.mask, out=noise)
        np.multiply(d.state, d.phi, out=d.state)
        np.add(d.state, noise, out=d.state)
        return d.state
