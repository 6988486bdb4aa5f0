"""Radio faults on train-to-train links: a time-triggered blackout, a burst of losses, added latency.

One ``RadioImpairment`` per link direction, consulted by ``RadioLink.offer`` after its range and tunnel checks
(``link.impairment``): it returns the extra delay of a frame in ns, or None to drop it (counted as ``fault`` in
the link's statistics, so it is among the frames lost). Its loss draws come from the fault's own stream, never
from the link's, so the link's common random numbers stay as they were.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np


class RadioImpairment:
    """The active radio faults of one link direction."""

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self.blackouts = 0
        self.losses: dict[int, float] = {}  # fault index -> loss probability
        self.latency_ns: dict[int, int] = {}  # fault index -> extra latency

    def __bool__(self) -> bool:
        return bool(self.blackouts or self.losses or self.latency_ns)

    def __call__(self, t_ns: int) -> int | None:
        if self.blackouts:
            return None
        for p in self.losses.values():
            if self._rng.random() < p:
                return None
        return sum(self.latency_ns.values())


def pair_links(pair: int | None, n_trains: int) -> list[str]:
    """Link names (``"1>2"``, ``"2>1"``) of radio pair ``pair`` (trains pair, pair+1), or of every pair."""
    pairs = range(1, n_trains) if pair is None else [pair]
    return [name for p in pairs for name in (f"{p}>{p + 1}", f"{p + 1}>{p}")]


ImpairmentSetter = Callable[[str, RadioImpairment], None]  # (link name, its impairments now)


class RadioFaults:
    """Radio faults on a gateway's links (``links``: name -> RadioLink). ``apply(name, impairment)`` puts a link's
    impairments into effect (default: on the Python link; the engine's links: ``engine_net.engine_impairments``)."""

    def __init__(self, links: dict, n_trains: int, rng: np.random.Generator, apply: ImpairmentSetter | None = None) -> None:
        self._n = n_trains
        self._imp = {name: RadioImpairment(rng) for name in links}
        for name, link in links.items():
            link.impairment = None
        self._links = links
        self._set = apply or self._on_python_link

    def _on_python_link(self, name: str, imp: RadioImpairment) -> None:
        self._links[name].impairment = imp if imp else None

    def _apply(self, spec, index: int, on: bool) -> None:
        for name in pair_links(spec.pair, self._n):
            imp = self._imp[name]
            if spec.kind == "radio_blackout":
                imp.blackouts += 1 if on else -1
            elif spec.kind == "radio_burst_loss":
                _toggle(imp.losses, index, spec.probability, on)
            else:
                _toggle(imp.latency_ns, index, round(spec.latency_s * 1e9), on)
            self._set(name, imp)

    def start(self, spec, index: int) -> None:
        self._apply(spec, index, True)

    def end(self, spec, index: int) -> None:
        self._apply(spec, index, False)


def _toggle(table: dict, key: int, value, on: bool) -> None:
    if on:
        table[key] = value
    else:
        table.pop(key, None)
