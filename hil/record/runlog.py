"""The run log: every sampled signal, frame latency and event of one run, as numpy arrays.

The runtimes append to it while running (preallocated chunks, no per-sample allocation);
metrics and the rerun writer read it. Arrays are indexed [sample, unit] front to back.

A long run need not keep its samples: ``release_signals(row)`` summarises the rows before ``row`` for the metrics
(``hil.record.signal_summary``) and lets them go, so memory does not grow with the run's length. The array views
(``t``, ``x``, ...) then hold only the samples not released.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.can.bus_log import BusLog
from hil.scenario.layout import TrainLayout
from hil.record.signal_summary import SignalSummary
from hil.sample_table import SampleTable

SETTLE_BAND_MPS = 0.5 / 3.6  # the metrics' default settling band: 0.5 km/h
SUMMARY_BLOCK_ROWS = 512  # the signal summary takes rows in blocks this long, at fixed row numbers

__all__ = ["BusLog", "Event", "RunLog", "SampleTable"]


@dataclass
class Event:
    """Something that happened at a time: a fault, a timeout, an emergency brake."""

    t: float
    level: str  # "INFO" | "WARN" | "ERROR" (rerun TextLog levels)
    source: str  # entity-ish origin, e.g. "train1/unit2/ecu", "bus1", "radio1-2", "plant"
    text: str


@dataclass
class RunLog:
    """Everything a run produced, for metrics and recording."""

    layout: TrainLayout
    # per sample: t, x_r, v_r, then x[n], v[n], a[n], force_cmd[n], force_applied[n]
    signals: SampleTable = field(init=False)
    buses: list[BusLog] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    reference_change_times: list[float] = field(default_factory=list)
    radio_stats: dict[str, dict[str, int]] = field(default_factory=dict)  # link name -> counters
    codec_saturations: dict[str, int] = field(default_factory=dict)  # "Message.Signal" -> count
    e2e: dict[str, dict[str, int]] = field(default_factory=dict)  # ECU name -> E2E status -> count
    frames_lost: int = 0
    interrupted: bool = False  # stopped early (Ctrl-C): everything up to sim_time_s is valid
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    plant_command_rejects: dict[str, dict[str, int]] = field(default_factory=dict)  # per unit: out-of-sequence commands
    fault_report: dict | None = None  # the faults block of metrics.json, set by hil.faults when faults are scheduled
    silkit_report: dict | None = None  # the silkit block of metrics.json, set by a run under SIL Kit
    # (coupler band, settle band, line limit) -> the summary of the samples and how many rows it has seen
    summaries: dict[tuple, tuple[SignalSummary, int]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.signals = SampleTable(3 + 5 * self.layout.n_units)

    def summary(self, coupler_band: tuple[float, float], settle_band_mps: float = SETTLE_BAND_MPS,
                line_limit_mps: float | None = None) -> SignalSummary:
        """The summary of every sample so far, for these bands: kept up to date as samples come (a summary asked
        for after samples were released must have been asked for before, so it has seen them).

        The summary itself takes rows in whole blocks of SUMMARY_BLOCK_ROWS, at fixed row numbers, so its sums
        never depend on when it was asked (the wall clock paces the recording); the rows after the last whole
        block are added to a copy, which is what is returned."""
        key = (tuple(float(b) for b in coupler_band), float(settle_band_mps), line_limit_mps)
        summary, fed = self._fed_summary(key, line_limit_mps)
        n = len(self.signals)
        if n > fed:
            summary = copy.deepcopy(summary)
            summary.add(self.signals.rows(fed, n))
        return summary

    def _fed_summary(self, key: tuple, line_limit_mps: float | None) -> tuple[SignalSummary, int]:
        """The block-aligned summary of ``key``, fed every whole block of rows there is (made if new)."""
        summary, fed = self.summaries.get(key, (None, 0))
        if summary is None:
            if self.signals.released:
                raise ValueError(f"no summary for {key}: the samples before row {self.signals.released} were "
                                 "released without one")
            summary = SignalSummary(self.layout, key[0], key[1], self.reference_change_times, line_limit_mps)
        upto = fed + (len(self.signals) - fed) // SUMMARY_BLOCK_ROWS * SUMMARY_BLOCK_ROWS
        if upto > fed:
            summary.add(self.signals.rows(fed, upto))
        self.summaries[key] = (summary, upto)
        return summary, upto

    def release_signals(self, row: int) -> None:
        """Summarise the samples before ``row`` (every summary asked for so far) and let them go, but for those
        after the summaries' last whole block (they are let go with the next block)."""
        for key in list(self.summaries):
            row = min(row, self._fed_summary(key, key[2])[1])
        self.signals.release_before(row)

    def tally_frames_lost(self) -> int:
        """Frames lost in the network: dropped from TX queues (or by a fault) on the buses, and offered to the radio
        but not delivered. Sets and returns ``frames_lost`` (both runtimes count it here)."""
        not_delivered = sum(s.get("offered", 0) - s.get("delivered", 0) for s in self.radio_stats.values())
        self.frames_lost = sum(b.frames_dropped for b in self.buses) + not_delivered
        return self.frames_lost

    def add_sample(self, t: float, x_r: float, v_r: float, x: np.ndarray, v: np.ndarray, a: np.ndarray,
                   force_cmd: np.ndarray, force_applied: np.ndarray) -> None:
        self.signals.append(np.concatenate(((t, x_r, v_r), x, v, a, force_cmd, force_applied)))

    def event(self, t: float, level: str, source: str, text: str) -> None:
        self.events.append(Event(t, level, source, text))

    # ---- views on the sampled signals (each (k,) or (k, n))
    def _block(self, i: int) -> np.ndarray:
        n = self.layout.n_units
        return self.signals.array[:, 3 + i * n : 3 + (i + 1) * n]

    @property
    def t(self) -> np.ndarray:
        return self.signals.array[:, 0]

    @property
    def x_ref(self) -> np.ndarray:
        return self.signals.array[:, 1]

    @property
    def v_ref(self) -> np.ndarray:
        return self.signals.array[:, 2]

    @property
    def x(self) -> np.ndarray:
        return self._block(0)

    @property
    def v(self) -> np.ndarray:
        return self._block(1)

    @property
    def a(self) -> np.ndarray:
        return self._block(2)

    @property
    def force_cmd(self) -> np.ndarray:
        return self._block(3)

    @property
    def force_applied(self) -> np.ndarray:
        return self._block(4)

    @property
    def position_error(self) -> np.ndarray:
        """x - x* with x* = x_r - offset."""
        return self.x - (self.x_ref[:, None] - self.layout.offset_m[None, :])

    @property
    def speed_error(self) -> np.ndarray:
        return self.v - self.v_ref[:, None]

    @property
    def couplers(self) -> np.ndarray:
        """(k, n_couplers) coupler displacement e (> 0 stretched)."""
        p = self.layout.coupler_pairs()
        x = self.x
        if len(p) == 0:
            return np.zeros((len(x), 0))
        return x[:, p[:, 0]] - x[:, p[:, 1]] - self.layout.length_m[p[:, 0]][None, :]

    @property
    def gaps(self) -> np.ndarray:
        """(k, n_trains-1) gap between consecutive trains."""
        L = self.layout
        tails, heads = L.tails(), L.heads()
        x = self.x
        return (x[:, tails[:-1]] - L.length_m[tails[:-1]][None, :]) - x[:, heads[1:]]


@dataclass
class RunResult:
    """What a run left behind (either runtime): its log, its metrics, the folder and the files written there."""

    log: RunLog
    metrics: dict[str, Any]
    out_dir: Path
    files: list[Path] = field(default_factory=list)
