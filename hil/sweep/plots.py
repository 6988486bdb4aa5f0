"""Sweep plots (PNG): heatmaps of a metric over two axes and metric-vs-axis lines per hue, unsafe runs marked.

The spec is duck-typed (attributes or mapping keys), so any object of this shape works::

    spec.plots.heatmaps[i]: .metric, .x, .y, .where   # where: {axis: value} fixes other axes, or None
    spec.plots.lines[i]:    .metric, .x, .hue, .where      # hue may be None: one line

``rows`` are results.csv rows (dicts; values are strings or numbers). Each plotted point or cell is the mean
of the metric over every run that matches it: over seeds and over every axis not plotted and not fixed by
``where``. A cell is NaN when it has no run, when any of its runs failed (a non-empty ``error`` or a
``status`` of failed/error), or when any run's metric is undefined (empty or not a number, e.g. a settling
time that never came): a partial mean over the other runs would hide them. A cell is unsafe when ``unsafe``
is true for any of its runs. Figures use matplotlib's object API with the Agg canvas (no pyplot, no global backend switch).
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import NullFormatter, ScalarFormatter

AxisValue = float | str
_TRUE = {"true", "1", "yes", "y", "t"}
_FAILED_STATUS = {"failed", "error", "fail"}
DPI = 110


# --------------------------------------------------------------------------- reading rows


def _get(obj: Any, name: str, default: Any = None) -> Any:
    """``obj.name`` or ``obj[name]`` (pydantic models, dataclasses, plain dicts)."""
    if isinstance(obj, Mapping):
        return obj.get(name, default)
    return getattr(obj, name, default)


def axis_value(value: Any) -> AxisValue:
    """An axis value as a float if it reads as a number, else as a string ("priority", "finite_time")."""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, float, np.number)):
        return float(value)
    text = "" if value is None else str(value).strip()
    try:
        return float(text)
    except ValueError:
        return text


def metric_value(value: Any) -> float:
    """A metric as a float; NaN when empty, None or not a number."""
    if isinstance(value, (bool, int, float, np.number)):
        return float(value)
    try:
        return float(str(value).strip())
    except (TypeError, ValueError):
        return math.nan


def is_true(value: Any) -> bool:
    """results.csv truth: True, 1, "True", "true", "1", "yes" (anything else, incl. empty, is False)."""
    if isinstance(value, (bool, int, float, np.number)):
        return bool(value) and not (isinstance(value, float) and math.isnan(value))
    return str(value).strip().lower() in _TRUE


def run_failed(row: Mapping[str, Any]) -> bool:
    """A run that did not complete: a non-empty ``error``, or a ``status`` of failed/error."""
    if str(row.get("error") or "").strip():
        return True
    return str(row.get("status") or "").strip().lower() in _FAILED_STATUS


def _same(a: AxisValue, b: AxisValue) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    return str(a) == str(b)


def _sorted_values(values: Iterable[AxisValue]) -> list[AxisValue]:
    """Unique axis values: numerically if all are numbers, else by their text."""
    uniq: list[AxisValue] = []
    for v in values:
        if not any(_same(v, u) for u in uniq):
            uniq.append(v)
    if all(isinstance(v, float) for v in uniq):
        return sorted(uniq)  # type: ignore[type-var]
    return sorted(uniq, key=str)


def _index(values: Sequence[AxisValue], v: AxisValue) -> int:
    return next(i for i, u in enumerate(values) if _same(u, v))


def _check_columns(rows: Sequence[Mapping[str, Any]], what: str, names: Iterable[str]) -> None:
    columns = set().union(*(r.keys() for r in rows)) if rows else set()
    for name in names:
        if name not in columns:
            raise ValueError(f"{what}: no column {name!r} in the results (columns: {', '.join(sorted(columns))})")


def _check_numeric(rows: Sequence[Mapping[str, Any]], what: str, metric: str) -> None:
    """A metric column whose filled cells never read as numbers is a spec error, not a set of failures."""
    filled = [r[metric] for r in rows if str(r.get(metric) if r.get(metric) is not None else "").strip()]
    if filled and all(math.isnan(metric_value(v)) for v in filled):
        raise ValueError(f"{what}: metric {metric!r} is not numeric (e.g. {filled[0]!r})")


# --------------------------------------------------------------------------- aggregation


@dataclass(frozen=True)
class Grid:
    """A metric's cell means over two axes: ``values[i, j]`` at y = y_values[i], x = x_values[j]."""

    metric: str
    x: str
    y: str | None
    x_values: list[AxisValue]
    y_values: list[AxisValue]
    values: np.ndarray  # (ny, nx) float, NaN: no run, or a run failed
    unsafe: np.ndarray  # (ny, nx) bool: some run of the cell was unsafe
    runs: np.ndarray  # (ny, nx) int: runs in the cell
    failed: np.ndarray  # (ny, nx) int: failed runs in the cell
    undefined: np.ndarray  # (ny, nx) int: completed runs whose metric is empty or not a number


