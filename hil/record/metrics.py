"""Summary metrics of one run (settling, spacing, couplers, effort, CAN timing) as a JSON-ready dict.

Everything is computed vectorised from a RunLog. Values that are undefined (no samples, no couplers,
never settled, non-finite) are None, never NaN, so `json.dumps(..., allow_nan=False)` always works.
Durations "spent" in a condition use a zero-order hold: sample k holds until sample k+1.

Safety verdicts (``unsafe``, ``collision``) look at every recorded sample; ``string_stability_ratio`` is the
peak |gap - l_s| of the last train pair over that of the first pair (> 1: spacing errors grow along the chain).
CAN deadlines are implicit (deadline = period): a frame misses its deadline when its latency (enqueue to end of
transmission) exceeds its ID's period, taken as the median interval between the first 65 enqueues of that ID
on that bus (so it follows the scenario's cycle settings; with >= 50 % radio loss the period of forwarded frames is
overestimated). The frame statistics are kept as the frames come (hil/can/frame_stats.py), so a run need not keep
its frames: latency percentiles are exact (rounded to the microsecond past 65,536 distinct latencies). Frames dropped from a full TX queue are not in the latency table: see frames_dropped.

``safety`` is the safety supervisor's report (hil/record/safety.py): per verdict (gap below l_e, collision, coupler
out of band, overspeed) whether it happened, and each violation with its time, place, worst value and cause.
``faults`` (only when the scenario schedules faults) is hil/faults' injected-vs-detected report.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.can.frame_stats import LatencyCounts
from hil.record.runlog import BusLog, RunLog
from hil.record.safety import safety_report

KMH = 1.0 / 3.6
LEVELS = ("INFO", "WARN", "ERROR")


def compute_metrics(log: RunLog, coupler_band: tuple[float, float], settle_band_mps: float = 0.5 * KMH) -> dict[str, Any]:
    """All summary metrics of a run; `coupler_band` is (max compression < 0, max stretch > 0) in m."""
    lo, hi = _check_band(coupler_band)
    if not settle_band_mps > 0:
        raise ValueError(f"settle_band_mps must be > 0, got {settle_band_mps!r}")
    out: dict[str, Any] = {}
    out.update(_settling_metrics(log, settle_band_mps))
    out.update(_coupler_metrics(log, lo, hi))
    out.update(_gap_metrics(log))
    out.update(_safety_metrics(log, lo, hi))
    out.update(_effort_metrics(log))
    out.update(bus_metrics(log.buses))
    out["frames_lost"] = int(log.frames_lost)
    out["events_by_level"] = _events_by_level(log)
    out["codec_saturations"] = {str(k): int(v) for k, v in log.codec_saturations.items()}
    out["radio"] = _counters(log.radio_stats)
    out["e2e"] = _counters(log.e2e)
    out.update(_reader_samples(log.e2e))
    out["interrupted"] = bool(log.interrupted)
    out["safety"] = safety_report(log, (lo, hi))  # each violation with its time and cause (hil/record/safety.py)
    if log.fault_report is not None:  # set by hil.faults when the scenario schedules faults
        out["faults"] = log.fault_report
    out["sim_time_s"] = _f(log.sim_time_s)
    out["wall_time_s"] = _f(log.wall_time_s)
    out["realtime_factor"] = _f(log.sim_time_s / log.wall_time_s) if log.wall_time_s > 0 else None
    return out


# --------------------------------------------------------------------------- helpers


def _f(x: float | np.floating | None) -> float | None:
    """A plain float, or None if undefined or non-finite."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _fl(a: np.ndarray) -> list[float | None]:
    return [_f(v) for v in np.asarray(a, dtype=float).ravel()]


def _max(a: np.ndarray) -> float | None:
    return _f(np.max(a)) if a.size else None


def _min(a: np.ndarray) -> float | None:
    return _f(np.min(a)) if a.size else None


def _reader_samples(e2e: dict[str, dict[str, int]]) -> dict[str, int]:
    """Samples the ECUs' mailboxes skipped or read twice, summed over the ECUs: not frames lost on the bus.

    A mailbox keeps the latest frame of a stream and the firmware reads it once per cycle. When cycles and
    arrivals jitter (real time), a cycle may find two new samples, one of which it never saw (E2E ``LOST``, with
    ``frames_lost`` still 0), or a sender may send the same sample twice (``REPEATED``)."""
    return {"reader_samples_skipped": sum(int(c.get("LOST", 0)) for c in e2e.values()),
            "reader_samples_repeated": sum(int(c.get("REPEATED", 0)) for c in e2e.values())}


