"""The engine's oracle (test code): the Python CAN bus model, per-node TX queues, arbitration, exact frame durations, load and latency stats.

``CanBusModel`` is clock-agnostic (it is told the time): the oracle rig drives it from
the event kernel (``tests.oracle.python_bus.VirtualCanBus``), the oracle bus server from the wall clock.
Semantics: when the bus goes idle, every node offers the head of its TX queue (the lowest ID it holds
under the ``priority`` policy, its oldest frame under ``fifo``) and the lowest ID wins arbitration.
A frame's transmission ends after its last bit including the 3-bit intermission, which is the time
stamped on the received frame (the same convention as the response-time analysis).
"""
from __future__ import annotations

import heapq
from collections import deque
from dataclasses import dataclass
from typing import Callable

from hil.can.frame import bit_time_ns as _bit_ns, fd_frame_bits, fd_pad, frame_bits
from hil.can.bus_log import BusLog
from hil.can.transmission import Transmission

RxCallback = Callable[[int, bytes, int], None]  # (frame_id, data, t_end_ns)
# Queue entry: (arbitration key, seq, data, t_enqueue, node, frame_id, extended, format)
_Item = tuple[int, int, bytes, int, "CanNode", int, bool, int]
CLASSICAL, FD, FD_BRS = 0, 1, 2  # frame formats


def arbitration_key(frame_id: int, extended: bool) -> int:
    """A sort key in the order arbitration on the wire decides: base ID, then SRR and IDE (a standard
    frame beats an extended one with the same base ID), then the 18-bit ID extension."""
    if extended:
        return ((frame_id >> 18) << 20) | (0b11 << 18) | (frame_id & 0x3FFFF)
    return frame_id << 20


class CanNode:
    """A node's CAN controller: a bounded TX queue and a receive callback behind an acceptance filter.

    Under the ``priority`` policy the frames live in the bus's shared heap (the node only counts them):
    since every node offers its lowest ID, the bus-wide lowest ID is the arbitration winner either way.
    Under ``fifo`` the node keeps its own queue and offers its oldest frame.
    """

    def __init__(self, name: str, depth: int, on_rx: RxCallback | None, rx_ids: set[int] | None,
                 receive_own: bool = False) -> None:
        self.name = name
        self.on_rx = on_rx
        self.rx_ids = rx_ids  # None = accept everything
        self.receive_own = receive_own
        self.depth = depth
        self.queued = 0
        self.fifo: deque[_Item] = deque()
        self.sent = 0
        self.dropped = 0
        self.bus_off = False  # set by tests.oracle.bus_errors (fault confinement): a bus-off node neither sends nor receives
        self.refused = False  # a frame of it was refused: its first is in the bus's refusals, the rest counted only


