"""``hil recover RUN_DIR``: rebuild run.rrd and metrics.json of a real-time run whose rig was killed.

The orchestrator writes the recording when the run ends, from the files its node processes leave in
``RUN_DIR/nodes``. If the orchestrator itself dies (``kill -9``, an out-of-memory kill, a power cut of the
terminal), the nodes notice that their stdin closed, stop, and write their results; the plant has also streamed
its signal rows to ``nodes/signals.bin`` all along, and the orchestrator its bus servers' frame rows and load
windows to ``nodes/<bus>.*.bin`` every second. This merges those files as the orchestrator would have. What lived
only in the orchestrator is gone and is said so: its own events, the TX-queue drop counts, and the bus rows of the
last second. The result is marked ``"recovered": true`` and ``"interrupted": true``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.runtime.realtime.node import load_scenario_json
from hil.runtime.realtime.bus_spool import FRAME_WIDTH, spool_paths
from hil.runtime.realtime.merge import merge_nodes, open_recording, write_rest
from hil.runtime.realtime.orchestrator import RUN_FILE
from hil.record.integrity import RUNNING, write_json_atomic
from hil.record.metrics import run_metrics
from hil.record.runlog import BusLog, Event
from hil.record.safety import record_violations
from hil.runtime.realtime.live_tail import SIGNAL_STREAM
from hil.sample_table import row_chunks

MAX_PLAUSIBLE = 1e9  # no position (m), speed, acceleration or force (N) of a train comes near this
NODES_GRACE_S = 10.0  # how long the nodes of a killed rig may still be writing their results


class RecoverError(ValueError):
    """RUN_DIR is not a real-time run that can be recovered (the message says why)."""


def recover(out_dir: Path, wait_s: float = NODES_GRACE_S) -> dict:
    """Rebuild ``out_dir``'s run.rrd and metrics.json from its nodes' files; the new metrics."""
    out_dir = Path(out_dir)
    nodes_dir = out_dir / "nodes"
    status = _status(out_dir / "metrics.json")
    if not (nodes_dir / "scenario.json").is_file():
        raise RecoverError(f"{out_dir}: no nodes/scenario.json: not the output directory of a real-time run")
    if status == "failed":
        raise RecoverError(f"{out_dir}: the rig did not start, nothing ran; nothing to recover")
    if status is not None and status != RUNNING:
        raise RecoverError(f"{out_dir}: the run finished and wrote its results; nothing to recover")
    _wait_for_plant(nodes_dir, wait_s)
    sc = _scenario(nodes_dir)
    run = _read(nodes_dir / RUN_FILE)
    if not isinstance(run, dict) or not isinstance(run.get("t0"), (int, float)):
        raise RecoverError(f"{out_dir}: the rig never started (no valid nodes/{RUN_FILE}): there is no run to recover")
    pace, duration = float(run.get("pace", 1.0)), float(run.get("duration_s", sc.duration_s))
    layout = TrainLayout.from_config(sc.trains)
    every = max(1, round(sc.recording.period_s / sc.plant.step_s))  # the plant records every this many steps
    signals_end = check_signal_stream(nodes_dir / SIGNAL_STREAM, 3 + 5 * layout.n_units, every * sc.plant.step_s,
                                      duration)
    lost = Event(0.0, "WARN", "rig", "recovered by hil recover: the rig's orchestrator stopped during the run; its own "
                                     "events, the TX-queue drop counts and up to a second of bus rows were lost with it")
    notes = [lost] + _cut_stream_note(nodes_dir, signals_end, every * sc.plant.step_s)
    t0 = run.get("t0")
    buses = spooled_buses(nodes_dir, run) if t0 is not None else []
    with open_recording(sc, layout, out_dir / "run.rrd", None if t0 is None else (float(t0), pace),
                        [b.log.name for b in buses]) as rrd:
        log, extra = merge_nodes(sc, layout, nodes_dir, buses, notes, t0, pace, duration, 0.0,
                                 "the orchestrator died", [(rrd, 0)], keep_rows=False)
        record_violations(log, sc.plant.coupler_band_m)
        write_rest(rrd, log, nodes_dir)
    log.interrupted = True
    log.sim_time_s = signals_end  # what the recovered figures cover, whatever plant.json last said
    metrics = run_metrics(log, sc, "realtime", int(run.get("seed", sc.seed)), pace=pace)
    metrics.update(extra)
    metrics.update(recovered=True, recovered_covers_s=[0.0, signals_end], recovered_missing=[
        "orchestrator events", "TX-queue drop counts", "the bus rows of the last second before the kill"])
    write_json_atomic(out_dir / "metrics.json", metrics)
    return metrics


def _cut_stream_note(nodes_dir: Path, signals_end: float, period_s: float) -> list[Event]:
    """A WARN when the signal stream ends before the time the plant last reported (a cut file): the recovered
    figures and verdicts cover only the stream."""
    said = (_read(nodes_dir / "plant.json") or {}).get("sim_time_s")
    if isinstance(said, (int, float)) and said > signals_end + 1.5 * period_s:
        return [Event(signals_end, "WARN", "rig", f"the plant's signal stream ends at t = {signals_end:.2f} s, though "
                      f"the plant ran to {said:.2f} s: the recovered figures and verdicts cover 0-{signals_end:.2f} s")]
    return []


def _scenario(nodes_dir: Path):
    """The run's scenario, or RecoverError when nodes/scenario.json is not one."""
    try:
        return load_scenario_json(str(nodes_dir / "scenario.json"))
    except (OSError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
        first = str(exc).splitlines()
        raise RecoverError(f"{nodes_dir / 'scenario.json'}: not a valid scenario ({first[0] if first else exc}): "
                           "refusing to recover from it") from None


def check_signal_stream(path: Path, width: int, period_s: float, duration_s: float) -> float:
    """The time the plant's signal stream covers (its last sample), after checking every row is a sample: finite,
    of plausible size, its time advancing by the recording period from 0 up to the run's duration. Anything else
    is a RecoverError naming the row: a corrupt stream is refused, not turned into figures."""
    seen = 0
    for chunk in row_chunks(path, width):
        k = seen + np.arange(len(chunk))
        t = chunk[:, 0]
        bad = ~np.isfinite(chunk).all(axis=1) | (np.abs(chunk) > MAX_PLAUSIBLE).any(axis=1)
        bad |= (np.abs(t - k * period_s) > 1e-6 + 1e-9 * np.abs(t)) | (t > duration_s + period_s)
        if bad.any():
            i = int(np.argmax(bad))
            raise RecoverError(f"{path}: row {seen + i} is not a sample of this run (t = {float(t[i])!r}, expected "
                               f"{(seen + i) * period_s:g} s): the stream is corrupt; nothing recovered")
        seen += len(chunk)
    if seen == 0:
        raise RecoverError(f"{path}: no samples: the plant never recorded, there is nothing to recover")
    return (seen - 1) * period_s


def spooled_buses(nodes_dir: Path, run: dict) -> list[SimpleNamespace]:
    """The killed rig's buses as merge_nodes reads them: their spooled rows (hil/runtime/realtime/bus_spool.py), the
    epoch and bitrate from run.json; frames sent = the rows spooled, drops unknown (0)."""
    out = []
    for name, bus in (run.get("buses") or {}).items():
        frames, _ = spool_paths(nodes_dir, name)
        if frames.exists():
            sent = frames.stat().st_size // (8 * FRAME_WIDTH)
            out.append(SimpleNamespace(log=BusLog(name, int(bus["bitrate"]), frames_sent=sent), epoch0=float(bus["epoch0"])))
    return out


def _status(path: Path) -> str | None:
    data = _read(path)
    return None if data is None else data.get("status", "complete")


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _wait_for_plant(nodes_dir: Path, wait_s: float) -> None:
    """The plant writes plant.json when it stops; give a just-killed rig's nodes that long to finish."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        plant = _read(nodes_dir / "plant.json")
        if plant is not None and not _stream_growing(nodes_dir):
            return
        time.sleep(0.25)


def _stream_growing(nodes_dir: Path) -> bool:
    """True while the plant still appends to its signal stream (its rig died a moment ago)."""
    path = nodes_dir / SIGNAL_STREAM
    try:
        size = path.stat().st_size
        time.sleep(0.3)
        return path.stat().st_size != size
    except OSError:
        return False
