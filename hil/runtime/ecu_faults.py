"""ECU faults in virtual time: crash, hang, restart, and the restart policy (``ecu.restart_after_s``, a watchdog).

* crash: the firmware stops dead and its CAN node leaves the bus (queued frames are lost, nothing is received),
  as when the real-time rig kills the ECU's process. It comes back after the fault's ``duration_s``; without
  one, after ``ecu.restart_after_s`` if set, else never.
* hang: the firmware stops running its cycle but its node stays on the bus and keeps receiving. At the hang's
  end it resumes where it stopped (stale state, a jump in every alive counter it reads); a watchdog
  (``ecu.restart_after_s``) shorter than the hang restarts it instead.
* restart: ``Ecu.restart()`` (controller memory, mailboxes and E2E sequence state cleared) and, after a crash,
  a new CAN node with fresh error counters. An ECU stopped by its own controller (an exception or a NaN) is
  restarted by the watchdog the same way. When a stopped ECU restarts is ``hil.faults.watchdog``'s to say (the same
  policy as the real-time rig's).
"""
from __future__ import annotations

from collections.abc import Callable

from hil.faults.watchdog import Watchdog, restart_text
from hil.runtime.kernel import to_ns

EventFn = Callable[[float, str, str, str], None]  # (t, level, source, text)


class EcuFaults:
    """Crash, hang and restart of the virtual rig's ECUs; ``watchdog`` decides when a stopped one restarts."""

    def __init__(self, rig, restart_after_s: float | None, event: EventFn) -> None:
        self.rig = rig
        self.watchdog = Watchdog(restart_after_s)
        self.event = event
        self.restarts = 0
        if restart_after_s is not None:
            for u, ecu in enumerate(rig.ecus):
                ecu.monitors.append(lambda ecu, t, u=u: self._watch(u, ecu, t))

    def unit(self, spec) -> int:
        return self.rig.layout.index(spec.train - 1, spec.unit - 1)

    def _stopped(self, u: int, why: str, t: float, lasts_s: float | None = None) -> None:
        """Tell the watchdog; if it will restart the unit, set a kernel timer for then."""
        at = self.watchdog.stopped(u, why, t, lasts_s)
        if at is not None:
            self.rig.kernel.at(to_ns(at), self._watchdog_fires, at)

    # ---- faults
    def crash(self, spec, t: float) -> None:
        u = self.unit(spec)
        self.rig.ecus[u].alive = False
        self.rig.disconnect_ecu(u)
        self._stopped(u, "crash", t, spec.duration_s)

    def hang(self, spec, t: float) -> None:
        u = self.unit(spec)
        self.rig.ecus[u].alive = False
        self._stopped(u, "hang", t, spec.duration_s)

    def end(self, spec, t: float) -> None:
        u = self.unit(spec)
        if spec.kind == "ecu_crash" and self.watchdog.is_down(u, "crash"):
            self.restart(u, t, "the crash ended", self.watchdog.up(u))
        elif spec.kind == "ecu_hang" and self.watchdog.is_down(u, "hang"):
            self.watchdog.up(u)
            self.rig.ecus[u].alive = True
            self.event(t, "INFO", self.rig.ecus[u].name, "resumed after the hang (no reset)")

    # ---- restarts
    def _watch(self, u: int, ecu, t: float) -> None:
        """Monitor: the controller stopped the ECU (exception, NaN): the watchdog restarts it later."""
        if not ecu.alive and not self.watchdog.is_down(u):
            self._stopped(u, "error", t)

    def _watchdog_fires(self, at: float) -> None:
        for u, why in self.watchdog.due(at):
            self.restart(u, self.rig.kernel.now * 1e-9, "watchdog", why)

    def restart(self, u: int, t: float, by: str, why: str | None) -> None:
        """Restart unit ``u`` (down for ``why``) with a reset controller; after a crash, on a new CAN node."""
        ecu = self.rig.ecus[u]
        ecu.restart()
        if why == "crash":
            self.rig.reconnect_ecu(u)
        self.restarts += 1
        self.event(t, "INFO", ecu.name, restart_text(by, why))