def heatmap_grid(rows: Sequence[Mapping[str, Any]], metric: str, x: str, y: str | None,
                 where: Mapping[str, Any] | None = None) -> Grid:
    """Mean of ``metric`` per (x, y) over the rows matching ``where`` (the other axes and seeds averaged).

    ``y=None`` gives one row of cells (y_values == [""]): a single line over x.
    """
    what = f"plot of {metric} over {x}" + (f" x {y}" if y is not None else "")
    where = dict(where or {})
    _check_columns(rows, what, [metric, x, *([y] if y is not None else []), *where])
    _check_numeric(rows, what, metric)
    wanted = {k: axis_value(v) for k, v in where.items()}
    chosen = [r for r in rows if all(_same(axis_value(r.get(k)), v) for k, v in wanted.items())]
    if rows and not chosen:
        raise ValueError(f"{what}: no run matches where={where}")
    xs = _sorted_values(axis_value(r.get(x)) for r in chosen)
    ys = _sorted_values(axis_value(r.get(y)) for r in chosen) if y is not None else [""]
    total = np.zeros((len(ys), len(xs)))
    runs = np.zeros((len(ys), len(xs)), dtype=int)
    failed = np.zeros_like(runs)
    undefined = np.zeros_like(runs)
    unsafe = np.zeros((len(ys), len(xs)), dtype=bool)
    for r in chosen:
        i, j = (_index(ys, axis_value(r.get(y))) if y is not None else 0), _index(xs, axis_value(r.get(x)))
        runs[i, j] += 1
        unsafe[i, j] |= is_true(r.get("unsafe"))
        value = metric_value(r.get(metric))
        if run_failed(r):
            failed[i, j] += 1
        elif math.isnan(value):
            undefined[i, j] += 1
        else:
            total[i, j] += value
    with np.errstate(invalid="ignore"):
        values = np.where((runs > 0) & (failed == 0) & (undefined == 0), total / np.maximum(runs, 1), np.nan)
    return Grid(metric, x, y, xs, ys, values, unsafe, runs, failed, undefined)


# --------------------------------------------------------------------------- drawing


def _fmt(v: AxisValue) -> str:
    """An axis value as people write it: 1000000, not 1e+06; 0.05, not 5e-02."""
    if isinstance(v, float):
        return str(int(v)) if v.is_integer() and abs(v) < 1e12 else f"{v:g}"
    return str(v)


def value_decimals(values: np.ndarray) -> int | None:
    """Decimals that keep every two different values of a grid apart when written (fixed point), or None for
    values too large or too small for fixed point (then 4 significant digits). 2473.4 and 2477.9, not 2.47e+03."""
    finite = np.unique(values[np.isfinite(values)])
    if finite.size == 0:
        return 0
    big = np.abs(finite).max()
    if big >= 1e7 or 0 < big < 1e-4:
        return None
    steps = np.diff(finite)
    if not steps.size:
        return None  # one value: nothing to keep apart
    step = steps.min()
    return int(min(6, max(0, 1 - math.floor(math.log10(step)))))


def _value_text(v: float, decimals: int | None) -> str:
    return f"{v:.4g}" if decimals is None else f"{v:.{decimals}f}"


