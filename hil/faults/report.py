"""Injected vs detected: which monitor noticed each fault, when, and the counts for metrics.json.

A fault counts as detected when one of the monitors that can see it logged an event about its target between
its start and ``GRACE_S`` after its end (its whole run if it never ends). The monitors, by what they watch:

=====================  ====================================================================================
fault                  detected by (event source: text)
=====================  ====================================================================================
ecu_crash, ecu_hang    ``plant``: "train T unit U ...: no command ..., fail-safe" (the actuator's watchdog);
                       a neighbour ECU: "neighbour trainT/unitU stale"
sensor_stuck/_noise    the unit's own ECU: "own sensor implausible" (ecu_sim.diagnostics)
babbling_node          ``busT/guardian``: "babbling node"; the bus's ECUs: stale sensor/neighbour/reference;
                       ``plant``: fail-safe of a unit of that train
bus_corruption,        ``busT/can``: "error frame" or a bus-off (the receivers' CAN checks, engine/src/errors.rs);
bus_error_frames       an ECU of that train: "E2E ...: CRC errors" (a corruption CAN did not catch)
frame_drop             an ECU of that train: "E2E ...: lost frames / wrong sequences", or a stale input;
                       ``plant``: fail-safe of a unit of that train
radio_*                the head ECU behind the pair: "lost contact with the train ahead", a stale radio
                       neighbour, or "E2E Radio...: lost frames"; the tail ECU ahead of it: the same
actuator_degradation,  the unit's own ECU: "traction implausible" (ecu_sim.diagnostics, the force balance)
traction_loss
=====================  ====================================================================================

Fault windows come from the ``faults`` events (``#k kind on target: injected`` / ``: over``), so the same code
serves both runtimes. Each detection is added to the log as a ``faults`` event: ``#k ...: detected after X s
by SOURCE: TEXT``.
"""
from __future__ import annotations

import re
from typing import Any

from hil.scenario.layout import TrainLayout
from hil.record.runlog import Event, RunLog
from hil.faults.schedule import BUS_KINDS, SOURCE, label

GRACE_S = 3.0  # after a fault's end (radio contact is judged lost after 2 s)
_ECU = r"^train\d+/unit\d+/ecu$"


def detectors(spec, layout: TrainLayout) -> list[tuple[str, str]]:
    """(source regex, text regex) of the events that show fault ``spec`` was noticed."""
    kind, n = spec.kind, layout.units_per_train
    if kind in ("ecu_crash", "ecu_hang"):
        T, U = spec.train, spec.unit
        return [("^plant$", rf"^train {T} unit {U} \(#\d+\): no command"), (_ECU, rf"^neighbour train{T}/unit{U} stale")]
    if kind in ("sensor_stuck", "sensor_noise"):
        return [(rf"^train{spec.train}/unit{spec.unit}/ecu$", r"^own sensor implausible")]
    if kind in ("actuator_degradation", "traction_loss"):
        return [(rf"^train{spec.train}/unit{spec.unit}/ecu$", r"^traction implausible")]
    if kind in BUS_KINDS:
        T = spec.train
        ecus = rf"^train{T}/unit\d+/ecu$"
        failsafe = ("^plant$", rf"^train {T} unit \d+ \(#\d+\): no command")
        stale = (ecus, r"^(own sensor data stale|reference stale|neighbour .* stale)")
        if kind == "babbling_node":
            return [(rf"^bus{T}/guardian$", r"^babbling node"), stale, failsafe]
        if kind == "frame_drop":
            return [(ecus, r"^E2E .*(lost frames|wrong sequences)"), stale, failsafe]
        return [(rf"^bus{T}/can$", r"^(error frame|.*bus-off)"), (ecus, r"^E2E .*CRC errors")]
    pairs = range(1, layout.n_trains) if spec.pair is None else [spec.pair]
    out = []
    for p in pairs:
        out.append((rf"^train{p + 1}/unit1/ecu$", rf"^(lost contact with the train ahead|neighbour train{p}/unit{n} stale"
                                                  r"|E2E Radio\w+: .*lost frames)"))
        out.append((rf"^train{p}/unit{n}/ecu$", rf"^(neighbour train{p + 1}/unit1 stale|E2E Radio\w+: .*lost frames)"))
    return out


