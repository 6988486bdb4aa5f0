"""Metric family ``single_train``: one train of coupled cars tracking a reference (seeds 001 and 004).

Definitions (t_s = ``STARTUP_S`` = 10 s ends the start-up; W = the start-up window, from 0 to the first
disturbance or ``WINDOW_S`` = 60 s, whichever is earlier, and never beyond the run):

- ``spacing_time_s``: time to close the spacing: the first recorded t from which every car spacing
  x_j - x_{j+1} stays within ``SPACING_TOL_M`` = 1 cm of its rest value l_j until W ends, and for at least
  ``HOLD_S`` = 5 s (None if never);
- ``band_entry_s``: the same for the speed error of every car, |v - v_r| <= ``ERROR_BAND_MPS`` = 0.01 m/s;
- ``speed_err_min_mps`` / ``speed_err_max_mps``: the band of v - v_r over all cars after t_s (every plant step);
- ``speed_err_worst_mps``: max |v - v_r| over all cars and the whole run, start-up included;
- ``speed_err_worst_after_mps``: the same after t_s; ``adjacent_dv_max_mps``: max |v_j - v_{j+1}| after t_s;
- ``spacing_min_m`` / ``spacing_max_m``: the band of every car spacing after t_s (the seed's safe range is
  [80.5, 81.5] m); with rest length l these are l + coupler displacement;
- ``effort_mps2``: control effort, the time average of |F|/m over the run after t_s, mean over cars;
- ``peak_force_kn``: max |F| commanded over the whole run;
- ``chattering_kn_per_s``: total variation of the commanded force after t_s, sum |F_k - F_{k-1}| over
  every command the plant received, per second and per car (mean over cars);
- ``tv_total_mn``: the same total variation over the whole run, per car (MN).

The paper columns are seed 001's claims per law (empty for other laws).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from hil.compare.report import Column, MetricFamily, RunData, register_family
from hil.scenario.model import Scenario
from hil.record.metrics import bus_metrics

STARTUP_S = 10.0
WINDOW_S = 60.0
SPACING_TOL_M = 0.01
ERROR_BAND_MPS = 0.01
HOLD_S = 5.0

#: seed 001's claims (CONTROLLERS.md "001"), by law name
PAPER_001: dict[str, dict[str, Any]] = {
    "stsmca": {"paper_spacing_s": "within 4 s", "paper_band": "(-0.8 ... 1.1)e-3 m/s"},
    "smca": {"paper_worst": "0.083 m/s"},
    "pidca": {"paper_worst": "0.2326 m/s"},
    "cca": {"paper_worst": "0.534 m/s"},
}


def _settle_time(t: np.ndarray, inside: np.ndarray, end_s: float) -> float | None:
    """First t from which ``inside`` holds for every sample up to end_s, at least HOLD_S before end_s (else None)."""
    k_end = int(np.searchsorted(t, end_s, side="right"))
    if k_end == 0:
        return None
    ok = inside[:k_end]
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    t_in = float(t[bad[-1] + 1]) if len(bad) else float(t[0])
    return t_in if t_in <= min(end_s, float(t[k_end - 1])) - HOLD_S else None


def startup_window(scenario: Scenario) -> float:
    starts = [d.start_s for d in scenario.plant.disturbances]
    return min([WINDOW_S, scenario.duration_s] + starts)


@register_family
class SingleTrain(MetricFamily):
    name = "single_train"
    description = (f"one train of coupled cars; start-up = first {STARTUP_S:g} s; spacing closed = within "
                   f"{SPACING_TOL_M * 100:g} cm of rest; error band = {ERROR_BAND_MPS:g} m/s")
    columns = [
        Column("spacing_time_s", f"spacing within {SPACING_TOL_M * 100:g} cm after (s)", "{:.2f}"),
        Column("band_entry_s", f"|v - v_r| <= {ERROR_BAND_MPS:g} after (s)", "{:.2f}"),
        Column("speed_err_min_mps", "v - v_r min after start-up (m/s)", "{:.2e}"),
        Column("speed_err_max_mps", "v - v_r max after start-up (m/s)", "{:.2e}"),
        Column("speed_err_worst_mps", "worst |v - v_r| whole run (m/s)", "{:.4g}"),
        Column("adjacent_dv_max_mps", "max |v_j - v_j+1| after start-up (m/s)", "{:.2e}"),
        Column("spacing_min_m", "spacing min after start-up (m)", "{:.4f}"),
        Column("spacing_max_m", "spacing max after start-up (m)", "{:.4f}"),
        Column("effort_mps2", "effort mean |F|/m (m/s^2)", "{:.4f}"),
        Column("peak_force_kn", "peak |F| (kN)", "{:.1f}"),
        Column("chattering_kn_per_s", "chattering TV(F) after start-up (kN/s per car)", "{:.4g}"),
        Column("tv_total_mn", "TV(F) whole run (MN per car)", "{:.4g}"),
    ]
    paper_columns = [
        Column("paper_spacing_s", "paper: spacing", None),
        Column("paper_band", "paper: error band", None),
        Column("paper_worst", "paper: worst error", None),
    ]

    def applies(self, scenario: Scenario) -> bool:
        return scenario.trains.count == 1

    def startup_s(self, scenario: Scenario) -> float:
        return STARTUP_S

    def paper(self, law: str) -> dict[str, Any]:
        return dict(PAPER_001.get(law, {}))

    def compute(self, run: RunData) -> dict[str, Any]:
        log, env, cmd, sc = run.log, run.envelope, run.commands, run.scenario
        layout = log.layout
        t = log.t
        window = startup_window(sc)
        out: dict[str, Any] = {}
        e = log.couplers
        out["spacing_time_s"] = _settle_time(t, np.all(np.abs(e) <= SPACING_TOL_M, axis=1), window) if e.size else None
        out["band_entry_s"] = _settle_time(t, np.all(np.abs(log.speed_error) <= ERROR_BAND_MPS, axis=1), window)
        after = env.steps > 0 and np.all(np.isfinite(env.err_min[1]))
        out["speed_err_min_mps"] = float(env.err_min[1].min()) if after else None
        out["speed_err_max_mps"] = float(env.err_max[1].max()) if after else None
        worst = np.maximum(np.abs(env.err_min), np.abs(env.err_max))
        out["speed_err_worst_mps"] = float(np.max(worst[np.isfinite(worst)])) if np.isfinite(worst).any() else None
        out["speed_err_worst_after_mps"] = float(worst[1].max()) if after else None
        has_pairs = env.adjacent_max.shape[1] > 0
        out["adjacent_dv_max_mps"] = float(env.adjacent_max[1].max()) if after and has_pairs else None
        rest = float(layout.length_m[0])
        out["spacing_min_m"] = rest + float(env.spacing_dev_min[1].min()) if after and has_pairs else None
        out["spacing_max_m"] = rest + float(env.spacing_dev_max[1].max()) if after and has_pairs else None
        t_end = float(log.sim_time_s)
        span = t_end - STARTUP_S
        mass = layout.mass_kg
        out["effort_mps2"] = float(np.mean(cmd.abs_integral[1] / mass) / span) if span > 0 else None
        out["peak_force_kn"] = float(cmd.peak.max()) / 1e3 if cmd.count.sum() else None
        out["chattering_kn_per_s"] = float(np.mean(cmd.tv[1]) / span) / 1e3 if span > 0 else None
        out["tv_total_mn"] = float(np.mean(cmd.tv.sum(axis=0))) / 1e6
        out["coupler_max_abs_m"] = float(np.max(np.abs(e))) if e.size else None
        out["commands"] = int(cmd.count.sum())
        out["sim_time_s"] = t_end
        out["wall_time_s"] = float(log.wall_time_s)
        out["frames_lost"] = int(log.frames_lost)
        bus = bus_metrics(log.buses)
        out.update({key: bus[key] if log.buses else None for key in BUS_KEYS})
        return out


BUS_KEYS = ("bus_load_max", "frames_dropped", "frame_latency_p99_s", "frame_latency_max_s", "latency_to_period_max",
            "deadline_misses")  # the network's side of a run (None in the ideal loop)
