"""Turns (``hil run --realtime --turns``): whether a run's ECU cycles and plant publications are their nodes' turns,
whose frames go on the bus at their instants while the bus waits for them (protocol READ_TURNS/DONE,
hil/runtime/realtime/protocol.py). The modes and the rule that picks them, apart from the orchestrator so the
command line can offer them without importing it."""
from __future__ import annotations

from typing import Literal

TurnsMode = Literal["auto", "on", "off"]
TURNS_MODES: tuple[TurnsMode, ...] = ("auto", "on", "off")


def takes_turns(mode: TurnsMode, pace: float, socketcan: bool = False) -> bool:
    """Whether a run's nodes take turns: "on" always, "auto" faster than real time, "off" never; never on SocketCAN
    (no bus servers to hold). Faster than real time a node's Python takes a larger share of each simulated
    millisecond, so without turns its frames miss the readers virtual time's would reach (seed000 at pace 10: speed
    overshoot 26 m/s without, virtual time's 17.43 with; README, "Turns"); at pace 1 they are on time without the
    round trips turns cost."""
    if socketcan or mode == "off":
        return False
    return mode == "on" or pace > 1.0


def turns_text(mode: TurnsMode, pace: float, socketcan: bool = False) -> str:
    """What a run says of its turns (``takes_turns``): "on" or "off", and why where the mode did not say it."""
    if socketcan and mode != "off":
        return "off (SocketCAN: no bus servers to hold)"
    if mode != "auto":
        return mode
    return "on (auto: faster than real time)" if takes_turns(mode, pace) else "off (auto: not faster than real time)"
