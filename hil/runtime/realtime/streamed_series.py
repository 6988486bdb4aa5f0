"""A per-cycle series of a real-time node (ECU cycle lateness, plant publication lateness, sensor-to-actuator
latency), streamed to a file as it comes, with its distribution kept in 1 µs bins.

A node adds one (t, value) row per cycle: the rows go to ``path`` (native float64 pairs, appended every
FLUSH_ROWS rows and at ``flush()``) for the recording, and only the bin counts stay in memory, so a node's memory
does not grow with the run's length. Percentiles are numpy's linear interpolation over the values rounded to the
microsecond; the maximum and the count (of finite values) are exact. Without a path the rows are kept in
memory (``table()``).
"""
from __future__ import annotations

import math
import os
from array import array
from pathlib import Path

import numpy as np

from hil.sample_table import row_chunks

RESOLUTION_S = 1e-6
FLUSH_ROWS = 1024


class StreamedSeries:
    """(t, value) rows: streamed to ``path`` (or kept, without one), their values counted in 1 µs bins."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        # appended to, never truncated: a restarted ECU process's rows follow its predecessor's
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600) if path else None
        self._rows = array("d")  # t, value, t, value, ... not yet written (all of them without a path)
        self._bins: dict[int, int] = {}  # value in µs -> count
        self.n = 0
        self.max = -math.inf

    def add(self, t: float, value: float) -> None:
        self._rows.append(t)
        self._rows.append(value)
        if self._fd is not None and len(self._rows) >= 2 * FLUSH_ROWS:
            self.flush()
        if not math.isfinite(value):  # recorded, but no place in the distribution
            return
        k = round(value / RESOLUTION_S)
        self._bins[k] = self._bins.get(k, 0) + 1
        self.n += 1
        if value > self.max:
            self.max = value

    def flush(self) -> None:
        """Write the rows not written yet (a node calls this at its saves and at its end)."""
        if self._fd is not None and self._rows:
            os.write(self._fd, self._rows.tobytes())
            del self._rows[:]

    def close(self) -> None:
        self.flush()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def percentile(self, q: float) -> float | None:
        """As ``np.percentile(values, q)`` over the values rounded to the microsecond; None without values."""
        if not self.n:
            return None
        keys = np.array(sorted(self._bins), dtype=np.int64)
        cum = np.cumsum([self._bins[k] for k in keys])
        pos = q / 100.0 * (self.n - 1)
        lo, hi = int(math.floor(pos)), int(math.ceil(pos))
        a, b = (float(keys[np.searchsorted(cum, k, side="right")]) * RESOLUTION_S for k in (lo, hi))
        return a + (b - a) * (pos - lo)

    def table(self) -> np.ndarray:
        """(n, 2) rows kept in memory (a series without a path)."""
        if self.path is not None:
            raise ValueError(f"the rows of {self.path} are in the file: read_series({self.path})")
        return np.frombuffer(self._rows, dtype=float).reshape(-1, 2) if self._rows else np.zeros((0, 2))


def read_series(path: Path) -> np.ndarray:
    """Every (t, value) row of a series file."""
    parts = list(row_chunks(path, 2))
    return np.concatenate(parts) if parts else np.zeros((0, 2))
