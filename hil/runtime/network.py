"""The virtual network's seams as ``typing.Protocol``s: the event kernel the rig's tasks run on, and a train bus as
the rig, the fault machinery, the CAN logs and the frame recorder use it.

The shipped implementations are the engine's (``hil/runtime/engine_net.py``: ``EngineKernel``, ``EngineBus``); the
Python kernel (``hil/runtime/kernel.py: Kernel``, which the real-time nodes' paced kernel extends) and the oracle's
Python bus (``tests/oracle/python_bus.py``) meet them too.
"""
from __future__ import annotations

from typing import Any, Callable, Protocol, runtime_checkable

from hil.can.stats import BusLog
from hil.can.transmission import Transmission


@runtime_checkable
class EventKernel(Protocol):
    """Callbacks at integer-nanosecond times on one queue; ``run`` processes them up to a time."""

    @property
    def now(self) -> int: ...

    def at(self, t_ns: int, fn: Callable[[Any], None], arg: Any = None) -> None: ...

    def every(self, first_ns: int, period_ns: int, fn: Callable[[int], None]) -> None: ...

    def run(self, until_ns: int) -> None: ...


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
