"""Output folders: checked writable before any work, and held by the run that writes them.

A run holds its output folder: a lock file with its pid, so a second run into the same folder (even with
``--overwrite``) is refused instead of mixing one run's metrics with another's recording.

The lock is an ``flock`` on ``<out>/.hil-run.lock``: the kernel releases it when the process ends however it ends,
so a killed run never leaves a stale lock; the pid and start time in the file only serve the error message.
"""
from __future__ import annotations

import datetime
import errno
import fcntl
import os
from pathlib import Path

LOCK_NAME = ".hil-run.lock"

_HELD: dict[Path, int] = {}  # folder -> open lock fd, for the life of this process (or until release)


class OutputDirError(Exception):
    """An output folder that cannot be used (busy, read-only, not a folder); the message names it and why."""


class FolderBusy(OutputDirError):
    """Another live process holds the folder; the message names it."""


def ensure_writable_dir(out: Path, option: str = "--out") -> None:
    """Create ``out`` if needed and prove it writable with a probe file, before any work is done (a read-only
    folder used to fail with a traceback after the runs)."""
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise OutputDirError(f"{option} {out}: exists and is not a directory")
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".hil-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:  # no permission, a read-only file system, /sys, a name component over 255 bytes
        raise OutputDirError(f"{option} {out}: cannot write there: {exc.strerror or exc}") from None


def hold_folder(out: Path) -> None:
    """Take ``out``'s lock for this process (again: no-op), or raise FolderBusy naming the holder."""
    out = Path(out).resolve()
    if out in _HELD:
        return
    fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise FolderBusy(f"{out} is in use by a run that is still going ({holder}): wait for it to end, or --out "
                         "another directory") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"pid {os.getpid()}, started {datetime.datetime.now():%Y-%m-%d %H:%M:%S}\n".encode())
    _HELD[out] = fd


def release_folder(out: Path) -> None:
    """Give ``out``'s lock back (the file goes; the kernel drops the lock with the descriptor)."""
    fd = _HELD.pop(Path(out).resolve(), None)
    if fd is None:
        return
    try:
        os.unlink(Path(out).resolve() / LOCK_NAME)
    except OSError:
        pass
    os.close(fd)


def disk_full_outcome(out: Path, metrics_written: bool, sim_time_s: float) -> "DiskFullError":
    """The error a run that filled its disk ends with, saying truly what it left: how far run.rrd is readable, and
    whether metrics.json holds the run (written after the recording was cut, where it usually fits)."""
    from hil.record.diskspace import DiskFullError, free_bytes
    from hil.record.reader import recorded_until

    until = recorded_until(Path(out) / "run.rrd")
    rrd = (f"run.rrd is readable up to t = {until:.1f} s" if until is not None
           else "run.rrd holds no samples (the disk filled before its first flush of them)")
    metrics = (f"metrics.json holds the run's metrics to t = {sim_time_s:.1f} s" if metrics_written
               else "metrics.json could not be written either (it is the stub of the start)")
    return DiskFullError(errno.ENOSPC, f"no space left on {out} ({free_bytes(Path(out))} bytes free): {rrd}; {metrics}")


RESERVE_NAME = ".hil-reserve"
RESERVE_BYTES = 128 * 1024  # room kept for metrics.json (tens of kB) should the recording fill the disk


def reserve_space(out: Path) -> None:
    """Set RESERVE_BYTES aside in ``out`` (an allocated file), so that a run whose recording fills the disk can
    still write its metrics: ``write_metrics_when_full`` gives it back first. Where it cannot be had, nothing."""
    try:
        fd = os.open(Path(out) / RESERVE_NAME, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    except OSError:
        return
    try:
        os.posix_fallocate(fd, 0, RESERVE_BYTES)
    except OSError:  # no room even for that, or a file system without fallocate: no reserve
        os.close(fd)
        free_reserve(out)
        return
    os.close(fd)


def free_reserve(out: Path) -> None:
    """Give the reserved space back (at the end of every run, and before the metrics on a full disk)."""
    try:
        os.unlink(Path(out) / RESERVE_NAME)
    except OSError:
        pass


def write_metrics_when_full(path: Path, metrics: dict) -> bool:
    """Write metrics.json on a disk the recording filled: with the reserve given back first; False when it does not
    fit even then."""
    from hil.record.diskspace import DiskFullError
    from hil.record.integrity import write_json_atomic

    free_reserve(Path(path).parent)
    try:
        write_json_atomic(path, metrics)
    except DiskFullError:
        return False
    return True
