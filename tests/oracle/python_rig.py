"""The engine's oracle (test code): the virtual rig on the Python bus model instead of the compiled engine.

``PythonNetworkRig`` is ``hil.runtime.virtual.VirtualRig`` with its network hooks overridden: the Python event
kernel (``hil.runtime.kernel.Kernel``), one ``VirtualCanBus`` per train, per-frame callbacks into the plant, the ECUs
and a Python radio gateway; ``PythonNetworkFaults`` puts the bus faults on the Python error model. The differential
tests run scenarios through both rigs and compare frames, signals, events and counters bit for bit.
"""
from __future__ import annotations

import trainhil_engine as engine

from hil.plant.can_node import VALID_MODES
from hil.runtime.virtual_faults import VirtualFaults
from hil.radio.gateway import RadioGateway, build_gateway
from hil.record.runlog import BusLog
from hil.runtime.kernel import Kernel
from hil.runtime.virtual import VirtualRig
from tests.oracle.bus_faults import BusFaults
from tests.oracle.bus_model import CanNode
from tests.oracle.python_bus import VirtualCanBus


class PythonNetworkRig(VirtualRig):
    """A virtual rig whose buses, radio and kernel are the Python models."""

    def _make_network(self) -> None:
        self.net = None
        self.kernel = Kernel()

    def _make_bus(self, i: int, log: BusLog) -> VirtualCanBus:
        c = self.sc.can
        return VirtualCanBus(self.kernel, f"bus{i + 1}", c.bitrate, c.queue_policy, c.tx_queue_depth, c.extended_ids,
                             log=log, fd=c.fd, data_bitrate=c.data_rate, brs=c.brs)

    def _make_faults(self) -> VirtualFaults:
        return PythonNetworkFaults(self)

    def _attach_plant(self, i: int) -> CanNode:
        """The plant applies each TractionCmd at its end (the engine's check and decoding, then the plant node)."""
        io = self.plant_io
        inbox = engine.CommandInbox(io.command_table(i), VALID_MODES, [], self.layout.n_units)

        def on_rx(frame_id: int, data: bytes, t_ns: int) -> None:
            inbox.put(frame_id, data, t_ns * 1e-9)
            valid, refused, _ = inbox.take()
            for command in valid:
                io.apply(*command)
            for frame in refused:
                io.refuse(i, *frame)

        return self.buses[i].attach("Plant", on_rx, set(self.plant_io.cmd_unit[i]))

    def _ecu_node(self, u: int, ecu) -> CanNode:
        train, _ = self.layout.train_unit(u)
        on_frame = ecu.on_frame
        return self.buses[train].attach(self.layout.ecu_node_name(u),
                                        lambda fid, data, t: on_frame(fid, data, t * 1e-9), ecu.rx_ids)

    def _attach_radio(self) -> tuple[RadioGateway | None, list[CanNode]]:
        if self.layout.n_trains < 2:
            return None, []
        gateway = build_gateway(self.sc, self.db, self.parts.streams["radio"])
        nodes = []
        for i, bus in enumerate(self.buses):
            def on_rx(frame_id: int, data: bytes, t_ns: int, i: int = i) -> None:
                for dst_bus, dst_id, payload, t_deliver in gateway.on_frame(i, frame_id, data, t_ns):
                    self.kernel.at(t_deliver, self._gateway_send, (dst_bus, dst_id, payload))

            nodes.append(bus.attach("RadioGW", on_rx, gateway.ids_for_bus(i)))
        return gateway, nodes

    def _gateway_send(self, item: tuple[int, int, bytes]) -> None:
        bus, frame_id, data = item
        self.buses[bus].send(self._gw_nodes[bus], frame_id, data)

    def _plant_tick(self, t_ns: int) -> None:
        self._plant_step(t_ns)  # the commands were applied as they arrived

    def _before_run(self) -> None:
        pass

    def _collect(self) -> None:
        self._log_refusals()

    def _finish_network(self, now: int) -> None:
        for bus in self.buses:
            bus.finish(now)
        self._log_refusals()


class PythonNetworkFaults(VirtualFaults):
    """The fault machinery on the Python bus model: its error model and guardian log straight to the timeline."""

    def _bus_faults(self, seed: int, periods: dict[int, float], e2e_ok) -> list:
        rig = self.rig
        return [BusFaults(bus, i, seed, periods, self._sink(bus.name, "can"), self._sink(bus.name, "guardian"),
                          send=bus.send, e2e_ok=e2e_ok, packing=bus.packing) for i, bus in enumerate(rig.buses)]

    def _sink(self, bus: str, what: str):
        log = self.rig.log
        return lambda t_ns, level, text: log.event(t_ns * 1e-9, level, f"{bus}/{what}", text)

    def _radio_impairments(self, rng):
        return None  # the Python links draw their impairments themselves

    def _take_bus_events(self) -> None:
        pass  # the events went to the timeline as they happened


def rig_on(network: str, scenario, seed: int | None = None, **kwargs) -> VirtualRig:
    """The virtual rig on ``network``: "engine" (the shipped rig) or "python" (this oracle)."""
    if network not in ("engine", "python"):
        raise ValueError(f"network must be 'engine' or 'python', got {network!r}")
    return (VirtualRig if network == "engine" else PythonNetworkRig)(scenario, seed, **kwargs)