def _counters(nested: dict[str, dict[str, int]]) -> dict[str, dict[str, int]]:
    """A plain-int copy of name -> counter -> count."""
    return {str(name): {str(k): int(v) for k, v in c.items()} for name, c in nested.items()}


def _check_band(band: tuple[float, float]) -> tuple[float, float]:
    try:
        lo, hi = (float(b) for b in band)
    except (TypeError, ValueError):
        raise ValueError(f"coupler_band must be (min, max) in m, got {band!r}") from None
    if not lo < hi:
        raise ValueError(f"coupler_band must have min < max, got {band!r}")
    return lo, hi


def _hold_durations(t: np.ndarray) -> np.ndarray:
    """How long each sample holds (zero-order hold); the last sample holds 0 s."""
    if len(t) == 0:
        return np.zeros(0)
    return np.append(np.maximum(np.diff(t), 0.0), 0.0)


def _time_where(t: np.ndarray, flag: np.ndarray) -> float:
    return float(np.sum(_hold_durations(t)[flag]))


def _segments(log: RunLog) -> list[tuple[float, int, int]]:
    """(start time, first row, end row) of every reference segment; changes at t <= 0 are the initial reference."""
    t = log.t
    changes = sorted({float(c) for c in log.reference_change_times if c > 0})
    starts = [0.0] + changes
    rows = np.searchsorted(t, starts, side="left").tolist() + [len(t)]
    return [(s, rows[k], rows[k + 1]) for k, s in enumerate(starts)]


# --------------------------------------------------------------------------- settling / tracking


def _settle_row(within: np.ndarray) -> int | None:
    """First row r such that within[r:] is all True (and non-empty), else None."""
    bad = np.flatnonzero(~within)
    r = int(bad[-1]) + 1 if len(bad) else 0
    return r if r < len(within) else None


def _settling_metrics(log: RunLog, band: float) -> dict[str, Any]:
    t, err = log.t, log.speed_error
    within = np.all(np.abs(err) <= band, axis=1)
    segments = _segments(log)
    rows = [_settle_row(within[r0:r1]) for _, r0, r1 in segments]
    per_segment = [None if r is None else _f(t[r0 + r] - start) for r, (start, r0, _) in zip(rows, segments)]
    _, r0, r1 = segments[0]
    seg0 = err[r0:r1]
    overshoot = _max(seg0)
    return {
        "settling_time_s": per_segment[0],
        "settled": per_segment[0] is not None,
        "settling_time_per_segment_s": per_segment,
        "settle_band_mps": float(band),
        "speed_overshoot_max_mps": None if overshoot is None else max(0.0, overshoot),
        "speed_error_max_after_settling_mps": None if rows[0] is None else _max(np.abs(seg0[rows[0]:])),
        "speed_error_max_abs_mps": _max(np.abs(err)),
    }


# --------------------------------------------------------------------------- couplers and gaps


def _coupler_metrics(log: RunLog, lo: float, hi: float) -> dict[str, Any]:
    e = log.couplers
    out_of_band = np.any((e < lo) | (e > hi), axis=1) if e.size else np.zeros(len(e), dtype=bool)
    return {
        "coupler_band_m": [lo, hi],
        "coupler_max_abs_m": _max(np.abs(e)),
        "coupler_min_m": _min(e),
        "coupler_max_m": _max(e),
        "coupler_out_of_band_s": _time_where(log.t, out_of_band),
    }


def _gap_metrics(log: RunLog) -> dict[str, Any]:
    g, le = log.gaps, log.layout.emergency_gap_m
    k = len(g)
    below = np.any(g < le, axis=1) if g.size else np.zeros(k, dtype=bool)
    overall = _min(g)
    return {
        "gap_min_m": _fl(np.min(g, axis=0)) if k else [None] * g.shape[1],
        "gap_final_m": _fl(g[-1]) if k else [None] * g.shape[1],
        "gap_min_overall_m": overall,
        "gap_margin_to_emergency_m": None if overall is None else overall - le,
        "gap_below_emergency_s": _time_where(log.t, below),
        "position_error_final_m": _fl(log.position_error[-1]) if k else [None] * log.layout.n_units,
    }


