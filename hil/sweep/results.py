"""The results table of a sweep: DIR/results.csv, one row per finished run, and reading it back.

Columns: ``run_id, seed, status (ok/failed), error``, then each axis (tables flattened with dotted names,
e.g. ``radio.loss.model``, ``radio.loss.p``), then every metric of ``metrics.json`` flattened the same way
(nested dicts with dots, lists as ``name_1, name_2, ...``). Per-item tables that grow with the rig are
summed instead, so the columns do not explode: ``e2e`` (per ECU) -> ``e2e_total.<status>``,
``codec_saturations`` (per signal) -> ``codec_saturations_total``, ``radio`` (per link) ->
``radio_total.<counter>``; ``per_bus.<bus>.latency_max_by_id`` is left out (it stays in each run's
metrics.json). Safety keeps one column per verdict and figure (``safety.overspeed.count``, ``.total_s``,
``.first_s``, ``.violated``, and ``safety.safe``); the violations themselves are rows of
``DIR/safety_violations.csv`` (with the run id). Of the provenance, the scenario hash and the version. Empty cells are undefined values (None) or metrics of failed runs; a failed run's ``error`` is the first
line of its error.txt (type: message), cut to 200 characters. Runs not finished
(an interrupted sweep) have no row yet.

``wall_time_s`` and ``realtime_factor`` depend on the machine and its load; every other metric of a run is
deterministic (NONDETERMINISTIC lists the exceptions).
"""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from hil.sweep.spec import GridPoint, SweepSpec, flatten

RESULTS = "results.csv"
FIXED_COLUMNS = ["run_id", "seed", "status", "error"]
STRING_COLUMNS = {"run_id", "status", "error", "scenario", "runtime", "provenance.scenario_sha256", "provenance.version"}
NONDETERMINISTIC = {"wall_time_s", "realtime_factor"}
ERROR_CHARS = 200  # the error column is the first line of error.txt, cut to this length
SUMMED = {"e2e": "e2e_total", "codec_saturations": "codec_saturations_total", "radio": "radio_total"}
PROVENANCE_COLUMNS = ("scenario_sha256", "version")  # the rest of a run's provenance stays in its metrics.json
SAFETY_DETAILS = "safety_violations.csv"
SAFETY_COLUMNS = ["run_id", "verdict", "where", "start_s", "end_s", "duration_s", "worst", "worst_at_s", "limit", "cause"]


def flatten_metrics(metrics: dict[str, Any]) -> dict[str, Any]:
    """One run's metrics as CSV columns (see the module docstring for what is summed or left out)."""
    out: dict[str, Any] = {}
    for key, value in metrics.items():
        if key in SUMMED:
            out.update(_summed(value, SUMMED[key]))
        elif key == "safety":
            out.update(flatten(_verdicts(value), key))
        elif key == "provenance":
            out.update({f"{key}.{k}": value.get(k) for k in PROVENANCE_COLUMNS})
        elif key == "per_bus":
            per_bus = {bus: {k: v for k, v in stats.items() if k != "latency_max_by_id"} for bus, stats in value.items()}
            out.update(flatten(per_bus, key))
        else:
            out.update(flatten(value, key))
    return out


def _verdicts(safety: dict[str, Any]) -> dict[str, Any]:
    """``safe`` and per verdict its scalars (violated, count, total_s, first_s); the violations themselves go to
    SAFETY_DETAILS, one row each."""
    return {k: ({kk: vv for kk, vv in v.items() if kk != "violations"} if isinstance(v, dict) else v)
            for k, v in safety.items() if k != "overspeed_margin"}


def _summed(table: dict[str, Any], name: str) -> dict[str, Any]:
    """{item: count} -> one total; {item: {counter: count}} -> one total per counter."""
    if all(isinstance(v, (int, float)) for v in table.values()):
        return {name: sum(table.values())}
    totals: dict[str, int] = {}
    for counters in table.values():
        for k, v in counters.items():
            totals[k] = totals.get(k, 0) + v
    return {f"{name}.{k}": v for k, v in totals.items()}


def _row(point: GridPoint, run_dir: Path) -> dict[str, Any] | None:
    base = {"run_id": point.run_id, "seed": point.seed}
    metrics_file, error_file = run_dir / "metrics.json", run_dir / "error.txt"
    if metrics_file.is_file():
        metrics = json.loads(metrics_file.read_text(encoding="utf-8"))
        return {**base, "status": "ok", "error": None, **point.columns, **flatten_metrics(metrics)}
    if error_file.is_file():
        first = error_file.read_text(encoding="utf-8").split("\n", 1)[0]
        short = first if len(first) <= ERROR_CHARS else first[:ERROR_CHARS - 3] + "..."
        return {**base, "status": "failed", "error": short, **point.columns}
    return None


def write_results(spec: SweepSpec, out_dir: Path) -> tuple[list[dict[str, Any]], Path]:
    """Collect every finished run of the grid into out_dir/results.csv; returns its rows (as load_results reads them)."""
    rows = [r for p in spec.points if (r := _row(p, out_dir / "runs" / p.run_id)) is not None]
    columns = dict.fromkeys(FIXED_COLUMNS + spec.axis_columns)
    for r in rows:
        columns.update(dict.fromkeys(r))
    path = out_dir / RESULTS
    tmp = path.with_name(f".{RESULTS}.tmp")
    with tmp.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: _cell(r.get(k)) for k in columns})
    tmp.replace(path)
    _write_safety_details(spec, out_dir)
    return load_results(out_dir), path


def _write_safety_details(spec: SweepSpec, out_dir: Path) -> Path:
    """DIR/safety_violations.csv: every listed safety violation of every finished run, with the run's id."""
    path = out_dir / SAFETY_DETAILS
    tmp = path.with_name(f".{SAFETY_DETAILS}.tmp")
    with tmp.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=SAFETY_COLUMNS)
        writer.writeheader()
        for p in spec.points:
            metrics_file = out_dir / "runs" / p.run_id / "metrics.json"
            if not metrics_file.is_file():
                continue
            safety = json.loads(metrics_file.read_text(encoding="utf-8")).get("safety") or {}
            for verdict in safety.values():
                for v in (verdict.get("violations", []) if isinstance(verdict, dict) else []):
                    writer.writerow({"run_id": p.run_id, **{k: _cell(v.get(k)) for k in SAFETY_COLUMNS[1:]}})
    tmp.replace(path)
    return path


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # round-trips exactly
    return str(value)


def load_results(directory: str | Path) -> list[dict[str, Any]]:
    """Rows of DIR/results.csv (or of that CSV file) with types restored: None, bool, int, float or str."""
    path = Path(directory)
    if path.is_dir():
        path = path / RESULTS
    with path.open(newline="", encoding="utf-8") as f:
        return [{k: _parse(k, v) for k, v in row.items()} for row in csv.DictReader(f)]


def _parse(column: str, cell: str) -> Any:
    if cell == "":
        return None
    if column in STRING_COLUMNS:
        return cell
    if cell in ("true", "false"):
        return cell == "true"
    for kind in (int, float):
        try:
            return kind(cell)
        except ValueError:
            pass
    return cell
