"""trainhil as SIL Kit's network simulator for one CAN network: every controller's frames queued (TX queue depth;
overflow acknowledged ``TransmitQueueFull``), arbitrated (lowest ID first among the queue heads when the bus goes
idle), timed to the bit (the frame's exact stuffed length at the controller's bit rate, plus the 3-bit
intermission) and delivered to every other controller with their end-of-frame timestamp, the sender getting its
``Transmitted`` acknowledgement at the same instant.

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
This first version models one classical CAN bus without error injection; the engine's bus model (error
confinement, faults, CAN FD) is the next step.
"""
from __future__ import annotations

import ctypes
import threading
from dataclasses import dataclass, field
from typing import Any

from hil.can.frame import frame_bits, frame_duration_ns
from hil.silkit import capi
from hil.silkit.capi import Library

INTERMISSION_BITS = 3


@dataclass
class Request:
    """One frame a controller asked to send."""

    controller: int  # its controller descriptor
    can_id: int
    flags: int
    data: bytes
    user_context: int | None
    requested_ns: int


@dataclass
class SimulatedController:
    """What the simulator knows of one controller: its bit rate, state and TX queue."""

    descriptor: int
    bitrate: int = 500_000
    started: bool = True
    queue: list[Request] = field(default_factory=list)


class CanNetworkSimulator:
    """The simulated CAN network ``network`` of participant ``participant_handle`` (see the module docstring)."""

    def __init__(self, lib: Library, participant_handle: Any, network: str, grid_ns: int,
                 tx_queue_depth: int = 64) -> None:
        if grid_ns <= 0 or grid_ns % 2:
            raise ValueError(f"grid_ns = {grid_ns}: the participants' step must be a positive, even number of ns")
        self.lib, self.network, self.depth, self.grid_ns = lib, network, tx_queue_depth, grid_ns
        self.step_ns = grid_ns // 2  # the simulator's own step (see the module docstring)
        self.controllers: dict[int, SimulatedController] = {}
        self.delivered: list[tuple[int, int, int, bytes]] = []  # (end ns, sender, id, data): what went on the bus
        self.queue_full = 0
        self._lock = threading.Lock()
        self._arrived: list[tuple[int, int, int, bytes, Any]] = []  # requests since the last half step
        self._in_flight: list[tuple[Request, int, list[int]]] = []  # won the bus, end after the last horizon
        self._bus_free_ns = 0
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
        self.handle = ctypes.c_void_p()
        lib.call("SilKit_Experimental_NetworkSimulator_Create", ctypes.byref(self.handle), participant_handle)
        self._context = ctypes.c_int(1)  # SIL Kit wants a non-null network context; ours lives in self
        lib.call("SilKit_Experimental_NetworkSimulator_SimulateNetwork", self.handle, network.encode(),
                 capi.NETWORK_CAN, ctypes.byref(self._context), ctypes.byref(self._network_functions))

    def start(self) -> None:
        """Begin simulating (call before the lifecycle starts)."""
        self.lib.call("SilKit_Experimental_NetworkSimulator_Start", self.handle)

    def _keep_fn(self, fn: Any) -> Any:
        self._keep.append(fn)
        return fn

    # ------------------------------------------------------------------ SIL Kit's callbacks (its I/O thread)

    def _provide(self, out_controller: Any, out_functions: Any, descriptor: int, network: Any) -> None:
        with self._lock:
            self.controllers[descriptor] = SimulatedController(descriptor)
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

    def _on_mode(self, controller: Any, mode: Any) -> None:
        with self._lock:
            c = self.controllers.get(int(controller or 0))
            if c is not None:
                c.started = mode.contents.state == capi.CONTROLLER_STARTED
                if mode.contents.canControllerModeFlags & 2:  # CancelTransmitRequests
                    c.queue.clear()

    def _on_frame_request(self, controller: Any, request: Any) -> None:
        frame = request.contents.frame.contents
        data = ctypes.string_at(frame.data.data, frame.data.size) if frame.data.size else b""
        with self._lock:  # stamped at the next half step; one sender's requests keep their order
            self._arrived.append((int(controller or 0), int(frame.id), int(frame.flags), data,
                                  request.contents.userContext))

    # ------------------------------------------------------------------ the bus (the rig's step)

    def step(self, now_ns: int, duration_ns: int) -> None:
        """The simulator's step at ``now`` (every Δ/2): at the half steps kΔ + Δ/2, stamp what arrived with kΔ, run
        the bus to (k + 1)Δ and produce every frame that ends by then."""
        if now_ns % self.grid_ns != self.step_ns:
            return
        sent_at = now_ns - self.step_ns
        horizon = sent_at + self.grid_ns
        full = self._enqueue(sent_at)
        for descriptor, can_id, context in full:
            self._acknowledge(descriptor, can_id, capi.TRANSMIT_QUEUE_FULL, sent_at, context)
        with self._lock:
            while (winner := self._arbitrate(horizon)) is not None:
                request, start = winner
                bitrate = self.controllers[request.controller].bitrate
                bits = frame_bits(request.can_id, request.data, bool(request.flags & capi.FLAG_IDE))
                end = start + frame_duration_ns(bits, bitrate)
                self.controllers[request.controller].queue.remove(request)
                self._bus_free_ns = end + frame_duration_ns(INTERMISSION_BITS, bitrate)
                receivers = [d for d, c in self.controllers.items() if d != request.controller and c.started]
                self._in_flight.append((request, end, receivers))
            due = [f for f in self._in_flight if f[1] <= horizon]
            self._in_flight = [f for f in self._in_flight if f[1] > horizon]
        for request, end, receivers in due:
            self.delivered.append((end, request.controller, request.can_id, request.data))
            self._deliver(request, end, receivers)

    def _enqueue(self, sent_at: int) -> list[tuple[int, int, Any]]:
        """The requests that arrived since the last half step into their controllers' TX queues, stamped
        ``sent_at``; returns (controller, id, context) of those a full queue refused."""
        full = []
        with self._lock:
            arrived, self._arrived = self._arrived, []
            for descriptor, can_id, flags, data, context in arrived:
                c = self.controllers.get(descriptor)
                if c is None:
                    continue
                if len(c.queue) >= self.depth:
                    self.queue_full += 1
                    full.append((descriptor, can_id, context))
                else:
                    c.queue.append(Request(descriptor, can_id, flags, data, context, sent_at))
        return full

    def _arbitrate(self, horizon_ns: int) -> tuple[Request, int] | None:
        """The queue head that wins the bus next and when it starts, if that is before ``horizon`` (later, a
        request not yet known could still contend), else None."""
        heads = [min(c.queue, key=lambda r: r.can_id) for c in self.controllers.values() if c.queue and c.started]
        if not heads:
            return None
        start = max(self._bus_free_ns, min(r.requested_ns for r in heads))
        if start >= horizon_ns:
            return None
        contenders = [r for r in heads if r.requested_ns <= start]
        return min(contenders, key=lambda r: r.can_id), start

    def _deliver(self, request: Request, end_ns: int, receivers: list[int]) -> None:
        """The frame to every other started controller, and the acknowledgement to its sender, at ``end_ns``."""
        payload = (ctypes.c_uint8 * max(1, len(request.data))).from_buffer_copy(request.data.ljust(1, b"\0"))
        frame = capi.new(capi.CanFrame, id=request.can_id, flags=request.flags, dlc=len(request.data),
                         data=capi.ByteVector(ctypes.cast(payload, ctypes.POINTER(ctypes.c_uint8)), len(request.data)))
        event = capi.new(capi.CanFrameEvent, timestamp=end_ns, frame=ctypes.pointer(frame),
                         direction=capi.DIRECTION_RECEIVE, userContext=None)
        if receivers:
            self._produce(event, receivers)
        self._acknowledge(request.controller, request.can_id, capi.TRANSMITTED, end_ns, request.user_context)

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