def _safety_metrics(log: RunLog, lo: float, hi: float) -> dict[str, Any]:
    """Safety verdict over all samples, and the string-stability ratio of the spacing errors (None if undefined)."""
    g, e, L = log.gaps, log.couplers, log.layout
    if len(g) == 0:
        return {"unsafe": None, "collision": None, "string_stability_ratio": None}
    collision = bool(np.any(g < 0.0))
    unsafe = collision or bool(np.any(g < L.emergency_gap_m)) or bool(np.any((e < lo) | (e > hi)))
    ratio = None
    if g.shape[1] >= 2:
        peak = np.max(np.abs(g - L.spacing_m), axis=0)
        ratio = _f(peak[-1] / peak[0]) if peak[0] > 0 else None
    return {"unsafe": unsafe, "collision": collision, "string_stability_ratio": ratio}


# --------------------------------------------------------------------------- effort and jerk


def _effort_metrics(log: RunLog) -> dict[str, Any]:
    t = log.t
    if len(t) < 2:
        return {"control_effort": None, "jerk_rms_mps3": None}
    per_unit = np.trapezoid(np.abs(log.force_applied) / log.layout.mass_kg[None, :], t, axis=0)
    dt = np.diff(t)
    ok = dt > 0
    jerk = np.diff(log.a, axis=0)[ok] / dt[ok, None]
    return {
        "control_effort": _f(np.mean(per_unit)),
        "jerk_rms_mps3": _f(np.sqrt(np.mean(jerk**2))) if jerk.size else None,
    }


# --------------------------------------------------------------------------- CAN buses


def _id_name(frame_id: int) -> str:
    return f"0x{frame_id:03X}" if frame_id <= 0x7FF else f"0x{frame_id:08X}"


def _one_bus(bus: BusLog) -> dict[str, Any]:
    load = bus.load.array[:, 1]
    latency, deadlines = bus.frames.summary()
    misses, ratio_max = deadlines.totals()
    return {
        "frames_sent": int(bus.frames_sent),
        "frames_dropped": int(bus.frames_dropped),
        "load_max": _max(load),
        "load_mean": _f(np.mean(load)) if load.size else None,
        "latency_p50_s": _f(latency.percentile(50)),
        "latency_p99_s": _f(latency.percentile(99)),
        "latency_max_s": _f(latency.max()),
        "latency_max_by_id": {_id_name(i): float(m) for i, m in sorted(deadlines.max_by_id.items())},
        "deadline_misses": misses,
        "latency_to_period_max": _f(ratio_max),
    }


def bus_metrics(buses: list[BusLog]) -> dict[str, Any]:
    """Frames, drops, load, latency and deadline figures of the buses, together and per bus."""
    loads = np.concatenate([b.load.array[:, 1] for b in buses]) if buses else np.zeros(0)
    per_bus = {b.name: _one_bus(b) for b in buses}
    latency = LatencyCounts.merged(b.frames.summary()[0] for b in buses)
    ratios = [p["latency_to_period_max"] for p in per_bus.values() if p["latency_to_period_max"] is not None]
    return {
        "frames_sent": int(sum(b.frames_sent for b in buses)),
        "frames_dropped": int(sum(b.frames_dropped for b in buses)),
        "bus_load_max": _max(loads),
        "bus_load_mean": _f(np.mean(loads)) if loads.size else None,
        "frame_latency_p50_s": _f(latency.percentile(50)),
        "frame_latency_p99_s": _f(latency.percentile(99)),
        "frame_latency_max_s": _f(latency.max()),
        "deadline_misses": sum(p["deadline_misses"] for p in per_bus.values()),
        "latency_to_period_max": max(ratios) if ratios else None,
        "per_bus": per_bus,
    }


def _events_by_level(log: RunLog) -> dict[str, int]:
    counts = dict.fromkeys(LEVELS, 0)
    for ev in log.events:
        counts[ev.level] = counts.get(ev.level, 0) + 1
    return counts


def run_metrics(log: RunLog, scenario, runtime: str, seed: int, *, pace: float | None = None,
                overrides: dict | None = None, source: str | None = None) -> dict[str, Any]:
    """The metrics.json document of a run in either runtime: the metrics, what ran (scenario, runtime, pace) and
    its provenance, and whether it was interrupted."""
    from hil.record.provenance import provenance

    metrics = compute_metrics(log, scenario.plant.coupler_band_m)
    metrics["scenario"] = scenario.name
    metrics["runtime"] = runtime
    if pace is not None:
        metrics["pace"] = float(pace)
    metrics["provenance"] = provenance(scenario, runtime, seed, pace=pace, overrides=overrides, source=source)
    metrics["interrupted"] = log.interrupted
    return metrics
