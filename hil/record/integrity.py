"""Nothing lost: a run directory stays readable whatever stops the run, and ``check_run_dir`` proves it.

What a run writes to keep it so (``hil.session``):

* ``metrics.json`` is written atomically (temp file + rename), first as a stub ``{"status": "running",
  "interrupted": true, "sim_time_s": ...}`` when the run starts and again at every recording flush, then replaced
  by the full metrics at the end. A run killed at any moment (even SIGKILL) leaves JSON that parses and says
  it is incomplete, never a half-written file and never a stale result of an earlier run.
* ``StopSignals``: during the run loop SIGTERM and SIGHUP interrupt like Ctrl-C (the loop stops cleanly and
  everything so far is written), except inside a chunk's recording, which they interrupt only once it is done;
  during the final writing every stop signal is only remembered.

``check_run_dir(path)`` is the verdict the kill tests and the reliability benchmark share: metrics.json parses
and says complete or incomplete, run.rrd opens with rerun's Python API and streams to its end, and the two
agree (a complete run recorded up to its end; an incomplete one no further than it claims).
"""
from __future__ import annotations

import contextlib
import errno
import json
import multiprocessing
import os
import signal
import threading
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from hil.record.diskspace import disk_full

RUNNING = "running"
FAILED = "failed"  # the rig did not start
TIME_SLACK_S = 1.0  # recording vs metrics time: a flush and a sample period of slack


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON so readers see the old file or the new one, never a partial one; on a full disk a DiskFullError
    naming the place, and no temporary file left behind."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise disk_full(path) from None
        raise


def mark_running(path: Path, scenario: str, runtime: str, sim_time_s: float = 0.0, note: str | None = None) -> None:
    """The metrics.json stub of a run in progress (replaced by the full metrics when the run ends). ``note`` says
    where the data so far is; by default, in run.rrd up to sim_time_s (the virtual-time recorder flushes)."""
    write_json_atomic(path, {"scenario": scenario, "runtime": runtime, "status": RUNNING, "interrupted": True,
                             "sim_time_s": float(sim_time_s),
                             "note": note or "the run has not finished: run.rrd holds everything up to sim_time_s"})


def mark_failed(path: Path, scenario: str, runtime: str, error: str) -> None:
    """The metrics.json of a rig that did not start: nothing ran, so not "running" (which points to hil recover)."""
    write_json_atomic(path, {"scenario": scenario, "runtime": runtime, "status": FAILED, "interrupted": True,
                             "sim_time_s": 0.0, "error": error.splitlines()[0],
                             "note": "the rig did not start, nothing ran: there is nothing to recover"})


