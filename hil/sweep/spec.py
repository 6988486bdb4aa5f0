"""Sweep files: a base scenario, axes of dotted scenario keys and their grid, validated on load like scenarios.

A sweep file (TOML)::

    name = "latency-loss"
    description = "..."
    base = "seed000"              # packaged scenario name, or a path relative to the sweep file
    duration_s = 60               # optional: overrides the base's duration
    seeds = [0, 1]                # optional: every grid point runs once per seed (default: the base's seed)
    [overrides]                   # optional: dotted keys set in every run
    "radio.loss.model" = "bernoulli"
    [axes]                        # any dotted scenario key -> the values it takes; a value may be a table
    "radio.latency_s" = [0.0, 0.1, 0.5]
    "radio.loss.p" = [0.0, 0.2]
    "controller.law" = ["finite_time", "consensus"]
    [plots]                       # optional; `where` fixes other axis columns, the rest are averaged
    heatmaps = [{ metric = "gap_min_overall_m", x = "radio.latency_s", y = "radio.loss.p", where = { "controller.law" = "consensus" } }]
    lines = [{ metric = "coupler_max_abs_m", x = "radio.latency_s", hue = "controller.law" }]

The grid is the cartesian product of the axes (in file order) times the seeds. Each point's overrides are
applied shallowest key first, so ``"radio.loss"`` (a table) and ``"radio.loss.p"`` compose. Every point is
validated at load (the error names the axis and the value).

Controller law and parameters: parameters belong to a law. When a point's ``controller.law`` differs from the
base's law and no ``controller.params`` key is given (as an axis or in [overrides]), the params are reset to the
new law's defaults (``{}``); ``controller.params.<name>`` keys still apply on top. To sweep laws with their own
parameters, make ``controller`` itself the axis, with tables ``{ law = "...", params = { ... } }`` (a table without
``params`` means the law's defaults).
"""
from __future__ import annotations

import copy
import hashlib
import itertools
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import Field, PrivateAttr, ValidationError, field_validator

from hil.scenario.loader import (
    ScenarioError,
    format_validation_errors,
    packaged_files,
    read_scenario_data,
    read_toml,
    resolve,
    resolve_packaged,
    scenario_from_dict,
)
from hil.scenario.checks import non_finite
from hil.scenario.model import Scenario, Section

_DOTTED = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_RESERVED = {"seed": "use `seeds = [...]`"}
_QUOTE_HINT = "quote dotted keys in TOML, e.g. \"radio.latency_s\" = ..., or TOML reads them as nested tables"


class SweepError(ScenarioError):
    """A user error in a sweep file: the message names the file, the field and the bad value."""


