"""The orchestrator's watch for hung ECU processes: a firmware whose cycle never returns (an endless loop in a law).

Every ECU process says "alive" on stdout while its cycles run (``pacing.Heartbeat``, at most every HEARTBEAT_S
wall seconds). A process that has been silent for ``after_s`` wall seconds while the run goes on is hung: the
watch kills it (SIGKILL, as a hardware watchdog resets a stuck unit) and records an ERROR event per unit it
hosted, ending in ``ECU stopped``, so the ``ecu_failure`` verdict counts it and ``--check`` fails; the plant's
fail-safe holds the units meanwhile, as after a crash. A process stopped on purpose (an injected ``ecu_hang``,
SIGSTOP) is ``held`` and left alone: the fault machinery owns it.
"""
from __future__ import annotations

import subprocess
from typing import Protocol

from ecu_sim.runtime import ECU_STOPPED
from hil.record.runlog import Event
from hil.runtime.realtime.pacing import HEARTBEAT_S

HUNG_AFTER_S = 2.0  # wall seconds of silence that make an ECU process hung (eight heartbeats)
HUNG_AFTER_CYCLES = 20  # ... or this many ECU cycles at a slow pace, whichever is longer


class WatchedNode(Protocol):
    """What the watch reads of an orchestrator's node (``orchestrator.Node``)."""

    name: str  # its units' names, comma-separated
    kind: str
    proc: subprocess.Popen
    ready: bool
    reported: bool  # its end is already on the timeline
    held: bool  # stopped on purpose (an injected hang)
    last_alive: float  # epoch seconds of its last "alive" (or "ready") line


def hung_after_s(cycle_s: float, pace: float) -> float:
    """Wall seconds of silence after which an ECU process counts as hung at this cycle and pace."""
    return max(HUNG_AFTER_S, HUNG_AFTER_CYCLES * cycle_s / pace, 4 * HEARTBEAT_S)


class HangWatch:
    """Kills the ECU processes silent for longer than ``after_s`` since the later of their last line and ``t0``."""

    def __init__(self, after_s: float, t0: float) -> None:
        self.after_s, self.t0 = after_s, t0

    def check(self, nodes: list, now: float, sim_now: float, events: list[Event]) -> None:
        """Stop (kill) every hung ECU process among ``nodes`` at epoch ``now``; its units' events go to ``events``."""
        for n in nodes:
            silent = now - max(n.last_alive, self.t0)
            if self._watched(n) and silent > self.after_s:
                n.reported = True
                n.proc.kill()
                for name in n.name.split(","):
                    events.append(Event(sim_now, "ERROR", "rig",
                                        f"ECU process {name} hung: no cycle ended for {silent:.1f} s (wall), its "
                                        f"law or program does not return; process killed; {ECU_STOPPED}"))

    @staticmethod
    def _watched(n: WatchedNode) -> bool:
        return n.kind == "ecu" and n.ready and not n.reported and not n.held and n.proc.poll() is None
