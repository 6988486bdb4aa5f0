"""Write a run to a rerun .rrd file in column batches (one `send_columns` per entity per flush).

The writer owns its RecordingStream (never the global one), so several runs can record in one process.
It is incremental: the runtime calls write_* every few simulated seconds with the rows not yet written,
then `flush()`; whatever was flushed stays readable even if the process dies before `close()`.

What is written (paths in :mod:`hil.record.paths`, values in :mod:`hil.record.series`): every scalar signal on the
``sim_time`` timeline, the 2D track (unit boxes, gaps coloured by safety margin, the trains' slots), bus load and
frame latency, events as text logs, and optionally every CAN frame as a text row (:meth:`write_frames`). Real-time
runs pass ``wall_clock=(T0 epoch s, pace)``: every row then also carries a ``wall_time`` timestamp,
T0 + sim_time / pace (the mapping every real-time node uses), so the recording has both timelines.
"""
from __future__ import annotations

import os
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from hil.scenario.layout import TrainLayout
from hil.record import paths
from hil.record.blueprint import default_blueprint
from hil.record.live import LiveStream, LiveTarget
from hil.record.diskspace import MIN_FREE_BYTES, DiskFullError, check_space, disk_full, free_bytes
from hil.record.runlog import BusLog, Event, RunLog
from hil.record.series import MPS_TO_KMH, limit_values, margin_colors, signal_columns, track_geometry

FLUSH_TIMEOUT_S = 10.0  # a flush takes ~20 ms; one that takes this long means rerun's writer is stuck (a full disk)

APPLICATION_ID = "trainhil"
TIMELINE = "sim_time"
WALL_TIMELINE = "wall_time"
SCALARS = rr.Scalars.descriptor_scalars()
TRAIN_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75), (227, 119, 194),
                (127, 127, 127), (188, 189, 34), (23, 190, 207)]
__all__ = ["APPLICATION_ID", "MPS_TO_KMH", "TIMELINE", "WALL_TIMELINE", "RerunWriter", "event_path"]


def settle_file(path: Path, quiet_s: float = 0.2, limit_s: float = 2.0) -> None:
    """Wait (at most ``limit_s``) until ``path`` has not grown for ``quiet_s``: its writer has stopped."""
    start = time.monotonic()
    size, quiet_since = path.stat().st_size, start
    while (now := time.monotonic()) - quiet_since < quiet_s and now - start < limit_s:
        time.sleep(0.02)
        grown = path.stat().st_size
        if grown != size:
            size, quiet_since = grown, time.monotonic()


