"""Run a sweep's grid in parallel (local process pool, or Dask) and keep every run's result on disk.

Each run has its own directory ``OUT/runs/<run_id>/`` with ``overrides.json`` and either ``metrics.json``
(written atomically: temporary file + ``os.replace``) or ``error.txt`` (type, message, traceback), and
``warnings.txt`` if the run raised Python warnings (kept there, not printed over the progress bar). A point
whose ``metrics.json`` exists is not run again, so an interrupted sweep resumes where it stopped; failed
points are retried by the next invocation. A run's id is a hash of its overrides (seed included), so
extending a sweep (more axis values or seeds) into the same directory reuses every unchanged run, while
changing e.g. ``duration_s`` gives new ids (old run directories stay, but leave results.csv). A directory
whose runs came from another base scenario file is refused (``sweep.json`` keeps the base's hash).

Runs do not record (``record=False``: no ``run.rrd``, which would cost time and disk per run; to look at one
point, run ``load_scenario(base, overrides)`` with its overrides.json through ``run_scenario``). The
worker runs ``hil.session.run_scenario`` in a temporary directory and returns the metrics; the parent
writes every file. So workers need no shared file system, and a Dask cluster elsewhere works as well as
local processes (the Dask workers need trainhil installed, the same version).

Ctrl-C stops the sweep: pending runs are cancelled, runs in progress are abandoned (local worker processes
are terminated; on a remote Dask cluster they finish and are discarded), and what finished is written.
"""
from __future__ import annotations

import difflib

import hashlib
import json
import multiprocessing
import os
import signal
import tempfile
import traceback
import warnings
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.scenario.model import Scenario
from hil.sweep.spec import GridPoint, SweepError, SweepSpec

MANIFEST = "sweep.json"
CONNECT_TIMEOUT_S = 10


@dataclass
class SweepResult:
    """What a sweep left behind (``rows`` are the rows of results.csv)."""

    out_dir: Path
    csv_path: Path
    rows: list[dict[str, Any]]
    total: int
    ok: int
    failed: int
    reused: int  # points already done by an earlier invocation (not rerun)
    ran: int  # points run by this invocation (ok or failed)
    interrupted: bool = False
    failures: list[str] = field(default_factory=list)  # run ids

    @property
    def pending(self) -> int:
        return self.total - self.ok - self.failed


# --------------------------------------------------------------------------- the worker side


def execute_point(scenario: Scenario) -> dict[str, Any]:
    """Run one scenario (no recording) and return {"status": "ok", "metrics": ...} or the failure; never raises."""
    from hil.session import run_scenario

    with warnings.catch_warnings(record=True) as caught:  # kept with the run, not printed over the progress bar
        warnings.simplefilter("always")
        try:
            with tempfile.TemporaryDirectory(prefix="hil-sweep-") as tmp:
                result = run_scenario(scenario, Path(tmp), record=False, progress=False, keep_signals=False)
            outcome = {"status": "interrupted"} if result.log.interrupted else {"status": "ok", "metrics": result.metrics}
        except KeyboardInterrupt:
            outcome = {"status": "interrupted"}
        except Exception as exc:  # any failure of a run is a result of the sweep, not the end of it
            outcome = _failure(exc)
    outcome["warnings"] = [warnings.formatwarning(w.message, w.category, w.filename, w.lineno) for w in caught]
    return outcome


PROBE_S = 0.05  # simulated seconds of the run that tells which metric columns a sweep's runs will have


def metric_columns(scenario: Scenario) -> set[str]:
    """The results.csv metric columns a run of ``scenario`` gives (from a run of PROBE_S simulated seconds)."""
    from hil.session import run_scenario
    from hil.sweep.results import flatten_metrics

    with tempfile.TemporaryDirectory(prefix="hil-sweep-probe-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_scenario(scenario, Path(tmp), duration_s=min(PROBE_S, scenario.duration_s), record=False,
                              progress=False)
    return set(flatten_metrics(result.metrics))


