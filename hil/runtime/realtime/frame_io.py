"""How a real-time node's frames move: through the engine (``FrameLink``) on the emulated buses, through python-can on
SocketCAN. Both have one interface, so the node loops do not care which:

* ``wait(sim_t, on_frame, stop, spin_s=0)``: receive until simulated time ``sim_t`` (sleeping; the last ``spin_s``
  wall seconds polled), handing every frame to ``on_frame(bus, frame_id, data, t_sim)`` or, for ECU mailboxes
  routed with ``route``, straight into the mailbox;
* ``drain(on_frame)``: whatever waits now; ``wait_any(wall_s, on_frame)``: the first frames within ``wall_s``;
* ``send(bus, frames)``: queue ``[(frame_id, data)]`` on bus ``bus``.

With a CAN FD frame packing (``can.dbc = "train_fd.dbc"``), each ``send`` batch goes as its containers and every
container received is handed over as the frames it carries (``trainhil_engine.Packing``), in both classes.

The buses are python-can buses the node opened (``node.open_bus``): python-can makes the connection (handshake,
acceptance filters); the engine then reads and writes the socket itself, so no python-can ``Message`` is built per
frame. Frame times are the bus's end-of-transmission stamps in simulated seconds (``SimClock.from_epoch``).
"""
from __future__ import annotations

import time
from typing import Callable

import can
import trainhil_engine as engine

from hil.runtime.realtime.pacing import SimClock, drain, wait_until

FrameHandler = Callable[[int, int, bytes, float], None]  # (bus index, frame id, data, simulated arrival time)
MAX_SLEEP_S = 0.05  # wall seconds between stop checks


class EngineFrames:
    """The engine's FrameLink on each bus socket."""

    def __init__(self, clock: SimClock, buses: list[can.BusABC], extended: bool, fd: bool = False, brs: bool = True,
                 packing: engine.Packing | None = None) -> None:
        self.clock, self.extended, self.fd, self.brs = clock, extended, fd, brs
        self.links = [engine.FrameLink(bus.fileno(), clock.t0, clock.pace, keep=True) for bus in buses]
        if packing is not None:
            for link in self.links:
                link.set_packing(packing)
        self._fds = [link.fd for link in self.links]

    def route(self, bus: int, frame_id: int, mailbox: engine.Mailbox) -> None:
        """Frames of ``frame_id`` on ``bus`` go into ``mailbox`` in the engine (never to ``on_frame``)."""
        self.links[bus].route(frame_id, mailbox)

    def drain(self, on_frame: FrameHandler | None = None) -> None:
        """Everything waiting on every bus; ``on_frame`` sees the frames in time order across the buses."""
        taken = [(i, link.take()) for i, link in enumerate(self.links)]
        if on_frame is None:
            return
        batches = [(i, frames) for i, frames in taken if frames]
        if len(batches) == 1:
            i, frames = batches[0]
            for frame_id, data, t in frames:
                on_frame(i, frame_id, data, t)
        elif batches:
            merged = sorted(((t, i, k, fid, data) for i, frames in batches for k, (fid, data, t) in enumerate(frames)))
            for t, i, _, frame_id, data in merged:
                on_frame(i, frame_id, data, t)

    def wait_any(self, wall_s: float, on_frame: FrameHandler | None) -> None:
        """Sleep until a frame arrives or ``wall_s`` passed, then hand over what waits."""
        engine.wait_readable(self._fds, max(wall_s, 0.0))
        self.drain(on_frame)

    def wait(self, sim_t: float, on_frame: FrameHandler | None, stop, spin_s: float = 0.0) -> None:
        """Sleep to ``sim_t`` (the last ``spin_s`` polled), then hand over every frame that arrived meanwhile.

        No wake-up per frame: mailboxes keep the latest frame of each stream, and a handler gets the frames in
        time order with their bus timestamps, so taking them at once is the same as taking them one by one."""
        clock = self.clock
        while not stop:
            rem = clock.wall_until(sim_t) - spin_s
            if rem <= 0:
                break
            time.sleep(min(rem, MAX_SLEEP_S))
        while clock.wall_until(sim_t) > 0 and not stop:
            pass
        self.drain(on_frame)

    def send(self, bus: int, frames: list[tuple[int, bytes]]) -> None:
        self.links[bus].send(frames, self.extended, self.fd, self.brs)


class PythonCanFrames:
    """python-can in both directions (SocketCAN); routed mailboxes are filled from Python."""

    def __init__(self, clock: SimClock, buses: list[can.BusABC], extended: bool, fd: bool = False, brs: bool = True,
                 packing: engine.Packing | None = None) -> None:
        self.clock, self.buses, self.extended, self.fd, self.brs = clock, buses, extended, fd, brs
        self.packing = packing
        self._routes: list[dict[int, list[engine.Mailbox]]] = [{} for _ in buses]
        self._handler: FrameHandler | None = None

    def route(self, bus: int, frame_id: int, mailbox: engine.Mailbox) -> None:
        self._routes[bus].setdefault(frame_id, []).append(mailbox)

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

    def send(self, bus: int, frames: list[tuple[int, bytes]]) -> None:
        for frame_id, data in self.packing.pack(frames) if self.packing is not None else frames:
            self.buses[bus].send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=self.extended,
                                             is_fd=self.fd, bitrate_switch=self.fd and self.brs))


def node_frames(clock: SimClock, buses: list[can.BusABC], can_cfg,
                packing: engine.Packing | None = None) -> EngineFrames | PythonCanFrames:
    """The engine on the rig's emulated buses, python-can on SocketCAN; ``packing``: CAN FD containers."""
    cls = EngineFrames if can_cfg.transport == "emulated" else PythonCanFrames
    return cls(clock, buses, can_cfg.extended_ids, can_cfg.fd, can_cfg.brs, packing)
