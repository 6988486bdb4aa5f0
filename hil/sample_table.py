"""Growable tables of float rows: what the run log and the bus statistics append to while a run goes on."""
from __future__ import annotations

from array import array
from collections.abc import Iterator
from pathlib import Path

import numpy as np


class SampleTable:
    """Growable table of float rows (time first): appends go to a flat C array, O(1) and allocation-light.

    ``array`` materialises an (n, width) read-only numpy view, cached until the next append."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._buf = array("d")
        self._cache: np.ndarray | None = None
        self.released = 0  # rows let go from the front (release_before): the table holds rows released..len

    def append(self, row) -> None:
        if len(row) != self.width:
            raise ValueError(f"row of {len(row)} values, table has {self.width} columns")
        self._cache = None  # before the rows change: a stop signal between the two never leaves a stale array
        if isinstance(row, np.ndarray):
            self._buf.frombytes(row.astype(float, copy=False).tobytes())
        else:
            self._buf.extend(row)

    def extend_bytes(self, rows: bytes) -> None:
        """Append whole rows given as native float64 bytes (how the frame engine hands over its statistics)."""
        if len(rows) % (8 * self.width):
            raise ValueError(f"{len(rows)} bytes are not whole rows of {self.width} float64 values")
        if rows:
            self._cache = None  # first, as in append
            self._buf.frombytes(rows)

    def __len__(self) -> int:
        """Rows appended so far (released ones included)."""
        return self.released + len(self._buf) // self.width

    def _held(self, start: int) -> int:
        if start < self.released:
            raise ValueError(f"row {start} was released (the table holds rows {self.released}..{len(self)})")
        return (start - self.released) * self.width

    def rows_bytes(self, start: int) -> bytes:
        """Rows ``start``.. as native float64 bytes (what ``extend_bytes`` takes): to stream a table to a file."""
        return self._buf[self._held(start):].tobytes()

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start``..``stop`` (row numbers count from the first row ever appended) as an array."""
        return np.frombuffer(self._buf[self._held(start):self._held(max(stop, start))].tobytes(),
                             dtype=float).reshape(-1, self.width)

    def release_before(self, row: int) -> None:
        """Let go of the rows before ``row`` (they were recorded and summarised): memory stays flat. The last row
        is always held (``last``)."""
        row = min(row, len(self) - 1)
        if row > self.released:
            self._cache = None
            del self._buf[:self._held(row)]
            self.released = row

    def last(self, column: int = 0) -> float:
        """Value of ``column`` in the last row (NaN when empty), without materialising the table."""
        return self._buf[len(self._buf) - self.width + column] if self._buf else float("nan")

    @property
    def array(self) -> np.ndarray:
        """A read-only (n, width) array of the rows held (all of them unless some were released)."""
        if self._cache is None:
            self._cache = np.frombuffer(self._buf.tobytes(), dtype=float).reshape(-1, self.width)
        return self._cache


def row_chunks(path: Path, width: int, rows: int = 1 << 16) -> Iterator[np.ndarray]:
    """The rows of a file of native float64 rows of ``width`` values (a node's stream, a spool), ``rows`` at a
    time; a missing file has none, and a row cut by a killed writer is left out."""
    try:
        f = open(path, "rb")
    except OSError:
        return
    with f:
        while data := f.read(8 * width * rows):
            whole = len(data) - len(data) % (8 * width)
            if whole:
                yield np.frombuffer(data[:whole], dtype=float).reshape(-1, width)
            if whole < len(data):
                break
