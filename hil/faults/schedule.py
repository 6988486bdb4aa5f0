"""The fault schedule of a scenario: what each ``[[faults]]`` entry hits, and when it starts and ends.

A fault starts at ``at_s`` (time trigger) or when the head of ``trigger_train`` (default: the fault's own train,
else train 1) reaches ``at_position_m`` (position trigger), and ends ``duration_s`` later (never, without one).
Both runtimes drive the same object: the virtual rig calls ``start``/``end`` at the exact times of time triggers
and ends and ``poll`` every sensor period for position triggers; the real-time plant node calls ``poll`` at every
publication (so its transitions are at most one publication period late, and logged at the time they happen).

Every start and end is an event of source ``faults`` whose text begins ``#k kind on target`` (k = the index in
``[[faults]]``); ``hil.faults.report`` reads them back to match detections to faults, in either runtime.
"""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.scenario.model import Scenario


def needs_fault_machinery(scenario: Scenario) -> bool:
    """Whether a run needs the fault machinery: a fault schedule, or the restart policy."""
    return bool(scenario.faults) or scenario.ecu.restart_after_s is not None


SOURCE = "faults"
BUS_KINDS = ("babbling_node", "bus_corruption", "bus_error_frames", "frame_drop")  # faults on a train's CAN bus
RADIO_KINDS = ("radio_blackout", "radio_burst_loss", "radio_latency")  # faults on the train-to-train radio
_SEED_TAG = 0x4641554C  # "FAUL": keeps fault draws apart from every other stream of the run seed


def fault_rng(seed: int, key: int) -> np.random.Generator:
    """The random stream of fault ``key`` (or of a bus: 1000 + bus index): the same in every process of a run."""
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=(_SEED_TAG, key)))


def target_of(spec) -> str:
    """What a fault hits, as the rig names it: ``train2/unit1``, ``bus2``, ``radio 1-2``, ``radio (all pairs)``."""
    if hasattr(spec, "unit"):
        return TrainLayout.name_of(spec.train - 1, spec.unit - 1)
    if hasattr(spec, "pair"):
        return "radio (all pairs)" if spec.pair is None else f"radio {spec.pair}-{spec.pair + 1}"
    return f"bus{spec.train}"


def label(index: int, spec) -> str:
    """``#k kind on target``: how events name a fault."""
    return f"#{index} {spec.kind} on {target_of(spec)}"


@dataclass
class ScheduledFault:
    """One fault of the schedule and where it stands."""

    index: int
    spec: Any  # a hil.scenario.model fault (their union is built at run time)
    start_s: float | None = None
    end_s: float | None = None

    @property
    def kind(self) -> str:
        return self.spec.kind  # type: ignore[attr-defined]

    @property
    def label(self) -> str:
        return label(self.index, self.spec)

    @property
    def active(self) -> bool:
        return self.start_s is not None and self.end_s is None


class FaultSchedule:
    """The scenario's faults with their triggers (see the module docstring)."""

    def __init__(self, scenario: Scenario, layout: TrainLayout | None = None) -> None:
        self.layout = layout or TrainLayout.from_config(scenario.trains)
        self.faults = [ScheduledFault(k, spec) for k, spec in enumerate(scenario.faults)]

    def __bool__(self) -> bool:
        return bool(self.faults)

    def trigger_unit(self, f: ScheduledFault) -> int:
        """Flat index of the head unit whose position triggers ``f``."""
        spec = f.spec
        train = spec.trigger_train or getattr(spec, "train", None) or getattr(spec, "pair", None) or 1
        return self.layout.index(train - 1, 0)

    def start_text(self, f: ScheduledFault) -> str:
        spec = f.spec
        how = f"at t = {spec.at_s:g} s" if spec.at_s is not None else \
            f"as train {self.layout.train_unit(self.trigger_unit(f))[0] + 1}'s head passed {spec.at_position_m:g} m"
        lasts = f"for {spec.duration_s:g} s" if spec.duration_s is not None else "until the end"
        return f"{f.label}: injected {how}, {lasts}{_details(spec)}"

    def start(self, f: ScheduledFault, t: float) -> None:
        f.start_s = t

    def end(self, f: ScheduledFault, t: float) -> None:
        f.end_s = t

    def poll(self, t: float, x: np.ndarray | None, timed: bool = True) -> list[tuple[ScheduledFault, str]]:
        """Transitions due by ``t`` given unit positions ``x`` (flat, front ends): (fault, "start" | "end"),
        starts first. Marks them done; the caller injects and logs them. ``timed = False``: position triggers
        only (the caller runs time triggers and ends at their exact times)."""
        out: list[tuple[ScheduledFault, str]] = []
        for f in self.faults:
            spec = f.spec
            if f.start_s is None and (timed or spec.at_position_m is not None):
                due = spec.at_s <= t if spec.at_s is not None else \
                    x is not None and x[self.trigger_unit(f)] >= spec.at_position_m
                if due:
                    f.start_s = t
                    out.append((f, "start"))
        for f in self.faults if timed else ():
            if f.active and f.spec.duration_s is not None and f.start_s + f.spec.duration_s <= t + 1e-12:
                f.end_s = t
                out.append((f, "end"))
        return out


def _details(spec) -> str:
    """The kind-specific parameters worth seeing on the timeline."""
    keys = ("position_noise_m", "speed_noise_mps", "frame_id", "probability", "bits", "count", "latency_s", "health")
    parts = []
    for k in keys:
        v = getattr(spec, k, None)
        if v is None or (k == "probability" and v == 1.0):
            continue
        parts.append(f"{k} = 0x{v:03X}" if k == "frame_id" else f"{k} = {v:g}")
    ids = getattr(spec, "frame_ids", None)
    if ids:
        parts.append("frames " + ", ".join(f"0x{i:03X}" for i in ids))
    return f" ({', '.join(parts)})" if parts else ""


def late_faults(sc, duration_s: float) -> list[str]:
    """Warnings for faults timed at or after the end of the run: they will not be injected (said at load time,
    and in the fault report's ``not_injected_because``)."""
    return [f"faults.{i}: at_s = {f.at_s:g} is not before the end of the run (t = {duration_s:g} s): it will not be "
            "injected" for i, f in enumerate(sc.faults) if f.at_s is not None and f.at_s >= duration_s]
