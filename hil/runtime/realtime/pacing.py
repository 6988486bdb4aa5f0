"""Wall-clock pacing of the real-time nodes: the shared simulated-time mapping, deadline waits, lateness statistics.

Every process of a rig maps wall time to simulated time the same way: ``sim_t = (wall_epoch - T0) * pace``, with
``T0`` chosen by the orchestrator once every node is ready. Frame timestamps from the bus servers (epoch seconds
of the end of transmission) convert with the same mapping. Waits sleep to absolute deadlines with the timer
slack at 1 ns (measured when the rig was designed: asyncio-style sleeps are 0.3-2 ms late); only the plant spins, for the last
``spin_s`` before a deadline, so at most one process per rig burns a core.
"""
from __future__ import annotations

import ctypes
import gc
import math
import select
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hil.runtime.realtime.protocol import TURN_HOLD_MAX_S
from hil.runtime.realtime.streamed_series import StreamedSeries, series_table

__all__ = ["SimClock", "LatenessStats", "StopFlag", "Heartbeat", "drain", "freeze_setup_heap", "handshake", "linger",
           "wait_until", "set_timer_slack"]
PR_SET_TIMERSLACK = 29
ALIVE_LINE = "alive"  # a node's stdout line while its event loop turns (the orchestrator's hang watch)
HEARTBEAT_S = 0.5  # wall seconds between two of them at most (each wakes a reader thread of the orchestrator)


def set_timer_slack(ns: int = 1) -> bool:
    """prctl(PR_SET_TIMERSLACK) for the calling thread so sleeps end on time; False where unavailable."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class SimClock:
    """sim_t = (wall_epoch - t0_epoch) * pace, read through the monotonic clock (immune to clock steps)."""

    def __init__(self, t0_epoch: float, pace: float = 1.0) -> None:
        if not (math.isfinite(pace) and pace > 0):
            raise ValueError(f"pace={pace!r} must be a positive number")
        self.t0 = float(t0_epoch)
        self.pace = float(pace)
        self._mono0 = time.monotonic() - (time.time() - self.t0)  # monotonic instant of sim t = 0

    def now(self) -> float:
        """Simulated seconds now."""
        return (time.monotonic() - self._mono0) * self.pace

    def from_epoch(self, stamp: float) -> float:
        """A bus timestamp (epoch s) in simulated seconds."""
        return (stamp - self.t0) * self.pace

    def wall_until(self, sim_t: float) -> float:
        """Wall seconds from now until simulated time ``sim_t`` (negative once passed)."""
        return (sim_t - self.now()) / self.pace


def periods_overrun(late: float, period: float) -> int:
    """The whole periods a cycle ``late`` overran: 0 unless it is more than a period late (a deadline miss, whose
    overrun cycles are skipped). The ECUs' and the plant's rule, in any unit."""
    return int(late // period) if late > period else 0


def turn_waited(turns: bool, late_s: float, pace: float) -> bool:
    """Whether a node's buses still waited for its turn when it acts ``late_s`` simulated seconds after the turn's
    instant: with turns, up to TURN_HOLD_MAX_S of wall time. Such a cycle or publication skips none after it, however
    late: those still find the bus at their instants. The ECUs' and the plant's rule."""
    return turns and late_s <= TURN_HOLD_MAX_S * pace


class LatenessStats:
    """Per-cycle lateness (actual start - deadline, wall seconds) and deadline misses of one periodic task.

    A miss is a cycle that starts after the next cycle's deadline (lateness > one period). The rows (deadline in
    simulated seconds, lateness) go to ``path`` as they come (``StreamedSeries``; kept in memory without one)."""

    def __init__(self, period_s: float, pace: float, path: Path | None = None) -> None:
        self.period_sim_s = period_s
        self.pace = pace
        self.series = StreamedSeries(path)
        self.misses = 0
        self.skipped = 0  # cycles not run at all because the task was more than a period late

    def add(self, lateness_sim_s: float, deadline: float = math.nan) -> int:
        """Record one cycle's lateness (given in simulated seconds); returns how many whole periods it overran."""
        self.series.add(deadline, lateness_sim_s / self.pace)
        overrun = periods_overrun(lateness_sim_s, self.period_sim_s)
        if overrun:
            self.misses += 1
        return overrun

    def table(self) -> np.ndarray:
        """(n, 2): deadline (simulated s), lateness (wall s) per cycle, for a task without a file."""
        return series_table(self.series)

    def summary(self) -> dict[str, float | int | None]:
        s = self.series
        return {"cycles": s.n, "lateness_p50_s": s.percentile(50), "lateness_p99_s": s.percentile(99),
                "lateness_max_s": s.max if s.n else None, "deadline_misses": self.misses,
                "cycles_skipped": self.skipped}


