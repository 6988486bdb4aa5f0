"""The safety supervisor: every run's safety verdicts, each violation with its time, place, worst value and cause.

Verdicts, judged on every recorded sample (a sample holds until the next, as in ``metrics``):

* ``gap_below_le``: the gap of a train pair below l_e (the emergency-braking gap);
* ``collision``: a gap below zero;
* ``coupler_out_of_band``: a coupler's displacement outside the band (max compression, max stretch);
* ``ecu_failure``: an ECU whose law or program raised, returned no command or a non-finite force, or called
  sys.exit (the ECU stops), whose process died, or that was restarted: firmware that fails must fail CI too;
* ``overspeed``: a unit faster than the reference speed v_r plus the ETCS emergency-brake intervention margin
  of ceiling speed monitoring (SUBSET-026 3.13.9.2.3, default values: 7.5 km/h up to 110 km/h, 15 km/h from
  210 km/h, linear in between), or than ``line_limit_mps`` if one is given. v_r is our stand-in for the line's
  permitted speed: the papers' trains follow a reference profile, not signalled limits.

A violation is one interval of one pair, coupler or unit: start, end (the first sample back within the limit,
or the last sample), duration, the worst value and when. Its cause is what the run's events say happened on
that train (or pair) shortly before: injected faults active then or ended up to ``CAUSE_WINDOW_S`` earlier
(from the ``faults`` events, hil/faults), else the last ERROR event or rig warning (an external unit gone
missing) there, else "none seen".
"""
from __future__ import annotations

import re
from dataclasses import asdict

from ecu_sim.runtime import ECU_STOPPED, RESTARTED
from hil.record.runlog import Event, RunLog
from hil.record.signal_summary import KMH, MAX_LISTED, Violation, ebi_margin

__all__ = ["KMH", "MAX_LISTED", "VERDICTS", "Violation", "check_safety", "ebi_margin", "explain", "safety_report"]

CAUSE_WINDOW_S = 60.0
VERDICTS = ("gap_below_le", "collision", "coupler_out_of_band", "overspeed")  # judged on the sampled signals
ECU_FAILURE = "ecu_failure"  # judged on the events: an ECU stopped, died or was restarted
_ECU_EXIT = re.compile(r"^ECU process \S+ exited with code")
_ECU_RESPAWN = re.compile(rf"^ECU process \S+ {RESTARTED}")  # real time: a new process for a unit (its restart)
_FAULT_EVENT = re.compile(r"^#(\d+) (\S+) on (.+?): (injected|over)")


def tally(log: RunLog, band: tuple[float, float], line_limit_mps: float | None = None) -> dict[str, tuple]:
    """Per verdict: (count, total seconds, first start, the MAX_LISTED earliest violations), from the log's
    signal summary (hil/record/signal_summary.py)."""
    summary = log.summary(band, line_limit_mps=line_limit_mps)
    t_last = summary.t_last if summary.t_last is not None else 0.0
    return {verdict: summary.violations[verdict].result(t_last) for verdict in VERDICTS}


def check_safety(log: RunLog, band: tuple[float, float], line_limit_mps: float | None = None) -> list[Violation]:
    """The violations of the run (the MAX_LISTED earliest of each verdict; all are counted in ``safety_report``),
    in time order, without causes (``explain`` adds them)."""
    out = [v for _, _, _, listed in tally(log, band, line_limit_mps).values() for v in listed]
    out.sort(key=lambda v: (v.start_s, v.verdict, v.where))
    return out


# --------------------------------------------------------------------------- causes


def _fault_windows(events: list[Event]) -> list[tuple[str, float, float | None]]:
    """(label "#k kind on target", start, end) of every injected fault, from the ``faults`` events."""
    starts: dict[str, float] = {}
    ends: dict[str, float] = {}
    for ev in events:
        if ev.source != "faults":
            continue
        m = _FAULT_EVENT.match(ev.text)
        if m:
            key = f"#{m.group(1)} {m.group(2)} on {m.group(3)}"
            (starts if m.group(4) == "injected" else ends)[key] = ev.t
    return [(k, s, ends.get(k)) for k, s in starts.items()]


def _fault_trains(label: str, n_trains: int) -> set[int]:
    m = re.search(r"on (?:train|bus)(\d+)", label)
    if m:
        return {int(m.group(1))}
    m = re.search(r"on radio (\d+)-(\d+)", label)
    if m:
        return {int(m.group(1)), int(m.group(2))}
    return set(range(1, n_trains + 1))  # all radio pairs


def _event_trains(ev: Event) -> set[int]:
    found = {int(x) for x in re.findall(r"train ?(\d+)", f"{ev.source} {ev.text}")}
    m = re.match(r"bus(\d+)", ev.source)
    if m:
        found.add(int(m.group(1)))
    return found


