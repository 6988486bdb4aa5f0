"""The Python bus model driven by the Python event kernel: the oracle the engine's virtual-time network is checked
against (``tests/oracle/python_rig.py: PythonNetworkRig``).

The default network is the compiled engine (``hil/runtime/engine_net.py``); both give the same frame schedule
(``tests/test_engine_differential.py``).
"""
from __future__ import annotations

from ecu_sim.runtime import encode_outputs
from tests.oracle.bus_model import CanBusModel, CanNode
from hil.runtime.kernel import Kernel


class VirtualCanBus(CanBusModel):
    """A CAN bus driven by the discrete-event kernel."""

    def __init__(self, kernel: Kernel, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.kernel = kernel
        self._arbitration_pending = False

    def send(self, node: CanNode, frame_id: int, data: bytes) -> bool:
        """Queue a frame at the kernel's current time. Same-time submissions all join one arbitration."""
        ok = self.enqueue(node, frame_id, data, self.kernel.now)
        if ok and self.current is None and not self._arbitration_pending:
            self._arbitration_pending = True
            self.kernel.at(max(self.kernel.now, self.busy_until), self._arbitrate_event)
        return ok

    def send_frames(self, node: CanNode, frames: list[tuple[int, bytes]]) -> None:
        """Queue several frames of one node at the kernel's current time, in order; with frame packing, a batch
        holding a container's parts goes as that container (as the engine does)."""
        for frame_id, data in self.packing.pack(frames) if self.packing is not None else frames:
            self.send(node, frame_id, data)

    def send_outputs(self, node: CanNode, outputs: list) -> None:
        """One ECU cycle's outputs (message, values, counter), encoded here and queued as ``send_frames``."""
        self.send_frames(node, encode_outputs(outputs))

    def _arbitrate_event(self, _: object = None) -> None:
        self._arbitration_pending = False
        tx = self.arbitrate(self.kernel.now)
        if tx is not None:
            self.kernel.at(tx.t_end, self._end_event)

    def _end_event(self, _: object = None) -> None:
        self.complete()
        if self._arbitration_pending or not self.pending():
            return
        if self.kernel.next_time() == self.kernel.now:
            # Other events at this same instant may queue frames: arbitrate after them so they compete.
            self._arbitration_pending = True
            self.kernel.at(self.kernel.now, self._arbitrate_event)
        else:
            self._arbitrate_event()
