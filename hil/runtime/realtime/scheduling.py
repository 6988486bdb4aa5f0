"""How the real-time rig's own threads and processes are scheduled: SCHED_FIFO where the host permits it.

A node wakes to a deadline. Under the normal scheduler it then waits behind whatever runs on the core (another
node's cycle, the orchestrator's spooling), and at pace 10 that wait made 0.3-0.7 % of the plant's publications
late. Under SCHED_FIFO a wake-up preempts ordinary work at once. Among the rig's own: the bus serving thread first
(every node's read waits for its SYNC), then the plant and the radio (publications, forwarding), then the ECUs.
The orchestrator's Python (supervision, spool, live view, recording) stays ordinary.

Priorities are low (1-3 of 1-99), below the kernel's interrupt threads (50). SCHED_RESET_ON_FORK: a process the
firmware starts runs under the normal scheduler. A node that never sleeps (firmware in an endless loop) gets at
most the kernel's real-time share of a core (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default), so the
machine and the orchestrator's watchdog still run.

Only what the user may do anyway: root, ``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO`` (``ulimit -r``) of at least 3.
"""
from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass, field
from typing import Callable, Literal

from hil.runtime.errors import RigDidNotStart, os_words
from hil.runtime.realtime.cpu_layout import format_cores, pin

SchedulingMode = Literal["auto", "fifo", "normal"]  # fifo where permitted / fifo or fail / never
SCHEDULING_MODES: tuple[SchedulingMode, ...] = ("auto", "fifo", "normal")
PRIORITIES = {"bus servers": 3, "radio": 2, "plant": 2, "ecu": 1}  # SCHED_FIFO priority by role


class SchedulingRefused(RigDidNotStart):
    """``--scheduling fifo`` on a host that does not permit SCHED_FIFO."""


def set_fifo_priority(priority: int, tid: int = 0, reset_on_fork: bool = True) -> str | None:
    """Run thread ``tid`` (0: the calling thread) under SCHED_FIFO at ``priority`` (1-99); None when done, else why
    not (the OS's words). ``reset_on_fork``: the threads and processes it starts run under the normal scheduler
    (without it they inherit SCHED_FIFO, as a server's serving thread should)."""
    try:  # (AttributeError: a platform without SCHED_FIFO)
        policy = os.SCHED_FIFO | (os.SCHED_RESET_ON_FORK if reset_on_fork else 0)
        os.sched_setscheduler(tid, policy, os.sched_param(priority))
    except (AttributeError, OSError, ValueError) as exc:
        return os_words(exc)
    return None


def current_policy(tid: int = 0) -> Literal["fifo", "normal"]:
    """What the kernel runs thread ``tid`` (0: the calling thread) under: "fifo" or "normal"."""
    try:
        policy = os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK
    except (AttributeError, OSError):
        return "normal"
    return "fifo" if policy == os.SCHED_FIFO else "normal"


@dataclass(frozen=True)
class Scheduling:
    """The policy the rig's nodes run under, and why it is the normal one when it is."""

    policy: Literal["fifo", "normal"]
    why_normal: str = ""
    priorities: dict[str, int] = field(default_factory=lambda: dict(PRIORITIES))

    def describe(self) -> str:
        """One line for the progress output and the run's events."""
        if self.policy == "fifo":
            return "SCHED_FIFO: " + ", ".join(f"{role} {p}" for role, p in self.priorities.items())
        return f"normal scheduler ({self.why_normal})"

    def as_dict(self) -> dict[str, object]:
        """For metrics.json (``realtime.scheduling``)."""
        if self.policy == "fifo":
            return {"policy": "fifo", "priorities": dict(self.priorities)}
        return {"policy": "normal", "why": self.why_normal}


def choose_scheduling(mode: SchedulingMode, serving_tid: int | None) -> Scheduling:
    """Put the serving thread (``serving_tid``; None on SocketCAN, where there is none: a probe thread tries
    instead) under SCHED_FIFO unless ``mode`` is "normal", and decide the nodes' policy from the outcome.
    "fifo" on a host that refuses raises :class:`SchedulingRefused`; "auto" falls back to the normal scheduler."""
    priority = PRIORITIES["bus servers"]
    return _decide(mode, priority, lambda: set_fifo_priority(priority, serving_tid) if serving_tid is not None
                   else _probe(priority))


def choose_server_scheduling(mode: SchedulingMode, priority: int = PRIORITIES["bus servers"]) -> Scheduling:
    """A standalone bus server's (``hil bus-server``): the calling thread under SCHED_FIFO at ``priority`` unless
    ``mode`` is "normal", inherited by the serving thread it starts next; refusals as ``choose_scheduling``."""
    return _decide(mode, priority, lambda: set_fifo_priority(priority, reset_on_fork=False),
                   {"bus server": priority})


def _decide(mode: SchedulingMode, priority: int, try_fifo: Callable[[], str | None],
            priorities: dict[str, int] | None = None) -> Scheduling:
    """The policy ``mode`` gives where ``try_fifo()`` (None: done, else why not) is the host's answer."""
    if mode not in SCHEDULING_MODES:
        raise ValueError(f"scheduling={mode!r} must be one of {', '.join(SCHEDULING_MODES)}")
    if mode == "normal":
        return Scheduling("normal", "asked for: --scheduling normal")
    why = try_fifo()
    if why is None:
        return Scheduling("fifo", priorities=priorities or dict(PRIORITIES))
    if mode == "fifo":
        raise SchedulingRefused(f"--scheduling fifo: SCHED_FIFO is not permitted here ({why}); run as root, give "
                                f"python CAP_SYS_NICE, or raise RLIMIT_RTPRIO (ulimit -r {priority}); or use "
                                "--scheduling auto")
    return Scheduling("normal", f"SCHED_FIFO not permitted here: {why}")


def _probe(priority: int) -> str | None:
    """Whether this process may use SCHED_FIFO at ``priority``: tried on a short-lived thread of its own."""
    outcome: list[str | None] = []
    probe = threading.Thread(target=lambda: outcome.append(set_fifo_priority(priority)), name="fifo probe")
    probe.start()
    probe.join()
    return outcome[0] if outcome else "the probe thread failed"


def enter_role(role: str, fifo: bool, cpus: tuple[int, ...] | None = None) -> Literal["fifo", "normal"]:
    """A node's first step: under SCHED_FIFO at its role's priority when the orchestrator says so (``fifo``), on
    the cores it names (``cpus``, hil/runtime/realtime/cpu_layout.py). Returns the policy it runs under; a refusal
    is said on stderr and the node goes on under the normal scheduler, or anywhere."""
    if fifo and (why := set_fifo_priority(PRIORITIES[role])) is not None:
        print(f"{role} node: SCHED_FIFO refused ({why}); running under the normal scheduler", file=sys.stderr)
    if cpus is not None and (why := pin(cpus)) is not None:
        print(f"{role} node: cannot run on cores {format_cores(cpus)} ({why}); running anywhere", file=sys.stderr)
    return current_policy()


__all__ = ["PRIORITIES", "SCHEDULING_MODES", "Scheduling", "SchedulingMode", "SchedulingRefused", "choose_scheduling",
           "choose_server_scheduling", "current_policy", "enter_role", "set_fifo_priority"]
