"""The real-time bus server on the frame engine: the same bus, protocol and statistics as ``BusServer``, served by a
native thread outside the interpreter lock (``trainhil_engine.BusServerCore``, engine/src/server.rs).

This side makes the sockets exactly as ``BusServer`` does (owner-only run directory, the socket bound under a
temporary name, chmod 0o600 and linked into place; optional loopback TCP with a per-run token file) and the bell
its quiet readers ring (``<bus>.bell``, ``sockets.make_bell``), and hands their file descriptors to the engine. A
few times a second ``pump`` reports the engine's log lines through ``logging`` (and ``on_message``), feeds
``frame_listeners`` (CAN logs) and takes over the new log rows: from a small thread of its own, or from its owner's
loop (the rig's supervising loop: one thread fewer to wake per bus). CAN error confinement, the bus fault injectors
and the guardian run in the engine's bus (``enable_bus_errors`` ..., driven by ``hil.faults.bus.EngineBusFaults``).
"""
from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any, Callable

import trainhil_engine as engine

from hil.can.bus_log import LOAD_WINDOW_S
from hil.can.transmission import Transmission
from hil.runtime.realtime.bus_server import DEFAULT_SPIN_US, HELLO_TIMEOUT_S, MAX_CLIENTS, BusServerStats
from hil.runtime.realtime.sockets import (
    bind_unix_socket, check_server_args, listen_tcp, make_bell, remove_endpoints, socket_path,
)
from hil.record.runlog import BusLog

LOG = logging.getLogger("hil.runtime.realtime.bus_server")
PUMP_S = 0.2  # how often the Python side collects log lines and traced frames


