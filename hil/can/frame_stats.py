"""The per-frame rows of one bus and what the metrics need of them, kept as the rows come.

Each row is ``(t_end, frame_id, latency_s, queueing_s)``. A run can keep every row (the default: tests look frames
up), or hand them to the recording and let them go (``release``): the statistics stay, so memory does not grow
with the run's length. What is kept:

- the latency distribution, as a count per distinct latency value: percentiles are exact (numpy's linear
  interpolation between order statistics). Past MAX_DISTINCT distinct values (real-time jitter) the values are
  rounded to the microsecond;
- the largest latency of each frame ID;
- the deadline check (deadline = period): an ID's period is the median interval between its first
  PERIOD_INTERVALS + 1 enqueues (all of them, if it has fewer), and every frame whose latency exceeds it misses.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from hil.sample_table import SampleTable

WIDTH = 4
MAX_DISTINCT = 1 << 16
PERIOD_INTERVALS = 64


class LatencyCounts:
    """The multiset of latencies: sorted distinct values and their counts."""

    def __init__(self) -> None:
        self.values = np.zeros(0)
        self.counts = np.zeros(0, dtype=np.int64)

    def add(self, latencies: np.ndarray) -> None:
        if latencies.size:
            self._merge(*np.unique(latencies, return_counts=True))

    def _merge(self, values: np.ndarray, counts: np.ndarray) -> None:
        merged, inverse = np.unique(np.concatenate([self.values, values]), return_inverse=True)
        self.counts = np.bincount(inverse, weights=np.concatenate([self.counts, counts])).astype(np.int64)
        self.values = merged
        if self.values.size > MAX_DISTINCT:  # continuous jitter: keep the distribution to the microsecond
            rounded, inverse = np.unique(np.round(self.values, 6), return_inverse=True)
            self.counts = np.bincount(inverse, weights=self.counts).astype(np.int64)
            self.values = rounded

    @classmethod
    def merged(cls, parts: Iterable["LatencyCounts"]) -> "LatencyCounts":
        out = cls()
        for p in parts:
            if p.values.size:
                out._merge(p.values, p.counts)
        return out

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def _at(self, k: int) -> float:
        """The k-th smallest latency (0-based)."""
        return float(self.values[np.searchsorted(np.cumsum(self.counts), k, side="right")])

    def percentile(self, q: float) -> float | None:
        """As ``np.percentile(all_latencies, q)`` (linear interpolation); None without latencies."""
        n = self.n
        if n == 0:
            return None
        pos = q / 100.0 * (n - 1)
        lo, hi = int(np.floor(pos)), int(np.ceil(pos))
        a, b = self._at(lo), self._at(hi)
        return a + (b - a) * (pos - lo)

    def max(self) -> float | None:
        return float(self.values[-1]) if self.values.size else None


class DeadlineCheck:
    """Per frame ID: the largest latency, the period from its first enqueues, and the frames later than it."""

    def __init__(self) -> None:
        self.max_by_id: dict[int, float] = {}
        self._early: dict[int, list[tuple[float, float]]] = {}  # (release, latency) until the period is known
        self._period: dict[int, float] = {}
        self.misses = 0
        self.ratio_max: float | None = None

    def add(self, rows: np.ndarray) -> None:
        ids = rows[:, 1].astype(np.int64)
        order = np.argsort(ids, kind="stable")
        ids, rows = ids[order], rows[order]
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(ids)]):
            self._add_id(int(ids[a]), rows[a:b, 0] - rows[a:b, 2], rows[a:b, 2])

    def _add_id(self, frame_id: int, release: np.ndarray, latency: np.ndarray) -> None:
        self.max_by_id[frame_id] = max(self.max_by_id.get(frame_id, -np.inf), float(latency.max()))
        period = self._period.get(frame_id)
        if period is None:
            early = self._early.setdefault(frame_id, [])
            early.extend(zip(release.tolist(), latency.tolist()))
            if len(early) <= PERIOD_INTERVALS:
                return
            period = self._settle(frame_id)
            release, latency = np.zeros(0), np.zeros(0)  # counted in _settle
        self._count(latency, period)

    def _settle(self, frame_id: int) -> float:
        """Fix the ID's period from its buffered frames and count their misses."""
        period, misses, top = _judge(self._early.pop(frame_id))
        self._period[frame_id] = period
        self._book(misses, top)
        return period

    def _count(self, latency: np.ndarray, period: float) -> None:
        if latency.size and period > 0:  # False for NaN (a single frame: no period)
            ratio = latency / period
            self._book(int(np.count_nonzero(ratio > 1.0)), float(ratio.max()))

    def _book(self, misses: int, top: float | None) -> None:
        self.misses += misses
        if top is not None:
            self.ratio_max = top if self.ratio_max is None else max(self.ratio_max, top)

    def totals(self) -> tuple[int, float | None]:
        """(deadline misses, largest latency / period) so far, IDs with too few frames for a settled period judged
        on what they have (without fixing it: more frames may come)."""
        misses, ratio_max = self.misses, self.ratio_max
        for early in self._early.values():
            _, m, top = _judge(early)
            misses += m
            if top is not None:
                ratio_max = top if ratio_max is None else max(ratio_max, top)
        return misses, ratio_max


