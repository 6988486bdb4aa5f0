"""A train's CAN bus as the virtual rig, the fault machinery, the CAN logs and the frame recorder use it: a
``typing.Protocol``. The engine's ``hil.runtime.engine_net.EngineBus`` is the shipped one; the oracle's Python bus
(``tests/oracle/python_bus.py``) meets it too."""
from __future__ import annotations

from typing import Any, Callable, Protocol, runtime_checkable

from hil.can.bus_log import BusLog
from hil.can.transmission import Transmission


@runtime_checkable
class TrainBus(Protocol):
    """One train's CAN bus: nodes attach (the handle is the implementation's), send at the kernel's time, leave."""

    name: str
    log: BusLog
    frame_listeners: list[Callable[[Transmission], None]]

    def send(self, node: Any, frame_id: int, data: bytes) -> bool: ...

    def send_frames(self, node: Any, frames: list[tuple[int, bytes]]) -> None: ...

    def attached(self, node: Any) -> bool: ...

    def detach(self, node: Any) -> int: ...

    def take_refusals(self) -> list[tuple[int, str]]:
        """Each node's first frame refused (a full TX queue, bus-off) since the last call: (t_ns, what happened)."""
        ...
