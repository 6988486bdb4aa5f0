"""The real-time (HIL) runtime: emulated CAN bus servers in wall-clock time and the python-can ``trainhil`` plugin.

``BusServer`` (``hil.realtime.busserver``) serves one bus; ``TrainhilBus`` (``hil.realtime.pycan_bus``) is the
python-can interface nodes use to join it; ``hil.realtime.sockets`` says where the sockets live.
"""
from __future__ import annotations

__all__ = ["BusServer", "TrainhilBus"]


def __getattr__(name: str):
    """Lazy exports: importing the package does not import python-can or start anything."""
    if name == "BusServer":
        from hil.realtime.busserver import BusServer

        return BusServer
    if name == "TrainhilBus":
        from hil.realtime.pycan_bus import TrainhilBus

        return TrainhilBus
    raise AttributeError(f"module 'hil.realtime' has no attribute {name!r}")
