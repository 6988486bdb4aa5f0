"""The bus server seam: what the orchestrator, the merge, the fault machinery and ``hil bus-server`` need of a
server of one emulated CAN bus, as a ``typing.Protocol``, with its statistics and defaults.

The shipped implementation is the engine's ``NativeBusServer`` (``native_server.py``); the Python server the engine
is checked against lives with the tests (``tests/oracle/python_server.py``) and meets the same protocol.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

from hil.can.bus_log import BusLog

DEFAULT_SPIN_US = 200
MAX_CLIENTS = 256  # connections beyond this are refused and counted
HELLO_TIMEOUT_S = 5.0  # wall seconds a connection may take to complete its handshake (AUTH, HELLO)


@dataclass
class BusServerStats:
    """What a bus server has carried so far."""

    channel: str
    bitrate: int
    uptime_s: float  # model seconds (wall seconds x pace), as are frames_per_s, load and the latencies
    clients: int
    frames: int  # transmissions completed
    frames_per_s: float
    load: float  # busy time / uptime
    load_last_window: float | None  # the last closed window of the BusLog
    frames_dropped: int  # TX queue full, or queued when the node disconnected
    frames_rejected: int  # not a classical data frame (remote, error, FD, bad id)
    rx_overruns: int  # deliveries lost because a node did not read
    latency_p50_s: float | None  # enqueue -> end of transmission (queueing + transmission)
    latency_p99_s: float | None
    latency_max_s: float | None
    lateness_p50_s: float | None  # frame handed to the nodes' sockets - its end time on the bus (wall seconds)
    lateness_p99_s: float | None
    lateness_max_s: float | None
    protocol_errors: int = 0  # nodes disconnected for breaking the protocol (garbage, unknown kinds, no HELLO)
    truncated_records: int = 0  # connections that ended inside a record (the partial record is discarded)
    auth_failures: int = 0  # TCP connections refused for a missing or wrong token
    clients_refused: int = 0  # connections refused: not loopback, or more than max_clients
    eager_clients: int = 0  # of clients, those taking frames as they end (python-can programs, devices; not lazy nodes)
    tcp_port: int | None = None  # the loopback TCP port, when listening on TCP
    wake_ups: int = 0  # turns of the serving loop so far (each a wake-up of its thread)
    turns_held: int = 0  # nodes' turns the bus waited for (ECU cycles, plant publications: hil run --turns)
    turn_overruns: int = 0  # turns let go: held TURN_HOLD_MAX_S without their end, or the bus already behind
    turns_let_go: dict[str, int] = field(default_factory=dict)  # of those, held without their end: by node name
    turns_behind: int = 0  # of those, let go at once: the bus itself further behind the wall clock than a turn holds
    # the read time (epoch s) at which the server gave turns up, having let 20 go at once within a second of wall time
    # (TURNS_BEHIND_MAX; None: it takes them still): from then on it holds its bus for none, as with turns off
    turns_given_up_s: float | None = None
    dropped_by_node: dict[str, int] = field(default_factory=dict)  # of frames_dropped, by node name (none: left out)

    def as_dict(self, t0: float | None = None, pace: float = 1.0) -> dict:
        """The figures as ``metrics.json`` has them; given the run's T0 (epoch s) and pace, ``turns_given_up_s`` in
        simulated seconds, as every other time there."""
        d = asdict(self)
        if t0 is not None and self.turns_given_up_s is not None:
            d["turns_given_up_s"] = (self.turns_given_up_s - t0) * pace
        return d


def turns_let_go_text(stats: list[BusServerStats]) -> str | None:
    """What a run's turns let go, summed over its buses, by who was late; None when none was. A turn let go puts its
    frames on the bus after the instant they carry, so the loop there is not virtual time's."""
    total = sum(s.turn_overruns for s in stats)
    if not total:
        return None
    late: dict[str, int] = {}
    for s in stats:
        for name, n in s.turns_let_go.items():
            late[name] = late.get(name, 0) + n
    parts = [f"{name} {n}" for name, n in sorted(late.items(), key=lambda kv: -kv[1])]
    behind = sum(s.turns_behind for s in stats)
    if behind:
        parts.append(f"{behind} at once, the bus behind the wall clock")
    return (f"{total} turns let go ({', '.join(parts)}): their frames went on the bus after their instant, so the "
            "loop is not virtual time's from the first of them")


def turns_given_up(stats: list[BusServerStats], t0: float, pace: float) -> tuple[float, str] | None:
    """When a run's servers gave their turns up (simulated s, the first of them) and what to say of it; None when
    none did. A server gives turns up when its bus keeps falling further behind the wall clock than a turn may hold
    it: the machine did not keep up with them, and holding the bus for more would only put it further behind."""
    given_up = {s.channel.rsplit("/", 1)[-1]: (s.turns_given_up_s - t0) * pace  # "run/bus1": bus1
                for s in stats if s.turns_given_up_s is not None}
    if not given_up:
        return None
    where = ", ".join(f"{name} at {t:.1f} s" for name, t in sorted(given_up.items(), key=lambda kv: kv[1]))
    return min(given_up.values()), (
        f"turns given up ({where}): the machine did not keep up with them (the buses fell behind the wall clock); "
        "from then on each node's frames went on the bus when it sent them, as with --turns off")


@runtime_checkable
class BusServer(Protocol):
    """A server of one bus in wall-clock time: nodes connect to ``path`` (and TCP with a token, optionally);
    ``epoch0`` is the epoch time of the bus's time zero; ``log`` its frame rows and load windows (read it under
    ``with_log``); ``frame_listeners`` get every completed transmission, fed by ``pump`` (a thread of the server's
    own unless it was started with ``pump_thread=False``: then its owner calls ``pump``)."""

    path: Path

    @property
    def epoch0(self) -> float: ...

    @property
    def pace(self) -> float: ...

    @property
    def log(self) -> BusLog: ...

    @property
    def frame_listeners(self) -> list[Callable[..., None]]: ...

    @property
    def stats(self) -> BusServerStats: ...

    def with_log(self, fn: Callable[[BusLog], Any]) -> Any: ...

    def align_load_windows(self, t0: float) -> None: ...

    def start(self, pump_thread: bool = True) -> "BusServer": ...

    def pump(self) -> None: ...

    def shutdown(self, wait: bool = True) -> None: ...

    def close(self) -> None: ...


if __name__ == "__main__":  # python -m hil.runtime.realtime.bus_server: the same as `hil bus-server`
    import sys

    from hil.runtime.realtime.command_line import bus_server_main

    sys.exit(bus_server_main())