def _windows(events: list[Event]) -> dict[int, tuple[float, float | None]]:
    """Fault index -> (start, end or None) from the ``faults`` events."""
    out: dict[int, list] = {}
    for ev in events:
        if ev.source == SOURCE:
            m = re.match(r"^#(\d+) \S+ on .+?: (injected|over)", ev.text)
            if m:
                w = out.setdefault(int(m.group(1)), [None, None])
                w[0 if m.group(2) == "injected" else 1] = ev.t
    return {k: (w[0], w[1]) for k, w in out.items() if w[0] is not None}


def fault_report(faults: list, layout: TrainLayout, log: RunLog, can: dict[str, dict] | None = None,
                 extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Match detections to the faults of ``faults`` (the scenario's list), add a ``detected`` event per detected
    fault to the end of ``log.events``, and return the ``faults`` block of metrics.json."""
    events = sorted(log.events, key=lambda e: e.t)  # (the log's own order is kept: recorders track its length)
    windows = _windows(events)
    run_end = log.sim_time_s
    rows, added = [], []
    for k, spec in enumerate(faults):
        name = label(k, spec)
        row: dict[str, Any] = {"index": k, "kind": spec.kind, "target": name.split(" on ", 1)[1], "injected": k in windows,
                               "start_s": None, "end_s": None, "detected": False, "detected_s": None,
                               "detection_latency_s": None, "detected_by": None, "detection": None,
                               "detectors": {}}
        if k not in windows:
            row["not_injected_because"] = never_triggered(spec, run_end)
        if k in windows:
            start, end = windows[k]
            row["start_s"], row["end_s"] = start, end
            until = (end if end is not None else run_end) + GRACE_S
            hits = [h for rule in detectors(spec, layout) if (h := _first_detection([rule], events, start, until))]
            hits.sort(key=lambda e: e.t)
            if hits:
                hit = hits[0]
                row.update(detected=True, detected_s=hit.t, detection_latency_s=hit.t - start, detected_by=hit.source,
                           detection=hit.text,
                           detectors={h.source: round(h.t - start, 6) for h in reversed(hits)})
                added.append(Event(hit.t, "WARN", SOURCE, f"{name}: detected after {hit.t - start:.3f} s by "
                                                          f"{hit.source}: {hit.text}"))
        rows.append(row)
    log.events.extend(added)  # appended: events already recorded keep their place
    by_kind: dict[str, dict[str, int]] = {}
    for r in rows:
        c = by_kind.setdefault(r["kind"], {"injected": 0, "detected": 0})
        c["injected"] += r["injected"]
        c["detected"] += r["detected"]
    out: dict[str, Any] = {"injected": sum(r["injected"] for r in rows), "detected": sum(r["detected"] for r in rows),
                           "scheduled": len(rows), "by_kind": by_kind, "faults": rows}
    if can:
        tot = {k: sum(b.get(k, 0) for b in can.values()) for k in
               ("corrupted", "rejected", "undetected", "undetected_caught_by_e2e", "undetected_unknown_id",
                "undetected_accepted", "error_frames")}
        out["can_errors"] = {**tot, "buses": can}
    if extra:
        out.update(extra)
    return out


def _first_detection(rules: list[tuple[str, str]], events: list[Event], start: float, until: float) -> Event | None:
    compiled = [(re.compile(s), re.compile(t)) for s, t in rules]
    for ev in events:
        if ev.t < start - 1e-9 or ev.source in (SOURCE, "safety"):
            continue
        if ev.t > until:
            break
        if any(s.search(ev.source) and t.search(ev.text) for s, t in compiled):
            return ev
    return None


def never_triggered(spec, run_end_s: float) -> str:
    """Why a scheduled fault was not injected: its time lies beyond the run, or its position was never reached."""
    at = getattr(spec, "at_s", None)
    if at is not None:
        return f"scheduled at t = {at:g} s, after the end of the run (t = {run_end_s:g} s)"
    return "its position trigger was not reached during the run"
