"""Merging a real-time run's outputs: the nodes' files (plant signals and statistics, ECU and radio results, timing
series) and the bus servers' logs become one ``RunLog`` in simulated time, its timing metrics, and ``run.rrd``.

The orchestrator calls it when a run ends; ``hil recover`` calls it on the files a killed rig left behind.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hil.layout import TrainLayout
from hil.runtime.realtime.busserver import BusServer
from hil.runtime.realtime.live_tail import SIGNAL_STREAM
from hil.runtime.realtime.series_stats import read_series
from hil.record import paths
from hil.record.rerun_writer import write_runlog
from hil.record.runlog import BusLog, Event, RunLog
from hil.reference import ReferenceProfile
from hil.scenario.model import Scenario


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def merge_nodes(sc: Scenario, layout: TrainLayout, nodes_dir: Path, servers: list[BusServer], events: list[Event],
           t0: float | None, pace: float, duration: float, wall: float, stop_reason: str | None):
    log = RunLog(layout)
    log.reference_change_times = ReferenceProfile.from_config(sc.reference).change_times
    plant = _read_json(nodes_dir / "plant.json") or {}
    log.signals.extend_bytes(_signal_rows(nodes_dir, log.signals.width))
    log.events.extend(Event(*e) for e in plant.get("events", []))
    ecus = [d for p in sorted(nodes_dir.glob("ecu_*.json")) if (d := _read_json(p))]
    for d in ecus:
        log.events.extend(Event(t, level, d["name"], text) for t, level, text in d["events"])
        log.e2e[d["name"]] = d["e2e"]
    log.events.extend(events)
    if stop_reason:
        log.events.append(Event(float(plant.get("sim_time_s", 0.0)), "WARN", "rig", f"run stopped early: {stop_reason}"))
    log.events.sort(key=lambda e: e.t)
    radio = (_read_json(nodes_dir / "radio.json") or {}).get("links", {})
    log.radio_stats = radio
    for s in servers:
        log.buses.append(s.log if t0 is None else _sim_bus_log(s, t0, pace, duration))
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


def _signal_rows(nodes_dir: Path, width: int) -> bytes:
    """The plant's signal rows, whole rows of its stream (signals.bin; a plant killed mid-write leaves a part)."""
    try:
        streamed = (nodes_dir / SIGNAL_STREAM).read_bytes()
    except OSError:
        return b""
    return streamed[:len(streamed) - len(streamed) % (8 * width)]


def _sim_bus_log(server: BusServer, t0: float, pace: float, duration: float) -> BusLog:
    """The server's BusLog with its times moved to simulated time (model t -> t - (T0 - epoch0) * pace)."""
    src, shift = server.log, (t0 - server.epoch0) * pace
    out = BusLog(src.name, src.bitrate, frames_sent=src.frames_sent, frames_dropped=src.frames_dropped)
    for table, dst in ((src.load.array, out.load), (src.frames.array, out.frames)):
        if len(table):
            rows = table.copy()
            rows[:, 0] -= shift
            rows = rows[(rows[:, 0] >= 0) & (rows[:, 0] <= duration + 1e-9)]
            dst.extend_bytes(np.ascontiguousarray(rows, dtype=float).tobytes())
    return out


def _timing_metrics(plant: dict, ecus: list[dict], servers: list[BusServer]) -> dict[str, Any]:
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


def write_recording(sc: Scenario, layout: TrainLayout, log: RunLog, path: Path, nodes_dir: Path,
                    wall_clock: tuple[float, float] | None) -> None:
    """The recording of a real-time run: signals, buses, events and timing on sim time, plus the wall-clock
    timeline (``wall_clock`` = (T0 epoch s, pace)) when the run got as far as its start."""
    write_runlog(path, log, sc, wall_clock=wall_clock, realtime=True, extra_series=timing_scalars(nodes_dir))


def timing_scalars(nodes_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Entity path -> (sim time, value in ms) of every timing series the nodes left (cycle lateness per node,
    sensor-to-actuator latency)."""
    out = {}
    for entity, f in timing_series(nodes_dir):
        data = read_series(f)
        if len(data):
            out[entity] = (data[:, 0], data[:, 1] * 1e3)
    return out


def timing_series(nodes_dir: Path) -> list[tuple[str, Path]]:
    """(entity path, file of (sim time, value s) rows, hil/runtime/realtime/series_stats.py) of every timing series
    the nodes left."""
    out = [(paths.TIMING + "/plant/lateness_ms", nodes_dir / "timing_plant.bin"),
           (paths.TIMING + "/e2e_latency_ms", nodes_dir / "timing_e2e.bin")]
    for f in sorted(nodes_dir.glob("timing_ecu_*_*.bin")):
        train, unit = f.stem.split("_")[-2:]
        out.append((f"{paths.TIMING}/train{train}/unit{unit}/ecu_lateness_ms", f))
    return [(entity, f) for entity, f in out if f.exists()]
