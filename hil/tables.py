"""Growable tables of float rows: what the run log and the bus statistics append to while a run goes on."""
from __future__ import annotations

from array import array

import numpy as np


class SampleTable:
    """Growable table of float rows (time first): appends go to a flat C array, O(1) and allocation-light.

    ``array`` materialises an (n, width) read-only numpy view, cached until the next append."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._buf = array("d")
        self._cache: np.ndarray | None = None

    def append(self, row) -> None:
        if len(row) != self.width:
            raise ValueError(f"row of {len(row)} values, table has {self.width} columns")
        if isinstance(row, np.ndarray):
            self._buf.frombytes(row.astype(float, copy=False).tobytes())
        else:
            self._buf.extend(row)
        self._cache = None

    def extend_bytes(self, rows: bytes) -> None:
        """Append whole rows given as native float64 bytes (how the frame engine hands over its statistics)."""
        if len(rows) % (8 * self.width):
            raise ValueError(f"{len(rows)} bytes are not whole rows of {self.width} float64 values")
        if rows:
            self._buf.frombytes(rows)
            self._cache = None

    def __len__(self) -> int:
        return len(self._buf) // self.width

    def rows_bytes(self, start: int) -> bytes:
        """Rows ``start``.. as native float64 bytes (what ``extend_bytes`` takes): to stream a table to a file."""
        return self._buf[start * self.width:].tobytes()

    def last(self, column: int = 0) -> float:
        """Value of ``column`` in the last row (NaN when empty), without materialising the table."""
        return self._buf[len(self._buf) - self.width + column] if self._buf else float("nan")

    @property
    def array(self) -> np.ndarray:
        """A read-only (n, width) array of the rows so far."""
        if self._cache is None:
            self._cache = np.frombuffer(self._buf.tobytes(), dtype=float).reshape(-1, self.width)
        return self._cache
