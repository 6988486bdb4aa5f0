"""Merging a real-time run's outputs: the nodes' files (plant signals and statistics, ECU and radio results, timing
series) and the bus servers' logs become one ``RunLog`` in simulated time, its timing metrics, and ``run.rrd``.

The orchestrator calls it when a run ends; ``hil recover`` calls it on the files a killed rig left behind.
"""
from __future__ import annotations

import json
from pathlib import Path
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.can.bus_log import LOAD_WINDOW_S
from hil.scenario.layout import TrainLayout
from hil.runtime.realtime.bus_server import BusServer
from hil.runtime.realtime.live_tail import SIGNAL_STREAM
from hil.runtime.realtime.bus_spool import FRAME_WIDTH, LOAD_WIDTH, spool_paths
from hil.sample_table import row_chunks
from hil.record import paths
from hil.record.runlog import BusLog, Event, RunLog
from hil.reference_profile import ReferenceProfile
from hil.scenario.model import Scenario

if TYPE_CHECKING:  # rerun is imported when a recording is opened: a run without one (--no-record) never needs it
    from hil.record.rerun_writer import RerunWriter


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


Sink = tuple  # (RerunWriter, first signal row it still needs)
SIGNAL_CHUNK_ROWS = 4096  # signal rows merged at a time (each is 3 + 5 x units values, with their columns)


def merge_nodes(sc: Scenario, layout: TrainLayout, nodes_dir: Path, servers: Sequence[Any], events: list[Event],
                t0: float | None, pace: float, duration: float, wall: float, stop_reason: str | None,
                sinks: Sequence[Sink] = (), keep_rows: bool = True, radio_stats: dict | None = None):
    """The nodes' files and the servers' spools as one RunLog in simulated time, and the timing metrics.
    ``servers``: the bus servers (``BusServer``), or anything with their ``log`` and ``epoch0`` (``hil recover``).

    The plant's signals and the buses' rows are read chunk by chunk into the log's statistics and into each of
    ``sinks`` (writers, with the first signal row each needs); ``keep_rows=False`` lets each chunk go once it is
    counted and written, so the merge of a long run needs no memory for them. ``radio_stats``: the radio links'
    counters when the radio ran in the bus servers (else the radio node's ``radio.json``)."""
    log = RunLog(layout)
    log.reference_change_times = ReferenceProfile.from_config(sc.reference).change_times
    log.summary(sc.plant.coupler_band_m)  # the metrics' figures, kept as the chunks come
    plant = _read_json(nodes_dir / "plant.json") or {}
    _stream_signals(log, nodes_dir, sinks, keep_rows)
    log.events.extend(Event(*e) for e in plant.get("events", []))
    ecus = [d for p in sorted(nodes_dir.glob("ecu_*.json")) if (d := _read_json(p))]
    for d in ecus:
        log.events.extend(Event(t, level, d["name"], text) for t, level, text in d["events"])
        log.e2e[d["name"]] = d["e2e"]
    log.events.extend(events)
    if stop_reason:
        log.events.append(Event(float(plant.get("sim_time_s", 0.0)), "WARN", "rig", f"run stopped early: {stop_reason}"))
    log.events.sort(key=lambda e: e.t)
    log.plant_command_rejects = plant.get("command_rejects", {})
    if radio_stats is None:
        radio_stats = (_read_json(nodes_dir / "radio.json") or {}).get("links", {})
    log.radio_stats = radio_stats
    for s in servers:
        shift = 0.0 if t0 is None else (t0 - s.epoch0) * pace
        log.buses.append(_stream_bus(s.log, nodes_dir, shift, None if t0 is None else duration, sinks, keep_rows))
    log.tally_frames_lost()
    sat: dict[str, int] = {}
    for d in [plant, *ecus]:
        for k, v in d.get("codec_saturations", {}).items():
            sat[k] = sat.get(k, 0) + v
    log.codec_saturations = sat
    log.sim_time_s = float(plant.get("sim_time_s", 0.0))
    if len(log.signals):  # a plant killed between saves of plant.json streamed further than it says
        log.sim_time_s = max(log.sim_time_s, float(log.signals.last(0)))
    log.wall_time_s = float(plant.get("wall_time_s") or wall)  # the plant's: sim t = 0 to its last step
    log.interrupted = bool(stop_reason) or bool(plant.get("interrupted", True))
    return log, _timing_metrics(plant, ecus, servers)


def _stream_signals(log: RunLog, nodes_dir: Path, sinks: Sequence[Sink], keep_rows: bool) -> None:
    """The plant's signal rows (its stream, signals.bin; a row cut by a killed plant is left out) into the log."""
    for rows in row_chunks(nodes_dir / SIGNAL_STREAM, log.signals.width, SIGNAL_CHUNK_ROWS):
        start = len(log.signals)
        log.signals.extend_bytes(rows.tobytes())
        for writer, first in sinks:
            if len(log.signals) > max(start, first):
                writer.write_signals(log, max(start, first), len(log.signals))
                writer.flush()  # to the file now: rerun would hold the whole run in its buffers otherwise
        if not keep_rows:
            log.release_signals(len(log.signals))