def _where_text(where: Mapping[str, Any] | None) -> str:
    return ", ".join(f"{k} = {_fmt(axis_value(v))}" for k, v in (where or {}).items())


def _title(metric: str, where: Mapping[str, Any] | None) -> str:
    fixed = _where_text(where)
    return f"{metric}" + (f" ({fixed})" if fixed else "") + "\nmean over seeds and the axes not shown"


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=DPI)
    return path


def _cell_text(g: Grid, i: int, j: int, decimals: int | None) -> str:
    if g.runs[i, j] == 0:
        return "no run"
    if g.failed[i, j]:
        return f"failed\n{g.failed[i, j]}/{g.runs[i, j]}"
    if g.undefined[i, j]:
        return f"n/a\n{g.undefined[i, j]}/{g.runs[i, j]}"
    return _value_text(float(g.values[i, j]), decimals)


def draw_heatmap(g: Grid, path: Path, where: Mapping[str, Any] | None = None) -> Path:
    """The grid as a colour map with each cell's value written in it; unsafe cells hatched in red."""
    nx, ny = len(g.x_values), len(g.y_values)
    fig = Figure(figsize=(max(5.0, 1.0 * nx + 2.5), max(3.5, 0.6 * ny + 2.0)), layout="constrained")
    ax = fig.add_subplot()
    finite = g.values[np.isfinite(g.values)]
    cmap = colormaps["viridis"].with_extremes(bad="#d9d9d9")  # NaN cells (no run, failed, undefined) grey
    image = ax.imshow(np.ma.masked_invalid(g.values), origin="lower", aspect="auto", cmap=cmap,
                      vmin=finite.min() if finite.size else 0.0, vmax=finite.max() if finite.size else 1.0)
    bar = fig.colorbar(image, ax=ax, label=g.metric)
    bar.formatter = ScalarFormatter(useOffset=False)  # 2474, 2476, ... not 2.47e+03 with an offset
    bar.update_ticks()
    norm = image.norm
    decimals = value_decimals(g.values)
    for i in range(ny):
        for j in range(nx):
            v = g.values[i, j]
            dark = math.isfinite(v) and norm(v) < 0.6
            box = dict(facecolor="white", alpha=0.8, edgecolor="none", pad=1.5) if g.unsafe[i, j] else None
            ax.text(j, i, _cell_text(g, i, j, decimals), ha="center", va="center", fontsize=8,
                    color="white" if dark and box is None else "black", bbox=box)
            if g.unsafe[i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", edgecolor="red", linewidth=1.5))
    ax.set_xticks(range(nx), [_fmt(v) for v in g.x_values])
    ax.set_yticks(range(ny), [_fmt(v) for v in g.y_values])
    ax.set_xlabel(g.x)
    ax.set_ylabel(g.y)
    ax.set_title(_title(g.metric, where), fontsize=10)
    if g.unsafe.any():
        ax.legend(handles=[Patch(fill=False, hatch="///", edgecolor="red", label="unsafe (any seed)")],
                  loc="upper left", bbox_to_anchor=(0.0, -0.12), fontsize=8, frameon=False)
    return _save(fig, path)


def _positions(values: Sequence[AxisValue]) -> tuple[np.ndarray, bool]:
    """Plot positions of axis values: the values if all numeric, else 0..n-1 (categorical)."""
    numeric = all(isinstance(v, float) for v in values)
    return (np.array(values, dtype=float) if numeric else np.arange(len(values), dtype=float)), numeric


def _unsafe_spans(pos: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """x intervals to shade: each unsafe position widened to the midpoints with its neighbours."""
    if len(pos) == 1:
        return [(pos[0] - 0.5, pos[0] + 0.5)] if mask[0] else []
    mids = (pos[1:] + pos[:-1]) / 2
    lo = np.r_[pos[0] - (mids[0] - pos[0]), mids]
    hi = np.r_[mids, pos[-1] + (pos[-1] - mids[-1])]
    return [(lo[k], hi[k]) for k in np.flatnonzero(mask)]


def draw_lines(g: Grid, path: Path, where: Mapping[str, Any] | None = None) -> Path:
    """One line of the metric against x per hue value (the grid's y, or one line if None); unsafe points a
    red x, and the x where any line is unsafe shaded."""
    fig = Figure(figsize=(7.0, 4.5), layout="constrained")
    ax = fig.add_subplot()
    pos, numeric = _positions(g.x_values)
    for k, spans in enumerate(_unsafe_spans(pos, g.unsafe.any(axis=0))):
        ax.axvspan(*spans, color="red", alpha=0.12, linewidth=0, label="unsafe (any line)" if k == 0 else None)
    for i, hue in enumerate(g.y_values):
        ax.plot(pos, g.values[i], marker="o", label=g.metric if g.y is None else f"{g.y} = {_fmt(hue)}")
        bad = g.unsafe[i] & np.isfinite(g.values[i])
        ax.scatter(pos[bad], g.values[i][bad], marker="x", s=90, color="red", linewidths=2, zorder=3)
    handles, labels = ax.get_legend_handles_labels()
    if g.unsafe.any():
        handles.append(Line2D([], [], marker="x", color="red", linestyle="", markersize=9, markeredgewidth=2))
        labels.append("unsafe run(s)")
    ax.legend(handles, labels, fontsize=8)
    if not numeric:
        ax.set_xticks(pos, [_fmt(v) for v in g.x_values])
    elif pos.min() > 0 and pos.max() >= 4 * pos.min():  # e.g. bit rates 125000 .. 1000000: a log axis
        ax.set_xscale("log")
        ax.set_xticks(pos, [_fmt(v) for v in g.x_values])
        ax.xaxis.set_minor_formatter(NullFormatter())
    else:
        ax.ticklabel_format(axis="x", useOffset=False, style="plain")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_xlabel(g.x)
    ax.set_ylabel(g.metric)
    ax.grid(True, alpha=0.3)
    ax.set_title(_title(g.metric, where), fontsize=10)
    return _save(fig, path)


# --------------------------------------------------------------------------- the spec's plots


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+-]+", "_", text).strip("_")


def plot_file_name(kind: str, metric: str, x: str, other: str | None, where: Mapping[str, Any] | None) -> str:
    """``heatmap_<metric>__<y>_vs_<x>[__<axis>=<value>...].png`` / ``lines_<metric>__vs_<x>[_by_<hue>]...``."""
    middle = f"{other}_vs_{x}" if kind == "heatmap" else f"vs_{x}" + (f"_by_{other}" if other else "")
    fixed = "_".join(f"{k}={_fmt(axis_value(v))}" for k, v in (where or {}).items())
    return _slug(f"{kind}_{metric}__{middle}" + (f"__{fixed}" if fixed else "")) + ".png"


def _unique(path: Path, taken: set[Path]) -> Path:
    n, candidate = 2, path
    while candidate in taken:
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
        n += 1
    taken.add(candidate)
    return candidate


def make_plots(spec: Any, rows: Sequence[Mapping[str, Any]], out_dir: Path) -> list[Path]:
    """Render every heatmap and line plot the spec asks for into ``out_dir``; the PNG paths written."""
    plots = _get(spec, "plots")
    heatmaps = list(_get(plots, "heatmaps") or []) if plots is not None else []
    lines = list(_get(plots, "lines") or []) if plots is not None else []
    if not (heatmaps or lines) or not rows:
        return []
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    taken: set[Path] = set()
    for h in heatmaps:
        metric, x, y, where = _get(h, "metric"), _get(h, "x"), _get(h, "y"), _get(h, "where")
        path = _unique(out_dir / plot_file_name("heatmap", metric, x, y, where), taken)
        written.append(draw_heatmap(heatmap_grid(rows, metric, x, y, where), path, where))
    for ln in lines:
        metric, x, hue, where = _get(ln, "metric"), _get(ln, "x"), _get(ln, "hue"), _get(ln, "where")
        path = _unique(out_dir / plot_file_name("lines", metric, x, hue, where), taken)
        written.append(draw_lines(heatmap_grid(rows, metric, x, hue, where), path, where))
    return written
