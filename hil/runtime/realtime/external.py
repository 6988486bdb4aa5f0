"""External units, the device-under-test slot: when each joined, when it went missing, and its command timing.

A unit named in ``ecu.external`` gets no emulated ECU: a program or board outside the rig sends its frames (any
python-can program on the emulated bus, or a device on SocketCAN). The plant judges its TractionCmd frames like
any other's (length, E2E CRC, mode) and its fail-safe holds the unit until valid ones come. :class:`ExternalWatch`
lives in the plant node and sees every valid command with its bus timestamp (the end of its transmission), so
the period and jitter it reports are those seen on the bus. The orchestrator's side: on the emulated buses
:func:`wait_for_connections` holds simulated t = 0 back until each external unit's bus has a client of its own
(so a program started after the rig, and slow to import, is not braked by the plant's fail-safe at the start);
:class:`JoinWait` then ends the run when a unit has sent nothing valid within ``ecu.join_timeout_s`` of the rig
being ready.
"""
from __future__ import annotations

import math
import queue
import time
from array import array
from typing import Callable, Sequence

import numpy as np

from hil.scenario.layout import TrainLayout
from hil.record.runlog import Event
from hil.runtime.realtime.bus_server import BusServer

JOIN_LINE = "joined"  # the plant node's stdout line "joined <flat unit> <sim t>" when an external unit joins
CONNECT_POLL_S = 0.01  # wall seconds between two looks at the buses while waiting for the external units' clients


class ExternalUnitMissing(RuntimeError):
    """An external unit sent no valid command within the join timeout (the run's files are written first)."""


class ExternalWatch:
    """Valid-command arrivals of the external units: join, gaps (missing), period and jitter."""

    def __init__(self, layout: TrainLayout, units: list[int], missing_after_s: float) -> None:
        self.layout = layout
        self.missing_after_s = missing_after_s  # a gap longer than this (the plant's fail-safe hold) is "missing"
        self.arrivals = {u: array("d") for u in units}

    def command(self, u: int, t: float) -> bool:
        """Record a valid command of unit u at sim time t; True if it is the unit's first (it just joined)."""
        times = self.arrivals.get(u)
        if times is None:
            return False
        times.append(t)
        return len(times) == 1

    def events(self, end_s: float) -> list[Event]:
        """Joined, missing (each gap longer than ``missing_after_s``, and a silence up to the end) and never joined."""
        out = []
        for u, times in self.arrivals.items():
            who = f"{self.layout.unit_name(u)} (external)"
            if not times:
                out.append(Event(end_s, "ERROR", "rig", f"{who} never sent a valid TractionCmd"))
                continue
            t = np.frombuffer(times, dtype=float)
            out.append(Event(float(t[0]), "INFO", "rig", f"{who} joined: first valid TractionCmd at t = {t[0]:.3f} s"))
            for a, b in _gaps(t, end_s, self.missing_after_s):
                text = f"missing from t = {a:.3f} s to {b:.3f} s ({b - a:.3f} s without a valid TractionCmd)" \
                    if b < end_s else f"missing from t = {a:.3f} s to the end ({end_s - a:.3f} s)"
                out.append(Event(a, "WARN", "rig", f"{who} {text}"))
        return out

    def report(self, end_s: float) -> dict[str, dict]:
        """Per external unit: joined_s, commands, period mean/p50/p99/max, jitter (std), missing intervals."""
        return {self.layout.unit_name(u): _timing(np.frombuffer(times, dtype=float), end_s, self.missing_after_s)
                for u, times in self.arrivals.items()}


def _gaps(t: np.ndarray, end_s: float, longer_than: float) -> list[tuple[float, float]]:
    """(last command before, next command) of every gap longer than ``longer_than``, and a final silence."""
    edges = np.append(t, end_s)
    d = np.diff(edges)
    return [(float(edges[i]), float(edges[i + 1])) for i in np.flatnonzero(d > longer_than)]


