"""The virtual-time network on the compiled frame engine: buses, radio and delivery run in Rust, Python only per task.

``EngineKernel`` has the interface of :class:`hil.runtime.kernel.Kernel` (``at``, ``every``, ``run``, ``now``), but
its queue is the engine's: every CAN frame event (arbitration, end of transmission, delivery into the mailboxes,
radio forwarding) is handled inside ``trainhil_engine.Network.advance``, which returns to Python only when one of
the rig's own tasks is due (a plant step, an ECU cycle, a wayside tick). Events at equal times keep their
scheduling order across both kinds, so the frame schedule is the one of the Python bus model.

``EngineBus`` is one train bus as the rig sees it: attach nodes, send frames, and ``frame_listeners`` (CAN logs,
frame rows) that are fed from the engine's trace once per chunk instead of once per frame.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import trainhil_engine as engine

from ecu_sim.runtime import Ecu, Output
from hil.can.bus_log import LOAD_WINDOW_S
from hil.can.transmission import Transmission
from hil.radio.gateway import RadioIds, link_name, standard_routes
from hil.radio.link import RadioLink
from hil.record.runlog import BusLog
from hil.runtime.kernel import to_ns
from hil.scenario.model import CanConfig

LOAD_WINDOW_NS = to_ns(LOAD_WINDOW_S)  # the bus model's load window


class EngineKernel:
    """The rig's tasks on the engine's event queue (SimPy-like: callbacks at integer-ns times)."""

    def __init__(self, net: engine.Network) -> None:
        self.net = net
        self._handlers: dict[int, Callable[[int], None]] = {}  # token -> fn(t_ns)
        self._once: set[int] = set()  # tokens of one-shot events (forgotten after they ran)
        # called whenever the engine hands back control, before any task runs (the fault machinery takes the
        # buses' error events there, so the log keeps the order they happened in)
        self.after_advance: Callable[[], None] | None = None

    @property
    def now(self) -> int:
        return self.net.now

    def at(self, t_ns: int, fn: Callable[[Any], None], arg: Any = None) -> None:
        """Run ``fn(arg)`` once when the clock reaches t_ns."""
        token = self.net.every(t_ns, 0)
        self._handlers[token] = lambda _t: fn(arg)
        self._once.add(token)

    def every(self, first_ns: int, period_ns: int, fn: Callable[[int], None]) -> None:
        """Run ``fn(t)`` at first_ns, first_ns + period_ns, ... (rescheduled after each run)."""
        if period_ns <= 0:
            raise ValueError(f"period must be positive, got {period_ns} ns")
        self._handlers[self.net.every(first_ns, period_ns)] = fn

    def run(self, until_ns: int) -> None:
        """Process every event with time < until_ns (frames in the engine, tasks here), then set the clock to it."""
        advance, handlers, once, after = self.net.advance, self._handlers, self._once, self.after_advance
        while (token := advance(until_ns)) is not None:
            if after is not None:
                after()
            handlers[token](self.net.now)
            if once and token in once:
                once.discard(token)
                del handlers[token]
        if after is not None:
            after()


class EngineBus:
    """One train bus in the engine: nodes are integer indices; statistics land in ``log`` at ``collect``. Its error
    model and guardian (``enable_bus_errors`` ...) are driven by ``hil.faults.bus.EngineBusFaults``."""

    packing = None  # set by set_packing
    after_send: Callable[[], None] | None = None  # called after each send (the fault machinery takes error events)

    def __init__(self, net: engine.Network, name: str, can: CanConfig, log: BusLog) -> None:
        self.net = net
        self.name = name
        self.bitrate = can.bitrate
        self.log = log
        self.index = net.add_bus(name, can.bitrate, can.queue_policy, can.tx_queue_depth, can.extended_ids, LOAD_WINDOW_NS,
                                 fd=can.fd, data_bitrate=can.data_rate, brs=can.brs)
        self.frame_listeners: list[Callable[[Transmission], None]] = []
        self._tracing = False

    def attach(self, name: str) -> int:
        """A node that only sends (the wayside, a test's sender)."""
        return self.net.attach_sender(self.index, name)

    def attach_ecu(self, name: str, ecu: Ecu) -> int:
        """A node delivering into the ECU's mailboxes, behind their IDs as acceptance filter."""
        return self.net.attach_mailbox(self.index, name, ecu.mailbox)

    def attached(self, node: int) -> bool:
        """Whether ``node`` is on this bus."""
        return self.net.attached(self.index, node)

    def detach(self, node: int) -> int:
        """Take a node off the bus (a crashed ECU): its queued frames are dropped and counted, how many is returned."""
        return self.net.detach(self.index, node)

    def send(self, node: int, frame_id: int, data: bytes) -> bool:
        """Queue a frame at the current time (False: the node's TX queue was full, counted)."""
        ok = self.net.send(self.index, node, frame_id, data)
        if self.after_send is not None:
            self.after_send()
        return ok

    def trace_if_listened(self) -> None:
        """Keep the completed frames in the engine when someone listens (called before the run goes on)."""
        if self.frame_listeners and not self._tracing:
            self.net.set_trace(self.index, True)
            self._tracing = True

    def send_frames(self, node: int, frames: list[tuple[int, bytes]]) -> None:
        """Queue several frames of one node at the current time (one call for an ECU's outputs); with frame
        packing, a batch holding a container's parts goes as that container."""
        self.net.send_frames(self.index, node, frames)
        if self.after_send is not None:
            self.after_send()

    def send_outputs(self, node: int, outputs: list[Output]) -> None:
        """One ECU cycle's outputs (message, values, counter), encoded and queued by the engine in one call."""
        self.net.send_encoded(self.index, node, outputs)
        if self.after_send is not None:
            self.after_send()

    # ---- the error model and the guardian (engine/src/errors.rs, guardian.rs), for hil.faults.bus.EngineBusFaults
    def enable_bus_errors(self, rng_state: tuple[int, int]) -> None:
        self.net.enable_bus_errors(self.index, rng_state)

    def set_guardian(self, allowances: dict[int, int], window_ns: int, share_ns: float) -> None:
        self.net.set_guardian(self.index, allowances, window_ns, share_ns)

    def add_bus_fault(self, fault: int, kind: str, rng_state: tuple[int, int], probability: float,
                      frame_ids: list[int] | None, count: int | None, bits: int = 1) -> None:
        self.net.add_bus_fault(self.index, fault, kind, rng_state, probability, frame_ids, count, bits)

    def start_babbler(self, fault: int, name: str, frame_id: int, data: bytes, extended: bool) -> int:
        return self.net.start_babbler(self.index, fault, name, frame_id, data, extended)

    def end_bus_fault(self, fault: int) -> None:
        self.net.end_bus_fault(self.index, fault)

    def bus_errors(self) -> dict | None:
        return self.net.bus_errors(self.index)

    def set_packing(self, packing: engine.Packing) -> None:
        """Pack the batches sent on this (CAN FD) bus into containers, unpacked at the receivers."""
        self.net.set_packing(self.index, packing)
        self.packing = packing

    def collect(self) -> None:
        """Move the statistics and the traced frames gathered since the last call into the log and the listeners."""
        frames, load, sent, dropped = self.net.take_stats(self.index)
        self.log.frames.extend_bytes(frames)
        self.log.load.extend_bytes(load)
        if dropped != self.log.frames_dropped:
            self.log.dropped_by_node = self.net.dropped_by_node(self.index)
        self.log.frames_sent, self.log.frames_dropped = sent, dropped
        self.collect_frames()

    def take_refusals(self) -> list[tuple[int, str]]:
        """Each node's first frame refused (a full TX queue, bus-off) since the last call: (t_ns, what happened)."""
        return self.net.take_refusals(self.index)

    def collect_frames(self) -> None:
        """Hand the traced frames completed since the last call to the listeners (without the statistics)."""
        if self._tracing:
            for frame_id, data, ext, t_enq, t_start, t_end, node, fd, brs in self.net.take_trace(self.index):
                tx = Transmission(node, frame_id, data, t_enq, t_start, t_end, ext, fd=fd, brs=brs)  # node: the engine's
                for listener in self.frame_listeners:
                    listener(tx)


class RadioTarget(Protocol):
    """What carries the radio gateway in the engine: the virtual-time ``Network`` or the real-time ``RadioHub``."""

    def add_link(self, name: str, range_m: float, blackouts: list[tuple[float, float]], latency_ns: int,
                 period_ns: int | None, loss_model: str, p: float, p_good_to_bad: float, p_bad_to_good: float,
                 loss_good: float, loss_bad: float, initially_bad: bool, refill: Callable) -> int: ...

    def add_route(self, src_bus: int, src_id: int, dst_bus: int, dst_id: int, link: int, reverse: int | None) -> None: ...

    def set_position_codec(self, codec: engine.MessageCodec) -> None: ...

    def set_impairment(self, link: int, blackout: bool, losses: list[float], extra_ns: int, refill: Callable) -> None: ...


def configure_radio(target: RadioTarget, n_buses: int, links: dict[str, RadioLink], units_per_train: int,
                    forward_aux: bool, position_codecs, ids: RadioIds) -> None:
    """The radio gateway in the engine: the links (their random numbers drawn by the Python ``RadioLink`` objects,
    so every model sees the same losses and jitter), the routing table and the position frames."""
    index: dict[str, int] = {}
    for name, link in links.items():
        cfg = link.cfg
        loss = cfg.loss
        index[name] = target.add_link(
            name, cfg.range_m, [(b.start_m, b.end_m) for b in cfg.blackouts], link.latency_ns, link.period_ns,
            loss.model, loss.p, loss.p_good_to_bad, loss.p_bad_to_good, loss.loss_good, loss.loss_bad, link.starts_bad,
            link.next_draws)
    for route in standard_routes(n_buses, units_per_train, forward_aux, ids):
        src, dst = (int(t) - 1 for t in route.link.split(">"))
        target.add_route(route.src_bus, route.src_id, route.dst_bus, route.dst_id, index[route.link],
                         index.get(link_name(dst, src)))
    for codec in position_codecs:
        target.set_position_codec(codec)


def attach_radio(net: engine.Network, buses: list[EngineBus], links: dict[str, RadioLink], units_per_train: int,
                 forward_aux: bool, position_codecs, ids: RadioIds) -> None:
    """The radio gateway in the virtual-time network (``configure_radio``) and one gateway node per bus."""
    configure_radio(net, len(buses), links, units_per_train, forward_aux, position_codecs, ids)
    for bus in buses:
        net.attach_gateway(bus.index, "RadioGW")


FAULT_DRAWS_BLOCK = 1024


def engine_impairments(net: RadioTarget, names: list[str], rng) -> Callable:
    """``RadioFaults``' setter for the engine's links (named in their order in the engine): the burst losses draw
    from ``rng`` in blocks, one stream for every link, as the Python links draw from it one at a time."""
    index = {name: i for i, name in enumerate(names)}

    def refill() -> list[float]:
        return rng.random(FAULT_DRAWS_BLOCK).tolist()

    def apply(name: str, imp) -> None:
        net.set_impairment(index[name], imp.blackouts > 0, list(imp.losses.values()), sum(imp.latency_ns.values()), refill)

    return apply


def copy_link_stats(net: engine.Network | engine.RadioHub, links: dict[str, RadioLink]) -> None:
    """The engine's link counters into the Python links (what the run log reports)."""
    for i, link in enumerate(links.values()):
        link.stats.update(net.link_stats(i))
