"""The engine's oracle (test code) for the bus faults and the guardian: ``BusFaults`` drives the Python bus model's
error model (``tests/oracle/bus_errors.py``) and ``BusGuardian`` watches its frames, as the engine's errors.rs and
guardian.rs do for ``hil.faults.bus.EngineBusFaults``."""
from __future__ import annotations

from collections.abc import Callable

from hil.can.transmission import Transmission
from hil.faults.bus import BABBLE_BYTE, target_ids, undetected_summary
from hil.faults.guardian import SHARE_NS, UNKNOWN_ALLOWANCE, WINDOW_NS, EventSink, allowances, guardian_text
from hil.faults.schedule import fault_rng
from tests.oracle.bus_errors import BusErrors, Corruption, FrameSelection
from tests.oracle.bus_model import CanBusModel


class BusFaults:
    """Bus faults on the Python bus model (the engine's oracle), driven by the virtual rig: ``send(node, id, data)``
    queues a frame now and starts an arbitration on an idle bus (``VirtualCanBus.send``)."""

    def __init__(self, bus: CanBusModel, index: int, seed: int, periods: dict[int, float], sink: EventSink,
                 guardian_sink: EventSink, send: Callable[[object, int, bytes], bool],
                 e2e_ok: Callable[[int, bytes], bool | None] | None = None, packing=None) -> None:
        """``sink``/``guardian_sink(t_ns, level, text)`` take the error model's and the guardian's events (bus time);
        ``periods``: frame ID -> DBC cycle time (the guardian's allowance); ``e2e_ok(id, data)``: whether a frame
        passes its E2E CRC (None: an ID the DBC does not know), to judge corruptions CAN let through; ``packing``
        (CAN FD containers): a fault aimed at a message also hits the containers that carry it."""
        self.e2e_ok = e2e_ok
        self.packing = packing
        self.bus = bus
        self.seed = seed
        self.errors = BusErrors(bus, sink, fault_rng(seed, 1000 + index))
        self.guardian = BusGuardian(bus.name, periods, guardian_sink)
        bus.frame_listeners.append(self.guardian)
        self._send = send
        self._active: dict[int, object] = {}  # fault index -> its effect

    def start(self, spec, index: int, t_ns: int) -> None:
        e = self.errors
        if spec.kind == "babbling_node":
            data = bytes([BABBLE_BYTE]) * spec.dlc
            self._active[index] = b = e.start_babbler(spec.frame_id, data, t_ns, name=f"Babbler#{index}", queue=False)
            self._send(b.node, spec.frame_id, data)  # also starts an arbitration on an idle bus
            return
        rng = fault_rng(self.seed, index)
        ids = target_ids(spec, self.packing)
        if spec.kind == "bus_corruption":
            sel = Corruption(rng, spec.probability, ids, spec.count, bits=spec.bits)
            e.corruptions.append(sel)
        elif spec.kind == "bus_error_frames":
            sel = FrameSelection(rng, spec.probability, ids, spec.count)
            e.error_flags.append(sel)
        else:
            sel = FrameSelection(rng, spec.probability, ids, spec.count)
            e.drops.append(sel)
        self._active[index] = sel

    def end(self, spec, index: int) -> None:
        effect = self._active.pop(index, None)
        if effect is None:
            return
        e = self.errors
        if spec.kind == "babbling_node":
            e.stop_babbler(effect)
        else:
            for group in (e.corruptions, e.error_flags, e.drops):
                if effect in group:
                    group.remove(effect)

    def summary(self) -> dict:
        """The error model's counts, plus what became of the corruptions CAN did not detect: caught by the
        receivers' E2E CRC, dropped by every acceptance filter (an ID no node knows), or accepted (E2E CRC valid)."""
        return {**self.errors.summary(), "babbling_detections": self.guardian.detections,
                **undetected_summary(self.errors.undetected_frames, self.e2e_ok)}


class BusGuardian:
    def __init__(self, bus_name: str, periods: dict[int, float], sink: EventSink) -> None:
        self.name = bus_name
        self._allow = allowances(periods)
        self._sink = sink
        self._window_ns = WINDOW_NS
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
        over = {fid: n for fid, n in self._counts.items()
                if n > self._allow.get(fid, UNKNOWN_ALLOWANCE) and self._busy[fid] > SHARE_NS}
        for fid, n in sorted(over.items()):
            if fid not in self._flagged:
                self._flagged.add(fid)
                self.detections += 1
                self._sink(t_window, *guardian_text("babbling", {"frame_id": fid, "frames": n, "busy_ns": self._busy[fid],
                                                                 "allowance": self._allow.get(fid)}))
        for fid in sorted(self._flagged - set(over)):
            self._flagged.discard(fid)
            self._sink(t_window, *guardian_text("cleared", {"frame_id": fid}))
        self._counts.clear()
        self._busy.clear()
        self._end += self._window_ns * max(1, (t_ns - self._end) // self._window_ns + 1)