def _timing(t: np.ndarray, end_s: float, missing_after_s: float) -> dict:
    if not t.size:
        return {"joined_s": None, "commands": 0, "missing": [{"from_s": 0.0, "to_s": end_s}]}
    d = np.diff(t) * 1e3
    stats = {"period_mean_ms": float(d.mean()), "period_p50_ms": float(np.percentile(d, 50)),
             "period_p99_ms": float(np.percentile(d, 99)), "period_max_ms": float(d.max()),
             "jitter_std_ms": float(d.std())} if d.size else {}
    missing = [{"from_s": a, "to_s": b} for a, b in _gaps(t, end_s, missing_after_s)]
    return {"joined_s": float(t[0]), "commands": int(t.size), **stats, "missing": missing}


def wait_for_connections(servers: Sequence[BusServer], layout: TrainLayout, units: list[int], rig_eager: int,
                         deadline: float, stopped: Callable[[], bool], say=None) -> list[int]:
    """Wait, before simulated t = 0, until the bus of each external unit has a client beyond the rig's own
    ``rig_eager`` eager ones (its radio node, if any): a python-can program or device takes its frames as they
    end, while the rig's nodes read lazily. Ends at ``deadline`` (wall, ``time.time()``) or when ``stopped()``.
    Returns the units whose bus still has none. A logger connected first counts too: the server cannot tell."""
    buses = sorted({layout.train_unit(u)[0] for u in units})
    if say is not None:
        say(f"ready; simulated t = 0 waits up to {max(deadline - time.time(), 0.0):.0f} s for a client on "
            f"{', '.join(f'bus{b + 1}' for b in buses)} (the external unit(s))")
    while True:
        pending = [b for b in buses if servers[b].stats.eager_clients <= rig_eager]
        if not pending or stopped() or time.time() >= deadline:
            break
        time.sleep(CONNECT_POLL_S)
    missing = [u for u in units if layout.train_unit(u)[0] in pending]
    if say is not None:
        names = ", ".join(layout.unit_name(u) for u in (missing or units))
        say(f"nothing connected to the bus of external unit(s) {names} in time: starting without"
            if missing else f"a client connected to the bus of external unit(s) {names}: starting")
    return missing


class JoinWait:
    """The orchestrator waits up to ``timeout_s`` wall seconds from ``started`` (the rig ready, before any wait for
    connections) for each external unit's first valid command, reported by the plant node on its stdout."""

    def __init__(self, layout: TrainLayout, units: list[int], timeout_s: float, lines: "queue.Queue[str]",
                 started: float, say=None) -> None:
        self.layout, self.timeout_s, self.lines, self.say = layout, timeout_s, lines, say
        self.deadline = started + timeout_s
        self.waiting = set(units)
        self.joined: dict[int, float] = {}

    def poll(self, now: float) -> str | None:
        """Take the plant's join lines; the reason to stop the run if the timeout passed (``now``: wall,
        ``time.time()``) with units missing."""
        while True:
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                break
            parts = line.split()
            if len(parts) == 3 and parts[0] == JOIN_LINE:
                u, t = int(parts[1]), float(parts[2])
                self.waiting.discard(u)
                self.joined[u] = t
                if self.say is not None:
                    self.say(f"external unit {self.layout.unit_name(u)} joined at t = {t:.3f} s")
        if self.waiting and now > self.deadline:
            return self.missing(f"within ecu.join_timeout_s = {self.timeout_s:g} s of the rig being ready")
        return None

    def missing(self, when: str = "during the run") -> str:
        """Which units never joined, and when they were expected."""
        names = ", ".join(self.layout.unit_name(u) for u in sorted(self.waiting))
        return f"external unit {names} sent no valid TractionCmd {when}"


def missing_after_s(sc) -> float:
    """A gap in an external unit's commands longer than the plant's fail-safe hold counts as missing."""
    hold = sc.plant.failsafe.hold_s
    return float(hold) if math.isfinite(hold) and hold > 0 else 3 * sc.ecu.cycle_s
