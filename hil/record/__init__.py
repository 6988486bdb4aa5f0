"""Recording: the in-memory run log, metrics, the rerun .rrd writer and CAN logs; ``load_run`` reads a run back."""
from __future__ import annotations

from typing import Any

__all__ = ["load_run"]


def __getattr__(name: str) -> Any:
    if name == "load_run":  # lazily: importing hil.record.runlog must not import rerun's reader
        from hil.record.reader import load_run

        return load_run
    raise AttributeError(f"module 'hil.record' has no attribute {name!r}")