def explain(violations: list[Violation], events: list[Event], n_trains: int) -> list[Violation]:
    """Fill in each violation's cause from the run's events (see the module docstring)."""
    faults = _fault_windows(events)
    notable = [ev for ev in events if (ev.level == "ERROR" and ev.source not in ("faults", "safety"))
               or (ev.level == "WARN" and ev.source == "rig")]  # the rig's own warnings: a device gone missing
    for v in violations:
        trains = v.trains
        near = [f"{label} ({'active' if end is None or end >= v.start_s else f'ended at t = {end:.2f} s'})"
                for label, start, end in faults
                if start <= v.start_s and (end is None or end >= v.start_s - CAUSE_WINDOW_S)
                and _fault_trains(label, n_trains) & trains]
        if near:
            v.cause = "injected " + "; ".join(near)
            continue
        before = [ev for ev in notable if v.start_s - CAUSE_WINDOW_S <= ev.t <= v.start_s and _event_trains(ev) & trains]
        if before:
            ev = before[-1]
            v.cause = f"after {ev.source} at t = {ev.t:.2f} s: {ev.text}"
        else:
            v.cause = (f"no injected fault, ERROR event or rig warning on this train in the {CAUSE_WINDOW_S:g} s "
                       "before it")
    return violations


def safety_report(log: RunLog, band: tuple[float, float], line_limit_mps: float | None = None) -> dict:
    """The verdicts for metrics.json: per verdict whether it happened, how many intervals, how long in total,
    and the violations themselves (at most MAX_LISTED per verdict) with their causes."""
    counts = tally(log, band, line_limit_mps)
    listed = explain(check_safety(log, band, line_limit_mps), log.events, log.layout.n_trains)
    out: dict = {"safe": not any(c[0] for c in counts.values()),
                 "overspeed_margin": "ETCS EBI: 7.5 km/h to 110 km/h, 15 km/h from 210 km/h"}
    for verdict in VERDICTS:
        count, total, first, _ = counts[verdict]
        mine = [v for v in listed if v.verdict == verdict]
        out[verdict] = {"violated": bool(count), "count": count, "total_s": float(total), "first_s": first,
                        "violations": [asdict(v) for v in mine]}
    out[ECU_FAILURE] = ecu_failure_verdict(log.events)
    out["safe"] = out["safe"] and not out[ECU_FAILURE]["violated"]
    return out


def violated(safety: dict | None) -> dict[str, dict]:
    """The verdicts of a ``safety_report`` (metrics.json's ``safety``) that were violated, by name."""
    return {k: v for k, v in (safety or {}).items() if isinstance(v, dict) and v.get("violated")}


def ecu_failures(events: list[Event]) -> list[Event]:
    """The events that say an ECU stopped (its law or program raised, returned no command or a non-finite one,
    called sys.exit), its process died, or it was restarted: the ``ecu_failure`` verdict, in time order."""
    return sorted((ev for ev in events if _is_ecu_failure(ev)), key=lambda ev: ev.t)


def _is_ecu_failure(ev: Event) -> bool:
    if ev.level == "ERROR" and (ev.text.endswith(ECU_STOPPED) or ECU_STOPPED in ev.text.split(": ")[0]):
        return True
    if ev.level == "ERROR" and ev.source == "rig" and _ECU_EXIT.match(ev.text):
        return True
    return ev.text.startswith(RESTARTED) or (ev.source == "rig" and bool(_ECU_RESPAWN.match(ev.text)))


def ecu_failure_verdict(events: list[Event]) -> dict:
    """``ecu_failure`` for metrics.json: violated when any ECU stopped, died or restarted (``--check`` fails on
    it), with the first MAX_LISTED of them (time, ECU, what its event said)."""
    failures = ecu_failures(events)
    return {"violated": bool(failures), "count": len(failures), "total_s": 0.0,
            "first_s": failures[0].t if failures else None,
            "violations": [{"t_s": ev.t, "where": ev.source, "text": ev.text} for ev in failures[:MAX_LISTED]]}


def violation_events(log: RunLog, band: tuple[float, float]) -> list[Event]:
    """The violations as timeline events (source ``safety``, ERROR), at most MAX_LISTED per verdict."""
    violations = explain(check_safety(log, band), log.events, log.layout.n_trains)
    return [Event(v.start_s, "ERROR", "safety", v.text()) for v in violations]


def record_violations(log: RunLog, band: tuple[float, float]) -> None:
    """Put the run's violations on its timeline (every runtime calls this once, at the end of the run). Appended,
    not sorted in: the recorder writes the events incrementally by position (the viewer orders them by time)."""
    log.events.extend(violation_events(log, band))
