"""The bus statistics kept as frames come (hil/can/frame_stats.py): the same figures as computed from every row,
while the rows themselves can be let go once recorded (memory that does not grow with the frames)."""
from __future__ import annotations

import numpy as np
import pytest

from hil.can import frame_stats
from hil.can.frame_stats import FrameTable, LatencyCounts


def rows(n: int, rng, ids=(0x100, 0x0C0, 0x7FF)) -> np.ndarray:
    fid = rng.choice(ids, n)
    latency = np.round(rng.gamma(2.0, 3e-4, n), 6)  # repeated values, as bit-timed latencies are
    t_end = np.sort(rng.uniform(0, 100, n))
    return np.column_stack((t_end, fid, latency, latency / 2))


def test_percentiles_equal_numpys_on_every_row_in_chunks():
    rng = np.random.default_rng(3)
    data = rows(5000, rng)
    counts = LatencyCounts()
    for chunk in np.array_split(data[:, 2], 7):
        counts.add(chunk)
    for q in (0, 1, 50, 99, 99.9, 100):
        assert counts.percentile(q) == pytest.approx(np.percentile(data[:, 2], q), rel=0, abs=1e-15)
    assert counts.max() == data[:, 2].max() and counts.n == 5000
    assert LatencyCounts().percentile(50) is None


def test_released_rows_leave_the_statistics_and_the_offsets_intact():
    rng = np.random.default_rng(4)
    data = rows(3000, rng)
    kept, released = FrameTable(), FrameTable()
    for chunk in np.array_split(data, 10):
        for t in (kept, released):
            t.extend_bytes(np.ascontiguousarray(chunk).tobytes())
        released.release(len(released) - 5)  # as the recorder does after writing, keeping a few
    assert len(released) == len(kept) == 3000 and len(released.array) == 5
    np.testing.assert_array_equal(released.rows_from(2995), data[2995:])
    a, b = kept.summary(), released.summary()
    assert a[0].percentile(99) == b[0].percentile(99)
    assert a[1].max_by_id == b[1].max_by_id and a[1].totals() == b[1].totals()


def test_a_period_comes_from_the_first_enqueues_and_later_frames_are_judged_against_it():
    table = FrameTable()
    period = 0.01
    for k in range(200):  # every 10 ms, latency 1 ms; frame 150 is 12 ms late
        latency = 0.012 if k == 150 else 0.001
        table.append(np.array([k * period + latency, 0x100, latency, 0.0]))
    misses, ratio = table.summary()[1].totals()
    assert misses == 1 and ratio == pytest.approx(1.2)


def test_continuous_jitter_is_kept_to_the_microsecond(monkeypatch):
    monkeypatch.setattr(frame_stats, "MAX_DISTINCT", 100)
    counts = LatencyCounts()
    values = np.random.default_rng(5).uniform(0.001, 0.002, 10_000)
    counts.add(values)
    assert counts.values.size <= 1001 and counts.n == 10_000
    assert counts.percentile(99) == pytest.approx(np.percentile(values, 99), abs=1e-6)
