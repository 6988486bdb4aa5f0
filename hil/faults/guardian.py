"""The bus guardian: a monitor node on a train bus that notices a babbling idiot.

It counts every frame on the bus per ID in windows of ``WINDOW_S``, with the bus time the frames took. An ID
is reported as babbling (an event of source ``busN/guardian``) when, in one window, it sends more than its
allowance AND holds more than ``BABBLE_SHARE`` of the window's bus time; it is cleared after a window within
both. The allowance of an ID known to the DBC is twice its cycle's worth plus two frames (jitter and
retransmissions stay below that); an ID the DBC does not know may send two. The bus-time share keeps a node that
empties a backlog (after a starvation, 64 queued frames go out back to back) from reading as a babbler: a
babbling idiot is a node that monopolises the bus. It listens like a CAN logger (``frame_listeners``), so
it sees every frame of the bus, whatever the acceptance filters; in the real-time rig it runs in the bus server.
The compiled engine runs the monitor (engine/src/guardian.rs) with ``allowances`` from here; its Python oracle is
``tests/oracle/bus_faults.py: BusGuardian``; both report (kind, fields) events that ``guardian_text`` words.
"""
from __future__ import annotations

import math
from collections.abc import Callable


WINDOW_S = 0.1
WINDOW_NS = round(WINDOW_S * 1e9)
BABBLE_SHARE = 0.3
SHARE_NS = BABBLE_SHARE * WINDOW_NS  # bus time an ID must exceed in a window
UNKNOWN_ALLOWANCE = 2  # frames per window of an ID the DBC does not know
EventSink = Callable[[int, str, str], None]  # (t_ns, level, text), bus time


def allowances(periods: dict[int, float]) -> dict[int, int]:
    """Frames per window each ID with a DBC cycle time may send: twice its cycle's worth plus two."""
    return {fid: 2 * math.ceil(WINDOW_S / p) + 2 for fid, p in periods.items() if p > 0}


def guardian_text(kind: str, f: dict) -> tuple[str, str]:
    """(level, text) of a guardian event: ``babbling`` (frame_id, frames, busy_ns, allowance) or ``cleared``."""
    if kind == "babbling":
        known = f"its DBC cycle allows {f['allowance']}" if f["allowance"] is not None else "not in the DBC"
        return "ERROR", (f"babbling node: ID 0x{f['frame_id']:03X} sent {f['frames']} frames in {WINDOW_S * 1e3:.0f} ms, "
                         f"{f['busy_ns'] / WINDOW_NS:.0%} of the bus ({known})")
    if kind == "cleared":
        return "INFO", f"cleared: babbling ID 0x{f['frame_id']:03X}"
    raise ValueError(f"unknown guardian event kind {kind!r}")
