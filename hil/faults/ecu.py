"""ECU faults in virtual time: crash, hang, restart, and the restart policy (``ecu.restart_after_s``, a watchdog).

* crash: the firmware stops dead and its CAN node leaves the bus (queued frames are lost, nothing is received),
  as when the real-time rig kills the ECU's process. It comes back after the fault's ``duration_s``; without
  one, after ``ecu.restart_after_s`` if set, else never.
* hang: the firmware stops running its cycle but its node stays on the bus and keeps receiving. At the hang's
  end it resumes where it stopped (stale state, a jump in every alive counter it reads); a watchdog
  (``ecu.restart_after_s``) shorter than the hang restarts it instead.
* restart: ``Ecu.restart()`` (controller memory, mailboxes and E2E sequence state cleared) and, after a crash,
  a new CAN node with fresh error counters. An ECU stopped by its own controller (an exception or a NaN) is
  restarted by the watchdog the same way.
"""
from __future__ import annotations

from collections.abc import Callable

from hil.runtime.kernel import to_ns

EventFn = Callable[[float, str, str, str], None]  # (t, level, source, text)


class EcuFaults:
    def __init__(self, rig, restart_after_s: float | None, event: EventFn) -> None:
        self.rig = rig
        self.restart_after_s = restart_after_s
        self.event = event
        self.down: dict[int, str] = {}  # unit -> "crash" | "hang" | "error"
        self.restarts = 0
        if restart_after_s is not None:
            for u, ecu in enumerate(rig.ecus):
                ecu.monitors.append(lambda ecu, t, u=u: self._watch(u, ecu, t))

    def unit(self, spec) -> int:
        return self.rig.layout.index(spec.train - 1, spec.unit - 1)

    def _later(self, t: float, fn, arg) -> None:
        self.rig.kernel.at(to_ns(t), fn, arg)

    # ---- faults
    def crash(self, spec, t: float) -> None:
        u = self.unit(spec)
        rig = self.rig
        rig.ecus[u].alive = False
        rig.disconnect_ecu(u)
        self.down[u] = "crash"
        if spec.duration_s is None and self.restart_after_s is not None:
            self._later(t + self.restart_after_s, self._restart_event, (u, "crash", "watchdog"))

    def hang(self, spec, t: float) -> None:
        u = self.unit(spec)
        self.rig.ecus[u].alive = False
        self.down[u] = "hang"
        w = self.restart_after_s
        if w is not None and (spec.duration_s is None or w < spec.duration_s):
            self._later(t + w, self._restart_event, (u, "hang", "watchdog"))

    def end(self, spec, t: float) -> None:
        u = self.unit(spec)
        why = self.down.get(u)
        if spec.kind == "ecu_crash" and why == "crash":
            self.restart(u, t, "the crash ended")
        elif spec.kind == "ecu_hang" and why == "hang":
            del self.down[u]
            self.rig.ecus[u].alive = True
            self.event(t, "INFO", self.rig.ecus[u].name, "resumed after the hang (no reset)")

    # ---- restarts
    def _watch(self, u: int, ecu, t: float) -> None:
        """Monitor: the controller stopped the ECU (exception, NaN): the watchdog restarts it later."""
        if not ecu.alive and u not in self.down:
            self.down[u] = "error"
            self._later(t + self.restart_after_s, self._restart_event, (u, "error", "watchdog"))

    def _restart_event(self, item: tuple[int, str, str]) -> None:
        u, why, by = item
        if self.down.get(u) == why:
            self.restart(u, self.rig.kernel.now * 1e-9, by)

    def restart(self, u: int, t: float, by: str) -> None:
        rig = self.rig
        ecu = rig.ecus[u]
        why = self.down.pop(u, "?")
        ecu.restart()
        if why == "crash":
            rig.reconnect_ecu(u)
        self.restarts += 1
        self.event(t, "INFO", ecu.name, f"restarted with a reset controller ({by}, after {'a' if why != 'error' else 'a controller'} "
                                        f"{'crash' if why == 'crash' else 'hang' if why == 'hang' else 'error'})")
