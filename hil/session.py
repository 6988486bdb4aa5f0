"""One run from start to files: build the rig, run it with a progress bar, record, write metrics.

Recording is incremental (every few simulated seconds) so a run stopped with Ctrl-C still leaves a
readable ``run.rrd`` and ``metrics.json`` covering everything up to the stop.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from hil.can.bus import Transmission
from hil.record.metrics import compute_metrics
from hil.record.rerun_writer import RerunWriter
from hil.record.runlog import RunLog
from hil.runtime.ideal import IdealLoop
from hil.runtime.virtual import VirtualRig
from hil.scenario.model import Scenario


@dataclass
class RunResult:
    """What a run left behind."""

    log: RunLog
    metrics: dict[str, Any]
    out_dir: Path
    files: list[Path] = field(default_factory=list)


class IncrementalRecorder:
    """Feeds the rerun writer with what the run log gained since the last call."""

    def __init__(self, writer: RerunWriter) -> None:
        self.writer = writer
        self._signals = 0
        self._events = 0
        self._bus_offsets: dict[str, tuple[int, int]] = {}

    def __call__(self, log: RunLog) -> None:
        n = len(log.signals)
        if n > self._signals:
            self.writer.write_signals(log, self._signals, n)
            self._signals = n
        for bus in log.buses:
            start = self._bus_offsets.get(bus.name, (0, 0))
            self._bus_offsets[bus.name] = self.writer.write_bus(bus, *start)
        if len(log.events) > self._events:
            self.writer.write_events(log.events[self._events:])
            self._events = len(log.events)
        self.writer.flush()


def _can_loggers(rig: VirtualRig, out_dir: Path) -> list[can.ASCWriter]:
    """One ASC log per bus, each frame stamped with the end of its transmission (simulated seconds)."""
    writers = []
    for i, bus in enumerate(rig.buses):
        w = can.ASCWriter(out_dir / f"{bus.name}.asc", channel=i + 1)
        w.log_event("trainhil virtual time: timestamps are simulated seconds", 0.0)  # pins the time origin at t = 0

        def listener(tx: Transmission, w: can.ASCWriter = w, channel: int = i) -> None:
            w.on_message_received(can.Message(timestamp=tx.t_end * 1e-9, arbitration_id=tx.frame_id, data=tx.data,
                                              is_extended_id=tx.extended, is_rx=True, channel=channel))

        bus.frame_listeners.append(listener)
        writers.append(w)
    return writers


def run_scenario(scenario: Scenario, out_dir: Path, *, seed: int | None = None, duration_s: float | None = None,
                 can_log: bool = False, ideal: bool = False, record: bool = True, progress: bool = False,
                 chunk_s: float = 10.0, min_flush_wall_s: float = 2.0) -> RunResult:
    """Run a scenario (virtual time, or the ideal loop) and write run.rrd, metrics.json and CAN logs into out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    duration = scenario.duration_s if duration_s is None else duration_s
    files: list[Path] = []
    writer = None
    if record:
        writer = RerunWriter(out_dir / "run.rrd", _layout(scenario), scenario.name, scenario.plant.coupler_band_m,
                             scenario.trains.spacing_m, scenario.trains.emergency_gap_m)
        files.append(out_dir / "run.rrd")
    recorder = IncrementalRecorder(writer) if writer else None
    bar = _progress_bar(duration, scenario.name) if progress else None
    loggers: list[can.ASCWriter] = []
    try:
        if ideal:
            log = IdealLoop(scenario, seed).run(duration)
            if recorder:
                recorder(log)
        else:
            rig = VirtualRig(scenario, seed)
            if can_log:
                loggers = _can_loggers(rig, out_dir)
                files += [out_dir / f"{b.name}.asc" for b in rig.buses]
            log = rig.run(duration, progress=(lambda t: bar.update(round(t - bar.n, 3))) if bar else None,
                          on_chunk=_every(recorder, chunk_s, min_flush_wall_s) if recorder else None)
            if recorder:
                recorder(log)
    finally:
        if bar:
            bar.close()
        for w in loggers:
            w.stop()
        if writer:
            writer.close()
    metrics = compute_metrics(log, scenario.plant.coupler_band_m)
    metrics["scenario"] = scenario.name
    metrics["runtime"] = "ideal" if ideal else "virtual"
    metrics["interrupted"] = log.interrupted
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    files.append(out_dir / "metrics.json")
    return RunResult(log, metrics, out_dir, files)


def _every(fn, chunk_s: float, min_wall_s: float):
    """Call fn(log) once chunk_s of simulated time and min_wall_s of wall time have passed since the last call.

    Each flush costs ~20 ms of rerun calls whatever its size, so a fast run flushes by wall time."""
    state = {"next": chunk_s, "wall": time.perf_counter()}

    def maybe(log: RunLog) -> None:
        now = time.perf_counter()
        t = log.signals.last(0)
        if t >= state["next"] and now - state["wall"] >= min_wall_s:
            fn(log)
            state["next"], state["wall"] = t + chunk_s, now

    return maybe


def _layout(scenario: Scenario):
    from hil.layout import TrainLayout

    return TrainLayout.from_config(scenario.trains)


def _progress_bar(total: float, name: str):
    from tqdm import tqdm

    return tqdm(total=total, unit="s", desc=f"{name} (sim time)", bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}, {rate_fmt}]")