class RerunWriter:
    """Streams a RunLog (signals, track, buses, events, optional frames) into an .rrd with a default blueprint.

    ``frames``: the recording will hold per-frame text rows (adds the Frames tab); ``wall_clock``: (T0, pace) of a
    real-time run (adds the ``wall_time`` timeline and the Timing tab); ``realtime`` adds the Timing tab alone."""

    def __init__(self, path: Path | None, layout: TrainLayout, scenario_name: str, coupler_band: tuple[float, float],
                 spacing_m: float, emergency_gap_m: float, bus_names: list[str] | None = None, *,
                 frames: bool = False, realtime: bool = False, wall_clock: tuple[float, float] | None = None,
                 live: LiveTarget | None = None, recording_id: str | None = None) -> None:
        """``path``: the .rrd file (None: ``live`` only); ``live``: also stream to a viewer (hil/record/live.py)."""
        if path is None and live is None:
            raise ValueError("a RerunWriter needs a file, a live target, or both")
        self.path = Path(path) if path is not None else None
        self.layout = layout
        self._limits = limit_values(coupler_band, spacing_m, emergency_gap_m)
        self._pairs = layout.coupler_pairs()
        self._closed = False
        if wall_clock is not None and not wall_clock[1] > 0:
            raise ValueError(f"wall_clock pace must be > 0, got {wall_clock[1]!r}")
        self.wall_clock = wall_clock
        recording_id = recording_id if recording_id is not None else str(uuid.uuid4())
        self.live = LiveStream(live, APPLICATION_ID, recording_id) if live is not None else None
        self.rec = _Tee(self._file_stream(recording_id), self.live, self.path)
        self._flushed_size = 0  # bytes of the file written by the last flush that completed
        self.rec.send_recording_name(scenario_name)
        blueprint = default_blueprint(layout, bus_names, frames=frames, realtime=realtime or wall_clock is not None)
        self.rec.send_blueprint(blueprint, make_active=True, make_default=True)
        self._log_series_styles()
        self._log_track_statics()
        self.flush()  # the header, blueprint and statics on disk: a readable file from the start

    def _file_stream(self, recording_id: str) -> rr.RecordingStream | None:
        """The stream that writes run.rrd, or None without a file."""
        if self.path is None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, make_default=False,
                                 make_thread_default=False)
        try:
            rec.save(self.path)
        except RuntimeError as exc:
            raise as_disk_full(exc, self.path) from None
        return rec

    # ---------------------------------------------------------------- static styling

    def _style(self, path: str, name: str, color: tuple[int, int, int] | None = None) -> None:
        lines = rr.SeriesLines(names=[name], colors=None if color is None else [color])
        self.rec.log(path, lines, static=True)

    def _log_series_styles(self) -> None:
        """Legend names per series (every unit entity ends in the same word) and colours for the limits."""
        L = self.layout
        for u in range(L.n_units):
            i, j = L.train_unit(u)
            for signal in ("speed_kmh", "speed_error_kmh", "position_error_m"):
                self._style(paths.unit_path(i, j, signal), f"T{i + 1} U{j + 1}")
            self._style(paths.unit_path(i, j, "traction_kn"), f"T{i + 1} U{j + 1} cmd")
            self._style(paths.unit_path(i, j, "applied_kn"), f"T{i + 1} U{j + 1} applied")
        for front in self._pairs[:, 0]:
            i, j = L.train_unit(int(front))
            self._style(paths.coupler_path(i, j), f"T{i + 1} C{j + 1}")
        for i in range(1, L.n_trains):
            self._style(paths.gap_path(i), f"gap T{i}-T{i + 1}")
        self._style(paths.REF_SPEED, "reference", (128, 128, 128))
        self._style(paths.REF_POSITION, "reference", (128, 128, 128))
        for path, name, color in ((paths.LIMIT_COUPLER_MIN, "band min", (200, 0, 0)), (paths.LIMIT_COUPLER_MAX, "band max", (200, 0, 0)),
                                  (paths.LIMIT_SPACING, "l_s", (0, 150, 0)), (paths.LIMIT_EMERGENCY, "l_e", (200, 0, 0))):
            self._style(path, name, color)

    def _log_track_statics(self) -> None:
        """What does not change along the run: unit box sizes, colours (one per train) and labels; gap line width."""
        L = self.layout
        half = np.column_stack((0.5 * L.length_m, 0.25 * L.length_m))
        colors = [TRAIN_COLORS[L.train_unit(u)[0] % len(TRAIN_COLORS)] for u in range(L.n_units)]
        labels = [f"T{i + 1}U{j + 1}" for i, j in map(L.train_unit, range(L.n_units))]
        self.rec.log(paths.TRACK_UNITS, rr.Boxes2D.from_fields(half_sizes=half, colors=colors, labels=labels,
                                                            radii=-1.5, show_labels=False), static=True)
        self.rec.log(paths.TRACK_SLOTS, rr.Points2D.from_fields(colors=[(128, 128, 128)] * L.n_trains, radii=-4.0,
                                                             labels=[f"slot T{i + 1}" for i in range(L.n_trains)],
                                                             show_labels=False), static=True)
        if L.n_trains > 1:
            self.rec.log(paths.TRACK_GAPS, rr.LineStrips2D.from_fields(radii=-3.0), static=True)

    # ---------------------------------------------------------------- writing

    def _indexes(self, t: np.ndarray) -> list[rr.TimeColumn]:
        """sim_time, and wall_time = T0 + t / pace in real-time runs."""
        out = [rr.TimeColumn(TIMELINE, duration=t)]
        if self.wall_clock is not None:
            t0, pace = self.wall_clock
            out.append(rr.TimeColumn(WALL_TIMELINE, timestamp=t0 + np.asarray(t, dtype=float) / pace))
        return out

    def _send(self, path: str, times: list[rr.TimeColumn], values: np.ndarray) -> None:
        """One Scalars column (same on disk as rr.Scalars.columns, about 40 % less Python overhead)."""
        batch = rr.components.ScalarBatch(np.ascontiguousarray(values, dtype=np.float64))
        self.rec.send_columns(path, indexes=times, columns=[rr.ComponentColumn(SCALARS, batch)])

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"RerunWriter for {self.path} is closed")

    def write_signals(self, log: RunLog, start: int, stop: int) -> None:
        """Send sample rows [start, stop) of every sampled signal and of the track, one batched call per entity."""
        self._check_open()
        if not 0 <= start <= stop <= len(log.signals):
            raise ValueError(f"write_signals rows [{start}, {stop}) outside the log's {len(log.signals)} samples")
        if start == stop:
            return
        rows = log.signals.rows(start, stop)
        times = self._indexes(rows[:, 0])
        for path, values in signal_columns(self.layout, rows).items():
            self._send(path, times, values)
        self._write_track(times, rows)
        self._write_limits(rows[:, 0])

    def _write_track(self, times: list[rr.TimeColumn], rows: np.ndarray) -> None:
        L, k = self.layout, len(rows)
        geo = track_geometry(L, rows)
        cols = rr.Boxes2D.columns(centers=geo.unit_centers.reshape(-1, 2)).partition([L.n_units] * k)
        self.rec.send_columns(paths.TRACK_UNITS, indexes=times, columns=cols)
        cols = rr.Points2D.columns(positions=geo.slots.reshape(-1, 2)).partition([L.n_trains] * k)
        self.rec.send_columns(paths.TRACK_SLOTS, indexes=times, columns=cols)
        g = L.n_trains - 1
        if g:
            labels = [f"{s:.0f} m" for s in geo.gap_m.ravel()]
            cols = rr.LineStrips2D.columns(strips=geo.gap_strips.reshape(-1, 2, 2), labels=labels,
                                           colors=margin_colors(geo.gap_margin).reshape(-1, 4)).partition([g] * k)
            self.rec.send_columns(paths.TRACK_GAPS, indexes=times, columns=cols)

    def _write_limits(self, t: np.ndarray) -> None:
        """Constant reference lines: one point at each end of the written range."""
        ends = np.unique(t[[0, -1]])
        times = self._indexes(ends)
        for path, value in self._limits.items():
            self._send(path, times, np.full(len(ends), value))

    def write_bus(self, bus: BusLog, start_load: int, start_frames: int) -> tuple[int, int]:
        """Send bus load windows and frame latencies not yet written; return the new (load, frames) offsets."""
        self._check_open()
        load, frames = bus.load.rows(start_load, len(bus.load)), bus.frames.rows_from(start_frames)
        if len(load):
            self._send(paths.bus_path(bus.name, "load"), self._indexes(load[:, 0]), load[:, 1])
        if len(frames):
            self._send(paths.bus_path(bus.name, "frame_latency_ms"), self._indexes(frames[:, 0]), frames[:, 2] * 1000.0)
        return start_load + len(load), start_frames + len(frames)

    def write_events(self, events: list[Event]) -> None:
        """Text logs on /events/{source}, one batched call per source."""
        self._check_open()
        by_source: dict[str, list[Event]] = defaultdict(list)
        for ev in events:
            by_source[ev.source].append(ev)
        for source, evs in by_source.items():
            times = self._indexes(np.array([ev.t for ev in evs], dtype=float))
            columns = rr.TextLog.columns(text=[ev.text for ev in evs], level=[ev.level for ev in evs])
            self.rec.send_columns(event_path(source), indexes=times, columns=columns)

    def write_scalars(self, path: str, t: np.ndarray, values: np.ndarray) -> None:
        """Any other scalar series (e.g. the real-time timing under /timing) on the run's timelines."""
        self._check_open()
        if len(t):
            self._send(path, self._indexes(np.asarray(t, dtype=float)), values)

    def write_text_rows(self, path: str, t: np.ndarray, text: list[str], level: list[str]) -> None:
        """Text rows on one entity (per-frame entries: see hil.record.frames)."""
        self._check_open()
        if len(text):
            self.rec.send_columns(path, indexes=self._indexes(np.asarray(t, dtype=float)),
                                  columns=rr.TextLog.columns(text=text, level=level))

    # ---------------------------------------------------------------- lifecycle

    def flush(self) -> None:
        """Push everything sent so far to the file (it stays readable if the process then dies).

        A full disk is a DiskFullError naming the place: checked before, and after a flush with a deadline (rerun's
        writer thread dies when the disk fills, and an unbounded flush would then wait forever)."""
        self._check_open()
        if self.live is not None:
            self.live.flush()  # in the background: a stalled viewer never holds up the file
        if self.rec.file is None:  # live only: nothing on disk to check
            return
        try:
            check_space(self.path)
            try:
                self.rec.file.flush(timeout_sec=FLUSH_TIMEOUT_S)
            except RuntimeError as exc:  # "Flush timed out": the writer thread is stuck or gone
                check_space(self.path)
                raise RuntimeError(f"{self.path}: the recording could not be written within {FLUSH_TIMEOUT_S:g} s: "
                                   f"{exc}") from None
            check_space(self.path)
        except DiskFullError:
            self._cut_to_last_flush()
            raise
        self._flushed_size = self.path.stat().st_size

    def _cut_to_last_flush(self) -> None:
        """Cut a half-written last message off the file (the disk filled during a flush): a reader then gets
        everything up to the last flush that completed, instead of an error at the truncated message.

        First wait for rerun's writer thread to stop writing (the file's size stays put): a write that lands
        after the cut, in the space the cut freed, would leave a hole of zeros that no reader gets past."""
        try:
            settle_file(self.path)
            if self.path.stat().st_size > self._flushed_size:
                os.truncate(self.path, self._flushed_size)
        except OSError:
            pass

    def close(self) -> None:
        """Flush and close the file (writes the .rrd footer). Idempotent; bounded in time even on a full disk."""
        if self._closed:
            return
        self._closed = True
        if self.live is not None:
            self.live.close()
        if self.rec.file is None:
            return
        if free_bytes(self.path) < MIN_FREE_BYTES:
            self._cut_to_last_flush()
            return  # the disk is full: rerun's file writer has stopped, and waiting for it would never end
        try:
            self.rec.file.flush(timeout_sec=FLUSH_TIMEOUT_S)
        except RuntimeError:
            return  # as above, the writer is stuck: what reached the file stays readable
        self.rec.file.disconnect()

    def __enter__(self) -> "RerunWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def as_disk_full(exc: RuntimeError, path: Path | None) -> Exception:
    """rerun's RuntimeError for a write that found no space, as the DiskFullError naming the place; others as
    they are."""
    if "No space left" in str(exc) and path is not None:
        return disk_full(path)
    return exc