def _in_finalizer(frame: FrameType | None) -> bool:
    """Whether ``frame`` runs inside an object's ``__del__`` (an exception raised there is printed and dropped)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


class StopSignals:
    """Stop signals around a run: remembered while it is set up (``install``), raised as KeyboardInterrupt while
    the run loop runs (``arm``: SIGTERM and SIGHUP like Ctrl-C; one remembered during set-up raises at once),
    remembered again while the files are written (``defer``), then the previous handlers (``restore``), which
    re-sends a signal remembered meanwhile, so a Ctrl-C or SIGTERM during the final writing still takes effect.

    Python runs a signal handler between any two bytecodes; one that runs inside a finalizer (``__del__``, a
    generator being collected) has its KeyboardInterrupt printed (a traceback on stderr) and dropped. Inside a
    ``__del__`` the handler therefore only remembers the stop, and the run loop calls ``check`` at every chunk,
    which raises a stop that arrived while armed, so a stop is never lost.

    Active only in the main thread of a process that is not a multiprocessing child (a sweep's pool owns its
    workers' signals); elsewhere every method does nothing. Signals that were ignored stay ignored."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.received: str | None = None
        self._pending: int | None = None  # a signal remembered and not yet acted on
        self._previous: dict[int, Any] = {}
        self._armed = False
        self._active = threading.current_thread() is threading.main_thread() and multiprocessing.parent_process() is None

    def install(self) -> "StopSignals":
        if self._active:
            self._previous = {s: signal.getsignal(s) for s in self.SIGNALS}
            self._set(self._remember)
        return self

    def _set(self, handler) -> None:
        for s, previous in self._previous.items():
            if previous is not signal.SIG_IGN:
                signal.signal(s, handler)

    def _interrupt(self, signum: int, frame: FrameType | None) -> None:
        self.received = signal.Signals(signum).name
        if not _in_finalizer(frame):  # there it would be printed and dropped: ``check`` raises it
            raise KeyboardInterrupt(self.received)

    def _remember(self, signum: int, _frame) -> None:
        self.received = signal.Signals(signum).name
        self._pending = signum

    def arm(self) -> None:
        if self._previous:
            self._interrupt_from_now()
            if self._pending is not None:
                self._pending = None
                raise KeyboardInterrupt(self.received)

    def _interrupt_from_now(self) -> None:
        """Stop signals raise KeyboardInterrupt from here on (one remembered before stays remembered)."""
        self._armed = True
        self._set(self._interrupt)

    def check(self) -> None:
        """Raise the KeyboardInterrupt of a stop signal received while armed (one whose exception Python dropped
        because the handler ran inside a finalizer); nothing otherwise."""
        if self._armed and self.received is not None:
            raise KeyboardInterrupt(self.received)

    def defer(self) -> None:
        self._armed = False
        if self._previous:
            self._set(self._remember)

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """While armed, a stop signal inside the block is remembered and raised when the block ends, so work of
        several steps (a recording flush, the rows it lets go: a table's buffer and its offsets) is never left half
        done, which the metrics computed after the stop would trip over. An exception of the block's own goes on as
        it is (the stop stays remembered, as in the final writing). Outside the main thread (a SIL Kit run's chunks
        come in its simulation thread) nothing changes: a signal's exception is raised in the main thread, never
        inside the block."""
        if not self._armed or threading.current_thread() is not threading.main_thread():
            yield
            return
        self.defer()
        try:
            yield
        except BaseException:
            self._interrupt_from_now()
            raise
        self.arm()  # raises the stop that came meanwhile

    def restore(self) -> None:
        self._armed = False
        for s, h in self._previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        self._previous = {}
        pending, self._pending = self._pending, None
        if pending is not None:
            signal.raise_signal(pending)  # to the previous handler: Ctrl-C -> KeyboardInterrupt, SIGTERM -> exit


# --------------------------------------------------------------------------- the check


@dataclass
class IntegrityReport:
    """Verdict on one run directory (``ok``: both files readable and consistent; ``problems`` says why not)."""

    path: str
    ok: bool = False
    metrics_ok: bool = False
    rrd_ok: bool = False
    complete: bool | None = None  # metrics.json says the run finished (interrupted false, not a stub)
    status: str | None = None  # "running" for a stub, None for full metrics
    interrupted: bool | None = None
    sim_time_s: float | None = None  # as metrics.json says
    rrd_chunks: int = 0
    rrd_entities: int = 0
    rrd_last_time_s: float | None = None  # the latest sim_time in the recording
    rrd_last_train_time_s: float | None = None  # the latest sim_time of a train signal (/trains/...): the plant's
    problems: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def check_run_dir(path: Path | str, expect_complete: bool | None = None) -> IntegrityReport:
    """Check a run directory's metrics.json and run.rrd (see the module docstring); never raises for bad files.

    ``expect_complete``: also require the run to say it finished (True) or that it did not (False)."""
    path = Path(path)
    rep = IntegrityReport(str(path))
    _check_metrics(path / "metrics.json", rep)
    _check_rrd(path / "run.rrd", rep)
    if rep.metrics_ok and rep.rrd_ok:
        _check_agreement(rep)
    if expect_complete is not None and rep.complete is not None and rep.complete != expect_complete:
        rep.problems.append(f"the run says complete={rep.complete}, expected {expect_complete}")
    rep.ok = rep.metrics_ok and rep.rrd_ok and not rep.problems
    return rep


def _check_metrics(path: Path, rep: IntegrityReport) -> None:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        rep.problems.append(f"{path.name} is missing")
        return
    except (OSError, ValueError) as exc:
        rep.problems.append(f"{path.name} does not parse: {exc}")
        return
    if not isinstance(data, dict) or not isinstance(data.get("interrupted"), bool):
        rep.problems.append(f"{path.name} has no boolean 'interrupted'")
        return
    rep.metrics_ok = True
    rep.status = data.get("status")
    rep.interrupted = data["interrupted"]
    rep.complete = not rep.interrupted and rep.status != RUNNING
    t = data.get("sim_time_s")
    rep.sim_time_s = float(t) if isinstance(t, (int, float)) else None


def _check_rrd(path: Path, rep: IntegrityReport) -> None:
    if not path.exists():
        rep.problems.append(f"{path.name} is missing")
        return
    import warnings

    from rerun.chunk import RrdReader

    entities: set[str] = set()
    last = last_train = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "no footer": a recording whose writer did not close (killed)
            for ch in RrdReader(path).stream():
                rep.rrd_chunks += 1
                entities.add(ch.entity_path)
                rb = ch.to_record_batch()
                if "sim_time" in rb.schema.names and rb.num_rows:
                    t = rb.column("sim_time").cast("int64").to_numpy().max() * 1e-9
                    last = t if last is None else max(last, t)
                    if ch.entity_path.startswith("/trains/"):
                        last_train = t if last_train is None else max(last_train, t)
    except Exception as exc:  # rerun raises RuntimeError for damaged files; anything else is as bad
        rep.problems.append(f"{path.name} does not read with rerun: {exc}")
        return
    rep.rrd_ok = True
    rep.rrd_entities = len(entities)
    rep.rrd_last_time_s = float(last) if last is not None else None
    rep.rrd_last_train_time_s = float(last_train) if last_train is not None else None


def _check_agreement(rep: IntegrityReport) -> None:
    """A complete run is recorded to its end; no train signal is recorded beyond what metrics.json claims (bus
    statistics may run on a little: the bus servers of a stopped real-time run count until the nodes leave)."""
    t, last = rep.sim_time_s, rep.rrd_last_train_time_s
    if t is None:
        return
    if last is not None and last > t + TIME_SLACK_S and rep.status != RUNNING:
        rep.problems.append(f"run.rrd's train signals reach t = {last:.3f} s, beyond metrics.json's sim_time_s = {t:.3f} s")
    if rep.complete and (last is None or last < t - TIME_SLACK_S):
        rep.problems.append(f"a complete run recorded only to t = {last} s of sim_time_s = {t:.3f} s")
