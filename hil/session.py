"""One run from start to files: build the rig, run it with a progress bar, record, write metrics.

Recording is incremental (every few simulated seconds) so a run stopped with Ctrl-C still leaves a
readable ``run.rrd`` and ``metrics.json`` covering everything up to the stop. SIGTERM and SIGHUP stop it the
same way; metrics.json is a "running" stub (atomic writes, ``hil.record.integrity``) until the run ends, and a
plant that diverges ends the run with an ERROR event, the files written, then the error raised.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable


from hil.record.canlog import frame_listener, log_format, log_path, open_can_log
from hil.plant.dynamics import PlantDiverged
from hil.record.diskspace import DiskFullError
from hil.record.integrity import StopSignals, mark_failed, mark_running, write_json_atomic
from hil.record.out_dir import disk_full_outcome, write_metrics_when_full
from hil.record.live import LIVE_FLUSH_WALL_S, LiveTarget
from hil.record.metrics import run_metrics
from hil.record.rerun_writer import RerunWriter
from hil.record.runlog import RunLog, RunResult  # noqa: F401  (RunResult: what run_scenario returns)
from hil.runtime.errors import RigDidNotStart
from hil.runtime.ideal import IdealLoop
from hil.runtime.train_db import load_train_db
from hil.runtime.virtual import VirtualRig
from hil.silkit.options import SilKitOptions
from hil.scenario.model import Scenario


class IncrementalRecorder:
    """Feeds the rerun writer with what the run log gained since the last call."""

    def __init__(self, writer: RerunWriter) -> None:
        self.writer = writer
        self._signals = 0
        self._events = 0
        self._bus_offsets: dict[str, tuple[int, int]] = {}
        self.frames = None  # a hil.record.frames.FrameRecorder when [recording] frames = true

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
        if self.frames is not None:
            self.frames.write(self.writer)
        self.writer.flush()

    @property
    def signals_written(self) -> int:
        """How many signal rows are in the recording."""
        return self._signals

    def load_written(self, bus) -> int:
        """How many of ``bus``'s load windows are in the recording."""
        return self._bus_offsets.get(bus.name, (0, 0))[0]

    def frames_written(self, bus) -> int:
        """How many of ``bus``'s frame rows are in the recording."""
        return self._bus_offsets.get(bus.name, (0, 0))[1]


def _can_loggers(rig: VirtualRig, out_dir: Path, fmt: str) -> list:
    """One CAN log per bus, each frame stamped with the end of its transmission (simulated seconds)."""
    writers = []
    for i, bus in enumerate(rig.buses):
        w = open_can_log(out_dir, bus.name, i, "virtual time", fmt)
        bus.frame_listeners.append(frame_listener(w, i, lambda t_ns: t_ns * 1e-9))
        writers.append(w)
    return writers


def _silkit_rig(scenario: Scenario, seed: int | None, db, options: "SilKitOptions") -> VirtualRig:
    """The virtual rig as a SIL Kit participant; says on stdout where the participants join (also under --quiet)."""
    from hil.runtime.silkit_rig import SilKitRig

    rig = SilKitRig(scenario, seed, db=db, options=options)
    buses = ",".join(network.network for network in rig.networks)
    print(f"silkit registry={rig.registry_uri} participant=trainhil networks={buses} "
          f"external={','.join(scenario.ecu.external) or '-'}", flush=True)
    return rig