def canonical_json(value: Any) -> str:
    """Key-sorted compact JSON: equal overrides give equal text, so equal run ids."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def run_id(overrides: dict[str, Any]) -> str:
    """Stable short id of a run from its overrides (which include the seed)."""
    return hashlib.sha256(canonical_json(overrides).encode()).hexdigest()[:12]


def flatten(value: Any, prefix: str) -> dict[str, Any]:
    """Nested tables -> dotted names, lists -> name_1, name_2, ...; scalars stay (used for axis and metric columns)."""
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    if isinstance(value, (list, tuple)):
        out = {}
        for i, v in enumerate(value, start=1):
            out.update(flatten(v, f"{prefix}_{i}"))
        return out
    return {prefix: value}


# --------------------------------------------------------------------------- the file's schema


class HeatmapPlot(Section):
    """A metric over two axis columns; ``where`` fixes other axis columns ({column: value}), the rest are averaged."""

    metric: str
    x: str
    y: str
    where: dict[str, Any] | None = None


class LinePlot(Section):
    """A metric against one axis column, one line per value of ``hue`` (an axis column) if given."""

    metric: str
    x: str
    hue: str | None = None
    where: dict[str, Any] | None = None


class PlotsConfig(Section):
    heatmaps: list[HeatmapPlot] = []
    lines: list[LinePlot] = []


@dataclass(frozen=True)
class GridPoint:
    """One run of the sweep: its id, seed, axis values, the overrides applied to the base, the validated scenario."""

    run_id: str
    seed: int
    axes: dict[str, Any]
    overrides: dict[str, Any]
    scenario: Scenario

    @property
    def columns(self) -> dict[str, Any]:
        """The axis values as CSV columns (tables flattened with dotted names)."""
        out: dict[str, Any] = {}
        for key, value in self.axes.items():
            out.update(flatten(value, key))
        return out


class SweepSpec(Section):
    """A validated sweep file; ``points`` is its grid (built and checked at load)."""

    name: str = Field(min_length=1)
    description: str = ""
    base: str = Field(min_length=1, description="packaged scenario name, or a path relative to the sweep file")
    duration_s: float | None = Field(default=None, gt=0)
    seeds: list[int] | None = Field(default=None, min_length=1)
    overrides: dict[str, Any] = {}
    axes: dict[str, list[Any]] = {}
    plots: PlotsConfig = PlotsConfig()

    _source: str = PrivateAttr(default="<sweep>")
    _base_path: Path | None = PrivateAttr(default=None)
    _points: list[GridPoint] = PrivateAttr(default_factory=list)

    @field_validator("axes", mode="before")
    @classmethod
    def _axes_are_lists(cls, axes: Any) -> Any:
        if isinstance(axes, dict):
            for key, values in axes.items():
                if isinstance(values, dict):
                    raise ValueError(f"axis {key!r} is a table, not a list of values: {_QUOTE_HINT}")
        return axes

    @field_validator("overrides")
    @classmethod
    def _no_whole_sections(cls, overrides: dict[str, Any]) -> dict[str, Any]:
        for key, value in overrides.items():
            if "." not in key and isinstance(value, dict) and key != "controller":
                raise ValueError(f"{key!r} would replace the whole [{key}] section: {_QUOTE_HINT}")
        return overrides

    @field_validator("overrides", "axes")
    @classmethod
    def _dotted_keys(cls, value: dict[str, Any]) -> dict[str, Any]:
        for key in value:
            if not _DOTTED.match(key):
                raise ValueError(f"{key!r} is not a dotted scenario key (like \"radio.latency_s\")")
            if key in _RESERVED:
                raise ValueError(f"{key!r} cannot be set here: {_RESERVED[key]}")
        return value

    @field_validator("axes")
    @classmethod
    def _distinct_values(cls, axes: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in axes.items():
            if not values:
                raise ValueError(f"axis {key!r} has no values")
            bad = non_finite(values)
            if bad is not None:
                raise ValueError(f"axis {key!r}: value {bad} is NaN or infinite (a finite number is needed)")
            seen = [canonical_json(v) for v in values]
            for v, text in zip(values, seen):
                if seen.count(text) > 1:
                    raise ValueError(f"axis {key!r} lists the value {v!r} twice")
        return axes

    @field_validator("seeds")
    @classmethod
    def _distinct_seeds(cls, seeds: list[int] | None) -> list[int] | None:
        if seeds is not None and len(set(seeds)) != len(seeds):
            raise ValueError(f"seeds are not distinct: {seeds}")
        return seeds

    @property
    def source(self) -> str:
        return self._source

    @property
    def base_path(self) -> Path:
        assert self._base_path is not None, "SweepSpec built without load_sweep/sweep_from_dict"
        return self._base_path

    @property
    def points(self) -> list[GridPoint]:
        """Every run of the sweep: axes' cartesian product (file order), then seeds."""
        return self._points

    @property
    def axis_columns(self) -> list[str]:
        """CSV column names of the axes, in axis order (tables flattened, union over their values)."""
        cols: dict[str, None] = {}
        for key, values in self.axes.items():
            for v in values:
                cols.update(dict.fromkeys(flatten(v, key)))
        return list(cols)


# --------------------------------------------------------------------------- loading


def packaged_sweeps() -> dict[str, Path]:
    """Packaged sweep name -> file (hil/packaged/sweeps/*.toml)."""
    return packaged_files("sweeps")


def resolve_sweep(name_or_path: str | Path) -> Path:
    """A packaged sweep name (``latency-loss``) or a path to a TOML file."""
    return resolve_packaged(name_or_path, "sweeps", "sweep", SweepError)


def load_sweep(name_or_path: str | Path, overrides: dict[str, Any] | None = None,
               duration_s: float | None = None) -> SweepSpec:
    """Read, parse and validate a sweep file and its whole grid; every failure is a SweepError naming the file.

    ``overrides`` (``hil sweep --set``) join the file's ``[overrides]``, set in every run; ``duration_s``
    (``--duration``) replaces the file's. Both change the run ids, so they never reuse runs made without them."""
    path = resolve_sweep(name_or_path)
    data = read_toml(path, SweepError)
    axes = data.get("axes") if isinstance(data.get("axes"), dict) else {}
    clash = sorted(set(overrides or {}) & set(axes))
    if clash:  # the axis would silently win over --set in every run
        raise SweepError(f"{path}: --set {clash[0]}=...: {clash[0]!r} is an axis of this sweep (values "
                         f"{axes[clash[0]]}); a --set cannot fix it: sweep it, or copy the sweep file without that axis")
    if overrides:
        data["overrides"] = {**data.get("overrides", {}), **overrides}
    if duration_s is not None:
        data["duration_s"] = duration_s
    return sweep_from_dict(data, str(path), path.parent)


def sweep_from_dict(data: dict[str, Any], source: str = "<sweep>", base_dir: Path | None = None) -> SweepSpec:
    """Validate a parsed sweep (``base`` paths are relative to ``base_dir``) and build its grid."""
    try:
        spec = SweepSpec(**data)
    except ValidationError as exc:
        raise SweepError(format_validation_errors(source, exc, "sweep")) from None
    spec._source = source
    spec._base_path = _resolve_base(spec.base, source, base_dir or Path.cwd())
    base_data = _read_base(spec._base_path, source)
    spec._points = _build_grid(spec, base_data)
    _check_plots(spec)
    return spec


