"""Free space where a run writes: a full disk is a clear error naming the place, never a hang or a traceback.

rerun writes a recording in a thread of its own; when the disk fills, that thread dies and a flush waiting for it
would wait forever. So every flush has a deadline, and the free space is checked around it.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path

MIN_FREE_BYTES = 256 * 1024  # below this a flush or a metrics file may not fit: stop with a clear error


class DiskFullError(OSError):
    """No space left where the run writes (the message names the directory and the bytes free)."""


def free_bytes(path: Path) -> int:
    """Bytes an unprivileged writer may still use on the file system holding ``path`` (or its nearest parent)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    st = os.statvfs(p)
    return st.f_bavail * st.f_frsize


def check_space(path: Path, need: int = MIN_FREE_BYTES) -> None:
    """DiskFullError when fewer than ``need`` bytes are free where ``path`` lives."""
    free = free_bytes(path)
    if free < need:
        raise disk_full(path, free)


def disk_full(path: Path, free: int | None = None) -> DiskFullError:
    where = Path(path).parent if Path(path).suffix else Path(path)
    left = f" ({free} bytes free)" if free is not None else ""
    return DiskFullError(errno.ENOSPC, f"no space left on {where}{left}")
