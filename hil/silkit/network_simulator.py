"""trainhil as SIL Kit's network simulator for one CAN network, on the engine's bus model (the one every run of the
rig uses): each SIL Kit CAN controller is a node of an engine bus, so its frames are queued (TX queue depth;
overflow acknowledged ``TransmitQueueFull``), arbitrated, timed to the bit and delivered to every other controller
with their end-of-frame timestamp, the sender getting its ``Transmitted`` acknowledgement at the same instant.

**When a frame was sent.** SIL Kit's frame request carries no time, and under its time synchronisation a
participant may start its step t while the simulator is still between its own steps, so "the simulator's time when
the request arrived" depends on thread timing (measured: two runs of the same participants differed). The
simulator therefore steps at half the participants' step Δ and works only at the half steps: a participant's step
kΔ can only begin once the simulator has finished its step kΔ - Δ/2, and everything it sends has arrived before the
simulator's step kΔ + Δ/2 begins. So at that half step the requests that came since the last one are exactly those
sent in step kΔ, and are stamped kΔ; every arbitration that starts before (k + 1)Δ is then decided, and each frame
that ends by (k + 1)Δ is produced at once, which SIL Kit hands to the receivers before their step (k + 1)Δ. A frame
is seen in the first step at or after its end, with its exact end time, and the run does not depend on thread
timing. Participants must step on the Δ grid (a finer sender's frames are stamped at the Δ point before them).
A frame that ends exactly on a step boundary (k + 1)Δ is produced a step later. The engine's objects live on the
simulator's step thread: SIL Kit's callbacks only record what they are told. Under bus faults the engine's error
confinement counts a SIL Kit controller's errors like any node's, and each change of its error state (error
passive, bus-off, active again) is sent to it (``error_state_changed``). On a CAN FD bus SIL Kit controllers send
and receive CAN FD frames (FDF, BRS as the bus); the bus has one format, so a frame of the other is refused. Not
yet: per-controller bit rates (the bus has one; a controller that sets another is counted in
``bitrate_mismatches``).
"""
from __future__ import annotations

import ctypes
import threading
from dataclasses import dataclass
from typing import Any

from hil.silkit import capi
from hil.silkit.capi import Library
from trainhil_engine import Network


ERROR_STATES = {"error_passive": capi.ERROR_PASSIVE, "bus_off": capi.BUS_OFF, "error_active": capi.ERROR_ACTIVE,
                "recovered": capi.ERROR_ACTIVE}  # the engine's error-model events -> SIL Kit's CanErrorState


def node_name(descriptor: int) -> str:
    """The engine node name of the SIL Kit controller ``descriptor`` (what the run's events call it)."""
    return f"silkit:{descriptor}"


@dataclass
class SimulatedController:
    """What the simulator knows of one SIL Kit controller: its engine node, bit rate and state."""

    descriptor: int
    node: int | None = None  # attached to the engine bus at the next half step (the engine's thread)
    bitrate: int | None = None
    started: bool = True


def create_simulator(lib: Library, participant_handle: Any) -> ctypes.c_void_p:
    """The participant's network simulator (one per participant; start it once, after its networks are added)."""
    handle = ctypes.c_void_p()
    lib.call("SilKit_Experimental_NetworkSimulator_Create", ctypes.byref(handle), participant_handle)
    return handle


def start_simulator(lib: Library, simulator: ctypes.c_void_p) -> None:
    """Begin simulating every network added to ``simulator`` (before the lifecycle starts)."""
    lib.call("SilKit_Experimental_NetworkSimulator_Start", simulator)