def run_scenario(scenario: Scenario, out_dir: Path, *, seed: int | None = None, duration_s: float | None = None,
                 can_log: str | bool | None = None, ideal: bool = False, record: bool = True, progress: bool = False,
                 chunk_s: float = 10.0, min_flush_wall_s: float = 2.0, live: LiveTarget | None = None,
                 overrides: dict | None = None, source: str | None = None, keep_signals: bool = True,
                 silkit: "str | SilKitOptions | None" = None) -> RunResult:
    """Run a scenario (virtual time, or the ideal loop) and write run.rrd, metrics.json and CAN logs into out_dir
    (``can_log``: "asc", "blf" or "mf4", True for ASC).

    ``live``: also stream the recording to a viewer as the simulation goes (flushed every simulated second, at
    most every LIVE_FLUSH_WALL_S of wall time); with ``record=False`` only there. ``overrides`` and ``source``
    (the ``--set`` options and the scenario as named) go into metrics.json's provenance. ``keep_signals=False``
    (``hil run``, sweeps): the samples are let go once recorded and summarised for the metrics, so memory does not
    grow with the run's length, and ``result.log`` holds only the last of them. The ideal loop records as it goes
    too, and stops on Ctrl-C with what it has, as a virtual-time run does. ``silkit``: run as a Vector SIL Kit
    participant (hil/runtime/silkit_rig.py), on the registry at that URI ("" for a registry of the run's own) or as
    the options say."""
    if live is not None:
        chunk_s, min_flush_wall_s = min(chunk_s, 1.0), LIVE_FLUSH_WALL_S
    fmt = None if ideal else log_format(can_log)  # checked before anything is written
    db = None if ideal else load_train_db(scenario)  # so is the scenario's DBC
    out_dir.mkdir(parents=True, exist_ok=True)
    duration = scenario.duration_s if duration_s is None else duration_s
    runtime = "ideal" if ideal else "virtual" if silkit is None else "silkit"
    stop = StopSignals().install()  # a stop signal during set-up is remembered, raised once the run starts
    mark_running(out_dir / "metrics.json", scenario.name, runtime)  # never a stale or half-written result
    files: list[Path] = []
    writer = None
    if record or live is not None:
        writer = RerunWriter(out_dir / "run.rrd" if record else None, _layout(scenario), scenario.name,
                             scenario.plant.coupler_band_m, scenario.trains.spacing_m, scenario.trains.emergency_gap_m,
                             frames=scenario.recording.frames and not ideal, live=live)
        if record:
            files.append(out_dir / "run.rrd")
    recorder = IncrementalRecorder(writer) if writer else None
    bar = _progress_bar(duration, scenario.name) if progress else None
    loggers: list = []
    rig, failure = None, None
    try:
        stop.arm()  # from here SIGTERM/SIGHUP stop the run like Ctrl-C (the run loop returns what it has)
        rig = IdealLoop(scenario, seed) if ideal else VirtualRig(scenario, seed, db=db) if silkit is None else \
            _silkit_rig(scenario, seed, db, SilKitOptions(uri=silkit) if isinstance(silkit, str) else silkit)
        rig.log.summary(scenario.plant.coupler_band_m)  # the metrics' figures, kept as the samples come
        if not ideal:
            if recorder and scenario.recording.frames:
                from hil.record.frames import FrameRecorder

                recorder.frames = FrameRecorder(rig.buses, rig.db)
            if fmt is not None:
                loggers = _can_loggers(rig, out_dir, fmt)
                files += [log_path(out_dir, b.name, fmt) for b in rig.buses]
        flush = _every(_marking(recorder, out_dir, scenario.name, runtime), chunk_s, min_flush_wall_s) \
            if recorder else None
        log = rig.run(duration, progress=(lambda t: bar.update(round(t - bar.n, 3))) if bar else None,
                      on_chunk=_checking(stop, _then_release(flush, recorder, keep_signals)))
        if recorder:
            recorder(log)
    except PlantDiverged as exc:  # non-finite plant state: record what led to it, then report the error
        if rig is None:
            raise
        stop.defer()
        failure, log = exc, rig.log
        log.interrupted = True
        log.event(log.sim_time_s, "ERROR", "plant", f"run stopped: {exc}")
        if recorder:
            recorder(log)
    except RigDidNotStart as exc:  # nothing ran: say so in metrics.json, not "running"
        stop.defer()
        mark_failed(out_dir / "metrics.json", scenario.name, runtime, str(exc))
        raise
    except DiskFullError as exc:  # the recording filled the disk: stop; the metrics go after the recording's cut
        if rig is None:
            raise DiskFullError(exc.errno, f"{exc.strerror}: before the run started; nothing ran") from None
        stop.defer()
        failure, log = exc, rig.log
        log.interrupted = True
        log.event(log.sim_time_s, "ERROR", "rig", f"run stopped: {exc.strerror}")
    finally:
        stop.defer()  # from here on a stop signal is remembered: the files below are written whole
        if sys.exc_info()[0] is not None and failure is None:
            stop.restore()  # an unexpected error propagates: leave the process's handlers as they were
        if bar:
            bar.close()
        for w in loggers:
            w.stop()
        if writer:
            writer.close()
        if rig is not None:
            rig.parts.close()  # FMU instances back to the pool (a sweep worker's next run reuses them)
    try:
        metrics = run_metrics(log, scenario, runtime, scenario.seed if seed is None else seed, overrides=overrides,
                              source=source, pace=silkit.pace if isinstance(silkit, SilKitOptions) else None)
        if failure is not None:
            metrics["error"] = f"{type(failure).__name__}: {failure.strerror if isinstance(failure, OSError) else failure}"
        if isinstance(failure, DiskFullError):
            written = write_metrics_when_full(out_dir / "metrics.json", metrics)
        else:
            write_json_atomic(out_dir / "metrics.json", metrics)
    finally:
        stop.restore()
    files.append(out_dir / "metrics.json")
    if isinstance(failure, DiskFullError):
        raise disk_full_outcome(out_dir, written, log.sim_time_s)
    if failure is not None:
        raise failure
    return RunResult(log, metrics, out_dir, files)


def _checking(stop: StopSignals, on_chunk: Callable[[RunLog], None]) -> Callable[[RunLog], None]:
    """``on_chunk``, after raising a stop signal whose exception was lost (``StopSignals.check``); a stop signal
    that comes while it runs stops the run once it is done (``StopSignals.held``)."""
    def chunk(log: RunLog) -> None:
        stop.check()
        with stop.held():
            on_chunk(log)

    return chunk


def _then_release(flush, recorder, keep_signals: bool):
    """After each chunk (and its flush, if due), let go of the per-frame rows that are recorded (or, without a
    recording, counted): the bus statistics keep what the metrics need, so memory does not grow with the frames.
    Unless ``keep_signals``, the same for the sampled signals (the log's signal summary keeps what the metrics
    need)."""
    def chunk(log: RunLog) -> None:
        if flush is not None:
            flush(log)
        for bus in log.buses:
            bus.frames.release(recorder.frames_written(bus) if recorder is not None else len(bus.frames))
            bus.load.release_before(recorder.load_written(bus) if recorder is not None else len(bus.load))
        if not keep_signals:
            log.release_signals(recorder.signals_written if recorder is not None else len(log.signals))

    return chunk


def _marking(recorder, out_dir: Path, scenario: str, runtime: str):
    """The recorder, then the metrics.json stub moved on to the time recorded (a killed run says how far it got)."""
    def flush(log: RunLog) -> None:
        recorder(log)
        mark_running(out_dir / "metrics.json", scenario, runtime, log.signals.last(0) if len(log.signals) else 0.0)

    return flush


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
    from hil.scenario.layout import TrainLayout

    return TrainLayout.from_config(scenario.trains)


def _progress_bar(total: float, name: str):
    from tqdm import tqdm

    return tqdm(total=total, unit="s", desc=f"{name} (sim time)", bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}, {rate_fmt}]")