def _judge(early: list[tuple[float, float]]) -> tuple[float, int, float | None]:
    """(period, misses, largest ratio) of one ID's (release, latency) pairs: the period is the median interval
    of the first PERIOD_INTERVALS + 1 releases (NaN for a single frame: never a miss)."""
    early = sorted(early)
    release = np.array([r for r, _ in early])
    latency = np.array([lat for _, lat in early])
    intervals = np.diff(release[:PERIOD_INTERVALS + 1])
    period = float(np.median(intervals)) if intervals.size else float("nan")
    if not period > 0:
        return period, 0, None
    ratio = latency / period
    return period, int(np.count_nonzero(ratio > 1.0)), float(ratio.max())


class FrameTable:
    """Per-frame rows of one bus (``(t_end, frame_id, latency_s, queueing_s)``) and their statistics.

    ``len()`` counts every row ever added; ``rows_from(start)`` gives the rows from index ``start`` that are still
    kept; ``release(upto)`` lets the rows before ``upto`` go once they are recorded."""

    width = WIDTH

    def __init__(self) -> None:
        self._rows = SampleTable(WIDTH)
        self._first = 0  # index of the first kept row
        self._folded = 0  # rows counted into the statistics so far
        self.latency = LatencyCounts()
        self.deadlines = DeadlineCheck()

    # ---- adding
    def append(self, row) -> None:
        self._rows.append(row)

    def extend_bytes(self, rows: bytes) -> None:
        self._rows.extend_bytes(rows)

    def __len__(self) -> int:
        return self._first + len(self._rows)

    # ---- reading
    @property
    def array(self) -> np.ndarray:
        """The rows kept (every row, unless some were released)."""
        return self._rows.array

    def rows_from(self, start: int) -> np.ndarray:
        """The kept rows from index ``start`` (rows before the first kept one are gone)."""
        return self._rows.array[max(start - self._first, 0):]

    def release(self, upto: int) -> None:
        """Count the rows into the statistics and let those before index ``upto`` go."""
        self.fold()
        self.hand_off(upto)

    def hand_off(self, upto: int) -> None:
        """Let the rows before ``upto`` go uncounted: they went to a spool whose reader keeps their statistics (a
        real-time bus server's table, hil/runtime/realtime/bus_spool.py). This table's own statistics then cover
        none of the rows handed off."""
        drop = min(upto, len(self)) - self._first
        if drop > 0:
            kept = self._rows.rows_bytes(drop)
            self._rows = SampleTable(WIDTH)
            self._rows.extend_bytes(kept)
            self._first += drop
            self._folded = max(self._folded, self._first)

    def fold(self) -> None:
        """Bring the statistics up to the last row."""
        if self._folded < len(self):
            new = self.rows_from(self._folded)
            self.latency.add(new[:, 2])
            self.deadlines.add(new)
            self._folded = len(self)

    def summary(self) -> tuple[LatencyCounts, DeadlineCheck]:
        """The statistics of every row so far."""
        self.fold()
        return self.latency, self.deadlines
