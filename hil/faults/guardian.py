"""The bus guardian: a monitor node on a train bus that notices a babbling idiot.

It counts every frame on the bus per ID in windows of ``WINDOW_S``, with the bus time the frames took. An ID
is reported as babbling (an event of source ``busN/guardian``) when, in one window, it sends more than its
allowance AND holds more than ``BABBLE_SHARE`` of the window's bus time; it is cleared after a window within
both. The allowance of an ID known to the DBC is twice its cycle's worth plus two frames (jitter and
retransmissions stay below that); an ID the DBC does not know may send two. The bus-time share keeps a node that
empties a backlog (after a starvation, 64 queued frames go out back to back) from reading as a babbler: a
babbling idiot is a node that monopolises the bus. It listens like a CAN logger (``frame_listeners``), so
it sees every frame of the bus, whatever the acceptance filters; in the real-time rig it runs in the bus server.
"""
from __future__ import annotations

import math
from collections.abc import Callable

from hil.can.bus import Transmission

WINDOW_S = 0.1
BABBLE_SHARE = 0.3
EventSink = Callable[[int, str, str], None]  # (t_ns, level, text), bus time


class BusGuardian:
    def __init__(self, bus_name: str, periods: dict[int, float], sink: EventSink) -> None:
        self.name = bus_name
        self._allow = {fid: 2 * math.ceil(WINDOW_S / p) + 2 for fid, p in periods.items() if p > 0}
        self._sink = sink
        self._window_ns = round(WINDOW_S * 1e9)
        self._end = self._window_ns
        self._counts: dict[int, int] = {}
        self._busy: dict[int, int] = {}  # bus time (ns) per ID in the window
        self._flagged: set[int] = set()
        self.detections = 0

    def __call__(self, tx: Transmission) -> None:
        if tx.t_end >= self._end:
            self._judge(tx.t_end)
        fid = tx.frame_id
        self._counts[fid] = self._counts.get(fid, 0) + 1
        self._busy[fid] = self._busy.get(fid, 0) + tx.t_end - tx.t_start

    def _judge(self, t_ns: int) -> None:
        """Close the window ending at self._end (and any empty ones after it)."""
        t_window = self._end
        share = BABBLE_SHARE * self._window_ns
        over = {fid: n for fid, n in self._counts.items() if n > self._allow.get(fid, 2) and self._busy[fid] > share}
        for fid, n in sorted(over.items()):
            if fid not in self._flagged:
                self._flagged.add(fid)
                self.detections += 1
                known = f"its DBC cycle allows {self._allow[fid]}" if fid in self._allow else "not in the DBC"
                self._sink(t_window, "ERROR", f"babbling node: ID 0x{fid:03X} sent {n} frames in "
                                              f"{WINDOW_S * 1e3:.0f} ms, {self._busy[fid] / self._window_ns:.0%} of the bus ({known})")
        for fid in sorted(self._flagged - set(over)):
            self._flagged.discard(fid)
            self._sink(t_window, "INFO", f"cleared: babbling ID 0x{fid:03X}")
        self._counts.clear()
        self._busy.clear()
        self._end += self._window_ns * max(1, (t_ns - self._end) // self._window_ns + 1)
