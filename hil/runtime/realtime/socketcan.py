"""The SocketCAN option of the real-time rig: put every node on the host's (v)can interfaces instead of bus servers.

``[can] transport = "socketcan"`` with ``socketcan_channels = ["vcan0", ...]`` (one per train) makes every node
open ``can.Bus(interface="socketcan", channel=...)``; nothing else changes (configuration only). The kernel's
vcan has no bitrate, arbitration or frame duration: frames arrive at once, so bus timing, load and the CAN
model's faults apply only on the emulated buses. Create the interfaces (as root) with
``ip link add dev vcan0 type vcan && ip link set up vcan0``.
"""
from __future__ import annotations

import socket
from pathlib import Path


class SocketCanUnavailable(RuntimeError):
    """The host cannot provide the configured SocketCAN interfaces (the message says what is missing and how to fix it)."""


def af_can_available() -> bool:
    """True if this kernel lets us open a raw CAN socket (no vcan module or no AF_CAN: False)."""
    if not hasattr(socket, "AF_CAN"):
        return False
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        return False
    return True


def check_channels(channels: list[str], n_trains: int) -> None:
    """Raise SocketCanUnavailable unless there is one existing, up CAN interface per train."""
    if len(channels) != n_trains:
        raise SocketCanUnavailable(f"can.socketcan_channels has {len(channels)} interfaces, expected one per train ({n_trains})")
    if not af_can_available():
        raise SocketCanUnavailable("can.transport = 'socketcan', but this host has no SocketCAN (AF_CAN is unavailable: "
                                   "no can/vcan kernel module); use the default transport = 'emulated'")
    for name in channels:
        dev = Path("/sys/class/net") / name
        if not dev.exists():
            raise SocketCanUnavailable(f"can.socketcan_channels: interface {name!r} does not exist "
                                       f"(create it: ip link add dev {name} type vcan && ip link set up {name})")
        if (dev / "operstate").exists() and (dev / "flags").exists() and not int((dev / "flags").read_text(), 16) & 1:
            raise SocketCanUnavailable(f"can.socketcan_channels: interface {name!r} is down (ip link set up {name})")
