"""A frame on the wire, as the bus reports it to its listeners (CAN logs, the frame recorder, the guardian): who
sent it, its ID and payload, when it was queued, started and ended (ns, bus time), and its format."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(slots=True)
class Transmission:
    """A frame on the wire."""

    node: Any  # the sender: a model's node in the oracle, the engine's node index where the engine carried it
    frame_id: int
    data: bytes
    t_enqueue: int
    t_start: int
    t_end: int
    extended: bool = False
    error: str | None = None  # set by the error model when the frame is destroyed: not delivered, retransmitted
    fd: bool = False  # a CAN FD frame
    brs: bool = False  # ... with its data phase at the data bitrate
