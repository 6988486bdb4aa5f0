"""Bus faults on one train bus: babbling node, corrupted frames, error frames, frame drops (via hil/can/errors.py).

``BusFaults`` owns the bus's ``BusErrors`` (attached when the scenario has any fault, so error counters and
confinement run on every bus of a faulty run) and its ``BusGuardian``, and turns the schedule's starts and ends
into effects on the wire. It works on any ``CanBusModel``: the virtual rig passes ``send`` (which also starts an
arbitration on an idle bus), the bus server calls it from its loop under its lock.
"""
from __future__ import annotations

from collections.abc import Callable

from hil.can.bus import CanBusModel
from hil.can.errors import BusErrors, Corruption, EventSink, FrameSelection
from hil.faults.guardian import BusGuardian
from hil.faults.schedule import fault_rng

BABBLE_BYTE = 0xA5


class BusFaults:
    def __init__(self, bus: CanBusModel, index: int, seed: int, periods: dict[int, float], sink: EventSink,
                 guardian_sink: EventSink, send: Callable | None = None,
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
            self._active[index] = b = e.start_babbler(spec.frame_id, data, t_ns, name=f"Babbler#{index}", queue=self._send is None)
            if self._send is not None:
                self._send(b.node, spec.frame_id, data)
            return
        rng = fault_rng(self.seed, index)
        ids = frozenset(spec.frame_ids) if spec.frame_ids else None
        if ids is not None and self.packing is not None:
            ids |= frozenset(self.packing.containers_of(list(ids)))
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
        out = {**self.errors.summary(), "babbling_detections": self.guardian.detections}
        verdicts = [self.e2e_ok(fid, data) if self.e2e_ok else None for _, _, fid, data, *_ in self.errors.undetected_frames]
        out["undetected_caught_by_e2e"] = sum(v is False for v in verdicts)
        out["undetected_unknown_id"] = sum(v is None for v in verdicts)
        out["undetected_accepted"] = sum(v is True for v in verdicts)
        out["undetected_frames"] = [{"t_bus_s": t * 1e-9, "sent_id": f"0x{a:03X}", "delivered_id": f"0x{b:03X}",
                                     "sent_data": sent.hex(), "delivered_data": d.hex(), "flipped_bits": flips}
                                    for t, a, b, d, sent, flips in self.errors.undetected_frames[:20]]
        return out


def e2e_checker(db) -> Callable[[int, bytes], bool | None]:
    """``e2e_ok(id, data)`` from the DBC: the frame's E2E CRC under its ID's data ID (None: unknown ID or length)."""
    def ok(frame_id: int, data: bytes) -> bool | None:
        codec = db.by_id.get(frame_id)
        if codec is None or len(data) != codec.dlc:
            return None
        return codec.crc_ok(data)

    return ok
