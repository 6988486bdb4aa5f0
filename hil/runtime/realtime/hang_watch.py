"""The orchestrator's watch for hung node processes: an ECU whose cycle never returns (an endless loop in a law), a
plant whose step never returns (a model stuck in its solver).

The ECU and plant processes say "alive" on stdout while their events run (``pacing.Heartbeat``, at most every
HEARTBEAT_S wall seconds). One silent for ``after_s`` wall seconds while the run goes on is hung, and the watch
kills it (SIGKILL, as a hardware watchdog resets a stuck unit):

* an ECU process: an ERROR event per unit it hosted, ending in ``ECU stopped``, so the ``ecu_failure`` verdict
  counts it and ``--check`` fails; the run goes on, the plant's fail-safe holding the units, as after a crash;
* the plant: an ERROR event, and the run stops there (nothing closes the loop any more), as when it dies.

A process stopped on purpose (an injected ``ecu_hang``, SIGSTOP) is ``held`` and left alone: the fault machinery
owns it.
"""
from __future__ import annotations

import subprocess
from collections.abc import Sequence
from typing import Protocol

from ecu_sim.runtime import ECU_STOPPED
from hil.record.runlog import Event
from hil.runtime.realtime.pacing import HEARTBEAT_S

HUNG_AFTER_S = 2.0  # wall seconds of silence that make a node hung (four heartbeats)
HUNG_AFTER_PERIODS = 20  # ... or this many of its periods at a slow pace, whichever is longer
WATCHED_KINDS = ("ecu", "plant")


class WatchedNode(Protocol):
    """What the watch reads of an orchestrator's node (``orchestrator.Node``)."""

    name: str  # an ECU process: its units' names, comma-separated
    kind: str
    proc: subprocess.Popen
    ready: bool
    reported: bool  # its end is already on the timeline
    held: bool  # stopped on purpose (an injected hang)
    last_alive: float  # epoch seconds of its last "alive" (or "ready") line


def hung_after_s(period_s: float, pace: float) -> float:
    """Wall seconds of silence after which a node whose events come every ``period_s`` (simulated) is hung."""
    return max(HUNG_AFTER_S, HUNG_AFTER_PERIODS * period_s / pace, 4 * HEARTBEAT_S)


class HangWatch:
    """Kills the ECU and plant processes silent for longer than ``after_s`` since the later of their last line
    and ``t0``."""

    def __init__(self, after_s: float, t0: float) -> None:
        self.after_s, self.t0 = after_s, t0

    def check(self, nodes: Sequence[WatchedNode], now: float, sim_now: float, events: list[Event]) -> str | None:
        """Stop (kill) every hung process among ``nodes`` at epoch ``now``, its events to ``events``; returns why
        the run must stop (the plant hung), else None."""
        stop = None
        for n in nodes:
            silent = now - max(n.last_alive, self.t0)
            if not self._watched(n) or silent <= self.after_s:
                continue
            n.reported = True
            n.proc.kill()
            if n.kind == "ecu":
                for name in n.name.split(","):
                    events.append(Event(sim_now, "ERROR", "rig",
                                        f"ECU process {name} hung: no cycle ended for {silent:.1f} s (wall), its "
                                        f"law or program does not return; process killed; {ECU_STOPPED}"))
            else:
                stop = f"{n.kind} node hung: no step ended for {silent:.1f} s (wall)"
                events.append(Event(sim_now, "ERROR", "rig", f"{n.kind} process hung: no step ended for "
                                                             f"{silent:.1f} s (wall), its model does not return; "
                                                             "process killed; run stopped"))
        return stop

    @staticmethod
    def _watched(n: WatchedNode) -> bool:
        return n.kind in WATCHED_KINDS and n.ready and not n.reported and not n.held and n.proc.poll() is None