def check_plot_metrics(spec: SweepSpec) -> None:
    """Every plot's metric must be a metric column, checked before the first run (with a "did you mean")."""
    plots = [("heatmaps", i, p) for i, p in enumerate(spec.plots.heatmaps)] + \
            [("lines", i, p) for i, p in enumerate(spec.plots.lines)]
    if not plots or not spec.points:
        return
    known = metric_columns(spec.points[0].scenario)
    for kind, i, plot in plots:
        if plot.metric in known:
            continue
        close = difflib.get_close_matches(plot.metric, sorted(known), n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else \
            " (the metric columns are the keys of a run's metrics.json, nested keys joined by dots)"
        raise SweepError(f"{spec.source}: plots.{kind}.{i}.metric: {plot.metric!r} is not a metric of these runs{hint}")


def _failure(exc: BaseException) -> dict[str, Any]:
    return {"status": "failed", "error": f"{type(exc).__name__}: {exc}".splitlines()[0],
            "traceback": "".join(traceback.format_exception(exc))}


def _ignore_sigint() -> None:
    """Pool workers leave Ctrl-C to the parent, which cancels and terminates them."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# --------------------------------------------------------------------------- backends


class _PoolBackend:
    """concurrent.futures process pool; workers come from a fresh forkserver (or spawn), never a fork of this process."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=_mp_context(), initializer=_ignore_sigint)
        self.futures: dict[Future, GridPoint] = {}

    def results(self, points: list[GridPoint]) -> Iterator[tuple[GridPoint, dict[str, Any]]]:
        self.futures = {self.pool.submit(execute_point, p.scenario): p for p in points}
        for fut in as_completed(self.futures):
            yield self.futures.pop(fut), _outcome(fut)

    def finished(self) -> Iterator[tuple[GridPoint, dict[str, Any]]]:
        """Results that completed but were not yet collected (after an interruption)."""
        for fut, point in list(self.futures.items()):
            if fut.done() and not fut.cancelled() and fut.exception() is None:
                yield point, fut.result()

    def stop(self) -> None:
        for fut in self.futures:
            fut.cancel()
        processes = list(getattr(self.pool, "_processes", {}).values())  # 3.11 has no public terminate_workers()
        self.pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            if proc.is_alive():
                proc.terminate()
        for proc in processes:
            proc.join(timeout=5)

    def close(self) -> None:
        self.pool.shutdown(wait=True)


class _DaskBackend:
    """A Dask distributed Client: on a LocalCluster (``"local"``, bound to 127.0.0.1) or an existing scheduler."""

    def __init__(self, address: str, workers: int) -> None:
        from distributed import Client, LocalCluster

        self.cluster = None
        if address == "local":
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None, host="127.0.0.1")
            self.client = Client(self.cluster)
        else:
            try:
                self.client = Client(address, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError, ValueError) as exc:
                raise SweepError(f"--dask {address}: cannot connect to a Dask scheduler there: {exc}") from None
        self.futures: dict[Any, GridPoint] = {}

    def results(self, points: list[GridPoint]) -> Iterator[tuple[GridPoint, dict[str, Any]]]:
        from distributed import as_completed as dask_completed

        self.futures = {self.client.submit(execute_point, p.scenario, pure=False): p for p in points}
        for fut in dask_completed(list(self.futures)):
            point = self.futures.pop(fut)
            try:
                outcome = fut.result()
            except Exception as exc:  # the worker died (KilledWorker) or the task could not be sent
                outcome = _failure(exc)
            yield point, outcome

    def finished(self) -> Iterator[tuple[GridPoint, dict[str, Any]]]:
        for fut, point in list(self.futures.items()):
            if fut.status == "finished":
                yield point, fut.result()

    def stop(self) -> None:
        self.client.cancel(list(self.futures))
        self.close()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _outcome(fut: Future) -> dict[str, Any]:
    exc = fut.exception()
    return fut.result() if exc is None else _failure(exc)  # e.g. BrokenProcessPool: a worker process died


def _mp_context():
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" in methods:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["hil.sweep.runner", "hil.session"])  # imported once, then forked per worker
        return ctx
    return multiprocessing.get_context("spawn")


def _backend(workers: int | None, dask: str | None) -> _PoolBackend | _DaskBackend:
    n = workers or os.cpu_count() or 1
    if n < 1:
        raise SweepError(f"--workers must be >= 1, got {workers}")
    return _DaskBackend(dask, n) if dask else _PoolBackend(n)


