"""The safety supervisor: every run's safety verdicts, each violation with its time, place, worst value and cause.

Verdicts, judged on every recorded sample (a sample holds until the next, as in ``metrics``):

* ``gap_below_le``: the gap of a train pair below l_e (the emergency-braking gap);
* ``collision``: a gap below zero;
* ``coupler_out_of_band``: a coupler's displacement outside the band (max compression, max stretch);
* ``overspeed``: a unit faster than the reference speed v_r plus the ETCS emergency-brake intervention margin
  of ceiling speed monitoring (SUBSET-026 3.13.9.2.3, default values: 7.5 km/h up to 110 km/h, 15 km/h from
  210 km/h, linear in between), or than ``line_limit_mps`` if one is given. v_r is our stand-in for the line's
  permitted speed: the papers' trains follow a reference profile, not signalled limits.

A violation is one interval of one pair, coupler or unit: start, end (the first sample back within the limit,
or the last sample), duration, the worst value and when. Its cause is what the run's events say happened on
that train (or pair) shortly before: injected faults active then or ended up to ``CAUSE_WINDOW_S`` earlier
(from the ``faults`` events, hil/faults), else the last degraded-mode or ERROR event there, else "none seen".
"""
from __future__ import annotations

import re
from dataclasses import asdict, dataclass

import numpy as np

from hil.record.runlog import Event, RunLog

KMH = 1.0 / 3.6
EBI_MIN_MARGIN, EBI_MAX_MARGIN = 7.5 * KMH, 15.0 * KMH  # dV_ebi_min / dV_ebi_max
EBI_MIN_SPEED, EBI_MAX_SPEED = 110.0 * KMH, 210.0 * KMH  # V_ebi_min / V_ebi_max
CAUSE_WINDOW_S = 60.0
MAX_LISTED = 50  # violations listed per verdict (all are counted)
VERDICTS = ("gap_below_le", "collision", "coupler_out_of_band", "overspeed")
_FAULT_EVENT = re.compile(r"^#(\d+) (\S+) on (.+?): (injected|over)")


@dataclass
class Violation:
    verdict: str
    where: str  # "train 1-2", "train 2 coupler 1-2", "train 3 unit 1"
    start_s: float
    end_s: float
    duration_s: float
    worst: float  # the gap (m), the displacement (m) or the excess speed (m/s) at its worst
    worst_at_s: float
    limit: float
    cause: str = ""

    @property
    def trains(self) -> set[int]:
        """1-based trains this violation is about."""
        m = re.match(r"train (\d+)(?:-(\d+))?", self.where)
        return {int(g) for g in m.groups() if g} if m else set()

    def text(self) -> str:
        what = {"gap_below_le": f"gap {self.worst:.1f} m below l_e = {self.limit:g} m",
                "collision": f"collision (gap {self.worst:.2f} m)",
                "coupler_out_of_band": f"coupler at {self.worst:+.3f} m outside the band",
                "overspeed": f"{self.worst * 3.6:.1f} km/h above the permitted speed + margin"}[self.verdict]
        return (f"SAFETY {self.verdict} on {self.where} from t = {self.start_s:.2f} s to {self.end_s:.2f} s "
                f"({self.duration_s:.2f} s): {what} at t = {self.worst_at_s:.2f} s; cause: {self.cause}")


