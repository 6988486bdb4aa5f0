"""Sensor faults: a unit's speed and position sensors stuck at their last value, or noisy.

The injector interposes on ``Plant.measure`` (an instance attribute wraps the method), so neither the plant nor
its CAN node knows about faults: Sensor frames keep coming with advancing alive counters and valid CRCs, only
their values are wrong, which is what the firmware's plausibility check must notice (``ecu_sim.diagnostics``).
"""
from __future__ import annotations

import numpy as np

from hil.plant.dynamics import Plant


class SensorFaults:
    """Stuck and noisy sensors of a plant (one injector per plant, any number of faulty units)."""

    def __init__(self, plant: Plant, layout, rng: np.random.Generator) -> None:
        self._layout = layout
        self._measure = plant.measure
        self._rng = rng
        self._stuck: dict[int, tuple[float, float]] = {}  # unit -> frozen (x, v)
        self._noise: dict[int, tuple[float, float]] = {}  # unit -> (sigma x, sigma v)
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        plant.measure = self  # type: ignore[method-assign]

    def _unit(self, spec) -> int:
        return self._layout.index(spec.train - 1, spec.unit - 1)

    def start(self, spec) -> None:
        u = self._unit(spec)
        if spec.kind == "sensor_stuck":
            x, v = self._last if self._last is not None else self._measure()
            self._stuck[u] = (float(x[u]), float(v[u]))
        else:
            self._noise[u] = (spec.position_noise_m, spec.speed_noise_mps)

    def end(self, spec) -> None:
        u = self._unit(spec)
        (self._stuck if spec.kind == "sensor_stuck" else self._noise).pop(u, None)

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        x, v = self._measure()
        for u, (sx, sv) in self._noise.items():
            if sx > 0:
                x[u] += self._rng.normal(0.0, sx)
            if sv > 0:
                v[u] += self._rng.normal(0.0, sv)
        self._last = (x.copy(), v.copy())  # what the sensors showed: a sensor sticks at its last reading
        for u, (xs, vs) in self._stuck.items():
            x[u], v[u] = xs, vs
        return x, v
