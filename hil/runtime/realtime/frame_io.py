"""How a real-time node's frames move: through the engine (``FrameLink``) on the emulated buses, through python-can on
SocketCAN. Both have one interface, so the node loops do not care which:

* ``wait(sim_t, on_frame, stop, spin_s=0)``: receive until simulated time ``sim_t`` (sleeping; the last ``spin_s``
  wall seconds polled), handing every frame to ``on_frame(bus, frame_id, data, t_sim)`` or, for ECU mailboxes
  routed with ``route`` and a plant's command inboxes routed with ``route_commands``, straight into them;
* ``drain(on_frame)``: whatever waits now; ``wait_any(wall_s, on_frame)``: the first frames within ``wall_s``;
* ``send(bus, frames, sender=0)``: queue ``[(frame_id, data)]`` on bus ``bus``; ``send_outputs(bus, outputs,
  sender=0)``: an ECU cycle's unencoded outputs ``[(codec, values, counter)]``, encoded and sent by the engine in
  one call. ``sender``: which of the node's ECUs sends them; on the emulated bus each has its own TX queue, as
  separate CAN controllers (protocol.MAX_SENDERS); on SocketCAN the kernel queues a socket's frames in one;
* ``read_every(first, period, buses)``: the node's read times (simulated s) on some buses, for a lazy reader.

A lazy reader (``lazy=True``, the ECU and plant nodes on the emulated buses) tells its bus servers when it reads
(``read_every``; an unforeseen wait asks once), and the servers hand its frames over only then, with a SYNC: no
server wakes at each frame end for it, and ``wait`` blocks on the sockets until the SYNC of its time, so it sees
exactly the frames that ended by then. Its sent frames carry the instant they were sent, at which the server
queues them. Where the server has a bell, the reader is also quiet: its sends do not wake the server, which reads
them at its next wake-up, unless the server needs a frame at its end (the engine link rings the bell then).

With a CAN FD frame packing (``can.dbc = "train_fd.dbc"``), each ``send`` batch goes as its containers and every
container received is handed over as the frames it carries (``trainhil_engine.Packing``), in both classes.

The buses are python-can buses the node opened (``node.open_bus``): python-can makes the connection (handshake,
acceptance filters); the engine then reads and writes the socket itself, so no python-can ``Message`` is built per
frame. Frame times are the bus's end-of-transmission stamps in simulated seconds (``SimClock.from_epoch``).
"""
from __future__ import annotations

import contextlib
import time
from typing import Callable

import can
import trainhil_engine as engine

from ecu_sim.runtime import Output, encode_outputs
from hil.runtime.realtime.pacing import SimClock, drain, wait_until
from hil.runtime.realtime.pycan_bus import TrainhilBus

FrameHandler = Callable[[int, int, bytes, float], None]  # (bus index, frame id, data, simulated arrival time)
MAX_SLEEP_S = 0.05  # wall seconds between stop checks
SYNC_GRACE_S = 0.05  # wall seconds a lazy reader waits past its read time for the server's SYNC


def _bell(bus: can.BusABC) -> int | None:
    """The server's bell a quiet reader's link rings (``TrainhilBus.bell_fileno``), None for any other bus."""
    return bus.bell_fileno() if isinstance(bus, TrainhilBus) else None


