"""Bus faults on one train bus: babbling node, corrupted frames, error frames, frame drops.

A faulty run has error counters, fault confinement and a guardian on every bus, and the schedule's starts and ends
become effects on the wire. ``EngineBusFaults`` does it on a bus of the compiled engine (engine/src/errors.rs,
guardian.rs): the virtual network's ``EngineBus`` or a real-time ``NativeBusServer``. The oracle the engine is checked
against does it on the Python bus model (``tests/oracle/bus_faults.py``); both draw the same numpy streams
(``fault_rng``) and give the same frames, events and counts.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hil.can.error_events import event_text
from hil.faults.guardian import SHARE_NS, WINDOW_NS, allowances, guardian_text
from hil.faults.schedule import fault_rng

BABBLE_BYTE = 0xA5
GUARDIAN_KINDS = ("babbling", "cleared")
ENGINE_EFFECTS = {"bus_corruption": "corruption", "bus_error_frames": "error_flags", "frame_drop": "drops"}


def describe_bus_event(kind: str, fields: dict) -> tuple[str, str, str]:
    """(source suffix "can" or "guardian", level, text) of an engine bus event."""
    if kind in GUARDIAN_KINDS:
        return ("guardian", *guardian_text(kind, fields))
    return ("can", *event_text(kind, fields))


def rng_state(rng: np.random.Generator) -> tuple[int, int]:
    """(state, inc) of a numpy PCG64 stream: what the engine needs to continue it draw for draw."""
    bits = rng.bit_generator
    if not isinstance(bits, np.random.PCG64):
        raise TypeError(f"the engine continues PCG64 streams only, not {type(bits).__name__}")
    state = bits.state["state"]
    return state["state"], state["inc"]


def target_ids(spec, packing) -> frozenset[int] | None:
    """The frame IDs a bus fault aims at (None: all), with the CAN FD containers that carry them."""
    ids = frozenset(spec.frame_ids) if spec.frame_ids else None
    if ids is not None and packing is not None:
        ids |= frozenset(packing.containers_of(list(ids)))
    return ids


def undetected_summary(frames: list, e2e_ok: Callable[[int, bytes], bool | None] | None) -> dict:
    """What became of the corruptions CAN did not detect, from (t_ns, sent id, delivered id, delivered data, sent data,
    flipped bits): caught by the receivers' E2E CRC, dropped by every acceptance filter (an ID no node knows), or
    accepted (E2E CRC valid); the first 20 listed."""
    verdicts = [e2e_ok(fid, bytes(data)) if e2e_ok else None for _, _, fid, data, *_ in frames]
    return {"undetected_caught_by_e2e": sum(v is False for v in verdicts),
            "undetected_unknown_id": sum(v is None for v in verdicts),
            "undetected_accepted": sum(v is True for v in verdicts),
            "undetected_frames": [{"t_bus_s": t * 1e-9, "sent_id": f"0x{a:03X}", "delivered_id": f"0x{b:03X}",
                                   "sent_data": bytes(sent).hex(), "delivered_data": bytes(d).hex(),
                                   "flipped_bits": list(flips)}
                                  for t, a, b, d, sent, flips in frames[:20]]}


class EngineBusFaults:
    """Bus faults on a bus of the compiled engine: ``bus`` has the engine's bus-error methods (``EngineBus``,
    ``NativeBusServer``). The error model and the guardian run in the engine; this turns specs into effects."""

    def __init__(self, bus, index: int, seed: int, periods: dict[int, float],
                 e2e_ok: Callable[[int, bytes], bool | None] | None = None, packing=None) -> None:
        self.bus, self.seed, self.e2e_ok, self.packing = bus, seed, e2e_ok, packing
        bus.enable_bus_errors(rng_state(fault_rng(seed, 1000 + index)))
        bus.set_guardian(allowances(periods), WINDOW_NS, SHARE_NS)

    def start(self, spec, index: int, t_ns: int | None = None) -> None:
        if spec.kind == "babbling_node":
            self.bus.start_babbler(index, f"Babbler#{index}", spec.frame_id, bytes([BABBLE_BYTE]) * spec.dlc, False)
            return
        ids = target_ids(spec, self.packing)
        bits = spec.bits if spec.kind == "bus_corruption" else 1
        self.bus.add_bus_fault(index, ENGINE_EFFECTS[spec.kind], rng_state(fault_rng(self.seed, index)), spec.probability,
                               None if ids is None else sorted(ids), spec.count, bits)

    def end(self, spec, index: int) -> None:
        self.bus.end_bus_fault(index)

    def summary(self) -> dict:
        """The engine's counts, as ``BusFaults.summary`` gives them."""
        counts = self.bus.bus_errors()
        frames = counts.pop("undetected_frames")
        return {**counts, **undetected_summary(frames, self.e2e_ok)}


def e2e_checker(db) -> Callable[[int, bytes], bool | None]:
    """``e2e_ok(id, data)`` from the DBC: the frame's E2E CRC under its ID's data ID (None: unknown ID or length)."""
    def ok(frame_id: int, data: bytes) -> bool | None:
        codec = db.by_id.get(frame_id)
        if codec is None or len(data) != codec.dlc:
            return None
        return codec.crc_ok(data)

    return ok