class NativeBusServer:
    """One CAN bus on ``<run dir>/<bus>.sock`` served by the engine (see the module docstring); the interface of
    ``BusServer``: ``start``, ``shutdown``, ``close``, ``stats``, ``log``, ``epoch0``, ``frame_listeners``."""

    def __init__(self, run: str, bus: str, bitrate: int, policy: str = "priority", depth: int = 64, *,
                 path: Path | str | None = None, extended: bool = False, load_window_s: float = LOAD_WINDOW_S,
                 spin_us: float = DEFAULT_SPIN_US, keep_log: bool = True, log: BusLog | None = None,
                 pace: float = 1.0, tcp: bool = False, tcp_host: str = "127.0.0.1", tcp_port: int = 0,
                 max_clients: int = MAX_CLIENTS, hello_timeout_s: float = HELLO_TIMEOUT_S, fd: bool = False,
                 data_bitrate: int | None = None, radio: tuple[engine.RadioHub, int] | None = None,
                 serving_thread: engine.ServingThread | None = None) -> None:
        """``fd``: a CAN FD bus (its nodes may send both formats), FD frames with BRS at ``data_bitrate``;
        ``radio``: the rig's radio and this bus's index in it (``EngineRadio.port``); ``serving_thread``: the engine
        thread it shares with the rig's other buses (one wake-up serves every bus that needs that instant; None: a
        thread of its own)."""
        check_server_args(run, bus, tcp, tcp_host, spin_us, pace)
        if policy not in ("priority", "fifo"):
            raise ValueError(f"queue policy must be 'priority' or 'fifo', got {policy!r}")
        if not isinstance(bitrate, int) or bitrate <= 0 or 1_000_000_000 % bitrate:
            raise ValueError(f"bitrate {bitrate!r} has no whole-nanosecond bit time")
        self.path = Path(path) if path is not None else socket_path(run, bus, create=True)
        self.channel = f"{run}/{bus}" if path is None else str(self.path)
        self._pace = float(pace)
        self._log = log if log is not None else BusLog(bus, bitrate)
        self._listener = bind_unix_socket(self.path)
        self._inode = os.lstat(self.path).st_ino
        self.token: bytes | None = None
        self.token_file: Path | None = None
        tcp_sock = None
        if tcp:
            try:
                tcp_sock, self.token, self.tcp_address, self.token_file = listen_tcp(tcp_host, tcp_port, self.path)
            except BaseException:
                self._listener.close()
                os.unlink(self.path)
                raise
        self._bell_inode: int | None = None
        try:
            bell_fd, self._bell_inode = make_bell(self.path)
            self._core = engine.BusServerCore(
                self.channel, os.dup(self._listener.fileno()), None if tcp_sock is None else os.dup(tcp_sock.fileno()),
                self.token, bitrate, policy, depth, extended, int(load_window_s * 1e9), self._pace, int(spin_us * 1000),
                max_clients, hello_timeout_s, keep_log, fd, data_bitrate, radio, bell_fd,
                serving_thread)  # owns bell_fd from here
        except BaseException:
            self._listener.close()
            if tcp_sock is not None:
                tcp_sock.close()
            remove_endpoints(self.path, self._inode, self.token_file, self._bell_inode)
            raise
        self._listener.close()  # the engine owns its duplicate, and the bell
        if tcp_sock is not None:
            tcp_sock.close()
        self._tcp = tcp
        self.frame_listeners: list = []
        # (level, text, t_ns) of each log line as reported; t_ns: the model time it happened (ns since epoch0)
        self.on_message: Callable[[str, str, int], None] | None = None
        self._tracing = False
        self._stop = threading.Event()
        self._pump: threading.Thread | None = None
        self._closed = False
        self._lock = threading.Lock()

    # ---- the BusServer interface
    @property
    def pace(self) -> float:
        return self._pace

    @property
    def epoch0(self) -> float:
        """Epoch seconds of the bus's time zero: a BusLog time t happened at epoch0 + t / pace."""
        return self._core.epoch0_ns * 1e-9

    @property
    def log(self) -> BusLog:
        """The bus's frames and load windows so far (taken over from the engine on each access)."""
        self._collect_log()
        return self._log

    @property
    def bitrate(self) -> int:
        return self._core.bitrate

    @property
    def serving(self) -> bool:
        """Whether the engine's serving thread runs."""
        return self._core.serving

    @property
    def transmitting(self) -> bool:
        """Whether a frame is on the wire now."""
        return self._core.current() is not None

    def start(self, pump_thread: bool = True) -> "NativeBusServer":
        """The engine serves from construction on; this starts the Python side's log and trace pump: its first turn
        now (tracing on for the listeners already attached), then every ``PUMP_S`` from a thread of its own, or, with
        ``pump_thread`` False, from the owner, who calls ``pump()``."""
        self.pump()
        if self._pump is None and pump_thread:
            self._pump = threading.Thread(target=self._pump_loop, name=f"bus-server pump {self.channel}", daemon=True)
            self._pump.start()
        return self

    def align_load_windows(self, t0: float) -> None:
        """Let the load windows end at the run's t = k x the window, as virtual time's (``t0``: the epoch time of
        its t = 0, still ahead), so that a window's load reads the same span of the run in both runtimes."""
        self._core.align_load_windows(max(0, round((t0 - self.epoch0) * self._pace * 1e9)))  # (a clock set back)

    def serve_forever(self) -> None:
        """Block until shutdown() (the CLI's foreground mode)."""
        self.start()
        self._stop.wait()

    def shutdown(self, wait: bool = True) -> None:
        self._stop.set()

    def close(self) -> None:
        """Stop serving, disconnect every node, collect what is left and remove the socket (if it is still ours)."""
        if self._closed:
            return
        self._stop.set()
        if self._pump is not None and self._pump is not threading.current_thread():
            self._pump.join()
        self._core.shutdown()
        self._report()
        self._feed_listeners()
        self._collect_log()
        self._closed = True
        remove_endpoints(self.path, self._inode, self.token_file, self._bell_inode)

    def __enter__(self) -> "NativeBusServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def stats(self) -> BusServerStats:
        """A consistent snapshot (thread-safe); reports the engine's pending log lines first."""
        self._report()
        s: dict[str, Any] = self._core.stats()
        up = max(s["now_ns"], 1) * 1e-9
        return BusServerStats(
            self.channel, self._core.bitrate, up, s["clients"], s["frames"], s["frames"] / up, s["busy_ns"] / max(s["now_ns"], 1),
            s["load_last_window"], s["frames_dropped"], s["frames_rejected"], s["rx_overruns"],
            s["latency_p50_s"], s["latency_p99_s"], s["latency_max_s"], s["lateness_p50_s"], s["lateness_p99_s"],
            s["lateness_max_s"], protocol_errors=s["protocol_errors"], truncated_records=s["truncated_records"],
            auth_failures=s["auth_failures"], clients_refused=s["clients_refused"], eager_clients=s["eager_clients"],
            tcp_port=self.tcp_address[1] if self._tcp else None, wake_ups=s["turns"],
            turns_held=s["turns_held"], turn_overruns=s["turn_overruns"], turns_let_go=s["turns_let_go"],
            turns_behind=s["turns_behind"], turns_given_up_s=s["turns_given_up_s"], dropped_by_node=s["dropped_by_node"])

    # ---- the error model and the guardian (engine/src/errors.rs, guardian.rs), for hil.faults.bus.EngineBusFaults
    def enable_bus_errors(self, rng_state: tuple[int, int]) -> None:
        self._core.enable_bus_errors(rng_state)

    def set_guardian(self, allowances: dict[int, int], window_ns: int, share_ns: float) -> None:
        self._core.set_guardian(allowances, window_ns, share_ns)

    def add_bus_fault(self, fault: int, kind: str, rng_state: tuple[int, int], probability: float,
                      frame_ids: list[int] | None, count: int | None, bits: int = 1) -> None:
        self._core.add_bus_fault(fault, kind, rng_state, probability, frame_ids, count, bits)

    def start_babbler(self, fault: int, name: str, frame_id: int, data: bytes, extended: bool) -> int:
        return self._core.start_babbler(fault, name, frame_id, data, extended)

    def end_bus_fault(self, fault: int) -> None:
        self._core.end_bus_fault(fault)

    def take_bus_events(self) -> list[tuple[int, str, dict]]:
        """The error model's and the guardian's events since the last call: (model t_ns, kind, fields)."""
        return self._core.take_bus_events()

    def bus_errors(self) -> dict | None:
        return self._core.bus_errors()

    # ---- the pump
    def pump(self) -> None:
        """One turn of the pump: the engine's log lines reported, the traced frames to ``frame_listeners``, the new
        log rows taken over (so the engine's buffers stay small)."""
        self._report()
        self._feed_listeners()
        self._collect_log()

    def _pump_loop(self) -> None:
        while not self._stop.wait(PUMP_S):
            self.pump()

    def _report(self) -> None:
        for level, text, t_ns in self._core.take_messages():
            LOG.log(logging.WARNING if level == "WARNING" else logging.INFO, "%s", text)
            if self.on_message is not None:
                self.on_message(level, text, t_ns)

    def _feed_listeners(self) -> None:
        with self._lock:
            if self.frame_listeners and not self._tracing:
                self._core.set_trace(True)
                self._tracing = True
            if not self._tracing:
                return
            for frame_id, data, ext, t_enq, t_start, t_end, fd, brs in self._core.take_trace():
                tx = Transmission(None, frame_id, data, t_enq, t_start, t_end, ext, fd=fd, brs=brs)  # type: ignore[arg-type]
                for listener in self.frame_listeners:
                    listener(tx)

    def _collect_log(self) -> None:
        with self._lock:
            self._collect_locked()

    def _collect_locked(self) -> None:
        if self._closed:
            return
        frames, load, sent, dropped = self._core.take_log()
        self._log.frames.extend_bytes(frames)
        self._log.load.extend_bytes(load)
        if dropped != self._log.frames_dropped:
            self._log.dropped_by_node = self._core.dropped_by_node()
        self._log.frames_sent, self._log.frames_dropped = sent, dropped

    def with_log(self, fn):
        """``fn(log)`` under the server's lock, the engine's new rows taken over first (the rig's spool)."""
        with self._lock:
            self._collect_locked()
            return fn(self._log)