class EngineFrames:
    """The engine's FrameLink on each bus socket."""

    def __init__(self, clock: SimClock, buses: list[can.BusABC], extended: bool, fd: bool = False, brs: bool = True,
                 packing: engine.Packing | None = None, lazy: bool = False) -> None:
        self.clock, self.extended, self.fd, self.brs, self.lazy, self.packing = clock, extended, fd, brs, lazy, packing
        self.links = [engine.FrameLink(bus.fileno(), clock.t0, clock.pace, keep=True, lazy=lazy, bell=_bell(bus))
                      for bus in buses]
        self.group = engine.LinkGroup(self.links)  # a lazy reader's waits, on every bus at once
        if packing is not None:
            for link in self.links:
                link.set_packing(packing)
        self._fds = [link.fd for link in self.links]

    def route(self, bus: int, frame_id: int, mailbox: engine.Mailbox) -> None:
        """Frames of ``frame_id`` on ``bus`` go into ``mailbox`` in the engine (never to ``on_frame``)."""
        self.links[bus].route(frame_id, mailbox)

    def route_commands(self, bus: int, inbox: engine.CommandInbox) -> None:
        """Frames of ``inbox.ids`` on ``bus`` go into the plant's ``inbox`` in the engine (never to ``on_frame``)."""
        self.links[bus].route_commands(inbox)

    def drain(self, on_frame: FrameHandler | None = None) -> None:
        """Everything waiting on every bus; ``on_frame`` sees the frames in time order across the buses."""
        taken = [(i, link.take()) for i, link in enumerate(self.links)]
        if on_frame is not None:
            _hand_over(on_frame, [(i, frames) for i, frames in taken if frames])

    def wait_any(self, wall_s: float, on_frame: FrameHandler | None) -> None:
        """Sleep until a frame arrives or ``wall_s`` passed, then hand over what waits."""
        engine.wait_readable(self._fds, max(wall_s, 0.0))
        self.drain(on_frame)

    def read_every(self, first: float, period: float, buses: list[int] | None = None, turns: bool = False) -> None:
        """A lazy reader's read times ``first + k * period`` (simulated s) on ``buses`` (default: every bus);
        nothing for an eager one. A wait at such a time waits for those buses' SYNCs only.

        ``turns``: each read time is the node's turn. Its frames then carry the read time however late it sends
        them, and its bus servers run no further than that instant until it ends the turn (``end_turn``, or a
        ``send(..., end_turn=True)``), up to ``TURN_HOLD_MAX_S`` of wall time: what it sends in the turn competes
        for the bus at that instant, as in virtual time, though its work takes wall time."""
        if self.lazy:
            for i in range(len(self.links)) if buses is None else buses:
                self.group.read_every(i, first, period, turns)

    def sends_at_least(self, bus: int, data_bytes: int) -> None:
        """Every frame this node will send on ``bus`` carries at least ``data_bytes`` bytes (said before its first):
        that bus's server need not wait for a shorter frame before it SYNCs a read, so it SYNCs reads up to that
        frame's length ahead at once (protocol LEAST_DATA), and refuses a shorter frame. Nothing with containers,
        whose parts may be shorter."""
        if self.lazy and self.packing is None:
            self.links[bus].sends_at_least(data_bytes)

    def name_sender(self, bus: int, sender: int, name: str) -> None:
        """Call ``sender``'s bus node on ``bus`` ``name`` (said before its first frame; protocol SENDER_NAME): an
        ECU process names each unit's TX queue as virtual time names that unit's node."""
        self.links[bus].name_sender(sender, name)

    def end_turn(self, buses: list[int] | None = None) -> None:
        """End the node's open turns on ``buses`` (default: every bus; see ``read_every``): it sends nothing more
        there before its next read time. A turn left open ends when the node next waits for a later instant."""
        if self.lazy:
            self.group.end_turn(buses)

    def end_turns_for_good(self) -> None:
        """The node's turns are over (its run ended): its servers hold their buses for none of its read times any
        more, so lingering after its last turn does not hold them (each would be let go and counted). A server
        already gone holds nothing: the node goes on to save its results."""
        if self.lazy:
            with contextlib.suppress(ConnectionError, OSError):
                self.group.end_turns_for_good()

    def wait(self, sim_t: float, on_frame: FrameHandler | None, stop, spin_s: float = 0.0) -> None:
        """Sleep to ``sim_t`` (the last ``spin_s`` polled), then hand over every frame that arrived meanwhile.

        No wake-up per frame: mailboxes keep the latest frame of each stream, and a handler gets the frames in
        time order with their bus timestamps, so taking them at once is the same as taking them one by one.

        A lazy reader sleeps on its sockets instead, until each server's SYNC of ``sim_t``, which may come up to
        one frame before ``sim_t`` (the server's ``anticipate``: while a frame on the wire ends after it, or within
        the least frame any connection could still send, ``sends_at_least``): it then has every frame that will
        have ended by ``sim_t``, so it acts at once, as at ``sim_t``. Its frames sent from then on carry ``sim_t`` while that is still ahead
        (``FrameLink.act_at``), and the server queues them at that instant. One wake-up per read, on the SYNC,
        rather than a timer's and then the SYNC's."""
        if not self.lazy:
            self._sleep_until(sim_t, stop, spin_s)
            self.drain(on_frame)
            return
        self._wait_synced(sim_t, stop)
        taken = self.group.finish(sim_t)
        if on_frame is not None and taken:
            _hand_over(on_frame, taken)

    def _sleep_until(self, sim_t: float, stop, spin_s: float = 0.0) -> None:
        """Sleep to ``sim_t``, noticing a stop request every MAX_SLEEP_S; the last ``spin_s`` wall seconds polled."""
        while not stop and (rem := self.clock.wall_until(sim_t) - spin_s) > 0:
            time.sleep(min(rem, MAX_SLEEP_S))
        while not stop and self.clock.wall_until(sim_t) > 0:
            pass

    def _wait_synced(self, sim_t: float, stop) -> None:
        """Until every bus server has synced us to ``sim_t`` (asking once if it is not a foreseen read time), or
        SYNC_GRACE_S past it (a server that does not answer: go on with what came). The buses are waited for
        together (one sleep for whichever SYNC comes next), so a node on several buses does not wake once per bus;
        the engine's ``LinkGroup`` does the bookkeeping, so a wait whose SYNCs are here is one call."""
        waiting = self.group.begin_wait(sim_t)
        while waiting and not stop:
            left = self.clock.wall_until(sim_t)
            if left < -SYNC_GRACE_S:
                break
            waiting = self.group.wait_more(sim_t, min(max(left, 0.0) + SYNC_GRACE_S, MAX_SLEEP_S))

    def send(self, bus: int, frames: list[tuple[int, bytes]], sender: int = 0, end_turn: bool = False) -> None:
        """``end_turn``: the frames end the node's turn on this bus (``read_every``), in the same write."""
        self.links[bus].send(frames, self.extended, self.fd, self.brs, sender, end_turn)

    def send_outputs(self, bus: int, outputs: list[Output], sender: int = 0, end_turn: bool = False) -> None:
        self.links[bus].send_encoded(outputs, self.extended, self.fd, self.brs, sender, end_turn)