def _stream_bus(src: BusLog, nodes_dir: Path, shift: float, duration: float | None, sinks: Sequence[Sink],
                keep_rows: bool) -> BusLog:
    """A server's spooled rows (hil/runtime/realtime/bus_spool.py) moved to simulated time (model t -> t - shift)
    and cut to [0, duration] (None: as they are), as one BusLog, written to the sinks chunk by chunk. Cut, a load
    window is kept only whole: the server's windows end at the run's t = k x the window (``align_load_windows``), so
    the first kept ends at t = one window, as in virtual time; and the frames sent are the run's, those of its rows
    (the server's count goes on past the run's end)."""
    out = BusLog(src.name, src.bitrate, frames_sent=src.frames_sent, frames_dropped=src.frames_dropped,
                 dropped_by_node=dict(src.dropped_by_node))
    frames_path, load_path = spool_paths(nodes_dir, src.name)
    offsets = [(0, 0) for _ in sinks]
    for path, width, dst, first in ((load_path, LOAD_WIDTH, out.load, LOAD_WINDOW_S),
                                    (frames_path, FRAME_WIDTH, out.frames, 0.0)):
        for rows in row_chunks(path, width):
            rows = rows.copy()
            rows[:, 0] -= shift
            if duration is not None:
                rows = rows[(rows[:, 0] >= first - 1e-9) & (rows[:, 0] <= duration + 1e-9)]
            dst.extend_bytes(np.ascontiguousarray(rows, dtype=float).tobytes())
            offsets = [writer.write_bus(out, *at) for (writer, _), at in zip(sinks, offsets)]
            for writer, _ in sinks:
                writer.flush()
            if not keep_rows:
                out.frames.release(len(out.frames))
                out.load.release_before(len(out.load))
    if duration is not None:
        out.frames_sent = len(out.frames)
    return out


def _timing_metrics(plant: dict, ecus: list[dict], servers: Sequence[Any]) -> dict[str, Any]:
    def worst(key: str, rows: list[dict]) -> float | None:
        vals = [r[key] for r in rows if r.get(key) is not None]
        return max(vals) if vals else None

    return {
        "cycle_lateness_p50_s": worst("lateness_p50_s", ecus),
        "cycle_lateness_p99_s": worst("lateness_p99_s", ecus),
        "cycle_lateness_max_s": worst("lateness_max_s", ecus),
        "cycle_deadline_misses": sum(r.get("deadline_misses", 0) for r in ecus),
        "plant_lateness_p99_s": plant.get("lateness_p99_s"),
        "plant_lateness_max_s": plant.get("lateness_max_s"),
        "plant_deadline_misses": plant.get("deadline_misses"),
        "e2e_latency_p50_s": plant.get("e2e_latency_p50_s"),
        "e2e_latency_p99_s": plant.get("e2e_latency_p99_s"),
        "e2e_latency_max_s": plant.get("e2e_latency_max_s"),
        **({"external_units": plant["external_units"]} if "external_units" in plant else {}),
        "realtime": {
            "ecus": {r["name"]: {k: v for k, v in r.items() if k not in ("events", "e2e", "codec_saturations", "name")}
                     for r in ecus},
            "plant": {k: v for k, v in plant.items() if k not in ("events", "codec_saturations", "external_units")},
        },
    }


def open_recording(sc: Scenario, layout: TrainLayout, path: Path, wall_clock: tuple[float, float] | None,
                   bus_names: list[str]) -> RerunWriter:
    """The run.rrd of a real-time run, for merge_nodes to stream into (``wall_clock`` = (T0 epoch s, pace), when
    the run got as far as its start: the wall-clock timeline)."""
    from hil.record.rerun_writer import RerunWriter

    return RerunWriter(path, layout, sc.name, sc.plant.coupler_band_m, sc.trains.spacing_m, sc.trains.emergency_gap_m,
                       bus_names or None, realtime=True, wall_clock=wall_clock)


def write_rest(w: RerunWriter, log: RunLog, nodes_dir: Path) -> None:
    """After merge_nodes streamed the signals and buses: the events and the nodes' timing series (in ms), flushed."""
    if log.events:
        w.write_events(log.events)
    for entity, f in timing_series(nodes_dir):  # cycle lateness per node, sensor-to-actuator latency
        for rows in row_chunks(f, 2):
            w.write_scalars(entity, rows[:, 0], rows[:, 1] * 1e3)
    w.flush()


def timing_series(nodes_dir: Path) -> list[tuple[str, Path]]:
    """(entity path, file of (sim time, value s) rows, hil/runtime/realtime/streamed_series.py) of every timing series
    the nodes left."""
    out = [(paths.TIMING + "/plant/lateness_ms", nodes_dir / "timing_plant.bin"),
           (paths.TIMING + "/e2e_latency_ms", nodes_dir / "timing_e2e.bin")]
    for f in sorted(nodes_dir.glob("timing_ecu_*_*.bin")):
        train, unit = f.stem.split("_")[-2:]
        out.append((f"{paths.TIMING}/train{train}/unit{unit}/ecu_lateness_ms", f))
    return [(entity, f) for entity, f in out if f.exists()]
