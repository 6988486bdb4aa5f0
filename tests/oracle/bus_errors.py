"""The engine's oracle (test code) for CAN errors on one bus: corrupted frames the receivers reject, error frames, retransmission, and fault confinement.

Fault confinement follows ISO 11898-1 (Bosch CAN 2.0 part A, section 8) for every controller on the bus:

* a receiver that detects an error adds 1 to its REC (rule 1); a transmitter whose frame is destroyed adds 8 to
  its TEC (rule 3); a successful transmission takes 1 off the TEC, a successful reception 1 off the REC, and a
  REC above 127 is set back to 127 (the standard allows 119..127);
* error passive once TEC or REC reaches 128, error active again when both are below 128;
* bus-off when TEC exceeds 255: the node neither sends nor receives (frames it queues are dropped and counted),
  and becomes error active with TEC = REC = 0 after 128 occurrences of 11 consecutive recessive bits.

What the wire looks like (``wire_bits``) and what a receiver does with it (``receive``) is modelled bit by bit:
a corrupted frame has some bits flipped as the receivers sample them (a local disturbance; the sender reads back
what it sent). The receivers destuff and parse it like a CAN controller and find a stuff error (six equal bits),
a form error (a dominant CRC or ACK delimiter) or a CRC error (CRC-15 mismatch, signalled after the ACK
delimiter); whatever they find, and the bit they find it at, decides when the error frame starts. An error frame
is taken at its longest: 12 dominant bits (a 6-bit error flag and the other nodes' superposed flags), the
8-bit delimiter and the 3-bit intermission, so a destroyed frame holds the bus for the bits up to the detection
plus 23. The sender then retransmits automatically: the frame goes back to its TX queue with its queueing time,
so its measured latency includes every attempt. A corruption the receivers do not detect (CAN's residual
error rate) is delivered with its corrupted bits, for the E2E CRC to catch, and counted as ``undetected``.

CAN FD frames get the same confinement. Their bits up to a detection are timed at both rates (the data phase at
the data bitrate), the error frame at the nominal rate. A corrupted FD frame is not modelled bit by bit: it is
rejected by its CRC check after the ACK delimiter (CRC-17/21, with the stuff count, leave no residual error to
speak of), which is the latest a receiver can find an error, so its error frame is taken at its longest.

Every transmission, destroyed or not, ends with 11 recessive bits (ACK delimiter + EOF + intermission, or the
error delimiter + intermission), so the recovery count of a bus-off node is: one sequence per frame on a busy
bus, and idle time / 11 bits in between. Not modelled: the error-passive transmitter's 8-bit suspend
transmission, passive error flags that do not destroy a frame (every receiver here sees the same bits, so an
error-active one always does), and REC rule 2 (+8 for a dominant bit after its own error flag).

The fault injectors that need the wire also live here: a babbling node (one frame ID back to back), frame drops
(gone from the sender's TX queue) and error flags from a faulty transceiver. ``BusErrors`` is attached to a
``CanBusModel`` (``bus.errors``) by ``hil.faults``; a bus without it runs the error-free fast path.

The compiled engine has the same model (engine/src/errors.rs), decision for decision: every random draw is one
``Generator.random()`` (a hit ``u < p``, a position ``floor(u * n)``, corrupted bits by a partial Fisher-Yates
shuffle), so the engine continues the same numpy streams and both give the same frames
(tests/test_engine_differential.py). Both report their events as (kind, fields); ``event_text`` words them.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from hil.can.error_events import (BUS_OFF_ABOVE, ERROR_PASSIVE_AT, RECESSIVE_SEQUENCE_BITS, RECOVERY_SEQUENCES,
                                  event_text)
from hil.can.transmission import Transmission
from tests.oracle.bus_model import CanBusModel, CanNode, _Item
from hil.can.frame import FD_TAIL_BITS, _crc15_bitwise, fd_frame_bits, stuffed_bits

ERROR_FLAG_PHASE_BITS = 12  # 6-bit error flag + up to 6 bits of the other nodes' superposed flags (the maximum)
ERROR_DELIMITER_BITS = 8
INTERMISSION_BITS = 3
ERROR_TAIL_BITS = ERROR_FLAG_PHASE_BITS + ERROR_DELIMITER_BITS + INTERMISSION_BITS
FD_EOF_IFS_BITS = 7 + 3  # the end of FD_TAIL_BITS: after the ACK delimiter
EPISODE_GAP_S = 0.1  # error frames less than this apart are one episode (one summary event)

EventSink = Callable[[int, str, str], None]  # (t_ns, level, text)


def pick_positions(rng: np.random.Generator, span: int, k: int) -> list[int]:
    """``k`` distinct positions of 1..span, sorted: a partial Fisher-Yates shuffle, one ``random()`` each (the
    engine's ``pick_positions`` draws alike)."""
    pool = list(range(1, span + 1))
    k = min(k, span)
    for i in range(k):
        j = i + int(rng.random() * (span - i))
        pool[i], pool[j] = pool[j], pool[i]
    return sorted(pool[:k])


class ErrorState(IntEnum):
    ERROR_ACTIVE = 0
    ERROR_PASSIVE = 1
    BUS_OFF = 2


class ErrorCounters:
    """TEC and REC of one controller and the fault-confinement state they give."""

    __slots__ = ("tec", "rec", "state", "tec_max", "rec_max", "passive_count", "bus_off_count")

    def __init__(self) -> None:
        self.tec = self.rec = 0
        self.state = ErrorState.ERROR_ACTIVE
        self.tec_max = self.rec_max = 0
        self.passive_count = self.bus_off_count = 0

    def tx_error(self) -> ErrorState | None:
        """Rule 3: the node's own frame was destroyed. Returns the new state if it changed."""
        self.tec += 8
        self.tec_max = max(self.tec_max, self.tec)
        return self._update()

    def rx_error(self) -> ErrorState | None:
        """Rule 1: the node detected an error as a receiver."""
        self.rec += 1
        self.rec_max = max(self.rec_max, self.rec)
        return self._update()

    def tx_ok(self) -> ErrorState | None:
        if self.tec:
            self.tec -= 1
        return self._update()

    def rx_ok(self) -> ErrorState | None:
        if self.rec > 127:
            self.rec = 127
        elif self.rec:
            self.rec -= 1
        return self._update()

    def recover(self) -> ErrorState | None:
        """Bus-off recovery complete: error active with both counters at zero."""
        self.tec = self.rec = 0
        old, self.state = self.state, ErrorState.ERROR_ACTIVE
        return self.state if old != self.state else None

    def _update(self) -> ErrorState | None:
        if self.state == ErrorState.BUS_OFF:
            return None  # only recover() leaves bus-off
        if self.tec > BUS_OFF_ABOVE:
            new = ErrorState.BUS_OFF
            self.bus_off_count += 1
        elif self.tec >= ERROR_PASSIVE_AT or self.rec >= ERROR_PASSIVE_AT:
            new = ErrorState.ERROR_PASSIVE
        else:
            new = ErrorState.ERROR_ACTIVE
        if new == self.state:
            return None
        if new == ErrorState.ERROR_PASSIVE:
            self.passive_count += 1
        self.state = new
        return new


# --------------------------------------------------------------------------- the wire, bit by bit


def wire_bits(can_id: int, data: bytes, extended: bool = False) -> list[int]:
    """A data frame as sent, SOF to the end of EOF: stuffed SOF..CRC, CRC delimiter, ACK slot (dominant, as the
    receivers drive it), ACK delimiter, 7 EOF bits. ``len - 10`` is the index of the CRC delimiter."""
    return stuffed_bits(can_id, data, extended) + [1, 0, 1] + [1] * 7


@dataclass(frozen=True)
class Reception:
    """What the receivers made of a frame: ``error`` (None: accepted) found at bit ``at`` (the error frame starts
    at ``at + 1``); an accepted frame's ID, format and data as they decoded them."""

    error: str | None
    at: int
    can_id: int = 0
    extended: bool = False
    data: bytes = b""


def _int(bits: Sequence[int]) -> int:
    """Bits (MSB first) as an integer."""
    value = 0
    for b in bits:
        value = (value << 1) | b
    return value


class _StuffError(Exception):
    def __init__(self, at: int) -> None:
        self.at = at


def receive(wire: Sequence[int]) -> Reception:
    """Decode a frame as a CAN receiver does: destuff and check the stuffing, parse the header to know the length,
    check the CRC-15 and the fixed-form delimiters. Bits beyond ``wire`` read recessive (an idle bus)."""
    n = len(wire)
    pos, last, run = 1, 0, 1  # SOF (dominant) already read
    out = [0]

    def take(count: int) -> None:
        nonlocal pos, last, run
        while count:
            bit = wire[pos] if pos < n else 1
            if run == 5:  # this must be a stuff bit
                if bit == last:
                    raise _StuffError(pos)
                last, run = bit, 1
                pos += 1
                continue
            run = run + 1 if bit == last else 1
            last = bit
            out.append(bit)
            pos += 1
            count -= 1

    try:
        take(13)  # 11 ID bits, RTR/SRR, IDE
        extended = out[13] == 1
        if extended:
            take(18 + 3)  # ID extension, RTR, r1, r0
        else:
            take(1)  # r0
        take(4)
        dlc = _int(out[-4:])
        rtr = out[-7] if extended else out[12]
        nbytes = 0 if rtr else min(dlc, 8)
        take(8 * nbytes)
        body = len(out)
        take(15)
        if run == 5:  # a stuff bit follows five equal CRC bits
            if (wire[pos] if pos < n else 1) == last:
                raise _StuffError(pos)
            pos += 1
    except _StuffError as exc:
        return Reception("stuff", exc.at)
    if (wire[pos] if pos < n else 1) == 0:
        return Reception("form", pos)  # the CRC delimiter must be recessive
    if (wire[pos + 2] if pos + 2 < n else 1) == 0:
        return Reception("form", pos + 2)  # the ACK delimiter too
    if _crc15_bitwise(out[:body]) != _int(out[body:body + 15]):
        return Reception("crc", pos + 2)  # signalled from the bit after the ACK delimiter
    payload = out[body - 8 * nbytes:body]
    data = bytes(_int(payload[8 * k:8 * k + 8]) for k in range(nbytes))
    can_id = (_int(out[1:12]) << 18) | _int(out[14:32]) if extended else _int(out[1:12])
    return Reception(None, pos + 2, can_id, extended, data)


def corrupt(wire: list[int], positions: Sequence[int]) -> list[int]:
    """The wire with the bits at ``positions`` flipped."""
    out = list(wire)
    for p in positions:
        out[p] ^= 1
    return out


# --------------------------------------------------------------------------- injected effects


@dataclass
class FrameSelection:
    """Which frames an effect hits: each with ``probability``, only ``frame_ids`` if given, at most ``count``."""

    rng: np.random.Generator
    probability: float = 1.0
    frame_ids: frozenset[int] | None = None
    count: int | None = None
    hits: int = 0

    def hit(self, frame_id: int) -> bool:
        if self.count is not None and self.hits >= self.count:
            return False
        if self.frame_ids is not None and frame_id not in self.frame_ids:
            return False
        if self.probability < 1.0 and self.rng.random() >= self.probability:
            return False
        self.hits += 1
        return True


@dataclass
class Corruption(FrameSelection):
    bits: int = 1


@dataclass
class Babbler:
    """A node that keeps one frame of ``frame_id`` queued all the time: it wins every arbitration it can."""

    node: CanNode
    frame_id: int
    data: bytes
    extended: bool = False
    sent: int = 0


@dataclass
class _Episode:
    start_ns: int
    last_ns: int
    by_error: dict[str, int] = field(default_factory=dict)


class BusErrors:
    """Error model and bus-level fault effects of one ``CanBusModel`` (see the module docstring).

    ``sink(t_ns, level, text)`` receives the events (state changes, error episodes) in the bus's time; the texts
    name the node, not the bus."""

    def __init__(self, bus: CanBusModel, sink: EventSink | None = None, rng: np.random.Generator | None = None) -> None:
        self.bus = bus
        self.sink = sink
        self.rng = rng or np.random.default_rng(0)
        self.corruptions: list[Corruption] = []
        self.error_flags: list[FrameSelection] = []
        self.drops: list[FrameSelection] = []
        self.babblers: list[Babbler] = []
        self.counters: dict[CanNode, ErrorCounters] = {}
        self._receiving: dict[CanNode, None] = {}  # nodes with REC > 0, in the order they got there
        self.stats = {"corrupted": 0, "rejected": 0, "undetected": 0, "error_frames": 0, "injected_error_flags": 0,
                      "retransmissions": 0, "dropped_by_fault": 0, "dropped_bus_off": 0, "babbled": 0}
        self.by_error: dict[str, int] = {}
        # (t_ns, sent id, delivered id, delivered data, sent data, flipped bit positions on the wire)
        self.undetected_frames: list[tuple[int, int, int, bytes, bytes, list[int]]] = []
        self._bit = bus.bit_ns
        self._seq_ns = RECESSIVE_SEQUENCE_BITS * bus.bit_ns
        self._run_start = 0  # end of the last dominant bit on the bus (start of the current recessive run)
        self._sequences = 0  # complete 11-bit recessive sequences in the runs that have ended
        self._bus_off: dict[CanNode, tuple[int, int]] = {}  # node -> (sequences at bus-off, time it went bus-off)
        self._bus_off_ns: dict[CanNode, int] = {}  # total time spent bus-off per node
        self._item: _Item | None = None  # queue entry of the transmission on the wire
        self._episode: _Episode | None = None
        bus.errors = self

    # ---- helpers
    def counters_of(self, node: CanNode) -> ErrorCounters:
        c = self.counters.get(node)
        if c is None:
            c = self.counters[node] = ErrorCounters()
        return c

    def _emit(self, t_ns: int, kind: str, **fields) -> None:
        if self.sink is not None:
            self.sink(t_ns, *event_text(kind, fields))

    def sequences(self, t_ns: int) -> int:
        """11-bit recessive sequences seen on the bus up to t (the run in progress counts if the bus is idle)."""
        if self.bus.current is not None:
            return self._sequences
        return self._sequences + max(t_ns - self._run_start, 0) // self._seq_ns

    # ---- hooks called by CanBusModel
    def admits(self, node: CanNode, t_ns: int) -> bool:
        """A bus-off node may queue again once it has recovered by t."""
        self._recoveries(t_ns)
        return not node.bus_off

    def before_arbitrate(self, t_ns: int) -> None:
        """At a start of frame: recoveries due by now, then close the recessive run."""
        self._recoveries(t_ns)
        self._sequences += max(t_ns - self._run_start, 0) // self._seq_ns
        self._run_start = t_ns

    def filter_winner(self, won: _Item | None, t_ns: int) -> _Item | None:
        """Frame drops: a hit frame vanishes from its sender's queue; the next pending frame competes instead."""
        while won is not None and self.drops:
            node, frame_id = won[4], won[5]
            if not any(d.hit(frame_id) for d in self.drops):
                break
            node.queued -= 1
            node.dropped += 1
            self.stats["dropped_by_fault"] += 1
            won = self.bus._pop_winner(t_ns)
        return won

    def on_start(self, tx: Transmission, won: _Item) -> None:
        """Decide what happens to the frame now on the wire: destroyed by an error flag, corrupted (the receivers
        judge it bit by bit), or clean. A destroyed frame ends early (its error frame included)."""
        self._item = won
        for b in self.babblers:
            if tx.node is b.node:
                b.sent += 1
                self.stats["babbled"] += 1
                self.bus.enqueue(b.node, b.frame_id, b.data, tx.t_start, b.extended, tx.fd, tx.brs)  # keep it babbling
        for sel in self.error_flags:
            if sel.hit(tx.frame_id):
                n_bits = len(wire_bits(tx.frame_id, tx.data, tx.extended)) if not tx.fd else sum(self._fd_phases(tx)) - 3
                at = 1 + int(self.rng.random() * (n_bits - 8))  # after SOF .. the ACK delimiter
                self.stats["injected_error_flags"] += 1
                self._fail(tx, "error flag", at)
                return
        for sel in self.corruptions:
            if sel.hit(tx.frame_id):
                self._corrupt(tx, sel.bits)
                return

    def _fd_phases(self, tx: Transmission) -> tuple[int, int]:
        """A CAN FD frame's bits at the nominal and at the data rate, SOF through the intermission."""
        return fd_frame_bits(tx.frame_id, tx.data, tx.extended, tx.brs)

    def _corrupt(self, tx: Transmission, bits: int) -> None:
        if tx.fd:
            self._corrupt_fd(tx)
            return
        wire = wire_bits(tx.frame_id, tx.data, tx.extended)
        span = len(wire) - 10  # bits after SOF up to and including the CRC delimiter
        flips = pick_positions(self.rng, span, bits)
        seen = receive(corrupt(wire, flips))
        self.stats["corrupted"] += 1
        if seen.error is not None:
            self.stats["rejected"] += 1
            self._fail(tx, seen.error, seen.at)
        else:  # CAN's residual error: delivered as decoded, for the E2E check to catch
            self.stats["undetected"] += 1
            self.undetected_frames.append((tx.t_start, tx.frame_id, seen.can_id, seen.data, tx.data, flips))
            tx.frame_id, tx.data, tx.extended = seen.can_id, seen.data, seen.extended

    def _corrupt_fd(self, tx: Transmission) -> None:
        """A corrupted CAN FD frame: rejected, found by its CRC check after the ACK delimiter (not bit by bit: the
        wire model above is classical CAN's; CRC-17/21 with the stuff count leave no residual error to model)."""
        nominal, data_phase = self._fd_phases(tx)
        self.stats["corrupted"] += 1
        self.stats["rejected"] += 1
        self._fail(tx, "crc", nominal + data_phase - FD_EOF_IFS_BITS - 1)

    def _fail(self, tx: Transmission, error: str, at: int) -> None:
        tx.error = error
        tx.t_end = tx.t_start + self._bits_ns(tx, at + 1) + ERROR_TAIL_BITS * self._bit
        self.bus.busy_until = tx.t_end

    def _bits_ns(self, tx: Transmission, k: int) -> int:
        """The time of a frame's first ``k`` bits (CAN FD with BRS: the data phase at the data rate)."""
        if not tx.brs:
            return k * self._bit
        nominal, data_phase = self._fd_phases(tx)
        arbitration = nominal - FD_TAIL_BITS
        fast = min(max(k - arbitration, 0), data_phase)
        return (k - fast) * self._bit + fast * self.bus.data_bit_ns

    def on_complete(self, tx: Transmission) -> bool:
        """End of a transmission: counters, events; a destroyed frame is requeued (False: do not deliver it)."""
        self._run_start = tx.t_end - self._seq_ns  # every transmission ends with 11 recessive bits
        item, self._item = self._item, None
        if tx.error is None:
            self._success(tx)
            return True
        self.stats["error_frames"] += 1
        self.by_error[tx.error] = self.by_error.get(tx.error, 0) + 1
        self._log_error(tx)
        for node in self.bus.nodes:
            if node is not tx.node and not node.bus_off:
                self._receiving[node] = None
                self._changed(node, self.counters_of(node).rx_error(), tx.t_end)
        self._changed(tx.node, self.counters_of(tx.node).tx_error(), tx.t_end)
        bus = self.bus
        self._bus_busy(tx)
        if tx.node.bus_off or tx.node not in bus.nodes:
            tx.node.dropped += 1
            self.stats["dropped_bus_off"] += 1
        elif item is not None:
            bus.requeue(item)
            self.stats["retransmissions"] += 1
        return False

    def _success(self, tx: Transmission) -> None:
        c = self.counters.get(tx.node)
        if c is not None and c.tec:
            self._changed(tx.node, c.tx_ok(), tx.t_end)
        if self._receiving:
            for node in list(self._receiving):
                if node is not tx.node and not node.bus_off:
                    c = self.counters[node]
                    self._changed(node, c.rx_ok(), tx.t_end)
                    if not c.rec:
                        del self._receiving[node]

    def _bus_busy(self, tx: Transmission) -> None:
        """A destroyed frame and its error frame occupy the bus: they count in the load."""
        bus = self.bus
        bus._close_windows(tx.t_end)
        bus._window_busy += tx.t_end - tx.t_start

    # ---- fault confinement
    def _changed(self, node: CanNode, new: ErrorState | None, t_ns: int) -> None:
        if new is None:
            return
        c = self.counters[node]
        if new == ErrorState.BUS_OFF:
            node.bus_off = True
            lost = self.bus.drop_queued(node)
            self.stats["dropped_bus_off"] += lost
            self._bus_off[node] = (self._sequences, t_ns)
            self.bus.refresh_receivers()
            self._emit(t_ns, "bus_off", node=node.name, tec=c.tec, lost=lost)
        else:
            self._emit(t_ns, new.name.lower(), node=node.name, tec=c.tec, rec=c.rec)

    def _recoveries(self, t_ns: int) -> None:
        """Bring back every bus-off node that has seen 128 recessive sequences by t (at the exact time it did)."""
        if not self._bus_off:
            return
        idle = self.bus.current is None
        for node, (seq0, t_off) in list(self._bus_off.items()):
            need = RECOVERY_SEQUENCES - (self._sequences - seq0)
            if need <= 0:
                t_rec = self._run_start  # reached at the end of an earlier run: logged at the latest bound
            elif idle and (t_ns - self._run_start) // self._seq_ns >= need:
                t_rec = self._run_start + need * self._seq_ns
            else:
                continue
            del self._bus_off[node]
            node.bus_off = False
            self._bus_off_ns[node] = self._bus_off_ns.get(node, 0) + t_rec - t_off
            self.counters_of(node).recover()
            self.bus.refresh_receivers()
            self._emit(t_rec, "recovered", node=node.name, after_ns=t_rec - t_off)

    # ---- events
    def _log_error(self, tx: Transmission) -> None:
        ep = self._episode
        if ep is not None and tx.t_end - ep.last_ns > EPISODE_GAP_S * 1e9:
            self._close_episode()
            ep = None
        if ep is None:
            self._episode = ep = _Episode(tx.t_end, tx.t_end)
            self._emit(tx.t_end, "error_frame", error=tx.error, frame_id=tx.frame_id, node=tx.node.name)
        ep.last_ns = tx.t_end
        ep.by_error[tx.error] = ep.by_error.get(tx.error, 0) + 1  # type: ignore[index]

    def _close_episode(self) -> None:
        ep, self._episode = self._episode, None
        if ep is None:
            return
        self._emit(ep.last_ns, "episode", start_ns=ep.start_ns, last_ns=ep.last_ns, by_error=dict(ep.by_error))

    # ---- effects
    def start_babbler(self, frame_id: int, data: bytes, t_ns: int, extended: bool = False,
                      name: str = "Babbler", queue: bool = True) -> Babbler:
        """Attach a babbling node; ``queue``: queue its first frame now (else the caller sends it, e.g. through
        ``VirtualCanBus.send``, which also starts an arbitration on an idle bus)."""
        node = self.bus.attach(name)
        b = Babbler(node, frame_id, data, extended)
        self.babblers.append(b)
        if queue:
            self.bus.enqueue(node, frame_id, data, t_ns, extended)
        return b

    def stop_babbler(self, babbler: Babbler) -> None:
        self.babblers.remove(babbler)
        if babbler.node in self.bus.nodes:
            self.bus.detach(babbler.node)

    def finish(self, t_ns: int) -> None:
        """End of the run: recoveries due, the open error episode, time still spent bus-off."""
        self._recoveries(t_ns)
        self._close_episode()
        for node, (_, t_off) in self._bus_off.items():
            self._bus_off_ns[node] = self._bus_off_ns.get(node, 0) + max(t_ns - t_off, 0)
            self._bus_off[node] = (self._bus_off[node][0], t_ns)

    def summary(self) -> dict:
        """Counts for metrics.json: frames corrupted/rejected/undetected, error frames by kind, per-node counters."""
        nodes = {}
        for node, c in self.counters.items():
            if c.tec_max or c.rec_max:
                nodes[node.name] = {"tec_max": c.tec_max, "rec_max": c.rec_max, "error_passive": c.passive_count,
                                    "bus_off": c.bus_off_count, "bus_off_s": self._bus_off_ns.get(node, 0) * 1e-9,
                                    "state": c.state.name.lower()}
        return {**self.stats, "by_error": dict(self.by_error), "nodes": nodes}