def _hand_over(on_frame: FrameHandler, batches: list[tuple[int, list[tuple[int, bytes, float]]]]) -> None:
    """Each bus's frames [(bus, [(frame_id, data, t)])] to ``on_frame``, in time order across the buses."""
    if len(batches) == 1:
        i, frames = batches[0]
        for frame_id, data, t in frames:
            on_frame(i, frame_id, data, t)
        return
    merged = sorted(((t, i, k, fid, data) for i, frames in batches for k, (fid, data, t) in enumerate(frames)))
    for t, i, _, frame_id, data in merged:
        on_frame(i, frame_id, data, t)


class PythonCanFrames:
    """python-can in both directions (SocketCAN); routed mailboxes are filled from Python."""

    def __init__(self, clock: SimClock, buses: list[can.BusABC], extended: bool, fd: bool = False, brs: bool = True,
                 packing: engine.Packing | None = None) -> None:
        self.clock, self.buses, self.extended, self.fd, self.brs = clock, buses, extended, fd, brs
        self.packing = packing
        self._routes: list[dict[int, list[engine.Mailbox | engine.CommandInbox]]] = [{} for _ in buses]
        self._handler: FrameHandler | None = None

    def route(self, bus: int, frame_id: int, mailbox: engine.Mailbox) -> None:
        self._routes[bus].setdefault(frame_id, []).append(mailbox)

    def route_commands(self, bus: int, inbox: engine.CommandInbox) -> None:
        for frame_id in inbox.ids:
            self._routes[bus].setdefault(frame_id, []).append(inbox)

    def read_every(self, first: float, period: float, buses: list[int] | None = None, turns: bool = False) -> None:
        """Nothing: python-can delivers every frame at its end."""

    def sends_at_least(self, bus: int, data_bytes: int) -> None:
        """Nothing: a SocketCAN bus has no server to tell."""

    def name_sender(self, bus: int, sender: int, name: str) -> None:
        """Nothing: on SocketCAN a process's frames leave through one socket."""

    def end_turn(self, buses: list[int] | None = None) -> None:
        """Nothing: a SocketCAN bus runs on the host's clock, with no turns."""

    def end_turns_for_good(self) -> None:
        """Nothing: a SocketCAN bus runs on the host's clock, with no turns."""

    def _on_msg(self, i: int, msg: can.Message) -> None:
        t, fid, data = self.clock.from_epoch(msg.timestamp), msg.arbitration_id, bytes(msg.data)
        parts = self.packing.unpack(fid, data) if self.packing is not None else None
        for part_id, part in parts if parts is not None else [(fid, data)]:
            self._hand_over(i, part_id, part, t)

    def _hand_over(self, i: int, fid: int, data: bytes, t: float) -> None:
        boxes = self._routes[i].get(fid)
        if boxes is not None:
            for mb in boxes:
                mb.put(fid, data, t)
        elif self._handler is not None:
            self._handler(i, fid, data, t)

    def drain(self, on_frame: FrameHandler | None = None) -> None:
        self._handler = on_frame
        drain(self.buses, self._on_msg, 0.0)

    def wait_any(self, wall_s: float, on_frame: FrameHandler | None) -> None:
        self._handler = on_frame
        drain(self.buses, self._on_msg, wall_s)

    def wait(self, sim_t: float, on_frame: FrameHandler | None, stop, spin_s: float = 0.0) -> None:
        self._handler = on_frame
        wait_until(self.clock, sim_t, self.buses, self._on_msg, spin_s)

    def send_outputs(self, bus: int, outputs: list[Output], sender: int = 0, end_turn: bool = False) -> None:
        self.send(bus, encode_outputs(outputs))

    def send(self, bus: int, frames: list[tuple[int, bytes]], sender: int = 0, end_turn: bool = False) -> None:
        """``sender`` is not told apart: the kernel queues one socket's frames together; no turns here."""
        for frame_id, data in self.packing.pack(frames) if self.packing is not None else frames:
            self.buses[bus].send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=self.extended,
                                             is_fd=self.fd, bitrate_switch=self.fd and self.brs))


def node_frames(clock: SimClock, buses: list[can.BusABC], can_cfg,
                packing: engine.Packing | None = None, lazy: bool = False) -> EngineFrames | PythonCanFrames:
    """The engine on the rig's emulated buses, python-can on SocketCAN; ``packing``: CAN FD containers; ``lazy``:
    a lazy reader (the buses were opened with ``open_bus(lazy=True)``; emulated buses only)."""
    if can_cfg.transport == "emulated":
        return EngineFrames(clock, buses, can_cfg.extended_ids, can_cfg.fd, can_cfg.brs, packing, lazy)
    return PythonCanFrames(clock, buses, can_cfg.extended_ids, can_cfg.fd, can_cfg.brs, packing)
