"""Statistics of one CAN bus: the load of every window and the latency of every frame, as the bus model keeps them."""
from __future__ import annotations

from dataclasses import dataclass, field

from hil.can.frame_stats import FrameTable
from hil.tables import SampleTable


@dataclass
class BusLog:
    """Per-bus statistics: load per window and the latency of every frame."""

    name: str  # "bus1" ... (1-based train number)
    bitrate: int
    load: SampleTable = field(default_factory=lambda: SampleTable(2))  # (t_window_end, load 0..1)
    # (t_end, frame_id, latency_s = end of transmission - enqueue time, queueing_s), and their statistics
    frames: FrameTable = field(default_factory=FrameTable)
    frames_sent: int = 0
    frames_dropped: int = 0  # TX-queue overflow or injected drop
