"""`hil compare`'s reporting side: the metric-family registry, what a family gets, the table and the plot.

A *metric family* turns one finished run into a flat dict of metrics (the columns of the comparison table),
for one kind of scenario: ``single_train`` (one train of coupled cars: seeds 001, 004) is built in; a
multi-train family (seed 002's Table 4) plugs in the same way.

How to register a family (e.g. ``hil/compare/multi_train.py``):

1. Write a module with a subclass of :class:`MetricFamily` that sets ``name``, ``description`` and
   ``columns`` (table order: :class:`Column` key, header label, format) and implements ``applies`` (can it
   judge this scenario?) and ``compute`` (``RunData`` -> metrics dict with at least the column keys; values
   are floats, ints, strings, lists of floats or None). Optionally override ``startup_s`` (where
   ``commands`` and ``envelope`` are split, see below) and ``paper`` (the paper's claims for a law: the
   table prints them under the family's ``paper_columns``).
2. Decorate the class with ``@register_family``.
3. Add the module's name to :data:`FAMILY_MODULES` below (one line), so ``hil compare`` imports it.

``hil compare`` picks the first registered family whose ``applies`` holds for every scenario, or the one
named by ``--family``. ``compute`` runs inside the worker process (the RunLog never crosses processes);
only the metrics dict and a down-sampled speed-error trace come back.

What ``compute`` gets (:class:`RunData`): the validated scenario, the run's RunLog (signals sampled at
``recording.period_s``), and two accumulators fed at full rate during the run, each split at
``startup_s`` into index 0 (before) and 1 (from then on):

- :class:`CommandStats`: every command the plant received (ECU period): total variation of the force
  (chattering), integral of |F| (effort), peak |F|, per unit;
- :class:`Envelope`: every plant step: min/max of v - v_r per unit, max |v_j - v_{j+1}| between coupled
  units, min/max of the spacing deviation x_j - x_{j+1} - l_j per coupler. Sampled recordings alias an
  oscillation at the ECU period (samples every 10 cycles see one phase of a period-2 mode), so bands
  and extremes come from here, not from the RunLog.
"""
from __future__ import annotations

import csv
import importlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from hil.record.runlog import RunLog
from hil.scenario.model import Scenario

#: modules that define built-in families (imported on first use; add yours here)
FAMILY_MODULES = ["hil.compare.single_train", "hil.compare.multi_train"]

_FAMILIES: dict[str, "MetricFamily"] = {}


# --------------------------------------------------------------------------- accumulators


class CommandStats:
    """Per-unit statistics of the command stream (force as received by the plant), split at ``split_s``."""

    def __init__(self, n_units: int, split_s: float) -> None:
        self.split_s = split_s
        self.tv = np.zeros((2, n_units))  # sum |F_k - F_{k-1}|, N
        self.abs_integral = np.zeros((2, n_units))  # integral of |F| dt (zero-order hold), N s
        self.peak = np.zeros((2, n_units))  # max |F|, N
        self.count = np.zeros((2, n_units), dtype=np.int64)
        self._last_f = [math.nan] * n_units
        self._last_t = [math.nan] * n_units

    def add(self, u: int, force: float, t: float) -> None:
        """One command for unit u at time t (called for every command: keep it cheap)."""
        phase = 0 if t < self.split_s else 1
        last_f, last_t = self._last_f[u], self._last_t[u]
        if last_f == last_f:  # not NaN: a previous command exists
            self.tv[phase, u] += abs(force - last_f)
            self._hold(u, abs(last_f), last_t, t)
        a = abs(force)
        if a > self.peak[phase, u]:
            self.peak[phase, u] = a
        self.count[phase, u] += 1
        self._last_f[u], self._last_t[u] = force, t

    def _hold(self, u: int, magnitude: float, a: float, b: float) -> None:
        """Add |F| held over [a, b) to the integral, the parts before and after split_s to their phases."""
        split = self.split_s
        self.abs_integral[0, u] += magnitude * max(0.0, min(b, split) - a)
        self.abs_integral[1, u] += magnitude * max(0.0, b - max(a, split))

    def finish(self, t_end: float) -> None:
        """Close the hold of the last command of each unit at the end of the run."""
        for u, (f, t) in enumerate(zip(self._last_f, self._last_t)):
            if f == f and t_end > t:
                self._hold(u, abs(f), t, t_end)
                self._last_t[u] = t_end


