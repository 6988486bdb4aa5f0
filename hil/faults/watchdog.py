"""The ECU watchdog (``ecu.restart_after_s``): which stopped unit is restarted, and when, in both runtimes.

One policy, three callers: the virtual rig (``hil.runtime.ecu_faults``, on kernel timers), the real-time orchestrator
(``hil.runtime.realtime.faults``, crashed and hung ECU processes, polled) and a real-time ECU process (controller errors,
polled once per cycle). Each restarts a unit its own way; this decides only whether and when:

* a crash without a ``duration_s``, and a controller error (an exception or a NaN), are restarted after
  ``restart_after_s``; a crash with a duration comes back when it ends, not before;
* a hang is restarted (reset) after ``restart_after_s`` if that is shorter than the hang, else it resumes.
"""
from __future__ import annotations

import heapq

from ecu_sim.runtime import RESTARTED

WHY = ("crash", "hang", "error")
_AFTER = {"crash": "a crash", "hang": "a hang", "error": "a controller error"}


def restart_text(by: str, why: str | None) -> str:
    """The timeline's words for a restart: ``by`` what (the watchdog, the crash's end), after what."""
    return f"{RESTARTED} ({by}, after {_AFTER.get(why or '', 'a stop')})"


class Watchdog:
    """The units that are down, why, and the restarts due (``restart_after_s`` None: no watchdog, none are)."""

    def __init__(self, restart_after_s: float | None) -> None:
        self.restart_after_s = restart_after_s
        self.down: dict[int, str] = {}  # unit -> "crash" | "hang" | "error"
        self._due: list[tuple[float, int, str]] = []  # (time, unit, why), a heap

    def stopped(self, unit: int, why: str, t: float, lasts_s: float | None = None) -> float | None:
        """``unit`` stopped at ``t`` (``why`` in WHY; a fault lasting ``lasts_s``, None: until restarted).

        Returns when the watchdog restarts it, None if it does not (no watchdog, or the fault ends first)."""
        if why not in WHY:
            raise ValueError(f"watchdog: unknown reason {why!r} (expected one of {', '.join(WHY)})")
        self.down[unit] = why
        w = self.restart_after_s
        if w is None or not (lasts_s is None or (why == "hang" and w < lasts_s)):
            return None
        heapq.heappush(self._due, (t + w, unit, why))
        return t + w

    def due(self, t: float) -> list[tuple[int, str]]:
        """The (unit, why) whose restart is due by ``t`` and that are still down for that reason; each is up
        again from here (the caller restarts it)."""
        out = []
        while self._due and self._due[0][0] <= t:
            _, unit, why = heapq.heappop(self._due)
            if self.down.get(unit) == why:
                del self.down[unit]
                out.append((unit, why))
        return out

    def up(self, unit: int) -> str | None:
        """``unit`` runs again (restarted or resumed by its fault's end): why it was down (None: it was not)."""
        return self.down.pop(unit, None)

    def is_down(self, unit: int, why: str | None = None) -> bool:
        """Whether ``unit`` is down (for ``why``, if given)."""
        return unit in self.down if why is None else self.down.get(unit) == why
