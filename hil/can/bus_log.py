"""Statistics of one CAN bus: the load of every window and the latency of every frame, as the bus model keeps them."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hil.can.frame_stats import FrameTable
from hil.sample_table import SampleTable

LOAD_WINDOW_S = 0.1  # the bus load's window, in every runtime: a row at t is the load of (t - LOAD_WINDOW_S, t]


class LoadTable(SampleTable):
    """(t_window_end, load 0..1) per load window, with the running maximum and sum of the loads: the metrics need
    only those, so recorded windows can be let go (``release_before``)."""

    def __init__(self) -> None:
        super().__init__(2)
        self.max = float("-inf")
        self.sum = 0.0
        self.count = 0

    def append(self, row) -> None:
        super().append(row)
        self._account(np.asarray(row, dtype=float)[None, 1])

    def extend_bytes(self, rows: bytes) -> None:
        super().extend_bytes(rows)
        self._account(np.frombuffer(rows, dtype=float)[1::2])

    def _account(self, loads: np.ndarray) -> None:
        if loads.size:
            self.max = float(np.maximum(self.max, np.max(loads)))
            self.sum += float(np.sum(loads))
            self.count += int(loads.size)


@dataclass
class BusLog:
    """Per-bus statistics: load per window and the latency of every frame."""

    name: str  # "bus1" ... (1-based train number)
    bitrate: int
    load: LoadTable = field(default_factory=LoadTable)  # (t_window_end, load 0..1)
    # (t_end, frame_id, latency_s = end of transmission - enqueue time, queueing_s), and their statistics
    frames: FrameTable = field(default_factory=FrameTable)
    frames_sent: int = 0
    frames_dropped: int = 0  # TX-queue overflow or injected drop
    dropped_by_node: dict[str, int] = field(default_factory=dict)  # of those, by node name (none: left out)
