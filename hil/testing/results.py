"""What a rig run hands to a test: signals as numpy arrays keyed by entity path, events, metrics, frame times.

The paths are the recording's (:mod:`hil.record.paths`), with the same values (:mod:`hil.record.series`), so a
curve named in a failing assertion is the curve of the same name in the .rrd that ``--hil-record`` keeps.
"""
from __future__ import annotations

import fnmatch
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from hil.record import paths
from hil.record.reader import Series
from hil.record.runlog import Event, RunLog
from hil.record.series import signal_columns
from hil.scenario.model import Scenario


class Signals(Mapping[str, Series]):
    """Entity path -> :class:`Series`; :meth:`match` selects with shell patterns (``/trains/*/units/*/speed_kmh``)."""

    def __init__(self, series: dict[str, Series]) -> None:
        self._series = series

    def __getitem__(self, path: str) -> Series:
        try:
            return self._series[path]
        except KeyError:
            raise KeyError(f"no signal {path!r}; {self._hint(path)}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._series)

    def __len__(self) -> int:
        return len(self._series)

    def match(self, pattern: str) -> dict[str, Series]:
        """Every signal whose path matches the shell pattern (``*`` matches within one path level too); a pattern
        that matches nothing raises KeyError listing similar paths."""
        found = {p: s for p, s in self._series.items() if fnmatch.fnmatchcase(p, pattern)}
        if not found:
            raise KeyError(f"no signal matches {pattern!r}; {self._hint(pattern)}")
        return found

    def _hint(self, path: str) -> str:
        leaf = path.rstrip("/").rsplit("/", 1)[-1]
        similar = sorted({p.rsplit("/", 1)[-1] for p in self._series})
        same_leaf = [p for p in self._series if p.endswith("/" + leaf)][:3]
        if same_leaf:
            return "e.g. " + ", ".join(same_leaf)
        return f"signal names: {', '.join(similar)}"


@dataclass(repr=False)
class HilRun:
    """One finished run of a rig: the scenario as run, its RunLog, metrics, and views for assertions."""

    scenario: Scenario
    log: RunLog
    metrics: dict[str, Any]
    runtime: str  # "virtual" | "realtime"
    controller: str  # the law the ECUs ran
    seed: int
    extra_series: dict[str, Series] = field(default_factory=dict)  # real time: /timing/... lateness, e2e latency
    wall_clock: tuple[float, float] | None = None  # real time: (T0 epoch s, pace)
    frame_recorder: Any = None  # hil.record.frames.FrameRecorder when [recording] frames = true
    rrd: Path | None = None  # set once saved

    def __repr__(self) -> str:
        return (f"HilRun({self.scenario.name!r}, law={self.controller!r}, {self.runtime}, {self.duration_s:g} s, "
                f"{len(self.log.signals)} samples)")

    @cached_property
    def signals(self) -> Signals:
        """Every scalar of the recording: per unit, coupler, gap, reference, bus (load, frame latency), timing."""
        log = self.log
        t = log.t
        out = {p: Series(t, v) for p, v in signal_columns(log.layout, log.signals.array).items()}
        for bus in log.buses:
            load, frames = bus.load.array, bus.frames.array
            out[paths.bus_path(bus.name, "load")] = Series(load[:, 0], load[:, 1])
            out[paths.bus_path(bus.name, "frame_latency_ms")] = Series(frames[:, 0], frames[:, 2] * 1000.0)
        out.update(self.extra_series)
        return Signals(out)

    @property
    def events(self) -> list[Event]:
        return self.log.events

    @property
    def duration_s(self) -> float:
        return self.log.sim_time_s

    def frame_times(self, frame_id: int, bus: str) -> np.ndarray:
        """End-of-transmission times (s) of every frame with this ID on this bus (when receivers got it)."""
        table = self._bus(bus).frames.array
        return table[table[:, 1] == frame_id, 0]

    def _bus(self, name: str):
        for b in self.log.buses:
            if b.name == name:
                return b
        raise KeyError(f"no bus {name!r} in this run (buses: {', '.join(b.name for b in self.log.buses) or 'none'})")

    def describe(self) -> str:
        """One line naming the run, for failure reports."""
        where = f"real time, pace {self.wall_clock[1]:g}" if self.wall_clock else self.runtime
        return (f"run: scenario {self.scenario.name!r}, law {self.controller!r}, {where}, "
                f"{self.duration_s:g} s simulated, seed {self.seed}")

    def save(self, out_dir: Path) -> Path:
        """Write run.rrd (default blueprint; wall_time timeline in real time) and metrics.json into out_dir."""
        from hil.record.rerun_writer import write_runlog

        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        rrd = write_runlog(out_dir / "run.rrd", self.log, self.scenario, wall_clock=self.wall_clock,
                           realtime=self.runtime == "realtime", frames=self.frame_recorder,
                           extra_series={p: (s.t, s.v) for p, s in self.extra_series.items()})
        (out_dir / "metrics.json").write_text(json.dumps(self.metrics, indent=2, allow_nan=False) + "\n")
        self.rrd = rrd
        return rrd