def ebi_margin(v_ref: np.ndarray) -> np.ndarray:
    """ETCS emergency-brake intervention margin above the permitted speed (m/s), per permitted speed (m/s)."""
    frac = np.clip((v_ref - EBI_MIN_SPEED) / (EBI_MAX_SPEED - EBI_MIN_SPEED), 0.0, 1.0)
    return EBI_MIN_MARGIN + frac * (EBI_MAX_MARGIN - EBI_MIN_MARGIN)


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """(first row, row after the last) of every run of True in a 1-D boolean array."""
    edges = np.diff(np.concatenate(([0], flag.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _intervals(verdict: str, t: np.ndarray, bad: np.ndarray, value: np.ndarray, worst_is_min: bool,
               names: list[str], limit: float) -> list[Violation]:
    out = []
    for j in np.flatnonzero(bad.any(axis=0)):
        for a, b in _runs(bad[:, j]):
            seg = value[a:b, j]
            k = int(np.argmin(seg) if worst_is_min else np.argmax(seg))
            end = t[b] if b < len(t) else t[-1]
            out.append(Violation(verdict, names[j], float(t[a]), float(end), float(end - t[a]), float(seg[k]),
                                 float(t[a + k]), limit))
    return out


def check_safety(log: RunLog, band: tuple[float, float], line_limit_mps: float | None = None) -> list[Violation]:
    """Every violation of the run, in time order, without causes (``explain`` adds them)."""
    t, L = log.t, log.layout
    if len(t) == 0:
        return []
    lo, hi = band
    out: list[Violation] = []
    g = log.gaps
    if g.size:
        pairs = [f"train {i + 1}-{i + 2}" for i in range(g.shape[1])]
        out += _intervals("gap_below_le", t, g < L.emergency_gap_m, g, True, pairs, L.emergency_gap_m)
        out += _intervals("collision", t, g < 0.0, g, True, pairs, 0.0)
    e = log.couplers
    if e.size:
        names = [f"train {L.train_unit(int(a))[0] + 1} coupler {L.train_unit(int(a))[1] + 1}-{L.train_unit(int(a))[1] + 2}"
                 for a, _ in L.coupler_pairs()]
        out += _intervals("coupler_out_of_band", t, (e < lo) | (e > hi), np.abs(e), False, names, hi)
    permitted = log.v_ref[:, None] + ebi_margin(log.v_ref)[:, None]
    if line_limit_mps is not None:
        permitted = np.minimum(permitted, line_limit_mps)
    excess = log.v - permitted
    units = [f"train {L.train_unit(u)[0] + 1} unit {L.train_unit(u)[1] + 1}" for u in range(L.n_units)]
    out += _intervals("overspeed", t, excess > 0.0, excess, False, units, 0.0)
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
    notable = [ev for ev in events if ev.level == "ERROR" and ev.source not in ("faults", "safety")]
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
            v.cause = f"no injected fault or ERROR event on this train in the {CAUSE_WINDOW_S:g} s before it"
    return violations


def safety_report(log: RunLog, band: tuple[float, float], line_limit_mps: float | None = None) -> dict:
    """The verdicts for metrics.json: per verdict whether it happened, how many intervals, how long in total,
    and the violations themselves (at most MAX_LISTED per verdict) with their causes."""
    violations = explain(check_safety(log, band, line_limit_mps), log.events, log.layout.n_trains)
    out: dict = {"safe": not violations, "overspeed_margin": "ETCS EBI: 7.5 km/h to 110 km/h, 15 km/h from 210 km/h"}
    for verdict in VERDICTS:
        mine = [v for v in violations if v.verdict == verdict]
        out[verdict] = {"violated": bool(mine), "count": len(mine),
                        "total_s": float(sum(v.duration_s for v in mine)),
                        "first_s": mine[0].start_s if mine else None,
                        "violations": [asdict(v) for v in mine[:MAX_LISTED]]}
    return out


def violation_events(log: RunLog, band: tuple[float, float]) -> list[Event]:
    """The violations as timeline events (source ``safety``, ERROR), at most MAX_LISTED per verdict."""
    violations = explain(check_safety(log, band), log.events, log.layout.n_trains)
    out, per = [], dict.fromkeys(VERDICTS, 0)
    for v in violations:
        per[v.verdict] += 1
        if per[v.verdict] <= MAX_LISTED:
            out.append(Event(v.start_s, "ERROR", "safety", v.text()))
    return out


def record_violations(log: RunLog, band: tuple[float, float]) -> None:
    """Put the run's violations on its timeline (every runtime calls this once, at the end of the run). Appended,
    not sorted in: the recorder writes the events incrementally by position (the viewer orders them by time)."""
    log.events.extend(violation_events(log, band))
