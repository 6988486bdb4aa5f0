"""Comparison metrics of the multi-train seeds: seed 002's Table 4 and seed 003's tracking errors, plus plots.

Plain functions over a RunLog (hil/record/runlog.py). Definitions (the seeds define none of them; ours):

Seed 002 (spacing d = head-to-head distance x_i - x_i+1 of each pair, the paper's point-mass d_ij;
d_r = l_s + length of the train ahead, 7.4 km in seed002):
- convergence time: first time after which every train's |v - v_r| stays within ``band_mps`` (default
  0.5 m/s) until the first reference step;
- re-convergence after each reference step: the same, from the step to the next step (None if never);
- max spacing overshoot: per pair, the largest excursion of d outside the interval spanned by its start
  value and d_r (a gap that only closes towards d_r has none; one that passes d_r or first grows away from
  it has); the table gives the largest over pairs;
- spacing band once converged: [min d, max d] over all pairs from the convergence time to the end;
- mean steady spacing error per pair: mean of d - d_r over the same period (and of |d - d_r|: the paper's
  values are all positive, so they may be magnitudes);
- peak acceleration demanded: max |commanded force| / effective mass (the law's demand, before any limit).
Seed 003 (x~ = x - (x_r - offset) the slot error, v~ = v - v_r): per train and overall, the max and RMS of
|x~| and |v~| over [``window_start_s``, end], and the max speed against a limit (time above it).
All values are plain floats (None when undefined), so the dicts dump to JSON.

``hil compare`` families (hil/compare/report.py): ``multi_train`` (seed 002's Table 4, for every multi-train
scenario whose law is not one of seed 003's ``chain_*``) and ``multi_train_tracking`` (seed 003's protocols).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from hil.compare.report import Column, MetricFamily, RunData, register_family
from hil.record.runlog import RunLog
from hil.scenario.model import Scenario

BAND_MPS = 0.5


def _f(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def head_distances(log: RunLog) -> np.ndarray:
    """(k, pairs) head-to-head distance d = x_head(i) - x_head(i+1), m."""
    heads = log.layout.heads()
    return log.x[:, heads[:-1]] - log.x[:, heads[1:]]


def desired_distances(log: RunLog) -> np.ndarray:
    """(pairs,) d_r = l_s + length of the train ahead (the rig's gap target, head to head)."""
    heads = log.layout.heads()
    return np.diff(log.layout.offset_m[heads])


def _segments(log: RunLog) -> list[tuple[float, int, int]]:
    """(start time, first row, end row) of every reference segment."""
    t = log.t
    changes = sorted({float(c) for c in log.reference_change_times if 0.0 < c < (t[-1] if len(t) else 0.0)})
    starts = [0.0] + changes
    rows = np.searchsorted(t, starts, side="left").tolist() + [len(t)]
    return [(s, rows[k], rows[k + 1]) for k, s in enumerate(starts)]


def settle_time(t: np.ndarray, within: np.ndarray, start: float) -> float | None:
    """Time from ``start`` to the first sample after which ``within`` holds to the end of the slice (None: never)."""
    if len(within) == 0:
        return None
    bad = np.flatnonzero(~within)
    r = int(bad[-1]) + 1 if len(bad) else 0
    return None if r >= len(within) else float(t[r] - start)


def spacing_overshoot(d: np.ndarray, d_r: np.ndarray) -> np.ndarray:
    """Per pair: largest excursion of d outside [min(d(0), d_r), max(d(0), d_r)] (m, >= 0)."""
    lo, hi = np.minimum(d[0], d_r), np.maximum(d[0], d_r)
    return np.maximum(np.max(d - hi, axis=0), np.max(lo - d, axis=0)).clip(min=0.0)


def seed002_metrics(log: RunLog, band_mps: float = BAND_MPS) -> dict[str, Any]:
    """Seed 002's Table 4 metrics (and more) of one run; distances in km like the paper's table."""
    t, L = log.t, log.layout
    within = np.all(np.abs(log.speed_error) <= band_mps, axis=1)
    segs = _segments(log)
    times = [settle_time(t[r0:r1], within[r0:r1], s) for s, r0, r1 in segs]
    d, d_r = head_distances(log), desired_distances(log)
    conv = times[0]
    after = t >= conv if conv is not None else np.zeros(len(t), dtype=bool)
    steady = d[after]
    accel = np.abs(log.force_cmd) / L.effective_mass_kg[None, :]
    gaps = log.gaps
    return {
        "band_mps": band_mps,
        "convergence_time_s": _f(conv),
        "reconvergence_s": [_f(x) for x in times[1:]],
        "reference_steps_s": [s for s, _, _ in segs[1:]],
        "max_spacing_overshoot_km": _f(np.max(spacing_overshoot(d, d_r)) / 1e3) if d.size else None,
        "spacing_overshoot_km": [_f(x / 1e3) for x in spacing_overshoot(d, d_r)] if d.size else [],
        "spacing_band_km": [_f(steady.min() / 1e3), _f(steady.max() / 1e3)] if steady.size else [None, None],
        "mean_steady_error_km": [_f(x / 1e3) for x in np.mean(steady - d_r, axis=0)] if steady.size else [],
        "mean_abs_steady_error_km": [_f(x / 1e3) for x in np.mean(np.abs(steady - d_r), axis=0)] if steady.size else [],
        "final_spacing_km": [_f(x / 1e3) for x in d[-1]] if d.size else [],
        "peak_accel_demand_mps2": _f(accel.max()) if accel.size else None,
        "speed_error_range_mps": [_f(log.speed_error.min()), _f(log.speed_error.max())],
        "min_gap_m": _f(gaps.min()) if gaps.size else None,
    }


def seed003_metrics(log: RunLog, window_start_s: float, speed_limit_mps: float | None = None) -> dict[str, Any]:
    """Tracking errors over [window_start_s, end] and the speed-limit check over the whole run."""
    w = log.t >= window_start_s
    xe, ve = log.position_error[w], log.speed_error[w]
    out: dict[str, Any] = {
        "window_start_s": window_start_s,
        "x_err_max_m": [_f(x) for x in np.abs(xe).max(axis=0)] if xe.size else [],
        "x_err_rms_m": [_f(x) for x in np.sqrt(np.mean(xe**2, axis=0))] if xe.size else [],
        "v_err_max_mps": [_f(x) for x in np.abs(ve).max(axis=0)] if ve.size else [],
        "v_err_rms_mps": [_f(x) for x in np.sqrt(np.mean(ve**2, axis=0))] if ve.size else [],
        "x_err_max_all_m": _f(np.abs(xe).max()) if xe.size else None,
        "x_err_rms_all_m": _f(np.sqrt(np.mean(xe**2))) if xe.size else None,
        "v_err_rms_all_mps": _f(np.sqrt(np.mean(ve**2))) if ve.size else None,
        "speed_max_mps": _f(log.v.max()) if log.v.size else None,
        "min_gap_m": _f(log.gaps.min()) if log.gaps.size else None,
    }
    if speed_limit_mps is not None:
        above = np.any(log.v > speed_limit_mps, axis=1)
        hold = np.append(np.diff(log.t), 0.0)
        out["speed_limit_mps"] = float(speed_limit_mps)
        out["time_above_limit_s"] = float(np.sum(hold[above]))
        out["speed_limit_exceeded"] = bool(above.any())
    return out


def speed_limit_of(scenario) -> float | None:
    """The speed limit a scenario's law enforces (``speed_limit_mps`` in its params), if any."""
    value = scenario.controller.params.get("speed_limit_mps")
    return None if value is None else float(value)


# ------------------------------------------------------------------------------------------------ report

PAPER_TABLE4 = {  # seed 002, Table 4: convergence, max overshoot, spacing band, mean steady error per pair
    "seed002": ("80 s", "0.21 km", "7.28-7.61 km", "[0.21, 0.11, 0.01, 0.13] km"),
    "seed002-bai": ("150 s", "5.43 km", "7.40 km", "[0, 0, 0, 0] km"),
    "seed002-lyg": ("320 s", "1.41 km", "7.32-8.79 km", "[0.58, 0.53, 0.12, 1.39] km"),
}
PAPER_RECONVERGENCE = "10 s / 30 s (fuzzy law)"
SEED003_WINDOW_S = 400.0  # disturbances act from here on
SEED003_LATE_S = 600.0  # also after protocol 3's slower (saturated) start-up has died out


def _fmt(x, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, list):
        return "[" + ", ".join(_fmt(v, digits) for v in x) + "]"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def table4_rows(logs: dict[str, RunLog], names: list[str]) -> list[str]:
    """Markdown rows: ours beside the paper's for every run present."""
    rows = ["| run | convergence (s) | re-convergence after steps (s) | max spacing overshoot (km) | spacing band once converged (km) "
            "| mean steady error per pair (km) | mean abs steady error per pair (km) | peak demand (m/s^2) "
            "| paper: conv. / overshoot / band / mean error |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name in names:
        if name not in logs:
            continue
        m = seed002_metrics(logs[name])
        base = name.split("+")[0].split("@")[0]
        paper = " / ".join(PAPER_TABLE4[base]) if base in PAPER_TABLE4 else "-"
        band = m["spacing_band_km"]
        band_txt = "-" if band[0] is None else f"{band[0]:.3f}-{band[1]:.3f}"
        rows.append(f"| {name} | {_fmt(m['convergence_time_s'], 4)} | {_fmt(m['reconvergence_s'], 3)} | "
                    f"{_fmt(m['max_spacing_overshoot_km'], 3)} | {band_txt} | {_fmt(m['mean_steady_error_km'], 2)} | "
                    f"{_fmt(m['mean_abs_steady_error_km'], 2)} | "
                    f"{_fmt(m['peak_accel_demand_mps2'], 3)} | {paper} |")
    return rows


def seed003_rows(logs: dict[str, RunLog], names: list[str], limits: dict[str, float | None]) -> list[str]:
    rows = [f"| run | max abs x~ over [{SEED003_WINDOW_S:.0f} s, end] per train (m) | RMS x~ all (m) | RMS v~ all (m/s) "
            f"| RMS x~ over [{SEED003_LATE_S:.0f} s, end] (m) | max speed (m/s) | speed limit (m/s) | time above it (s) |",
            "|---|---|---|---|---|---|---|---|"]
    limit = next((v for v in limits.values() if v is not None), None)
    for name in names:
        if name not in logs:
            continue
        m = seed003_metrics(logs[name], SEED003_WINDOW_S, limit)
        late = seed003_metrics(logs[name], SEED003_LATE_S)
        rows.append(f"| {name} | {_fmt(m['x_err_max_m'], 3)} | {_fmt(m['x_err_rms_all_m'], 3)} | {_fmt(m['v_err_rms_all_mps'], 3)} | "
                    f"{_fmt(late['x_err_rms_all_m'], 3)} | "
                    f"{_fmt(m['speed_max_mps'], 4)} | {_fmt(m.get('speed_limit_mps'), 4)} | {_fmt(m.get('time_above_limit_s'), 3)} |")
    return rows


def report_markdown(runs: dict[str, tuple[RunLog, Any]], extras: dict[str, dict] | None = None) -> str:
    """The tables of docs/multi_train.md from saved runs: name -> (RunLog, Scenario)."""
    logs = {k: v[0] for k, v in runs.items()}
    names002 = [n for n in logs if n.startswith("seed002")]
    order = sorted(names002, key=lambda n: ("@" in n, "+" in n, n))
    out = ["## Seed 002, Table 4 (ours beside the paper's)", ""]
    out += table4_rows(logs, [n for n in order if "+" not in n and "@" not in n]) + [""]
    out += ["### Ideal loop (no network)", ""] + table4_rows(logs, [n for n in order if "@" in n]) + [""]
    out += ["### Realistic traction limits", ""] + table4_rows(logs, [n for n in order if "+" in n]) + [""]
    names003 = sorted(n for n in logs if n.startswith("seed003"))
    limits = {n: speed_limit_of(runs[n][1]) for n in names003}
    out += ["## Seed 003 tracking errors", ""] + seed003_rows(logs, [n for n in names003 if "@" not in n], limits) + [""]
    out += ["### Ideal loop (no network)", ""] + seed003_rows(logs, [n for n in names003 if "@" in n], limits) + [""]
    if extras:
        out += ["## Events and saturations", ""]
        for name, extra in sorted(extras.items()):
            events = [e for e in extra.get("events", []) if e[1] in ("WARN", "ERROR")]
            sat = extra.get("saturations") or {}
            if events or sat:
                first = f"; first: t = {events[0][0]:.2f} s {events[0][2]}: {events[0][3]}" if events else ""
                out.append(f"- {name}: {len(events)} warnings/errors{first}; saturations {sat}")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------ plots


def plot_spacing(logs: dict[str, RunLog], path: Path, title: str = "") -> None:
    """One panel per law: head-to-head spacing of every pair over time, with d_r."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(logs)
    cols = 2 if n > 1 else 1
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7 * cols, 2.8 * rows), sharex=True, squeeze=False)
    for ax, (name, log) in zip(axes.ravel(), logs.items()):
        d = head_distances(log) / 1e3
        for k in range(d.shape[1]):
            ax.plot(log.t, d[:, k], lw=0.9, label=f"d{k + 1},{k + 2}")
        ax.axhline(desired_distances(log)[0] / 1e3, color="k", ls="--", lw=0.8, label="d_r")
        for s in log.reference_change_times:
            ax.axvline(s, color="grey", ls=":", lw=0.8)
        ax.set(title=name, ylabel="spacing (km)")
        ax.legend(loc="upper right", fontsize=7, ncol=5)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_seed003(logs: dict[str, RunLog], path: Path, what: str = "tracking", speed_limit_mps: float | None = None) -> None:
    """One panel per protocol: slot errors x~ (``tracking``) or speeds with the limit (``speed``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(logs), 1, figsize=(10, 2.8 * len(logs)), sharex=True, squeeze=False)
    for ax, (name, log) in zip(axes[:, 0], logs.items()):
        y = log.position_error if what == "tracking" else log.v
        for k in range(y.shape[1]):
            ax.plot(log.t, y[:, k], lw=0.8, label=f"train {k + 1}")
        if what == "tracking":
            ax.set(ylim=(-30, 30), ylabel="x - x* (m)")
            ax.axvline(SEED003_WINDOW_S, color="grey", ls=":", lw=0.8)
        else:
            ax.plot(log.t, log.v_ref, "k--", lw=0.8, label="v_r")
            if speed_limit_mps is not None:
                ax.axhline(speed_limit_mps, color="r", ls=":", lw=1.0, label="speed limit")
            ax.set(ylabel="v (m/s)")
        ax.set(title=name)
        ax.legend(loc="upper right", fontsize=7, ncol=7)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ hil compare families

LINE_LIMIT_MPS = 300 / 3.6  # seed003's line speed limit
PAPER_BY_LAW = {"potential": PAPER_TABLE4["seed002"], "fixed_spacing": PAPER_TABLE4["seed002-bai"],
                "safe_range": PAPER_TABLE4["seed002-lyg"]}


@register_family
class MultiTrainSpacing(MetricFamily):
    name = "multi_train"
    description = (f"several trains (seed 002's Table 4): spacing d head to head; converged = every |v - v_r| <= "
                   f"{BAND_MPS:g} m/s to the first reference step; band and mean errors from then to the end")
    columns = [
        Column("convergence_time_s", "convergence (s)", "{:.4g}"),
        Column("reconvergence_s", "re-convergence after each v_r step (s)", "{:.3g}"),
        Column("max_spacing_overshoot_km", "max spacing overshoot (km)", "{:.3g}"),
        Column("spacing_band_km", "spacing band once converged (km)", "{:.4g}"),
        Column("mean_steady_error_km", "mean steady spacing error per pair (km)", "{:.2g}"),
        Column("mean_abs_steady_error_km", "mean |steady spacing error| per pair (km)", "{:.2g}"),
        Column("peak_accel_demand_mps2", "peak acceleration demanded (m/s^2)", "{:.3g}"),
        Column("min_gap_m", "min gap (m)", "{:.5g}"),
    ]
    paper_columns = [Column("paper_convergence", "paper: convergence", None), Column("paper_overshoot", "paper: overshoot", None),
                     Column("paper_band", "paper: band", None), Column("paper_mean_error", "paper: mean error", None)]

    def applies(self, scenario: Scenario) -> bool:
        return scenario.trains.count >= 2 and not scenario.controller.law.startswith("chain_")

    def paper(self, law: str) -> dict[str, Any]:
        claims = PAPER_BY_LAW.get(law)
        return dict(zip((c.key for c in self.paper_columns), claims)) if claims else {}

    def compute(self, run: RunData) -> dict[str, Any]:
        return seed002_metrics(run.log)


@register_family
class MultiTrainTracking(MetricFamily):
    name = "multi_train_tracking"
    description = ("seed 003's protocols: slot errors x - x* and v - v_r from the first disturbance on, "
                   "max speed against the law's speed_limit_mps (time above it over the whole run)")
    columns = [
        Column("x_err_max_all_m", "max |x - x*| (m)", "{:.3g}"),
        Column("x_err_rms_all_m", "RMS x - x* (m)", "{:.3g}"),
        Column("x_err_max_m", "max |x - x*| per train (m)", "{:.3g}"),
        Column("v_err_rms_all_mps", "RMS v - v_r (m/s)", "{:.3g}"),
        Column("speed_max_mps", "max speed (m/s)", "{:.4g}"),
        Column("time_above_limit_s", "time above the speed limit (s)", "{:.3g}"),
    ]

    def applies(self, scenario: Scenario) -> bool:
        return scenario.trains.count >= 2 and scenario.controller.law.startswith("chain_")

    def startup_s(self, scenario: Scenario) -> float:
        starts = [d.start_s for d in scenario.plant.disturbances]
        return min(starts) if starts else 0.0

    def compute(self, run: RunData) -> dict[str, Any]:
        sc = run.scenario
        # every protocol is judged against the same line limit: the one protocol 3 enforces, else seed 003's 300 km/h
        limit = speed_limit_of(sc) or LINE_LIMIT_MPS
        return seed003_metrics(run.log, self.startup_s(sc), limit)
