"""What the metrics and the safety verdicts need of the sampled signals, kept as the samples come.

``SignalSummary.add(rows)`` takes RunLog signal rows (t, x_r, v_r, x[n], v[n], a[n], F_cmd[n], F_applied[n]) in
time order, in chunks of any size, and keeps running figures: extremes, times spent in a condition, the settling
tail of each reference segment, the effort and jerk sums, and the safety violations. So a run need not keep its
samples to compute its metrics, and its memory does not grow with its length (``RunLog.release_signals``).

The figures do not depend on the chunking, except for the last bits of the sums (times spent, effort, jerk), which
are added chunk by chunk: ``RunLog.summary`` therefore feeds it in blocks of fixed row numbers, so metrics.json is
the same bit for bit however the wall clock paced the recording. Durations use a zero-order hold: sample k holds until sample k+1, the last one 0 s.
A violation is one interval of one pair, coupler or unit (hil/record/safety.py says which verdicts); all are
counted, and the MAX_LISTED earliest of each verdict are kept with their worst value.
"""
from __future__ import annotations

import bisect
import re
from dataclasses import dataclass, replace

import numpy as np

from hil.scenario.layout import TrainLayout

MAX_LISTED = 50  # violations kept per verdict (all are counted)
KMH = 1.0 / 3.6
EBI_MIN_MARGIN, EBI_MAX_MARGIN = 7.5 * KMH, 15.0 * KMH  # dV_ebi_min / dV_ebi_max
EBI_MIN_SPEED, EBI_MAX_SPEED = 110.0 * KMH, 210.0 * KMH  # V_ebi_min / V_ebi_max


def ebi_margin(v_ref: np.ndarray) -> np.ndarray:
    """ETCS emergency-brake intervention margin above the permitted speed (m/s), per permitted speed (m/s)
    (SUBSET-026 3.13.9.2.3, default values: the overspeed verdict of hil/record/safety.py)."""
    frac = np.clip((v_ref - EBI_MIN_SPEED) / (EBI_MAX_SPEED - EBI_MIN_SPEED), 0.0, 1.0)
    return EBI_MIN_MARGIN + frac * (EBI_MAX_MARGIN - EBI_MIN_MARGIN)


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
        """The timeline's line for it."""
        what = {"gap_below_le": f"gap {self.worst:.1f} m below l_e = {self.limit:g} m",
                "collision": f"collision (gap {self.worst:.2f} m)",
                "coupler_out_of_band": f"coupler at {self.worst:+.3f} m outside the band",
                "overspeed": f"{self.worst * 3.6:.1f} km/h above the permitted speed + margin"}[self.verdict]
        return (f"SAFETY {self.verdict} on {self.where} from t = {self.start_s:.2f} s to {self.end_s:.2f} s "
                f"({self.duration_s:.2f} s): {what} at t = {self.worst_at_s:.2f} s; cause: {self.cause}")