class _Tee:
    """Each recording call goes to the file's stream and to the live stream while the viewer keeps up. rerun says
    a full disk as a RuntimeError of the call that could not write: that is a DiskFullError here."""

    def __init__(self, file: rr.RecordingStream | None, live: LiveStream | None, path: Path | None = None) -> None:
        self.file, self.live, self.path = file, live, path

    def _call(self, method: str, *args: Any, **kwargs: Any) -> None:
        if self.file is not None:
            try:
                getattr(self.file, method)(*args, **kwargs)
            except RuntimeError as exc:
                raise as_disk_full(exc, self.path) from None
        if self.live is not None and self.live.alive:
            getattr(self.live.rec, method)(*args, **kwargs)

    def log(self, *args: Any, **kwargs: Any) -> None:
        self._call("log", *args, **kwargs)

    def send_columns(self, *args: Any, **kwargs: Any) -> None:
        self._call("send_columns", *args, **kwargs)

    def send_blueprint(self, *args: Any, **kwargs: Any) -> None:
        self._call("send_blueprint", *args, **kwargs)

    def send_recording_name(self, name: str) -> None:
        self._call("send_recording_name", name)


def event_path(source: str) -> str:
    """/events/{source}, each '/'-separated part of the source escaped for rerun."""
    parts = [rr.escape_entity_path_part(p) for p in source.split("/") if p]
    return "/events/" + ("/".join(parts) if parts else "unknown")


def write_runlog(path: Path, log: RunLog, scenario, *, wall_clock: tuple[float, float] | None = None,
                 realtime: bool = False, frames=None,
                 extra_series: dict[str, tuple[np.ndarray, np.ndarray]] | None = None) -> Path:
    """Write a finished RunLog to ``path`` in one go (tests keep failing runs this way, hil.testing too).

    ``frames``: a :class:`hil.record.frames.FrameRecorder` whose rows are written as well; ``extra_series``:
    entity path -> (t, values) of further scalars (the real-time timing series)."""
    with RerunWriter(path, log.layout, scenario.name, scenario.plant.coupler_band_m, scenario.trains.spacing_m,
                     scenario.trains.emergency_gap_m, [b.name for b in log.buses] or None,
                     frames=frames is not None, realtime=realtime, wall_clock=wall_clock) as w:
        if len(log.signals):
            w.write_signals(log, 0, len(log.signals))
        for bus in log.buses:
            w.write_bus(bus, 0, 0)
        if log.events:
            w.write_events(log.events)
        if frames is not None:
            frames.write(w)
        for entity, (t, values) in (extra_series or {}).items():
            w.write_scalars(entity, t, values)
    return Path(path)
