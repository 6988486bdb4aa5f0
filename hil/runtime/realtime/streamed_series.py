"""A per-cycle series of a real-time node (ECU cycle lateness, plant publication lateness, sensor-to-actuator
latency), streamed to a file as it comes, with its distribution kept in 1 µs bins.

A node adds one (t, value) row per cycle: the rows go to ``path`` (native float64 pairs, appended every
FLUSH_ROWS rows and at ``flush()``) for the recording, and only the bin counts stay in memory, so a node's memory
does not grow with the run's length. Percentiles are numpy's linear interpolation over the values rounded to the
microsecond; the maximum and the count (of finite values) are exact. Without a path the rows are kept in
memory (``series_table``).

The series is the engine's (``trainhil_engine.Series``, engine/src/series.rs): a node adds a row at every cycle,
woken cold, so the add is one engine call rather than a Python function. A full disk raises OSError there.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trainhil_engine as engine

from hil.sample_table import row_chunks

StreamedSeries = engine.Series
FLUSH_ROWS = engine.SERIES_FLUSH_ROWS


def series_table(series: engine.Series) -> np.ndarray:
    """(n, 2) rows of a series without a path (kept in memory)."""
    if series.path is not None:
        raise ValueError(f"the rows of {series.path} are in the file: read_series({series.path})")
    data = series.pending_bytes()
    return np.frombuffer(data, dtype=float).reshape(-1, 2) if data else np.zeros((0, 2))


def read_series(path: Path) -> np.ndarray:
    """Every (t, value) row of a series file."""
    parts = list(row_chunks(path, 2))
    return np.concatenate(parts) if parts else np.zeros((0, 2))