class CanBusModel:
    """Arbitration and timing of one CAN bus, told the time by its driver."""

    def __init__(self, name: str, bitrate: int, policy: str = "priority", depth: int = 64, extended: bool = False,
                 log: BusLog | None = None, load_window_s: float = 0.1, fd: bool = False,
                 data_bitrate: int | None = None, brs: bool = True) -> None:
        """``fd``: the nodes send CAN FD frames, their data phase at ``data_bitrate`` when ``brs`` is set."""
        if policy not in ("priority", "fifo"):
            raise ValueError(f"queue policy must be 'priority' or 'fifo', got {policy!r}")
        self.name = name
        self.bitrate = bitrate
        self.bit_ns = _bit_ns(bitrate)
        self.fd, self.brs = fd, fd and brs
        self.data_bitrate = data_bitrate if fd and data_bitrate is not None else bitrate
        self.data_bit_ns = _bit_ns(self.data_bitrate)
        self.policy = policy
        self.depth = depth
        self.extended = extended
        self.log = log if log is not None else BusLog(name, bitrate)
        self.nodes: list[CanNode] = []
        self._priority = policy == "priority"
        self._heap: list[_Item] = []
        self._seq = 0
        self._listeners: dict[int, list[CanNode]] = {}  # frame id -> filtered receivers (built lazily)
        self._catch_all: list[CanNode] = []
        self._detached: list[CanNode] = []  # nodes that left the bus (their drops still count)
        self.busy_until = 0
        self.current: Transmission | None = None
        self._window_ns = int(load_window_s * 1e9)
        self._window_end = self._window_ns
        self._window_busy = 0
        self.frame_listeners: list[Callable[[Transmission], None]] = []  # e.g. CAN log writers
        self.errors = None  # tests.oracle.bus_errors.BusErrors when faults or errors are modelled (None: error-free fast path)
        self.packing = None  # trainhil_engine.Packing: CAN FD containers, unpacked at the receivers (set_packing)
        self._refusals: list[tuple[int, str]] = []  # each node's first refused frame: (t_ns, what happened)

    # ---- topology
    def attach(self, name: str, on_rx: RxCallback | None = None, rx_ids: set[int] | None = None,
               receive_own: bool = False) -> CanNode:
        node = CanNode(name, self.depth, on_rx, rx_ids, receive_own)
        self.nodes.append(node)
        self._listeners.clear()
        self._catch_all = [n for n in self.nodes if n.on_rx is not None and n.rx_ids is None]
        return node

    def attached(self, node: CanNode) -> bool:
        """Whether ``node`` is on this bus."""
        return node in self.nodes

    def detach(self, node: CanNode) -> int:
        """Remove a node (it disconnected or crashed): its queued frames are dropped and counted, how many is
        returned; a frame of it already on the wire completes."""
        if node not in self.nodes:
            raise ValueError(f"node {node.name!r} is not attached to bus {self.name}")
        lost = self.drop_queued(node)
        self._detached.append(node)
        self.nodes.remove(node)
        self._listeners.clear()
        self._catch_all = [n for n in self.nodes if n.on_rx is not None and n.rx_ids is None]
        return lost

    def take_refusals(self) -> list[tuple[int, str]]:
        """Each node's first frame refused (a full TX queue, bus-off) since the last call: (t_ns, what happened)."""
        out, self._refusals = self._refusals, []
        return out

    def set_packing(self, packing) -> None:
        """Unpack this CAN FD bus's container frames (a ``trainhil_engine.Packing``) at its receivers, which accept
        a container when they accept any of its parts; the bus's driver packs what its nodes send."""
        if not self.fd:
            raise ValueError(f"{self.name}: frame packing needs a CAN FD bus (fd=True)")
        self.packing = packing
        self._listeners.clear()

    def _receivers(self, frame_id: int) -> list[CanNode]:
        found = self._listeners.get(frame_id)
        if found is None:
            parts = self.packing.parts(frame_id) if self.packing is not None else None
            ids = {frame_id, *(p[0] for p in parts or ())}
            found = [n for n in self.nodes if n.on_rx is not None and n.rx_ids is not None and not ids.isdisjoint(n.rx_ids)
                     and not n.bus_off]
            found += self._catch_all
            self._listeners[frame_id] = found
        return found

    # ---- queues and arbitration
    def enqueue(self, node: CanNode, frame_id: int, data: bytes, t: int, extended: bool | None = None,
                fd: bool | None = None, brs: bool | None = None) -> bool:
        """Queue a frame in a node's TX queue at time t; False (and counted) when the queue is full.

        ``extended`` picks the ID format of this frame (default: the bus's ``extended``), ``fd`` whether it is a CAN
        FD frame and ``brs`` whether it switches to the data bitrate (defaults: the bus's format; a classical bus sends
        classical frames only)."""
        if node.queued >= node.depth or (node.bus_off and not self.errors.admits(node, t)):
            node.dropped += 1
            if not node.refused:
                node.refused = True
                why = "it is bus-off" if node.bus_off else f"its TX queue of {node.depth} is full"
                self._refusals.append((t, f"node {node.name} dropped frame 0x{frame_id:X} ({why}); its later drops "
                                          "are only counted"))
            return False
        node.queued += 1
        self._seq += 1
        ext = self.extended if extended is None else extended
        fmt = CLASSICAL
        if self.fd if fd is None else fd and self.fd:
            data = fd_pad(data)
            fmt = FD_BRS if (self.brs if brs is None else brs) else FD
        item = (arbitration_key(frame_id, ext), self._seq, data, t, node, frame_id, ext, fmt)
        if self._priority:
            heapq.heappush(self._heap, item)
        else:
            node.fifo.append(item)
        return True

    def _pop_winner(self, t: int) -> _Item | None:
        """The frame that wins at t among those queued by then (engine: ``Bus::pop_winner``)."""
        if self._priority:
            later = []
            won = None
            while self._heap:
                item = heapq.heappop(self._heap)
                if item[3] <= t:
                    won = item
                    break
                later.append(item)
            for item in later:
                heapq.heappush(self._heap, item)
            return won
        heads = [n for n in self.nodes if n.fifo and n.fifo[0][3] <= t]
        if not heads:
            return None
        return min(heads, key=lambda n: n.fifo[0][0]).fifo.popleft()

    def arbitrate(self, t: int) -> Transmission | None:
        """If the bus is idle at t, start the winning pending frame and return it."""
        if self.current is not None or t < self.busy_until:
            return None
        errors = self.errors
        if errors is not None:
            errors.before_arbitrate(t)
        won = self._pop_winner(t)
        if errors is not None:
            won = errors.filter_winner(won, t)
        if won is None:
            return None
        _, _, data, t_enq, node, frame_id, ext, fmt = won
        node.queued -= 1
        t_end = t + self.duration_ns(frame_id, data, ext, fmt)
        self.current = Transmission(node, frame_id, data, t_enq, t, t_end, ext, fd=fmt != CLASSICAL, brs=fmt == FD_BRS)
        self.busy_until = t_end
        if errors is not None:
            errors.on_start(self.current, won)  # may destroy the frame: it then ends with its error frame
        return self.current

    def duration_ns(self, frame_id: int, data: bytes, extended: bool, fmt: int | None = None) -> int:
        """A data frame's time on this bus, SOF through the intermission (CAN FD: both phases). ``fmt``: CLASSICAL,
        FD or FD_BRS (default: the bus's own)."""
        if fmt is None:
            fmt = (FD_BRS if self.brs else FD) if self.fd else CLASSICAL
        if fmt == CLASSICAL:
            return frame_bits(frame_id, data, extended) * self.bit_ns
        nominal, data_phase = fd_frame_bits(frame_id, data, extended, fmt == FD_BRS)
        return nominal * self.bit_ns + data_phase * self.data_bit_ns

    def complete(self) -> Transmission:
        """End the current transmission: deliver it, update statistics."""
        tx = self.current
        assert tx is not None, "complete() without a transmission"
        self.current = None
        if self.errors is not None and not self.errors.on_complete(tx):
            return tx  # destroyed (tx.error): not delivered; tests.oracle.bus_errors requeued it for retransmission
        self._account(tx)
        parts = self.packing.unpack(tx.frame_id, tx.data) if self.packing is not None else None
        if parts is None:
            for node in self._receivers(tx.frame_id):
                if node is not tx.node or node.receive_own:
                    node.on_rx(tx.frame_id, tx.data, tx.t_end)  # type: ignore[misc]
        else:  # a container: each receiver takes the parts its filter accepts, as the frames they were
            receivers = self._receivers(tx.frame_id)
            for part_id, part in parts:
                for node in receivers:
                    if (node is not tx.node or node.receive_own) and (node.rx_ids is None or part_id in node.rx_ids):
                        node.on_rx(part_id, part, tx.t_end)  # type: ignore[misc]
        for listener in self.frame_listeners:
            listener(tx)
        return tx

    def requeue(self, item: _Item) -> None:
        """Put a destroyed frame back at its place in its node's queue (automatic retransmission)."""
        item[4].queued += 1
        if self._priority:
            heapq.heappush(self._heap, item)
        else:
            item[4].fifo.appendleft(item)

    def drop_queued(self, node: CanNode) -> int:
        """Drop (and count) every frame a node has queued, e.g. when it goes bus-off; returns how many."""
        lost = node.queued
        if self._priority and lost:
            self._heap = [item for item in self._heap if item[4] is not node]
            heapq.heapify(self._heap)
        node.fifo.clear()
        node.queued = 0
        node.dropped += lost
        return lost

    def refresh_receivers(self) -> None:
        """Rebuild the receiver lists (a node went bus-off or recovered)."""
        self._listeners.clear()
        self._catch_all = [n for n in self.nodes if n.on_rx is not None and n.rx_ids is None and not n.bus_off]

    def pending(self) -> bool:
        return bool(self._heap) if self._priority else any(n.fifo for n in self.nodes)

    # ---- statistics
    def _account(self, tx: Transmission) -> None:
        tx.node.sent += 1
        log = self.log
        log.frames_sent += 1
        log.frames.append((tx.t_end * 1e-9, tx.frame_id, (tx.t_end - tx.t_enqueue) * 1e-9, (tx.t_start - tx.t_enqueue) * 1e-9))
        self._book_load(tx.t_start, tx.t_end)

    def _book_load(self, start: int, end: int) -> None:
        """Book a transmission's bus time in the load windows it spans, each its own part (a frame that straddles a
        boundary would otherwise put more than a window's length into the later one: a load above 1)."""
        while end > self._window_end:
            if start < self._window_end:
                self._window_busy += self._window_end - max(start, self._window_end - self._window_ns)
            self.log.load.append((self._window_end * 1e-9, self._window_busy / self._window_ns))
            self._window_busy = 0
            self._window_end += self._window_ns
        self._window_busy += max(0, end - max(start, self._window_end - self._window_ns))

    def align_load_windows(self, origin_ns: int, now: int) -> None:
        """From now on the windows end at origin_ns + k x the window; the time booked so far counts in the first
        one, up to the part of it that has passed (engine: ``Bus::align_load_windows``)."""
        self._close_windows(now)
        ahead = (origin_ns - now) % self._window_ns
        self._window_end = now + (ahead or self._window_ns)
        self._window_busy = min(self._window_busy, now - min(self._window_end - self._window_ns, now))

    def _close_windows(self, t: int, inclusive: bool = False) -> None:
        """Emit load samples for every window that ended before t (at or before t if inclusive)."""
        while t > self._window_end or (inclusive and t == self._window_end):
            self.log.load.append((self._window_end * 1e-9, self._window_busy / self._window_ns))
            self._window_busy = 0
            self._window_end += self._window_ns

    def finish(self, t: int) -> None:
        """Close the load windows up to t and fold the nodes' drop counts into the log."""
        if self.errors is not None:
            self.errors.finish(t)
        self._close_windows(t, inclusive=True)
        self.log.frames_dropped = sum(n.dropped for n in self.nodes) + sum(n.dropped for n in self._detached)
        by_name: dict[str, int] = {}
        for n in [*self.nodes, *self._detached]:
            if n.dropped:
                by_name[n.name] = by_name.get(n.name, 0) + n.dropped
        self.log.dropped_by_node = dict(sorted(by_name.items()))
