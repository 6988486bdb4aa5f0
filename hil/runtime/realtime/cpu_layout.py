"""Which cores the real-time rig's work runs on (``hil run --realtime --cpu-layout``): the ECU processes on their own.

An ECU process sleeps between its units' cycles and wakes with its caches cold: what ran on its core meanwhile (the
bus serving thread, the plant's integration) has pushed its interpreter and its firmware's objects out. Kept on a
core of their own, the ECU processes find more of it still there. The bus serving thread and the plant, which work
with each other at every publication, share the first core the rig may use; the ECU processes get the others.

"auto" (the default) does this at pace 1 or slower where the rig may use two cores or more (the orchestrator's
affinity mask, so a container's or ``taskset``'s limits are kept); "none" leaves every placement to the kernel.
Faster than real time it does not: at pace 10 seed000's three ECU processes (one per train) queued behind each other
on their one core (ECU misses 72 and 49 against 41 and 4 in two alternated pairs, docs/realtime-performance.md, "CPU
layout"). The orchestrator's own Python (supervision, spooling, recording) is not pinned. Each node pins itself as
its first step (``pin``, from the cores the orchestrator names in its arguments), so the threads it starts after
follow it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

from hil.runtime.errors import os_words

CpuLayoutMode = Literal["auto", "none"]
CPU_LAYOUT_MODES: tuple[CpuLayoutMode, ...] = ("auto", "none")


@dataclass(frozen=True)
class CpuLayout:
    """The cores of the rig's own work (serving thread, plant, radio node) and of its ECU processes."""

    rig: tuple[int, ...]
    ecus: tuple[int, ...]

    def cores_for(self, role: str) -> tuple[int, ...]:
        """The cores a node of ``role`` ("ecu", "plant", "radio") runs on."""
        return self.ecus if role == "ecu" else self.rig

    def describe(self) -> str:
        """One line for the progress output and the run's events."""
        return f"CPU layout: bus servers and plant on {format_cores(self.rig)}, ECU processes on {format_cores(self.ecus)}"

    def as_dict(self) -> dict[str, list[int]]:
        """For metrics.json (``realtime.cpu_layout``)."""
        return {"rig": list(self.rig), "ecus": list(self.ecus)}


def choose_cpu_layout(mode: CpuLayoutMode, allowed: set[int] | None = None, pace: float = 1.0) -> CpuLayout | None:
    """The layout ``mode`` gives on the cores the rig may use (``allowed``, default this process's affinity mask) at
    ``pace``; None where the kernel places everything ("none", fewer than two cores, or faster than real time)."""
    if mode not in CPU_LAYOUT_MODES:
        raise ValueError(f"cpu_layout={mode!r} must be one of {', '.join(CPU_LAYOUT_MODES)}")
    cores = sorted(allowed if allowed is not None else os.sched_getaffinity(0))
    if mode == "none" or len(cores) < 2 or pace > 1.0:
        return None
    return CpuLayout(rig=(cores[0],), ecus=tuple(cores[1:]))


def pin(cores: tuple[int, ...], tid: int = 0) -> str | None:
    """Run thread ``tid`` (0: the calling one; the threads it starts after inherit it) on ``cores``; None when done,
    else why not (the OS's words)."""
    try:
        os.sched_setaffinity(tid, cores)
    except (AttributeError, OSError, ValueError) as exc:
        return os_words(exc)
    return None


def format_cores(cores: tuple[int, ...]) -> str:
    """Cores as a node argument and for people: "1", "1,2,3"."""
    return ",".join(str(c) for c in cores)


def parse_cores(text: str) -> tuple[int, ...]:
    """A node's ``--cpus`` argument: "1" or "1,2,3" (argparse type; a bad one is a usage error)."""
    try:
        cores = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"{text!r}: cores are integers separated by commas") from None
    if not cores or min(cores) < 0:
        raise ValueError(f"{text!r}: cores are integers >= 0")
    return cores


__all__ = ["CPU_LAYOUT_MODES", "CpuLayout", "CpuLayoutMode", "choose_cpu_layout", "format_cores", "parse_cores", "pin"]
