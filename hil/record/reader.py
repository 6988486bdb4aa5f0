"""Read a run back: ``load_run(path)`` gives every scalar series by entity path, the events and the metrics.

    from hil.record import load_run
    run = load_run("runs/seed000")                      # a run directory, or its run.rrd
    t, v = run.series["/trains/2/units/1/speed_kmh"]    # numpy arrays: simulated seconds, values
    [e for e in run.events if e.level == "ERROR"]       # (t, level, source, text), in time order
    run.metrics["safety"]["safe"]                        # metrics.json beside the recording (None if absent)

It reads the .rrd with rerun's own reader (``rerun.chunk.RrdReader``), chunk by chunk; a recording cut short (a run
killed, a disk that filled) reads up to its last complete message (``cut_short`` says so), and a file that is no
recording (garbage, empty) is a ValueError naming it.
"""
from __future__ import annotations

import contextlib
import json
import re
import tempfile
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from rerun.chunk import RrdReader

from hil.record.rrd_file import check_rrd
from hil.record.runlog import Event

SCALARS_COLUMN = "Scalars:scalars"
TIME_COLUMN = "sim_time"


class Series(NamedTuple):
    """One recorded signal: sample times (s, simulated) and values (unit in the path's suffix)."""

    t: np.ndarray
    v: np.ndarray

    def after(self, t0: float) -> "Series":
        """The samples at or after t0."""
        keep = self.t >= t0
        return Series(self.t[keep], self.v[keep])

    def at(self, t: float) -> float:
        """The value held at time t (the last sample at or before t; zero-order hold)."""
        i = int(np.searchsorted(self.t, t, side="right")) - 1
        if i < 0:
            raise ValueError(f"no sample at or before t = {t} s (first at {self.t[0] if len(self.t) else 'none'})")
        return float(self.v[i])


@dataclass(frozen=True)
class Recording:
    """A run read back from its .rrd (and metrics.json)."""

    path: Path
    series: Mapping[str, Series]
    events: list[Event]
    metrics: dict[str, Any] | None
    cut_short: bool = False  # the file ended mid-message: what is here are its complete messages

    def __getitem__(self, entity: str) -> Series:
        try:
            return self.series[entity]
        except KeyError:
            near = [p for p in self.series if p.rsplit("/", 1)[-1] == entity.rsplit("/", 1)[-1]][:3]
            raise KeyError(f"no series {entity!r} in {self.path}" + (f"; e.g. {', '.join(near)}" if near else "")) from None

    def __iter__(self) -> Iterator[str]:
        return iter(self.series)


def load_run(path: str | Path) -> Recording:
    """Every scalar series, event and the metrics of a run directory (or of one .rrd file)."""
    path = Path(path)
    rrd = path / "run.rrd" if path.is_dir() else path
    if not rrd.is_file():
        raise FileNotFoundError(f"{rrd}: no recording (hil run writes run.rrd in its output directory)")
    series: dict[str, list[tuple[np.ndarray, np.ndarray]]] = defaultdict(list)
    events: list[Event] = []
    with _readable(rrd) as (readable, cut_short):
        for chunk in RrdReader(readable).stream():
            _take(chunk, series, events)
    events.sort(key=lambda e: e.t)
    metrics_file = rrd.parent / "metrics.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else None
    return Recording(rrd, {entity: _joined(parts) for entity, parts in sorted(series.items())}, events, metrics,
                     cut_short)


@contextlib.contextmanager
def _readable(rrd: Path) -> Iterator[tuple[Path, bool]]:
    """(a file rerun's reader takes, whether it was cut short): the file itself when whole, else a temporary copy
    of its complete messages; ValueError naming the file when it is no recording at all."""
    check = check_rrd(rrd)
    if not check.ok:
        raise ValueError(f"{rrd}: {check.why}")
    if check.whole or check.complete_bytes == rrd.stat().st_size:  # whole, or ended between messages
        yield rrd, not check.whole
        return
    with tempfile.TemporaryDirectory(prefix="hil-rrd-") as tmp:  # the complete messages before the cut
        prefix = Path(tmp) / rrd.name
        with open(rrd, "rb") as src, open(prefix, "wb") as dst:
            dst.write(src.read(check.complete_bytes))
        yield prefix, True


def _take(chunk, series: dict, events: list[Event]) -> None:
    """One chunk's scalar rows into ``series`` and text rows into ``events``."""
    batch = chunk.to_record_batch()
    names = batch.schema.names
    if TIME_COLUMN not in names:
        return  # static rows (styles, blueprint)
    t = batch.column(TIME_COLUMN).cast("int64").to_numpy() * 1e-9
    if SCALARS_COLUMN in names:
        v = np.array([row[0] if row else np.nan for row in batch.column(SCALARS_COLUMN).to_pylist()], dtype=float)
        series[chunk.entity_path].append((t, v))
    elif "TextLog:text" in names and chunk.entity_path.startswith("/events/"):
        source = _event_source(chunk.entity_path)
        for ti, text, level in zip(t, batch.column("TextLog:text").to_pylist(), batch.column("TextLog:level").to_pylist()):
            events.append(Event(float(ti), (level or ["INFO"])[0], source, (text or [""])[0]))


def recorded_until(rrd: Path) -> float | None:
    """The last sample time an .rrd holds (a cut one up to its last complete message), None when it holds none or
    is no recording."""
    try:
        run = load_run(rrd)
    except (ValueError, OSError, RuntimeError):
        return None
    ends = [float(s.t[-1]) for s in run.series.values() if len(s.t)]
    return max(ends) if ends else None


def _joined(parts: list[tuple[np.ndarray, np.ndarray]]) -> Series:
    t = np.concatenate([p[0] for p in parts])
    v = np.concatenate([p[1] for p in parts])
    order = np.argsort(t, kind="stable")
    return Series(t[order], v[order])


def _event_source(entity: str) -> str:
    """The event's source from its entity path /events/<source> (rerun's escapes undone)."""
    return re.sub(r"\\(.)", r"\1", entity[len("/events/"):])
