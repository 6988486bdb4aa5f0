"""Summary metrics of one run (settling, spacing, couplers, effort, CAN timing) as a JSON-ready dict.

The sampled signals' figures come from the log's signal summary (hil/record/signal_summary.py), kept as the
samples come, so they need not be held to the end of a run. Values that are undefined (no samples, no couplers,
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
``plant_command_rejects``: per unit, the TractionCmd frames the plant refused because their alive counter did not
continue the unit's stream (REPEATED, WRONG_SEQUENCE: a second sender; hil/plant/command_streams.py).
``faults`` (only when the scenario schedules faults) is hil/faults' injected-vs-detected report.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.can.frame_stats import LatencyCounts
from hil.record.runlog import BusLog, RunLog
from hil.record.safety import safety_report
from hil.record.signal_summary import SignalSummary

KMH = 1.0 / 3.6
LEVELS = ("INFO", "WARN", "ERROR")


def compute_metrics(log: RunLog, coupler_band: tuple[float, float], settle_band_mps: float = 0.5 * KMH) -> dict[str, Any]:
    """All summary metrics of a run; `coupler_band` is (max compression < 0, max stretch > 0) in m."""
    lo, hi = _check_band(coupler_band)
    if not settle_band_mps > 0:
        raise ValueError(f"settle_band_mps must be > 0, got {settle_band_mps!r}")
    summary = log.summary((lo, hi), settle_band_mps)
    out: dict[str, Any] = {}
    out.update(_settling_metrics(summary, settle_band_mps))
    out.update(_coupler_metrics(summary, lo, hi))
    out.update(_gap_metrics(summary))
    out.update(_safety_metrics(summary))
    out.update(_effort_metrics(summary))
    out.update(bus_metrics(log.buses))
    out["frames_lost"] = int(log.frames_lost)
    out["events_by_level"] = _events_by_level(log)
    out["codec_saturations"] = {str(k): int(v) for k, v in log.codec_saturations.items()}
    out["radio"] = _counters(log.radio_stats)
    out["e2e"] = _counters(log.e2e)
    out.update(_reader_samples(log.e2e))
    out["plant_command_rejects"] = {k: dict(v) for k, v in log.plant_command_rejects.items()}
    out["interrupted"] = bool(log.interrupted)
    out["safety"] = safety_report(log, (lo, hi))  # each violation with its time and cause (hil/record/safety.py)
    if log.fault_report is not None:  # set by hil.faults when the scenario schedules faults
        out["faults"] = log.fault_report
    if log.silkit_report is not None:  # set by the rig under SIL Kit (hil/runtime/silkit_rig.py)
        out["silkit"] = log.silkit_report
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


def _fl(a: np.ndarray | None, n: int) -> list[float | None]:
    """Each value as ``_f``; ``n`` Nones if there is no array."""
    return [None] * n if a is None else [_f(v) for v in np.asarray(a, dtype=float).ravel()]


def _max(a: np.ndarray) -> float | None:
    return _f(np.max(a)) if a.size else None


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


# --------------------------------------------------------------------------- the sampled signals


def _settling_metrics(s: SignalSummary, band: float) -> dict[str, Any]:
    per_segment = [_f(v) for v in s.settling.settling_times()]
    overshoot = _f(s.settling.overshoot.max)
    return {
        "settling_time_s": per_segment[0],
        "settled": per_segment[0] is not None,
        "settling_time_per_segment_s": per_segment,
        "settle_band_mps": float(band),
        "speed_overshoot_max_mps": None if overshoot is None else max(0.0, overshoot),
        "speed_error_max_after_settling_mps": None if per_segment[0] is None else _f(s.settling.tail_max_abs),
        "speed_error_max_abs_mps": _f(s.speed_error.max),
    }


def _coupler_metrics(s: SignalSummary, lo: float, hi: float) -> dict[str, Any]:
    return {
        "coupler_band_m": [lo, hi],
        "coupler_max_abs_m": _f(s.coupler_abs.max),
        "coupler_min_m": _f(s.coupler.min),
        "coupler_max_m": _f(s.coupler.max),
        "coupler_out_of_band_s": s.coupler_out.total,
    }


def _gap_metrics(s: SignalSummary) -> dict[str, Any]:
    le, n_pairs = s.layout.emergency_gap_m, s.layout.n_trains - 1
    overall = _f(np.min(s.gap.min)) if s.gap.min is not None and np.size(s.gap.min) else None
    return {
        "gap_min_m": _fl(s.gap.min, n_pairs),
        "gap_final_m": _fl(s.final_gaps(), n_pairs),
        "gap_min_overall_m": overall,
        "gap_margin_to_emergency_m": None if overall is None else overall - le,
        "gap_below_emergency_s": s.gap_below.total,
        "position_error_final_m": _fl(s.final_position_error(), s.layout.n_units),
    }


def _safety_metrics(s: SignalSummary) -> dict[str, Any]:
    """Safety verdict over all samples, and the string-stability ratio of the spacing errors (None if undefined)."""
    if not s.rows:
        return {"unsafe": None, "collision": None, "string_stability_ratio": None}
    ratio = None
    peak = s.gap_spacing_error.max
    if peak is not None and np.size(peak) >= 2:
        ratio = _f(peak[-1] / peak[0]) if peak[0] > 0 else None
    return {"unsafe": s.unsafe, "collision": s.collision, "string_stability_ratio": ratio}


def _effort_metrics(s: SignalSummary) -> dict[str, Any]:
    if s.rows < 2:
        return {"control_effort": None, "jerk_rms_mps3": None}
    return {
        "control_effort": _f(np.mean(s.effort)),
        "jerk_rms_mps3": _f(math.sqrt(s.jerk_sq / s.jerk_n)) if s.jerk_n else None,
    }


# --------------------------------------------------------------------------- CAN buses


def _id_name(frame_id: int) -> str:
    return f"0x{frame_id:03X}" if frame_id <= 0x7FF else f"0x{frame_id:08X}"


def _one_bus(bus: BusLog) -> dict[str, Any]:
    load = bus.load
    latency, deadlines = bus.frames.summary()
    misses, ratio_max = deadlines.totals()
    return {
        "frames_sent": int(bus.frames_sent),
        "frames_dropped": int(bus.frames_dropped),
        "frames_dropped_by_node": {name: int(n) for name, n in sorted(bus.dropped_by_node.items())},
        "load_max": _f(load.max) if load.count else None,
        "load_mean": _f(load.sum / load.count) if load.count else None,
        "latency_p50_s": _f(latency.percentile(50)),
        "latency_p99_s": _f(latency.percentile(99)),
        "latency_max_s": _f(latency.max()),
        "latency_max_by_id": {_id_name(i): float(m) for i, m in sorted(deadlines.max_by_id.items())},
        "deadline_misses": misses,
        "latency_to_period_max": _f(ratio_max),
    }


def dropped_by_node(per_bus: dict[str, dict] | None) -> dict[str, int]:
    """The frames each node dropped, over every bus of a run's ``per_bus`` metrics, keyed "<bus>/<node>"."""
    return {f"{bus}/{node}": n for bus, b in (per_bus or {}).items()
            for node, n in (b.get("frames_dropped_by_node") or {}).items()}


def bus_metrics(buses: list[BusLog]) -> dict[str, Any]:
    """Frames, drops, load, latency and deadline figures of the buses, together and per bus."""
    windows = sum(b.load.count for b in buses)
    per_bus = {b.name: _one_bus(b) for b in buses}
    latency = LatencyCounts.merged(b.frames.summary()[0] for b in buses)
    ratios = [p["latency_to_period_max"] for p in per_bus.values() if p["latency_to_period_max"] is not None]
    return {
        "frames_sent": int(sum(b.frames_sent for b in buses)),
        "frames_dropped": int(sum(b.frames_dropped for b in buses)),
        "bus_load_max": _f(max(b.load.max for b in buses)) if windows else None,
        "bus_load_mean": _f(sum(b.load.sum for b in buses) / windows) if windows else None,
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
