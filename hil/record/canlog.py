"""CAN log files of a run: one log per bus (ASC, BLF or MF4, python-can's writers), every frame stamped in
simulated seconds.

Both runtimes attach :func:`frame_listener` to each bus model's ``frame_listeners``; ``to_seconds`` maps the
model's end-of-transmission time (ns) to simulated seconds, so virtual and real-time logs line up. Channels
follow python-can: each message carries the bus's 0-based index (bus1 -> 0), the same as the trainhil
interface gives its messages, so python-can reads every log back with bus1 on channel 0, and the ASC and BLF
files (1-based by format) show busN as channel N, as ``python -m can.logger -i trainhil`` writes them.
MF4 needs asammdf (``pip install 'trainhil[mf4]'``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import can

from hil.can.transmission import Transmission
from hil.deferred_mf4 import enable_mf4

TIME_NOTE = "trainhil {runtime}: timestamps are simulated seconds"
LOG_FORMATS = ("asc", "blf", "mf4")


class CanLogUnavailable(ValueError):
    """A log format this installation cannot write (the message says what to install)."""


def log_format(can_log: str | bool | None) -> str | None:
    """The format of a ``can_log`` argument: None (no log), True (ASC, as before), or a name of LOG_FORMATS."""
    if can_log is None or can_log is False:
        return None
    fmt = "asc" if can_log is True else str(can_log).lower()
    if fmt not in LOG_FORMATS:
        raise CanLogUnavailable(f"--can-log {can_log!r}: choose one of {', '.join(LOG_FORMATS)}")
    if fmt == "mf4":
        try:
            enable_mf4()  # the `hil` command imported python-can without it (hil/deferred_mf4.py)
        except ImportError:
            raise CanLogUnavailable("--can-log mf4 needs asammdf: pip install 'trainhil[mf4]'") from None
    return fmt


def log_path(out_dir: Path, bus: str, fmt: str) -> Path:
    return Path(out_dir) / f"{bus}.{fmt}"


def open_can_log(out_dir: Path, bus: str, index: int, runtime: str, fmt: str) -> can.io.generic.MessageWriter:
    """A writer of bus ``index`` (0-based) to ``<out_dir>/<bus>.<fmt>``; an ASC log notes its time base."""
    path = log_path(out_dir, bus, fmt)
    if fmt == "asc":
        writer = can.ASCWriter(path, channel=index + 1)
        writer.log_event(TIME_NOTE.format(runtime=runtime), 0.0)
        return writer
    if fmt == "blf":
        return can.BLFWriter(path, channel=index + 1)
    return can.MF4Writer(path)


def frame_listener(writer: can.Listener, index: int, to_seconds: Callable[[int], float]) -> Callable[[Transmission], None]:
    """A bus frame listener writing each completed transmission of bus ``index`` (0-based, as python-can
    numbers channels) to ``writer`` at ``to_seconds(tx.t_end)``."""

    def listener(tx: Transmission) -> None:
        writer.on_message_received(can.Message(timestamp=to_seconds(tx.t_end), arbitration_id=tx.frame_id, data=tx.data,
                                               is_extended_id=tx.extended, is_rx=True, channel=index, is_fd=tx.fd,
                                               bitrate_switch=tx.brs))

    return listener