class CanNetworkSimulator:
    """The simulated CAN network ``network`` of participant ``participant_handle`` (see the module docstring)."""

    def __init__(self, lib: Library, participant_handle: Any, network: str, grid_ns: int, bitrate: int = 500_000,
                 tx_queue_depth: int = 64, bus: tuple[Network, int] | None = None,
                 simulator: ctypes.c_void_p | None = None, fd: bool = False, data_bitrate: int | None = None,
                 brs: bool = True) -> None:
        """``bus``: an engine network and bus index to put the controllers on (the rig's own bus, whose clock the rig
        advances and whose frames it hands to :meth:`frame_ended`); default: a network of the simulator's own,
        driven by :meth:`step`. ``simulator``: the participant's network simulator when it simulates several
        networks (SIL Kit allows one per participant: :func:`create_simulator`); default: one made here. ``fd``,
        ``data_bitrate``, ``brs``: a CAN FD bus (the rig's bus says so itself: pass the scenario's), whose every
        frame is CAN FD; a frame whose format the bus does not carry (:meth:`_fits`) is acknowledged ``Canceled``
        and counted in ``format_refused``."""
        if grid_ns <= 0 or grid_ns % 2:
            raise ValueError(f"grid_ns = {grid_ns}: the participants' step must be a positive, even number of ns")
        self.lib, self.network, self.grid_ns, self.bitrate = lib, network, grid_ns, bitrate
        self.step_ns = grid_ns // 2  # the simulator's own step (see the module docstring)
        self.controllers: dict[int, SimulatedController] = {}  # those on the network now
        self.controllers_seen = 0  # every controller SIL Kit gave the network, also those since removed
        self.queue_full = 0
        self.format_refused = 0  # frames whose CAN format the bus does not carry (see _fits)
        self.bitrate_mismatches = 0
        self.fd, self._data_bitrate, self._brs = fd, data_bitrate, brs
        self._lock = threading.Lock()
        self._arrived: list[tuple[int, int, int, bytes, Any]] = []  # requests since the last half step
        self._contexts: dict[tuple[int, int], list[Any]] = {}  # (node, id) -> user contexts of frames queued
        self._net: Network | None = bus[0] if bus else None
        self._bus = bus[1] if bus else 0
        self._depth = tx_queue_depth
        self._by_node: dict[int, int] = {}  # engine node -> controller descriptor
        self._by_name: dict[str, int] = {}  # engine node name -> controller descriptor
        self._producer: Any = None
        self._keep: list[Any] = []
        self._controller_functions = capi.new(
            capi.SimulatedCanControllerFunctions, OnSetBaudrate=self._keep_fn(capi.OnSetBaudrate(self._on_baudrate)),
            OnFrameRequest=self._keep_fn(capi.OnFrameRequest(self._on_frame_request)),
            OnSetControllerMode=self._keep_fn(capi.OnSetControllerMode(self._on_mode)))
        self._network_functions = capi.new(
            capi.SimulatedNetworkFunctions,
            ProvideSimulatedController=self._keep_fn(capi.ProvideController(self._provide)),
            SimulatedControllerRemoved=self._keep_fn(capi.ControllerRemoved(self._removed)),
            SetEventProducer=self._keep_fn(capi.SetEventProducer(self._set_producer)))
        self.handle = simulator if simulator is not None else create_simulator(lib, participant_handle)
        self._context = ctypes.c_int(1)  # SIL Kit wants a non-null network context; ours lives in self
        lib.call("SilKit_Experimental_NetworkSimulator_SimulateNetwork", self.handle, network.encode(),
                 capi.NETWORK_CAN, ctypes.byref(self._context), ctypes.byref(self._network_functions))

    def start(self) -> None:
        """Begin simulating (call before the lifecycle starts; with a shared simulator, once: start_simulator)."""
        start_simulator(self.lib, self.handle)

    def _keep_fn(self, fn: Any) -> Any:
        self._keep.append(fn)
        return fn

    # ------------------------------------------------------------------ SIL Kit's callbacks (its I/O thread)

    def _provide(self, out_controller: Any, out_functions: Any, descriptor: int, network: Any) -> None:
        with self._lock:
            self.controllers[descriptor] = SimulatedController(descriptor)
            self.controllers_seen += 1
        out_controller[0] = ctypes.c_void_p(descriptor)  # our handle for it is its descriptor
        out_functions[0] = ctypes.cast(ctypes.pointer(self._controller_functions), ctypes.c_void_p)

    def _removed(self, descriptor: int, network: Any) -> None:
        with self._lock:
            self.controllers.pop(descriptor, None)

    def _set_producer(self, producer: Any, network: Any) -> None:
        self._producer = producer

    def _on_baudrate(self, controller: Any, config: Any) -> None:
        with self._lock:
            c = self.controllers.get(int(controller or 0))
            if c is not None and config.contents.rate:
                c.bitrate = int(config.contents.rate)
                if c.bitrate != self.bitrate:
                    self.bitrate_mismatches += 1

    def _on_mode(self, controller: Any, mode: Any) -> None:
        with self._lock:
            c = self.controllers.get(int(controller or 0))
            if c is not None:
                c.started = mode.contents.state == capi.CONTROLLER_STARTED

    def _on_frame_request(self, controller: Any, request: Any) -> None:
        frame = request.contents.frame.contents
        data = ctypes.string_at(frame.data.data, frame.data.size) if frame.data.size else b""
        with self._lock:  # stamped at the next half step; one sender's requests keep their order
            self._arrived.append((int(controller or 0), int(frame.id), int(frame.flags), data,
                                  request.contents.userContext))

    # ------------------------------------------------------------------ the bus (the rig's step)

    def step(self, now_ns: int, duration_ns: int) -> None:
        """The simulator's step at ``now`` (every Δ/2), on a network of its own: at the half steps kΔ + Δ/2, queue
        what arrived at kΔ on the engine bus, run it to (k + 1)Δ and produce every frame that ended before then."""
        if now_ns % self.grid_ns != self.step_ns:
            return
        net, bus = self._engine()
        sent_at = now_ns - self.step_ns
        net.advance(sent_at)
        self.inject(sent_at)
        net.advance(sent_at + self.grid_ns)
        for can_id, data, extended, _, _, end, node, fd, brs in net.take_trace(bus):
            self.frame_ended(node, can_id, data, extended, end, fd, brs)

    def inject(self, sent_at: int) -> None:
        """Queue the requests that arrived since the last half step on the engine bus, whose clock is at
        ``sent_at``; a request refused (a full TX queue, a format the bus does not carry) is acknowledged so."""
        net, bus = self._engine()
        for descriptor, can_id, context, status in self._queue(net, bus):
            self._acknowledge(descriptor, can_id, status, sent_at, context)

    def frame_ended(self, node: int, can_id: int, data: bytes, extended: bool, end_ns: int, fd: bool = False,
                    brs: bool = False) -> None:
        """A frame the engine carried to its end: to every SIL Kit controller but its sender (flagged FDF, and BRS,
        when it was a CAN FD frame), and the sender's acknowledgement when a SIL Kit controller sent it."""
        sender = self._by_node.get(node)
        if sender is None and not self._by_node:
            return  # no SIL Kit controller on this bus (yet): nothing to hand over
        context = None
        if sender is not None:
            queued = self._contexts.get((node, can_id))
            context = queued.pop(0) if queued else None
        with self._lock:
            receivers = [d for d, c in self.controllers.items() if d != sender and c.started and c.node is not None]
        flags = (capi.FLAG_IDE if extended else 0) | (capi.FLAG_FDF if fd else 0) | (capi.FLAG_BRS if fd and brs else 0)
        self._deliver(sender, can_id, data, flags, end_ns, receivers, context)

    def error_state_changed(self, node_name: str, kind: str, t_ns: int) -> None:
        """An engine error-model event (``error_passive``, ``bus_off``, ``error_active``, ``recovered``) of node
        ``node_name``: when it is a SIL Kit controller's, its new error state goes to that controller."""
        state = ERROR_STATES.get(kind)
        descriptor = self._by_name.get(node_name)
        if state is None or descriptor is None:
            return
        event = capi.new(capi.CanErrorStateChangeEvent, timestamp=t_ns, errorState=state)
        self._produce(event, [descriptor])

    def _engine(self) -> tuple[Network, int]:
        """The engine network and bus (made here, on the step thread, when the simulator has its own), with every
        known controller attached."""
        if self._net is None:
            self._net = Network()
            self._bus = self._net.add_bus(self.network, self.bitrate, "priority", self._depth, fd=self.fd,
                                          data_bitrate=self._data_bitrate, brs=self._brs)
            self._net.set_trace(self._bus, True)
        with self._lock:
            new = [c for c in self.controllers.values() if c.node is None]
        for c in sorted(new, key=lambda c: c.descriptor):
            name = node_name(c.descriptor)
            c.node = self._net.attach_sender(self._bus, name)
            self._by_node[c.node] = c.descriptor
            self._by_name[name] = c.descriptor
        return self._net, self._bus

    def _fits(self, flags: int, data: bytes) -> bool:
        """Whether the bus carries this frame: every frame of a CAN FD bus is CAN FD (the engine's bus has one
        format), so a classical request there is refused, as an FD one (or more than 8 bytes) on a classical bus."""
        return bool(flags & capi.FLAG_FDF) == self.fd and (self.fd or len(data) <= 8)

    def _queue(self, net: Network, bus: int) -> list[tuple[int, int, Any, int]]:
        """Send the requests that arrived since the last half step into the engine at its current time, controller
        by controller (each one's in its own order: the run does not depend on which controller's came first);
        returns (controller, id, context, status) of those refused: a full TX queue, a format the bus does not
        carry."""
        with self._lock:
            arrived, self._arrived = self._arrived, []
            nodes = {d: c.node for d, c in self.controllers.items()}
        refused = []
        for descriptor, can_id, flags, data, context in sorted(arrived, key=lambda r: r[0]):  # stable: keeps order
            node = nodes.get(descriptor)
            if node is None:
                continue
            if not self._fits(flags, data):
                self.format_refused += 1
                refused.append((descriptor, can_id, context, capi.CANCELED))
            elif net.send(bus, node, can_id, data):
                self._contexts.setdefault((node, can_id), []).append(context)
            else:
                self.queue_full += 1
                refused.append((descriptor, can_id, context, capi.TRANSMIT_QUEUE_FULL))
        return refused

    def _deliver(self, sender: int | None, can_id: int, data: bytes, flags: int, end_ns: int, receivers: list[int],
                 context: Any) -> None:
        """The frame to the ``receivers``, and the acknowledgement to its sender (a SIL Kit one), at ``end_ns``."""
        payload = (ctypes.c_uint8 * max(1, len(data))).from_buffer_copy(data.ljust(1, b"\0"))
        frame = capi.new(capi.CanFrame, id=can_id, flags=flags, dlc=len(data),
                         data=capi.ByteVector(ctypes.cast(payload, ctypes.POINTER(ctypes.c_uint8)), len(data)))
        event = capi.new(capi.CanFrameEvent, timestamp=end_ns, frame=ctypes.pointer(frame),
                         direction=capi.DIRECTION_RECEIVE, userContext=None)
        if receivers:
            self._produce(event, receivers)
        if sender is not None:
            self._acknowledge(sender, can_id, capi.TRANSMITTED, end_ns, context)

    def _acknowledge(self, descriptor: int, can_id: int, status: int, t_ns: int, context: Any) -> None:
        ack = capi.new(capi.CanFrameTransmitEvent, userContext=context, timestamp=t_ns, status=status, canId=can_id)
        self._produce(ack, [descriptor])

    def _produce(self, message: Any, receivers: list[int]) -> None:
        if self._producer is None:
            return
        ids = (ctypes.c_uint64 * len(receivers))(*receivers)
        to = capi.new(capi.EventReceivers, numReceivers=len(receivers), controllerDescriptors=ids)
        self.lib.call("SilKit_Experimental_CanEventProducer_Produce", self._producer,
                      ctypes.cast(ctypes.byref(message), ctypes.POINTER(capi.StructHeader)), ctypes.byref(to))
