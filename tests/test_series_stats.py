"""The real-time nodes' per-cycle series (hil/runtime/realtime/streamed_series.py): streamed to a file as they come,
their percentiles to the microsecond from bin counts, their maximum and count exact."""
from __future__ import annotations

import numpy as np
import pytest

from hil.runtime.realtime.pacing import LatenessStats
from hil.runtime.realtime.streamed_series import FLUSH_ROWS, StreamedSeries, read_series, series_table
from hil.sample_table import row_chunks


def test_rows_go_to_the_file_and_only_the_unwritten_ones_stay(tmp_path):
    path = tmp_path / "s.bin"
    s = StreamedSeries(path)
    rng = np.random.default_rng(1)
    values = rng.gamma(2.0, 2e-4, size=3 * FLUSH_ROWS + 17)
    for k, v in enumerate(values):
        s.add(k * 0.01, float(v))
    assert len(s.pending_bytes()) == 2 * 17 * 8  # the rest is on disk
    s.close()
    rows = read_series(path)
    assert rows.shape == (len(values), 2) and np.array_equal(rows[:, 1], values)
    assert [len(c) for c in row_chunks(path, 2, rows=1000)] == [1000, 1000, 1000, 89]
    with pytest.raises(ValueError, match="read_series"):
        series_table(s)


def test_percentiles_are_numpys_to_the_microsecond_and_the_maximum_exact():
    s = StreamedSeries()
    values = np.random.default_rng(2).exponential(3e-4, size=20_000)
    for v in values:
        s.add(0.0, float(v))
    for q in (50, 99):
        assert s.percentile(q) == pytest.approx(np.percentile(values, q), abs=1e-6)
    assert s.max == values.max() and s.n == len(values)
    assert StreamedSeries().percentile(50) is None


def test_a_series_without_a_file_keeps_its_rows_non_finite_ones_included():
    s = StreamedSeries()
    s.add(0.5, 2e-4)
    s.add(1.5, float("nan"))  # a row, not a value of the distribution
    table = series_table(s)
    assert table.shape == (2, 2) and table[0].tolist() == [0.5, 2e-4] and np.isnan(table[1, 1])
    assert s.n == 1 and s.max == 2e-4 and s.percentile(99) == pytest.approx(2e-4)


def test_a_row_cut_by_a_killed_writer_is_left_out(tmp_path):
    path = tmp_path / "cut.bin"
    path.write_bytes(np.array([[1.0, 2.0], [3.0, 4.0]]).tobytes() + b"\x00" * 9)
    assert read_series(path).tolist() == [[1.0, 2.0], [3.0, 4.0]]


def test_a_restarted_node_appends_to_its_predecessors_rows(tmp_path):
    path = tmp_path / "timing_ecu_1_1.bin"
    for t0 in (0.0, 5.0):
        stats = LatenessStats(0.01, 1.0, path)
        for k in range(3):
            stats.add(1e-4, t0 + k * 0.01)
        stats.series.close()
    assert read_series(path)[:, 0].tolist() == pytest.approx([0.0, 0.01, 0.02, 5.0, 5.01, 5.02])