def runs_of(flag: np.ndarray) -> list[tuple[int, int]]:
    """(first row, row after the last) of every run of True in a 1-D boolean array."""
    edges = np.diff(np.concatenate(([0], flag.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


class HoldTime:
    """Time during which a per-sample flag holds, with a zero-order hold across chunks."""

    def __init__(self) -> None:
        self.total = 0.0
        self._last: tuple[float, bool] | None = None  # (t, flag) of the last sample so far

    def add(self, t: np.ndarray, flag: np.ndarray) -> None:
        if not len(t):
            return
        if self._last is not None and self._last[1]:
            self.total += max(float(t[0]) - self._last[0], 0.0)
        self.total += float(np.sum(np.maximum(np.diff(t), 0.0)[flag[:-1]]))
        self._last = (float(t[-1]), bool(flag[-1]))


class Intervals:
    """The violations of one verdict, column by column: bad rows as intervals with their worst value."""

    def __init__(self, verdict: str, names: list[str], limit: float, worst_is_min: bool) -> None:
        self.verdict, self.names, self.limit, self.worst_is_min = verdict, names, limit, worst_is_min
        self.open: dict[int, list[float]] = {}  # column -> [start, worst, worst at]
        self.count = 0
        self.total_s = 0.0
        self.first_s: float | None = None
        self.kept: list[Violation] = []  # the earliest closed ones, by (start, where)

    def add(self, t: np.ndarray, bad: np.ndarray, value: np.ndarray) -> None:
        """Rows ``t`` with their flags ``bad`` (k, columns) and the value judged (k, columns)."""
        for j in sorted(set(np.flatnonzero(bad.any(axis=0)).tolist()) | set(self.open)):
            col = bad[:, j]
            if j in self.open and not col[0]:
                self._close(j, float(t[0]))
            for a, b in runs_of(col):
                seg = value[a:b, j]
                k = int(np.argmin(seg) if self.worst_is_min else np.argmax(seg))
                worst, at = float(seg[k]), float(t[a + k])
                current = self.open.get(j) if a == 0 else None
                if current is None:
                    self.open[j] = [float(t[a]), worst, at]
                elif (worst < current[1]) if self.worst_is_min else (worst > current[1]):
                    current[1], current[2] = worst, at
                if b < len(t):
                    self._close(j, float(t[b]))

    def _close(self, j: int, end: float) -> None:
        start, worst, at = self.open.pop(j)
        v = self._violation(j, start, end, worst, at)
        self.count += 1
        self.total_s += v.duration_s
        self.first_s = start if self.first_s is None else min(self.first_s, start)
        bisect.insort(self.kept, v, key=lambda x: (x.start_s, x.where))
        del self.kept[MAX_LISTED:]

    def _violation(self, j: int, start: float, end: float, worst: float, at: float) -> Violation:
        return Violation(self.verdict, self.names[j], start, end, end - start, worst, at, self.limit)

    def result(self, t_last: float) -> tuple[int, float, float | None, list[Violation]]:
        """(count, total seconds, first start, the MAX_LISTED earliest), the open ones ending at ``t_last``."""
        still = [self._violation(j, s, t_last, w, at) for j, (s, w, at) in self.open.items()]
        listed = sorted([replace(v) for v in self.kept] + still, key=lambda x: (x.start_s, x.where))[:MAX_LISTED]
        first = min([v.start_s for v in still] + ([self.first_s] if self.first_s is not None else []), default=None)
        return self.count + len(still), self.total_s + sum(v.duration_s for v in still), first, listed


class Extremes:
    """Running min and max (NaN propagates, as numpy's) of an array's columns, or of all of it (``axis=None``)."""

    def __init__(self, axis: int | None = None) -> None:
        self.axis = axis
        self.min: np.ndarray | float | None = None
        self.max: np.ndarray | float | None = None

    def add(self, a: np.ndarray) -> None:
        if not a.size:
            return
        lo, hi = np.min(a, axis=self.axis), np.max(a, axis=self.axis)
        self.min = lo if self.min is None else np.minimum(self.min, lo)
        self.max = hi if self.max is None else np.maximum(self.max, hi)


class Settling:
    """Per reference segment: when its final all-within-band tail began; for the first, overshoot and the error
    after settling."""

    def __init__(self, change_times: list[float], band: float) -> None:
        self.starts = [0.0] + sorted({float(c) for c in change_times if c > 0})
        self.band = band
        self.tail_start: list[float | None] = [None] * len(self.starts)
        self.overshoot = Extremes()  # of the signed error, first segment
        self.tail_max_abs: float | None = None  # max |error| in the first segment's current tail

    def add(self, t: np.ndarray, err: np.ndarray) -> None:
        within = np.all(np.abs(err) <= self.band, axis=1)
        bounds = np.searchsorted(t, self.starts, side="left").tolist() + [len(t)]
        for s in range(len(self.starts)):
            r0, r1 = bounds[s], bounds[s + 1]
            if r0 < r1:
                self._segment(s, t[r0:r1], err[r0:r1], within[r0:r1])

    def _segment(self, s: int, t: np.ndarray, err: np.ndarray, within: np.ndarray) -> None:
        bad = np.flatnonzero(~within)
        if len(bad):
            tail = int(bad[-1]) + 1  # the first row of this chunk's all-within tail
            self.tail_start[s] = float(t[tail]) if tail < len(t) else None
        elif self.tail_start[s] is None:  # no rows before, or the last one was outside the band
            tail = 0
            self.tail_start[s] = float(t[0])
        else:
            tail = None  # the tail goes on
        if s == 0:
            self.overshoot.add(err)
            rest = np.abs(err[tail or 0:])
            m = float(np.max(rest)) if rest.size else None
            if tail is not None:
                self.tail_max_abs = m
            elif m is not None:
                self.tail_max_abs = float(np.maximum(self.tail_max_abs, m))

    def settling_times(self) -> list[float | None]:
        """Per segment, from its start to the start of its final all-within tail (None: not settled)."""
        return [None if ts is None else ts - start for ts, start in zip(self.tail_start, self.starts)]


class SignalSummary:
    """Everything the metrics (hil/record/metrics.py) and the safety verdicts (hil/record/safety.py) read of the
    sampled signals; ``add`` chunks of rows in time order."""

    def __init__(self, layout: TrainLayout, coupler_band: tuple[float, float], settle_band_mps: float,
                 change_times: list[float], line_limit_mps: float | None = None) -> None:
        self.layout, self.band, self.line_limit_mps = layout, coupler_band, line_limit_mps
        L = layout
        self.n = L.n_units
        self.pairs = L.coupler_pairs()
        self.rows = 0
        self.t_last: float | None = None
        self.last_row: np.ndarray | None = None  # the last sample (gap_final, position_error_final, sums across chunks)
        self.settling = Settling(change_times, settle_band_mps)
        self.speed_error = Extremes()
        self.coupler = Extremes()
        self.coupler_abs = Extremes()
        self.coupler_out = HoldTime()
        self.gap = Extremes(axis=0)
        self.gap_below = HoldTime()
        self.gap_spacing_error = Extremes(axis=0)  # |gap - l_s| per pair: string stability
        self.effort = np.zeros(self.n)  # integral of |F_applied| / m per unit
        self.jerk_sq, self.jerk_n = 0.0, 0
        self.collision = self.unsafe = False
        self.violations = self._violation_trackers()

    def _violation_trackers(self) -> dict[str, Intervals]:
        L = self.layout
        pairs = [f"train {i + 1}-{i + 2}" for i in range(L.n_trains - 1)]
        couplers = [f"train {L.train_unit(int(a))[0] + 1} coupler {L.train_unit(int(a))[1] + 1}-"
                    f"{L.train_unit(int(a))[1] + 2}" for a, _ in self.pairs]
        units = [f"train {L.train_unit(u)[0] + 1} unit {L.train_unit(u)[1] + 1}" for u in range(L.n_units)]
        return {"gap_below_le": Intervals("gap_below_le", pairs, L.emergency_gap_m, True),
                "collision": Intervals("collision", pairs, 0.0, True),
                "coupler_out_of_band": Intervals("coupler_out_of_band", couplers, self.band[1], False),
                "overspeed": Intervals("overspeed", units, 0.0, False)}

    # ---- the signals of a chunk
    def _columns(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        n, L = self.n, self.layout
        x_r, v_r = rows[:, 1], rows[:, 2]
        x, v = rows[:, 3:3 + n], rows[:, 3 + n:3 + 2 * n]
        tails, heads = L.tails(), L.heads()
        e = (x[:, self.pairs[:, 0]] - x[:, self.pairs[:, 1]] - L.length_m[self.pairs[:, 0]][None, :]
             if len(self.pairs) else np.zeros((len(rows), 0)))
        return {"t": rows[:, 0], "x_r": x_r, "v_r": v_r, "x": x, "v": v, "a": rows[:, 3 + 2 * n:3 + 3 * n],
                "f_app": rows[:, 3 + 4 * n:3 + 5 * n], "err": v - v_r[:, None], "e": e,
                "g": (x[:, tails[:-1]] - L.length_m[tails[:-1]][None, :]) - x[:, heads[1:]]}

    def add(self, rows: np.ndarray) -> None:
        """Signal rows, later than every row added before."""
        if not len(rows):
            return
        c = self._columns(rows)
        t = c["t"]
        self.settling.add(t, c["err"])
        self.speed_error.add(np.abs(c["err"]))
        self._couplers(t, c["e"])
        self._gaps(t, c["g"])
        self._effort_and_jerk(rows, c)
        self._overspeed(t, c["v"], c["v_r"])
        self.rows += len(rows)
        self.t_last = float(t[-1])
        self.last_row = np.array(rows[-1], dtype=float)

    def _couplers(self, t: np.ndarray, e: np.ndarray) -> None:
        lo, hi = self.band
        out = (e < lo) | (e > hi)
        self.coupler.add(e)
        self.coupler_abs.add(np.abs(e))
        self.coupler_out.add(t, out.any(axis=1) if e.size else np.zeros(len(t), dtype=bool))
        self.unsafe |= bool(out.any())
        self.violations["coupler_out_of_band"].add(t, out, np.abs(e))

    def _gaps(self, t: np.ndarray, g: np.ndarray) -> None:
        le = self.layout.emergency_gap_m
        below = g < le
        self.gap.add(g)
        self.gap_below.add(t, below.any(axis=1) if g.size else np.zeros(len(t), dtype=bool))
        self.gap_spacing_error.add(np.abs(g - self.layout.spacing_m))
        self.collision |= bool((g < 0.0).any())
        self.unsafe |= bool(below.any()) or self.collision
        self.violations["gap_below_le"].add(t, below, g)
        self.violations["collision"].add(t, g < 0.0, g)

    def _effort_and_jerk(self, rows: np.ndarray, c: dict[str, np.ndarray]) -> None:
        """Trapezoid integral of |F| / m, and the jerk (a difference over dt > 0), joined across chunks."""
        t, a, y = c["t"], c["a"], np.abs(c["f_app"]) / self.layout.mass_kg[None, :]
        if self.last_row is not None:
            prev = self.last_row
            n = self.n
            t = np.concatenate(([prev[0]], t))
            a = np.vstack((prev[3 + 2 * n:3 + 3 * n], a))
            y = np.vstack((np.abs(prev[3 + 4 * n:3 + 5 * n]) / self.layout.mass_kg, y))
        if len(t) < 2:
            return
        dt = np.diff(t)
        self.effort += np.sum(dt[:, None] * (y[1:] + y[:-1]) / 2.0, axis=0)
        ok = dt > 0
        jerk = np.diff(a, axis=0)[ok] / dt[ok, None]
        self.jerk_sq += float(np.sum(jerk**2))
        self.jerk_n += jerk.size

    def _overspeed(self, t: np.ndarray, v: np.ndarray, v_r: np.ndarray) -> None:
        permitted = v_r[:, None] + ebi_margin(v_r)[:, None]
        if self.line_limit_mps is not None:
            permitted = np.minimum(permitted, self.line_limit_mps)
        excess = v - permitted
        self.violations["overspeed"].add(t, excess > 0.0, excess)

    # ---- what the last sample says
    def final_gaps(self) -> np.ndarray | None:
        return None if self.last_row is None else self._columns(self.last_row[None, :])["g"][0]

    def final_position_error(self) -> np.ndarray | None:
        if self.last_row is None:
            return None
        x = self.last_row[3:3 + self.n]
        return x - (self.last_row[1] - self.layout.offset_m)