class StopFlag:
    """Set by "stop" (or EOF) on stdin, SIGTERM, or the node itself; SIGINT is ignored (the orchestrator owns
    Ctrl-C and tells every node to stop)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.on_line: Callable[[str], None] | None = None  # other stdin lines (fault commands, hil/faults)
        signal.signal(signal.SIGTERM, lambda *_: self.event.set())
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch_stdin(self) -> None:
        """Read further stdin lines in a daemon thread: "stop" or EOF sets the flag; others go to ``on_line``."""
        def reader() -> None:
            for line in sys.stdin:
                if line.strip() == "stop":
                    break
                if self.on_line is not None:
                    self.on_line(line.strip())
            self.event.set()

        threading.Thread(target=reader, name="stdin-watch", daemon=True).start()

    def __bool__(self) -> bool:
        return self.event.is_set()


class Heartbeat:
    """Says "alive" on stdout at most every ``every_s`` wall seconds when called from a node's event loop: a node
    whose loop stops turning (a law that never returns) falls silent, and the orchestrator stops it as hung.
    Written to the process's own stdout (``sys.__stdout__``), so a law that redirects ``sys.stdout`` to silence
    itself does not silence the heartbeat."""

    def __init__(self, every_s: float = HEARTBEAT_S) -> None:
        self.every_s = every_s
        self._next = 0.0

    def __call__(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.every_s
            try:
                print(ALIVE_LINE, file=sys.__stdout__, flush=True)
            except (OSError, ValueError):  # the orchestrator is gone (the stdin watch stops us) or stdout closed
                pass


def freeze_setup_heap() -> None:
    """Leave the objects a node made while setting up (modules, the DBC, the firmware) out of every later garbage
    collection, so a collection during the run walks only the objects of the run. A node's heap is cold in the
    cache after each sleep, so a full walk of it is dear: measured on seed000 (bench_realtime_scale.py, 2 cores),
    ECU processes -35 % CPU, the plant -25 %. Virtual time, one process with a warm heap, gains nothing."""
    gc.collect()
    gc.freeze()


def handshake(stop: StopFlag) -> float:
    """Print "ready", wait for "go <T0 epoch>" on stdin, return T0 (exit quietly on "stop" or EOF). The node's
    set-up is over: its heap is frozen first (``freeze_setup_heap``)."""
    freeze_setup_heap()
    print("ready", flush=True)
    while True:
        line = sys.stdin.readline()
        if not line or line.strip() == "stop":
            raise SystemExit(0)
        parts = line.split()
        if len(parts) == 2 and parts[0] == "go":
            stop.watch_stdin()
            return float(parts[1])


def linger(clock: SimClock, sim_s: float = 0.02, max_wall_s: float = 0.2) -> None:
    """Stay connected a little after the last send so frames still queued on the bus go out (a node that
    disconnects drops its TX queue, which the server counts as lost frames)."""
    time.sleep(min(sim_s / clock.pace, max_wall_s))


def drain(buses: Sequence, on_msg: Callable[[int, Any], None], timeout_s: float) -> None:
    """Wait up to ``timeout_s`` wall seconds for any bus to have a frame, then hand every waiting frame to
    ``on_msg(bus_index, msg)`` (bus_index is the position in ``buses``)."""
    ready = select.select(buses, [], [], max(timeout_s, 0.0))[0]  # one syscall, also when polling (timeout 0)
    for b in ready:
        i = buses.index(b)
        while (msg := b.recv(0)) is not None:
            on_msg(i, msg)


def wait_until(clock: SimClock, sim_t: float, buses: Sequence, on_msg: Callable[[int, Any], None],
               spin_s: float = 0.0, max_wait_s: float = 0.05) -> None:
    """Receive frames until simulated time ``sim_t``: select-sleep to ``spin_s`` before it, then poll (spin).

    Sleeps are at most ``max_wait_s`` each so a stop request is noticed."""
    while True:
        rem = clock.wall_until(sim_t)
        if rem <= spin_s:
            break
        drain(buses, on_msg, min(rem - spin_s, max_wait_s))
    while clock.wall_until(sim_t) > 0:
        drain(buses, on_msg, 0.0)
