"""The CPUs' wake-up latency limit for a real-time run (Linux PM QoS, ``/dev/cpu_dma_latency``), held as cyclictest
holds it.

A node sleeps between its cycles. On a virtual machine an idle CPU halts, and the hypervisor gives it back to the
guest later: on this project's 2-core KVM host a short piece of Python right after a 10 ms sleep runs 20-25 µs
longer than warm. A limit of 0 µs keeps idle CPUs polling in the guest's idle loop instead; seed000's ECU cycle
after a 10 ms sleep then costs 72 µs rather than 114 (warm: 9; ``bench/bench_cold_cycle.py``,
docs/realtime-performance.md, "Keeping idle CPUs awake"). The price: the idle CPUs no longer rest (the host sees
them busy).

A real-time run at pace 1 or slower holds 0 where the host permits it (``auto``, the default, as cyclictest does
and as the rig takes SCHED_FIFO where permitted), else leaves the host's limit and says why in its events. Faster
than real time, auto leaves the host's: nodes then sleep about 1 ms, and polling CPUs made the host take them
away more often (seed000 at pace 10: 37 and 41 late plant publications of 30,000 held, 17 and 20 not; at pace 1
five minutes of 64 ECUs reached p99 0.85 ms held, 1.57 not; docs/realtime-performance.md, "Keeping idle CPUs awake").
``host`` leaves it always; a number holds that many µs or refuses the run (exit 1).

The kernel keeps the limit while the file is open and drops it when it is closed, also when the process dies:
a killed rig leaves nothing behind.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Literal, Union

from hil.runtime.errors import RigDidNotStart

CPU_LATENCY_FILE = Path("/dev/cpu_dma_latency")
MAX_LIMIT_US = 2**31 - 1  # the kernel takes a signed 32-bit value
AUTO_LIMIT_US = 0  # what "auto" holds where permitted: idle CPUs poll
IdleLatencySetting = Union[int, Literal["auto", "host"]]  # a limit in µs, or auto (0 where permitted), or the host's


def latency_us(text: str) -> IdleLatencySetting:
    """An argparse type for ``--idle-latency-us``: auto, host, or a whole number of microseconds the kernel's limit
    takes."""
    if text in ("auto", "host"):
        return text  # type: ignore[return-value]  # one of the two literals
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not auto, host or a whole number of microseconds") from None
    if not 0 <= value <= MAX_LIMIT_US:
        raise argparse.ArgumentTypeError(f"{value} must be from 0 to {MAX_LIMIT_US} (µs), auto or host")
    return value


def check_setting(setting: IdleLatencySetting) -> None:
    """ValueError naming ``idle_latency_us`` unless it is auto, host or a limit the kernel takes."""
    if setting in ("auto", "host"):
        return
    try:
        IdleLatencyHold(setting)  # type: ignore[arg-type]  # validates the number
    except ValueError as exc:
        raise ValueError(f"{exc}, or 'auto' or 'host'") from None


def hold_for_run(setting: IdleLatencySetting, pace: float = 1.0) -> tuple["IdleLatencyHold | None", str]:
    """Open the hold ``setting`` asks for at ``pace``: the hold (None: the host's limit stays) and the sentence for
    the run's events. IdleLatencyRefused only for a number the host does not let us hold; auto falls back to the
    host's there, and faster than real time (the module docstring says why)."""
    if setting == "host":
        return None, "CPU wake-up latency: the host's (--idle-latency-us host)"
    if setting == "auto" and pace > 1.0:
        return None, "CPU wake-up latency: the host's (auto, faster than real time, where holding it measured worse)"
    if setting == "auto":
        try:
            hold = IdleLatencyHold(AUTO_LIMIT_US).open()
        except IdleLatencyRefused as exc:
            return None, f"CPU wake-up latency: the host's (auto could not hold {AUTO_LIMIT_US} µs: {exc.why})"
        return hold, f"{hold.describe()} (auto: idle CPUs poll; --idle-latency-us host leaves the host's)"
    hold = IdleLatencyHold(setting).open()
    return hold, hold.describe()


class IdleLatencyRefused(RigDidNotStart):
    """``--idle-latency-us N`` on a host that does not let this user hold the limit; ``why`` names the file and the
    OS's words (the message alone, so the exception pickles as any other)."""

    why: str = ""

    @classmethod
    def of(cls, limit_us: int, why: str) -> "IdleLatencyRefused":
        exc = cls(f"--idle-latency-us {limit_us}: {why}")
        exc.why = why
        return exc


class IdleLatencyHold:
    """Holds the CPUs' wake-up latency limit at ``limit_us`` from :meth:`open` to :meth:`close`."""

    def __init__(self, limit_us: int, path: Path | None = None) -> None:
        if isinstance(limit_us, bool) or not isinstance(limit_us, int) or not 0 <= limit_us <= MAX_LIMIT_US:
            raise ValueError(f"idle_latency_us={limit_us!r} must be a whole number of µs from 0 to {MAX_LIMIT_US}")
        self.limit_us, self.path = limit_us, CPU_LATENCY_FILE if path is None else path
        self._fd: int | None = None

    def open(self) -> "IdleLatencyHold":
        """Ask the kernel for the limit; IdleLatencyRefused (naming the file and the OS's words) where it is not
        permitted or not there."""
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as exc:
            raise IdleLatencyRefused.of(self.limit_us, f"cannot open {self.path} ({exc.strerror}); it needs root "
                                        "(or write access to that file) on a Linux host") from None
        try:
            os.write(fd, self.limit_us.to_bytes(4, "little", signed=True))
        except OSError as exc:
            os.close(fd)
            raise IdleLatencyRefused.of(self.limit_us, f"{self.path} refused it ({exc.strerror})") from None
        self._fd = fd
        return self

    def __enter__(self) -> "IdleLatencyHold":
        return self.open()

    def __exit__(self, *_exc) -> None:
        self.close()

    def close(self) -> None:
        """Let the limit go (the kernel's default returns once no one holds one)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def describe(self) -> str:
        return f"CPU wake-up latency held at {self.limit_us} µs ({self.path})"


def may_hold(path: Path | None = None) -> bool:
    """Whether this user may write the limit's file (root, or write access to it)."""
    return os.access(CPU_LATENCY_FILE if path is None else path, os.W_OK)


def current_limit_us(path: Path | None = None) -> int:
    """The limit the kernel applies now (the smallest one held; 2000000000 when none is)."""
    fd = os.open(CPU_LATENCY_FILE if path is None else path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        return int.from_bytes(os.read(fd, 4), "little", signed=True)
    finally:
        os.close(fd)
