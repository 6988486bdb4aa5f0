"""The real-time (HIL) runtime: emulated CAN bus servers in wall-clock time and the python-can ``trainhil`` plugin.

``BusServer`` (``hil.runtime.realtime.bus_server``: the protocol a bus server meets; ``NativeBusServer`` the engine's
implementation) serves one bus; ``TrainhilBus`` (``hil.runtime.realtime.pycan_bus``) is the
python-can interface nodes use to join it; ``hil.runtime.realtime.sockets`` says where the sockets live.
"""
from __future__ import annotations

__all__ = ["BusServer", "TrainhilBus"]


def __getattr__(name: str):
    """Lazy exports: importing the package does not import python-can or start anything."""
    if name == "BusServer":
        from hil.runtime.realtime.bus_server import BusServer

        return BusServer
    if name == "TrainhilBus":
        from hil.runtime.realtime.pycan_bus import TrainhilBus

        return TrainhilBus
    raise AttributeError(f"module 'hil.runtime.realtime' has no attribute {name!r}")
