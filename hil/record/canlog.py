"""CAN log files of a run: one ASC log per bus, every frame stamped in simulated seconds.

Both runtimes attach :func:`asc_listener` to each bus model's ``frame_listeners``; ``to_seconds`` maps the
model's end-of-transmission time (ns) to simulated seconds, so virtual and real-time logs line up.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import can

from hil.can.bus import Transmission

TIME_NOTE = "trainhil {runtime}: timestamps are simulated seconds"


def open_asc(path: Path, index: int, runtime: str) -> can.ASCWriter:
    """An ASC writer for bus ``index`` (0-based; ASC channels are 1-based), its time origin pinned at t = 0."""
    writer = can.ASCWriter(path, channel=index + 1)
    writer.log_event(TIME_NOTE.format(runtime=runtime), 0.0)
    return writer


def asc_listener(writer: can.ASCWriter, index: int, to_seconds: Callable[[int], float]) -> Callable[[Transmission], None]:
    """A bus frame listener writing each completed transmission of bus ``index`` (0-based, as python-can
    numbers channels) to ``writer`` at ``to_seconds(tx.t_end)``."""

    def listener(tx: Transmission) -> None:
        writer.on_message_received(can.Message(timestamp=to_seconds(tx.t_end), arbitration_id=tx.frame_id, data=tx.data,
                                               is_extended_id=tx.extended, is_rx=True, channel=index))

    return listener