class Envelope:
    """Extremes at every plant step (see the module docstring), split at ``split_s``."""

    def __init__(self, n_units: int, coupler_pairs: np.ndarray, rest_m: np.ndarray, split_s: float) -> None:
        self.split_s = split_s
        self.err_min = np.full((2, n_units), math.inf)
        self.err_max = np.full((2, n_units), -math.inf)
        nc = len(coupler_pairs)
        self.adjacent_max = np.zeros((2, nc))
        self.spacing_dev_min = np.full((2, nc), math.inf)
        self.spacing_dev_max = np.full((2, nc), -math.inf)
        self._front, self._rear = coupler_pairs[:, 0], coupler_pairs[:, 1]
        self._rest = rest_m
        self._err = np.empty(n_units)
        self._tmp = np.empty(nc)
        self.steps = 0

    def add(self, t: float, x: np.ndarray, v: np.ndarray, v_r: float) -> None:
        p = 0 if t < self.split_s else 1
        np.subtract(v, v_r, out=self._err)
        np.minimum(self.err_min[p], self._err, out=self.err_min[p])
        np.maximum(self.err_max[p], self._err, out=self.err_max[p])
        if len(self._tmp):
            tmp = self._tmp
            np.subtract(v[self._front], v[self._rear], out=tmp)
            np.abs(tmp, out=tmp)
            np.maximum(self.adjacent_max[p], tmp, out=self.adjacent_max[p])
            np.subtract(x[self._front], x[self._rear], out=tmp)
            np.subtract(tmp, self._rest, out=tmp)
            np.minimum(self.spacing_dev_min[p], tmp, out=self.spacing_dev_min[p])
            np.maximum(self.spacing_dev_max[p], tmp, out=self.spacing_dev_max[p])
        self.steps += 1


@dataclass
class RunData:
    """Everything a family may use to judge one run."""

    label: str
    runtime: str  # "virtual" (over CAN) or "ideal"
    scenario: Scenario
    log: RunLog
    commands: CommandStats
    envelope: Envelope


# --------------------------------------------------------------------------- families


@dataclass(frozen=True)
class Column:
    """One table column: metric key, header label, format spec (``"{:.3g}"``) or ``None`` for str()."""

    key: str
    label: str
    fmt: str | None = "{:.4g}"


class MetricFamily:
    """Base of a metric family (see the module docstring for how to add one)."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    columns: ClassVar[list[Column]] = []
    paper_columns: ClassVar[list[Column]] = []

    def applies(self, scenario: Scenario) -> bool:
        raise NotImplementedError

    def startup_s(self, scenario: Scenario) -> float:
        """Where the accumulators split (start-up before, the rest of the run after)."""
        return 0.0

    def compute(self, run: RunData) -> dict[str, Any]:
        raise NotImplementedError

    def paper(self, law: str) -> dict[str, Any]:
        """The paper's claims for a law, keyed like ``paper_columns`` (empty when none)."""
        return {}


def register_family(cls: type[MetricFamily]) -> type[MetricFamily]:
    """Class decorator: make a family available to ``hil compare`` under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"metric family {cls.__name__} has no name")
    if cls.name in _FAMILIES and type(_FAMILIES[cls.name]) is not cls:
        raise ValueError(f"metric family {cls.name!r} registered twice")
    _FAMILIES[cls.name] = cls()
    return cls


def families() -> dict[str, MetricFamily]:
    """Every registered family (imports the modules of FAMILY_MODULES first)."""
    for module in FAMILY_MODULES:
        importlib.import_module(module)
    return dict(_FAMILIES)


def choose_family(scenarios: list[Scenario], name: str | None = None) -> MetricFamily:
    """The family named ``name``, or the first one that applies to every scenario; errors name the choices."""
    known = families()
    if name is not None:
        if name not in known:
            raise ValueError(f"unknown metric family {name!r} (known: {', '.join(sorted(known)) or 'none'})")
        fam = known[name]
        bad = [sc.name for sc in scenarios if not fam.applies(sc)]
        if bad:
            raise ValueError(f"metric family {name!r} does not apply to {', '.join(bad)}")
        return fam
    for fam in known.values():
        if all(fam.applies(sc) for sc in scenarios):
            return fam
    raise ValueError(f"no metric family applies to all of {', '.join(sc.name for sc in scenarios)} "
                     f"(known: {', '.join(sorted(known))}); mix only scenarios of one kind")


# --------------------------------------------------------------------------- results


@dataclass
class CompareRun:
    """One finished run as the parent process sees it."""

    label: str
    law: str
    runtime: str
    metrics: dict[str, Any]
    t: np.ndarray  # (k,) recording times
    speed_error: np.ndarray  # (k, n) v - v_r, float32
    paper: dict[str, Any] = field(default_factory=dict)


def _cell(value: Any, fmt: str | None) -> str:
    if value is None:
        return "–"
    if isinstance(value, float) and not math.isfinite(value):
        return "–"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_cell(v, fmt) for v in value) + "]"
    if fmt is None or isinstance(value, (str, bool)):
        return str(value)
    return fmt.format(value)


def table_rows(runs: list[CompareRun], family: MetricFamily) -> tuple[list[str], list[list[str]]]:
    """Header and formatted rows: run, law, runtime, the family's columns, then the paper's columns."""
    cols = family.columns + family.paper_columns
    header = ["run", "law", "runtime"] + [c.label for c in cols]
    rows = []
    for r in runs:
        values = {**r.metrics, **{c.key: r.paper.get(c.key) for c in family.paper_columns}}
        rows.append([r.label, r.law, r.runtime] + [_cell(values.get(c.key), c.fmt) for c in cols])
    return header, rows


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    esc = lambda s: s.replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(esc(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def text_table(header: list[str], rows: list[list[str]]) -> str:
    """The same table transposed for a terminal: one line per metric, one column per run."""
    width = max(len(h) for h in header)
    colw = [max(len(cell) for cell in row) for row in rows]
    return "\n".join(f"{h:<{width}}  " + "  ".join(f"{row[i]:>{w}}" for row, w in zip(rows, colw))
                     for i, h in enumerate(header))


def write_outputs(runs: list[CompareRun], family: MetricFamily, out: Path, title: str = "") -> dict[str, Path]:
    """compare.md, compare.csv, compare.json, speed_error.png and traces.npz in ``out``; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    header, rows = table_rows(runs, family)
    paths = {k: out / f for k, f in (("md", "compare.md"), ("csv", "compare.csv"), ("json", "compare.json"),
                                     ("png", "speed_error.png"))}
    md = (f"# {title}\n\n" if title else "") + f"Metric family `{family.name}`: {family.description}\n\n" + markdown_table(header, rows) + "\n"
    paths["md"].write_text(md)
    with paths["csv"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["run", "law", "runtime"] + [c.key for c in family.columns] + [f"paper_{c.key}" for c in family.paper_columns])
        for r in runs:
            w.writerow([r.label, r.law, r.runtime] + [_csv(r.metrics.get(c.key)) for c in family.columns]
                       + [_csv(r.paper.get(c.key)) for c in family.paper_columns])
    payload = {"family": family.name, "runs": [{"run": r.label, "law": r.law, "runtime": r.runtime,
                                                  "metrics": r.metrics, "paper": r.paper} for r in runs]}
    paths["json"].write_text(json.dumps(payload, indent=2, allow_nan=False, default=_json_default))
    plot_speed_errors(runs, paths["png"], title)
    paths["npz"] = out / "traces.npz"
    save_traces(runs, paths["npz"])
    return paths