def _resolve_base(base: str, source: str, base_dir: Path) -> Path:
    local = base_dir / base
    try:
        return resolve(local if (base.endswith(".toml") or local.exists()) else base)
    except ScenarioError as exc:
        raise SweepError(f"{source}: base = {base!r}: {exc}") from None


def _read_base(path: Path, source: str) -> dict[str, Any]:
    try:
        return read_scenario_data(path)
    except ScenarioError as exc:
        raise SweepError(f"{source}: base {path}: cannot read: {exc}") from None


# --------------------------------------------------------------------------- the grid


def _law_of(overrides: dict[str, Any]) -> str | None:
    if "controller.law" in overrides:
        return overrides["controller.law"]
    table = overrides.get("controller")
    return table.get("law") if isinstance(table, dict) else None


def _sets_params(overrides: dict[str, Any]) -> bool:
    table = overrides.get("controller")
    return "controller.params" in overrides or isinstance(table, dict)


def point_overrides(spec: SweepSpec, axes: dict[str, Any], seed: int, base_law: str) -> dict[str, Any]:
    """The overrides of one run, shallowest key first (see the module docstring for the law/params rule)."""
    ov: dict[str, Any] = {} if spec.duration_s is None else {"duration_s": spec.duration_s}
    ov.update(copy.deepcopy(spec.overrides))
    ov.update(copy.deepcopy(axes))
    ov["seed"] = seed
    law = _law_of(ov)
    if law is not None and law != base_law and not _sets_params(ov):
        ov["controller.params"] = {}
    return dict(sorted(ov.items(), key=lambda kv: kv[0].count(".")))


def _scenario(base_data: dict[str, Any], base_path: Path, overrides: dict[str, Any]) -> Scenario:
    return scenario_from_dict(copy.deepcopy(base_data), str(base_path), copy.deepcopy(overrides))


def _build_grid(spec: SweepSpec, base_data: dict[str, Any]) -> list[GridPoint]:
    """Validate the base with the fixed overrides, then every point; errors name the axis and the value."""
    try:
        base = _scenario(base_data, spec.base_path, {})
    except ScenarioError as exc:
        raise SweepError(f"{spec.source}: base = {spec.base!r} is not a valid scenario:\n  {_indent(exc)}") from None
    seeds = spec.seeds if spec.seeds is not None else [base.seed]
    base_law = base.controller.law
    try:
        _scenario(base_data, spec.base_path, point_overrides(spec, {}, seeds[0], base_law))
    except ScenarioError as exc:
        raise SweepError(f"{spec.source}: [overrides] give an invalid scenario:\n  {_indent(exc)}") from None
    points = []
    keys = list(spec.axes)
    for combo in itertools.product(*spec.axes.values()):
        axes = dict(zip(keys, combo))
        for seed in seeds:
            ov = point_overrides(spec, axes, seed, base_law)
            try:
                scenario = _scenario(base_data, spec.base_path, ov)
            except ScenarioError as exc:
                raise _blame(spec, base_data, axes, seed, base_law, exc) from None
            points.append(GridPoint(run_id(ov), seed, axes, ov, scenario))
    return points


def _blame(spec: SweepSpec, base_data: dict[str, Any], axes: dict[str, Any], seed: int, base_law: str,
           exc: ScenarioError) -> SweepError:
    """Name the axis value that alone makes the scenario invalid, else the combination."""
    for key, value in axes.items():
        try:
            _scenario(base_data, spec.base_path, point_overrides(spec, {key: value}, seed, base_law))
        except ScenarioError as single:
            return SweepError(f"{spec.source}: axes.{key!r} value {_show(value)} gives an invalid scenario:\n  {_indent(single)}")
    combo = ", ".join(f"{k} = {_show(v)}" for k, v in axes.items())
    return SweepError(f"{spec.source}: the grid point ({combo}) gives an invalid scenario:\n  {_indent(exc)}")


def _check_plots(spec: SweepSpec) -> None:
    """Plot axes and ``where`` keys must be axis columns, ``where`` values values of them (metrics are known only later)."""
    values: dict[str, list[Any]] = {c: [] for c in spec.axis_columns}
    for p in spec.points:
        for col, v in p.columns.items():
            if v not in values[col]:
                values[col].append(v)
    known = f"(axis columns: {', '.join(values) or 'none'})"
    for kind, plots in (("heatmaps", spec.plots.heatmaps), ("lines", spec.plots.lines)):
        for i, plot in enumerate(plots):
            where = f"{spec.source}: plots.{kind}.{i}"
            for field in ("x", "y", "hue"):
                col = getattr(plot, field, None)
                if col is not None and col not in values:
                    raise SweepError(f"{where}.{field}: {col!r} is not an axis column {known}")
            for col, v in (plot.where or {}).items():
                if col not in values:
                    raise SweepError(f"{where}.where: {col!r} is not an axis column {known}")
                if v not in values[col]:
                    raise SweepError(f"{where}.where.{col}: {v!r} is not one of its values {values[col]}")


def _show(value: Any) -> str:
    return canonical_json(value) if isinstance(value, (dict, list)) else repr(value)


def _indent(exc: Exception) -> str:
    return str(exc).replace("\n", "\n  ")