# --------------------------------------------------------------------------- files


def write_atomic(path: Path, text: str) -> None:
    """Write text so that readers see the old file or the whole new one, never a part."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def run_dir(out_dir: Path, point: GridPoint) -> Path:
    return out_dir / "runs" / point.run_id


def is_done(out_dir: Path, point: GridPoint) -> bool:
    return (run_dir(out_dir, point) / "metrics.json").is_file()


def _prepare(out_dir: Path, point: GridPoint) -> None:
    d = run_dir(out_dir, point)
    d.mkdir(parents=True, exist_ok=True)
    for stale in ("error.txt", "warnings.txt"):
        (d / stale).unlink(missing_ok=True)
    info = {"run_id": point.run_id, "seed": point.seed, "axes": point.axes, "overrides": point.overrides}
    write_atomic(d / "overrides.json", json.dumps(info, indent=2) + "\n")


def _record(out_dir: Path, point: GridPoint, outcome: dict[str, Any]) -> str:
    """Write a finished run's metrics.json or error.txt; returns its status."""
    d = run_dir(out_dir, point)
    status = outcome["status"]
    if status == "ok":
        write_atomic(d / "metrics.json", json.dumps(outcome["metrics"], indent=2, allow_nan=False) + "\n")
    elif status == "failed":
        write_atomic(d / "error.txt", f"{outcome['error']}\n\n{outcome['traceback']}")
    if outcome.get("warnings"):
        write_atomic(d / "warnings.txt", "".join(outcome["warnings"]))
    return status


def _check_manifest(spec: SweepSpec, out_dir: Path) -> None:
    """Refuse to resume into a directory whose runs came from another base scenario file (compared by content)."""
    manifest = {"name": spec.name, "source": spec.source, "base": str(spec.base_path),
                "base_sha256": hashlib.sha256(spec.base_path.read_bytes()).hexdigest()}
    path = out_dir / MANIFEST
    if path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        if old.get("base_sha256") != manifest["base_sha256"]:
            raise SweepError(f"{out_dir}: holds runs of another base scenario ({old.get('base')}, or it changed since); "
                             f"use another --out or remove that directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(manifest, indent=2) + "\n")


# --------------------------------------------------------------------------- the sweep


def run_sweep(spec: SweepSpec, out_dir: Path, workers: int | None = None, dask: str | None = None,
              progress: bool = True) -> SweepResult:
    """Run every point of the grid not already done, write results.csv, and return the counts."""
    from hil.sweep.results import write_results

    out_dir = Path(out_dir)
    _check_manifest(spec, out_dir)
    check_plot_metrics(spec)
    todo = [p for p in spec.points if not is_done(out_dir, p)]
    reused = len(spec.points) - len(todo)
    for p in todo:
        _prepare(out_dir, p)
    bar = _progress_bar(spec, reused) if progress else None
    ran, failures, interrupted = 0, [], False
    backend = _backend(workers, dask) if todo else None
    try:
        if backend:
            for point, outcome in backend.results(todo):
                status = _record(out_dir, point, outcome)
                ran += status in ("ok", "failed")
                if status == "failed":
                    failures.append(point.run_id)
                if bar:
                    bar.set_postfix(failed=len(failures), refresh=False)
                    bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        for point, outcome in backend.finished():
            ran += _record(out_dir, point, outcome) in ("ok", "failed")
        backend.stop()
        backend = None
    finally:
        if backend:
            backend.close()
        if bar:
            bar.close()
    rows, csv_path = write_results(spec, out_dir)
    ok = sum(r["status"] == "ok" for r in rows)
    failed = sum(r["status"] == "failed" for r in rows)
    return SweepResult(out_dir, csv_path, rows, len(spec.points), ok, failed, reused, ran, interrupted,
                       [r["run_id"] for r in rows if r["status"] == "failed"])


def _progress_bar(spec: SweepSpec, done: int):
    from tqdm import tqdm

    return tqdm(total=len(spec.points), initial=done, unit="run", desc=spec.name, smoothing=0.1,
                postfix={"failed": 0})