def _csv(value: Any) -> Any:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, (list, tuple)):
        return json.dumps([_csv(v) if v != "" else None for v in value])
    return value


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {obj!r}")


# --------------------------------------------------------------------------- plot


def envelope_of(t: np.ndarray, y: np.ndarray, points: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    """Max of y over consecutive windows (about ``points`` of them; at least 1 s each), at the windows' middles.

    A dense oscillation at the ECU period would otherwise fill the plot; its envelope is what a reader compares.
    """
    if len(t) < 2:
        return t, y
    dt = float(np.median(np.diff(t)))
    per = max(1, int(round(max(1.0, (t[-1] - t[0]) / points) / dt)))
    n = len(y) // per
    if n == 0:
        return t, y
    return t[: n * per].reshape(n, per).mean(axis=1), y[: n * per].reshape(n, per).max(axis=1)


def save_traces(runs: list[CompareRun], path: Path) -> None:
    """The runs' recorded speed errors (to redraw the plot without running again: :func:`load_traces`)."""
    arrays = {}
    for i, r in enumerate(runs):
        arrays[f"t{i}"], arrays[f"e{i}"] = r.t, r.speed_error
    meta = json.dumps([{"label": r.label, "law": r.law, "runtime": r.runtime} for r in runs])
    np.savez_compressed(path, meta=np.array(meta), **arrays)


def load_traces(path: Path) -> list[CompareRun]:
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        return [CompareRun(m["label"], m["law"], m["runtime"], {}, z[f"t{i}"], z[f"e{i}"]) for i, m in enumerate(meta)]


def plot_speed_errors(runs: list[CompareRun], path: Path, title: str = "", zoom_s: float = 30.0) -> None:
    """Speed error of every run: worst car |v - v_r| over the whole run (log scale), and the start-up signed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 7.5))
    FigureCanvasAgg(fig)
    top, bottom = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    colours = [f"C{i % 10}" for i in range(len(runs))]
    for r, c in zip(runs, colours):
        if len(r.t) == 0:
            continue
        t_env, env = envelope_of(r.t, np.max(np.abs(r.speed_error), axis=1))
        top.semilogy(t_env, np.maximum(env, 1e-6), color=c, lw=0.9, label=f"{r.label} ({r.runtime})")
        k = np.searchsorted(r.t, zoom_s, side="right")
        idx = np.argmax(np.abs(r.speed_error[:k]), axis=1)
        bottom.plot(r.t[:k], r.speed_error[np.arange(k), idx], color=c, lw=0.8)
    top.set_ylabel("max over cars |v - v_r| (m/s),\nenvelope over windows")
    top.set_xlabel("t (s)")
    top.grid(True, which="both", alpha=0.3)
    top.legend(fontsize=8, loc="upper right")
    bottom.set_ylabel("v - v_r of the worst car (m/s)")
    bottom.set_xlabel(f"t (s), first {zoom_s:g} s")
    bottom.grid(True, alpha=0.3)
    fig.suptitle(title or "speed error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
