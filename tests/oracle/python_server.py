"""The engine's oracle for the real-time bus server (test code): one emulated CAN bus in wall-clock time, a unix-socket
server in Python that drives the clock-agnostic ``CanBusModel``. The rig serves its buses with the engine's
``NativeBusServer``; this one meets the same ``hil.runtime.realtime.bus_server.BusServer`` protocol, and the
tests run the same sessions through both (``tests/conftest.py: server_cls``).

Nodes (python-can ``TrainhilBus`` clients, see ``protocol``) connect to ``<run dir>/<bus>.sock``. One thread runs a
selector loop: frames read from a node are queued in its TX queue at the current time (ns since the server
started); when the bus is idle and frames wait, the model arbitrates; the loop sleeps until the transmission's
end, completes it and hands the frame, stamped with that end time, to every node whose acceptance filters take
it (filtering happens here, not in the nodes: measured when the rig was designed, it doubles how many ECU processes keep their
lateness low). When the server wakes late, frames that were waiting at an end time are arbitrated at that
model time, so the bus schedule stays exact and only the delivery is late (``lateness`` in the statistics).

Waits are precise: the timer slack of the serving thread is set to 1 ns, timeouts go through ``select`` on
the epoll fd (epoll itself only takes milliseconds), and the last ``spin_us`` (200 us) before a
transmission's end are spent polling (the sockets, so input is still read). Only the bus server spins; at
1 Mbit/s and full load a frame is shorter than the spin window, so the server then keeps one core busy, and a
rig with several buses has several spinners: lower ``spin_us`` (0 = sleep only) there. ``set_fifo_priority``
(``--fifo``) runs the server under SCHED_FIFO where permitted, which cuts its p99 lateness on a loaded machine.

Security (local only): the socket lives in the 0o700 run directory and is chmod 0o600. With ``tcp=True`` the
server also listens on a loopback address (127.0.0.1 or ::1; any other host is refused) and writes host, port
and a fresh 128-bit token to ``<run dir>/<bus>.tcp`` (mode 0o600): a TCP client must send that token (AUTH) as
its first record, else it is refused, counted (``auth_failures``) and logged. A peer that is not loopback, or
a connection beyond ``max_clients``, is refused and counted (``clients_refused``).

Bad input from a node never stops the server or disturbs the other nodes: a frame the bus cannot carry is
dropped and counted (``frames_rejected``); a record that breaks the protocol (unknown kind, garbage, a frame
before HELLO, bad filters, ...) disconnects that node and is counted (``protocol_errors``); a connection that
ends inside a record is counted (``truncated_records``); a connection that does not complete HELLO within
``hello_timeout_s`` is dropped (counted as a protocol error). Each is logged (the first few per kind).
"""
from __future__ import annotations

import hmac
import logging
import os
import selectors
import select
import socket
import threading
import time
from pathlib import Path

from hil.can.transmission import Transmission
from tests.oracle.bus_model import CanBusModel, CanNode
from hil.runtime.realtime.bus_server import DEFAULT_SPIN_US, HELLO_TIMEOUT_S, MAX_CLIENTS, BusServerStats
from hil.runtime.realtime.sockets import bind_unix_socket, check_server_args, listen_tcp, remove_endpoints, socket_path
from hil.runtime.realtime.protocol import (
    AUTH_TIMEOUT_S, FLAG_BRS, FLAG_ECHO, FLAG_EXTENDED, FLAG_FD, FRAME, KIND_AUTH, KIND_FILTER,
    KIND_FILTERS, KIND_FRAME, KIND_FRAME_DATA, KIND_HELLO, MAX_DLC, MAX_UNAUTHENTICATED, PROTOCOL_VERSION, RECORD_SIZE,
    REFUSED_FULL, REFUSED_TIMEOUT, REFUSED_TOKEN, REFUSED_WAITING, Filter, Frame, ProtocolError,
    filters_accept, frame_data_records, frame_error, join_frame, pack_filters_ack, pack_frame, pack_refused, pack_welcome,
    unpack_auth, unpack_filter, unpack_filters_head, unpack_hello,
)
from hil.can.bus_log import BusLog
from hil.runtime.realtime.pacing import set_timer_slack

LOG = logging.getLogger("hil.runtime.realtime.bus_server")  # the native server's logger too
READ_RECORDS = 32  # per node and loop turn: a babbling node cannot stall the loop, the rest waits in its socket
OUT_CAP_BYTES = 1 << 20  # a node that stops reading loses frames beyond this backlog (counted as overruns)
_RX_CACHE_MAX = 8192
LOG_FIRST = 10  # bad-input warnings logged per kind; the counters keep counting


class _Refused(Exception):
    """A connection that failed authentication: dropped and counted as an auth failure, not a protocol error."""


if hasattr(selectors, "EpollSelector"):
    class _PreciseSelector(selectors.EpollSelector):
        """epoll with microsecond timeouts: block in select() on the epoll fd (readable when any registered
        fd is), then collect the events without blocking. epoll_wait alone rounds up to whole milliseconds."""

        def select(self, timeout: float | None = None):
            if timeout is not None and timeout > 0:
                ready, _, _ = select.select([self._selector.fileno()], [], [], timeout)
                if not ready:
                    return []
                timeout = 0
            return super().select(timeout)
else:  # pragma: no cover - non-Linux
    _PreciseSelector = selectors.SelectSelector  # type: ignore[misc,assignment]


class _Histogram:
    """Durations in log-linear bins: 1 us wide below 1.024 ms, then 1/512 of the value (<= 0.2 %) wide.

    Bounded memory for endless runs, O(1) per sample; the maximum is kept exactly."""

    _LINEAR = 1024
    _SUB = 512

    def __init__(self) -> None:
        self.counts = [0] * (self._LINEAR + 40 * self._SUB)
        self.n = 0
        self.max_ns = 0

    def add(self, ns: int) -> None:
        us = max(ns, 0) // 1000
        if us < self._LINEAR:
            i = us
        else:
            e = us.bit_length() - 10
            i = self._LINEAR + (e - 1) * self._SUB + (us >> e) - self._SUB
        self.counts[min(i, len(self.counts) - 1)] += 1
        self.n += 1
        if ns > self.max_ns:
            self.max_ns = ns

    def _upper_us(self, i: int) -> int:
        if i < self._LINEAR:
            return i + 1
        e, m = divmod(i - self._LINEAR, self._SUB)
        return (m + self._SUB + 1) << (e + 1)

    def quantile_s(self, q: float) -> float | None:
        """Upper edge of the bin holding quantile q, capped at the maximum (None when empty)."""
        if not self.n:
            return None
        rank, seen = q * self.n, 0
        for i, c in enumerate(self.counts):
            seen += c
            if c and seen >= rank:
                return min(self._upper_us(i) * 1e-6, self.max_ns * 1e-9)
        return self.max_ns * 1e-9


def _try_send(sock: socket.socket, record: bytes) -> None:
    """Best effort: tell a connection why it is refused before closing it."""
    try:
        sock.send(record)
    except OSError:
        pass


class _Client:
    """One connected node: its socket, partial input, pending output, filters and counters."""

    __slots__ = ("sock", "cid", "name", "node", "rx", "out", "writing", "closed", "receive_own", "filters",
                 "pending", "pending_left", "pending_gen", "delivered", "overruns", "rejected", "tcp", "authed",
                 "t_open", "long")

    def __init__(self, sock: socket.socket, cid: int, tcp: bool = False) -> None:
        self.sock = sock
        self.cid = cid
        self.tcp = tcp  # a TCP client must authenticate (AUTH) before anything else
        self.authed = not tcp
        self.t_open = time.monotonic()
        self.name = f"#{cid}"
        self.node: CanNode | None = None  # set by HELLO
        self.rx = b""
        self.out = bytearray()
        self.writing = False
        self.closed = False
        self.receive_own = False
        self.filters: tuple[Filter, ...] | None = None  # None = accept everything
        self.pending: list[Filter] | None = None  # a FILTERS set being received
        self.long: tuple[Frame, bytearray, bool] | None = None  # a CAN FD frame, its FRAME_DATA so far, keep it?
        self.pending_left = 0
        self.pending_gen = 0
        self.delivered = 0
        self.overruns = 0
        self.rejected = 0


class PythonBusServer:
    """One CAN bus served on ``<run dir>/<bus>.sock`` in wall-clock time (see the module docstring).

    ``serve_forever()`` runs the loop in the calling thread, ``start()`` in a daemon thread; ``with BusServer(...)
    as srv:`` serves in the background for the block. ``shutdown()`` is thread-safe (and safe from a signal
    handler of the serving thread); ``close()`` removes the socket. The model's ``BusLog`` is ``log``.
    """

    def __init__(self, run: str, bus: str, bitrate: int, policy: str = "priority", depth: int = 64, *,
                 path: Path | str | None = None, extended: bool = False, load_window_s: float = 0.1,
                 spin_us: float = DEFAULT_SPIN_US, keep_log: bool = True, log: BusLog | None = None,
                 pace: float = 1.0, tcp: bool = False, tcp_host: str = "127.0.0.1", tcp_port: int = 0,
                 max_clients: int = MAX_CLIENTS, hello_timeout_s: float = HELLO_TIMEOUT_S, fd: bool = False,
                 data_bitrate: int | None = None) -> None:
        check_server_args(run, bus, tcp, tcp_host, spin_us, pace)
        self._pace = float(pace)
        self.model = CanBusModel(bus, bitrate, policy, depth, extended, log, load_window_s, fd=fd, data_bitrate=data_bitrate)
        self.path = Path(path) if path is not None else socket_path(run, bus, create=True)
        self.channel = f"{run}/{bus}" if path is None else str(self.path)
        self._spin_ns = int(spin_us * 1000)
        self._window_ns = int(load_window_s * 1e9)
        self._keep_log = keep_log
        self._listener = bind_unix_socket(self.path)
        self._inode = os.lstat(self.path).st_ino
        self._mono0 = time.monotonic_ns()
        self._epoch0_ns = time.time_ns()
        self._sel = _PreciseSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._listener, selectors.EVENT_READ, self._accept)
        self._max_clients = max_clients
        self._hello_timeout_s = hello_timeout_s
        self._bad: dict[str, int] = {"protocol_errors": 0, "truncated_records": 0, "auth_failures": 0,
                                     "clients_refused": 0}
        self._tcp_listener: socket.socket | None = None
        self.token: bytes | None = None  # the per-run TCP token (None without TCP)
        self.token_file: Path | None = None
        if tcp:
            self._listen_tcp(tcp_host, tcp_port)
        self._sel.register(self._wake_r, selectors.EVENT_READ, self._drain_wake)
        self._clients: dict[int, _Client] = {}
        self._by_node: dict[CanNode, _Client] = {}
        self._rx_cache: dict[int, tuple[_Client, ...]] = {}
        self._dirty: set[_Client] = set()
        self._ended: list[int] = []  # end times completed in this loop turn (for the lateness histogram)
        self._next_cid = 1
        self._next_window = self._window_ns
        self._busy_ns = 0
        self._frames = 0
        self._rejected = 0
        self._overruns = 0
        self._lateness = _Histogram()
        self._latency = _Histogram()
        self._lock = threading.Lock()
        self._stop = False
        self._closed = False
        self._serving = threading.Event()
        self._stopped = threading.Event()
        self._stopped.set()
        self._thread: threading.Thread | None = None
        self._loop_ident: int | None = None

    # ---- socket setup
    def _listen_tcp(self, host: str, port: int) -> None:
        """Listen on loopback ``host``:``port`` (0: any free port) and publish host, port and token (mode 0o600)."""
        try:
            sock, self.token, self.tcp_address, self.token_file = listen_tcp(host, port, self.path)
        except BaseException:
            self._listener.close()
            os.unlink(self.path)
            raise
        self._tcp_listener = sock
        self._sel.register(sock, selectors.EVENT_READ, self._accept_tcp)

    @property
    def bitrate(self) -> int:
        return self.model.bitrate

    @property
    def serving(self) -> bool:
        """Whether the serving loop runs."""
        return self._serving.is_set()

    @property
    def transmitting(self) -> bool:
        """Whether a frame is on the wire now."""
        return self.model.current is not None

    @property
    def frame_listeners(self) -> list:
        """Called with each completed transmission, in the serving thread (CAN logs)."""
        return self.model.frame_listeners

    # ---- time
    def _now(self) -> int:
        """Model time (ns since start): wall time x pace, so a frame lasts duration / pace of wall time."""
        if self._pace == 1.0:
            return time.monotonic_ns() - self._mono0
        return int((time.monotonic_ns() - self._mono0) * self._pace)

    @property
    def pace(self) -> float:
        """Model seconds per wall second (1.0 = real time)."""
        return self._pace

    @property
    def epoch0(self) -> float:
        """Epoch seconds of the bus's time zero: a BusLog time t happened at epoch0 + t / pace."""
        return self._epoch0_ns * 1e-9

    @property
    def log(self) -> BusLog:
        return self.model.log

    def with_log(self, fn):
        """``fn(log)`` under the server's lock (the rig's spool)."""
        with self._lock:
            return fn(self.model.log)

    def align_load_windows(self, t0: float) -> None:
        """Let the load windows end at the run's t = k x the window (t0: the epoch time of its t = 0)."""
        with self._lock:
            self.model.align_load_windows(round((t0 - self.epoch0) * self._pace * 1e9), self._now())

    # ---- running
    def serve_forever(self) -> None:
        """Run the loop in this thread until shutdown()."""
        if self._closed:
            raise RuntimeError(f"bus server {self.channel} is closed")
        set_timer_slack(1)
        self._loop_ident = threading.get_ident()
        self._stopped.clear()
        self._serving.set()
        try:
            while not self._stop:
                self._turn()
        finally:
            self._serving.clear()
            self._stopped.set()

    def start(self, pump_thread: bool = True) -> "PythonBusServer":
        """Serve in a daemon thread; returns once the loop runs. Its loop feeds the listeners itself, so there is no
        pump to place (``pump_thread`` is the protocol's, and changes nothing here)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self.serve_forever, name=f"bus-server {self.channel}", daemon=True)
            self._thread.start()
            self._serving.wait(5.0)
        return self

    def pump(self) -> None:
        """Nothing to do: the serving loop reports and feeds the listeners as it goes (the protocol's ``pump``)."""

    def shutdown(self, wait: bool = True) -> None:
        """Stop the loop (from any thread); waits for it unless called from the loop's own thread."""
        self._stop = True
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        if wait and threading.get_ident() != self._loop_ident:
            self._stopped.wait()

    def close(self) -> None:
        """Stop, disconnect every node, close the load windows and remove the socket (if it is still ours)."""
        if self._closed:
            return
        self.shutdown()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            for c in list(self._clients.values()):
                self._drop(c, "server closing")
            self._close_windows(self._now())
            self._closed = True
        for s in (self._listener, self._wake_r, self._wake_w, self._tcp_listener):
            if s is not None:
                s.close()
        self._sel.close()
        remove_endpoints(self.path, self._inode, self.token_file)

    def __enter__(self) -> "PythonBusServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the loop
    def _turn(self) -> None:
        """One loop turn: wait, complete what ended, read the nodes, start the next frame, send the output."""
        tx = self.model.current
        if tx is None:
            timeout = self._window_ns * 1e-9 / self._pace  # wake up now and then to close load windows
        else:
            remaining = (tx.t_end - self._now()) / self._pace  # wall ns
            timeout = (remaining - self._spin_ns) * 1e-9 if remaining > self._spin_ns else 0
        events = self._sel.select(timeout)
        now = self._now()
        with self._lock:
            self._advance(now)  # before reading: frames read now must not join arbitrations of the past
            if self._dirty:
                self._flush()  # deliver first, read later
            for key, mask in events:
                target = key.data
                if type(target) is _Client:
                    if not target.closed and mask & selectors.EVENT_READ:
                        self._read(target, now)
                    if not target.closed and mask & selectors.EVENT_WRITE:
                        self._send(target)
                else:
                    target(now)
            if self.model.current is None:
                self.model.arbitrate(now)
            self._flush()
            if now >= self._next_window:
                self._close_windows(now)
                self._expire_handshakes()

    def _advance(self, now: int) -> None:
        """Complete every transmission that ended by ``now``; frames waiting at an end start right at it."""
        m = self.model
        tx = m.current
        while tx is not None and tx.t_end <= now:
            m.complete()
            if tx.error is None:  # a frame destroyed by an error frame (tests.oracle.bus_errors) is not delivered
                self._deliver(tx)
            tx = m.arbitrate(tx.t_end)

    def _deliver(self, tx: Transmission) -> None:
        """Queue the frame record for every node whose filters take it (the sender only if it asked)."""
        flags = (FLAG_EXTENDED if tx.extended else 0) | (FLAG_FD if tx.fd else 0) | (FLAG_BRS if tx.brs else 0)
        stamp = (self._epoch0_ns + tx.t_end / self._pace) / 1e9
        record = pack_frame(tx.frame_id, tx.data, flags, stamp)
        sender = self._by_node.get(tx.node)
        for c in self._receivers(tx.frame_id, tx.extended):
            rec = record
            if c is sender:
                if not c.receive_own:
                    continue
                rec = pack_frame(tx.frame_id, tx.data, flags | FLAG_ECHO, stamp)
            if len(c.out) >= OUT_CAP_BYTES:
                c.overruns += 1
                self._overruns += 1
                continue
            c.out += rec
            c.delivered += 1
            self._dirty.add(c)
        self._frames += 1
        self._busy_ns += tx.t_end - tx.t_start
        self._latency.add(tx.t_end - tx.t_enqueue)
        self._ended.append(tx.t_end)

    def _receivers(self, frame_id: int, extended: bool) -> tuple[_Client, ...]:
        key = (frame_id << 1) | extended
        found = self._rx_cache.get(key)
        if found is None:
            if len(self._rx_cache) >= _RX_CACHE_MAX:
                self._rx_cache.clear()
            found = tuple(c for c in self._clients.values()
                          if c.node is not None and filters_accept(c.filters, frame_id, extended))
            self._rx_cache[key] = found
        return found

    def _flush(self) -> None:
        """Send the pending output, then account the delivery lateness of the frames completed in this turn."""
        for c in self._dirty:
            if not c.closed:
                self._send(c)
        self._dirty.clear()
        if self._ended:
            t = self._now()
            for t_end in self._ended:
                self._lateness.add(int((t - t_end) / self._pace))  # wall ns
            self._ended.clear()

    def _send(self, c: _Client) -> None:
        try:
            n = c.sock.send(c.out)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._drop(c, f"send failed: {exc}")
            return
        del c.out[:n]
        want = bool(c.out)
        if want != c.writing:
            self._sel.modify(c.sock, selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0), c)
            c.writing = want

    def _close_windows(self, now: int) -> None:
        """Close the BusLog's load windows up to now (a frame on the wire counts in the window it ends in)."""
        m = self.model
        t = now if m.current is None else min(now, m.current.t_end - 1)
        m.finish(t)
        self._next_window = (now // self._window_ns + 1) * self._window_ns
        if not self._keep_log and len(m.log.frames.array) >= 1 << 16:
            m.log.frames.release(len(m.log.frames))  # bounded memory: the statistics and histograms stay

    # ---- nodes
    def _accept(self, now: int) -> None:
        self._accept_from(self._listener, tcp=False)

    def _accept_tcp(self, now: int) -> None:
        self._accept_from(self._tcp_listener, tcp=True)

    def _accept_from(self, listener: socket.socket, tcp: bool) -> None:
        while True:
            try:
                sock, addr = listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. out of file descriptors: refuse this one, keep serving
                self._bad_input("clients_refused", f"accept failed: {exc}")
                return
            why, code = None, None
            if tcp and addr[0] not in ("127.0.0.1", "::1", "::ffff:127.0.0.1"):
                why = f"TCP peer {addr[0]} is not loopback"
            elif tcp and sum(not c.authed for c in self._clients.values()) >= MAX_UNAUTHENTICATED:
                why, code = f"{MAX_UNAUTHENTICATED} TCP connections are already waiting to authenticate", REFUSED_WAITING
            elif not tcp and self._authenticated() >= self._max_clients:
                why, code = f"more than {self._max_clients} connections", REFUSED_FULL
            if why is not None:
                if code is not None:
                    _try_send(sock, pack_refused(code))
                sock.close()
                self._bad_input("clients_refused", f"connection refused: {why}")
                continue
            sock.setblocking(False)
            if tcp:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c = _Client(sock, self._next_cid, tcp)
            self._next_cid += 1
            self._clients[c.cid] = c
            self._sel.register(sock, selectors.EVENT_READ, c)

    def _bad_input(self, kind: str, text: str) -> None:
        """Count one piece of bad input of ``kind``; log the first LOG_FIRST of each kind, then every 1000th."""
        self._bad[kind] += 1
        n = self._bad[kind]
        if n <= LOG_FIRST or n % 1000 == 0:
            LOG.warning("bus %s: %s (%s #%d)", self.channel, text, kind, n)

    def _authenticated(self) -> int:
        """Connections that count against max_clients: unix sockets, and TCP ones that showed the token."""
        return sum(c.authed for c in self._clients.values())

    def _expire_handshakes(self) -> None:
        """Drop TCP connections without the token after AUTH_TIMEOUT_S, and any that did not complete HELLO within
        hello_timeout_s (they hold a slot)."""
        now = time.monotonic()
        for c in [c for c in self._clients.values() if not c.authed and c.t_open < now - AUTH_TIMEOUT_S]:
            _try_send(c.sock, pack_refused(REFUSED_TIMEOUT))
            self._bad_input("auth_failures", f"TCP connection #{c.cid} sent no token within {AUTH_TIMEOUT_S:g} s")
            self._drop(c, "authentication timeout")
        limit = now - self._hello_timeout_s
        for c in [c for c in self._clients.values() if c.node is None and c.t_open < limit]:
            self._bad_input("protocol_errors", f"connection #{c.cid} sent no HELLO within {self._hello_timeout_s:g} s")
            self._drop(c, "handshake timeout")

    def _auth(self, c: _Client, buf: bytes, off: int) -> None:
        """The first record of a TCP client: AUTH with this bus's token, or the connection is refused."""
        token = unpack_auth(buf, off) if buf[off] == KIND_AUTH else None
        if token is None or self.token is None or not hmac.compare_digest(token, self.token):
            why = "no token" if token is None else "a wrong token"
            self._bad_input("auth_failures", f"TCP connection #{c.cid} refused: {why}")
            _try_send(c.sock, pack_refused(REFUSED_TOKEN))
            raise _Refused(why)
        if self._authenticated() >= self._max_clients:
            self._bad_input("clients_refused", f"TCP connection #{c.cid} refused: more than {self._max_clients} connections")
            _try_send(c.sock, pack_refused(REFUSED_FULL))
            raise _Refused("the bus is full")
        c.authed = True

    def _drain_wake(self, now: int) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass

    def _read(self, c: _Client, now: int) -> None:
        """Take whole records off a node's socket (at most READ_RECORDS per turn), keep the partial tail."""
        try:
            chunk = c.sock.recv(READ_RECORDS * RECORD_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(c, f"receive failed: {exc}")
            return
        if not chunk:
            if c.rx:
                self._bad_input("truncated_records", f"node {c.name} (#{c.cid}) disconnected inside a record "
                                f"({len(c.rx)} of {RECORD_SIZE} bytes, discarded)")
            self._drop(c, "disconnected")
            return
        buf = c.rx + chunk if c.rx else chunk
        end = len(buf) - len(buf) % RECORD_SIZE
        try:
            for off in range(0, end, RECORD_SIZE):
                self._record(c, buf, off, now)
        except ProtocolError as exc:
            self._bad_input("protocol_errors", f"node {c.name} (#{c.cid}) dropped: {exc}")
            self._drop(c, f"protocol error: {exc}")
            return
        except _Refused as exc:
            self._drop(c, f"refused: {exc}")
            return
        c.rx = buf[end:]

    def _record(self, c: _Client, buf: bytes, off: int, now: int) -> None:
        kind = buf[off]
        if not c.authed:
            self._auth(c, buf, off)
            return
        if kind == KIND_FRAME_DATA and c.long is not None:
            self._frame_data(c, buf, off, now)
        elif kind == KIND_FRAME and c.node is not None and c.long is not None:
            raise ProtocolError(f"FRAME before the FRAME_DATA records of the last one from node {c.name}")
        elif kind == KIND_FRAME and c.node is not None:
            _, flags, dlc, can_id, _, data = FRAME.unpack_from(buf, off)
            why = frame_error(can_id, dlc, flags, self.model.fd)
            if dlc > MAX_DLC:  # its FRAME_DATA records follow (read and dropped if the frame is refused)
                c.long = (Frame(can_id, data, flags, 0.0, dlc), bytearray(), why is None)
            elif why is None:
                self._enqueue(c, can_id, data[:dlc], flags, now)
            if why is None:
                return
            c.rejected += 1
            self._rejected += 1
            if c.rejected == 1:
                LOG.warning("bus %s: node %s sent a frame the bus cannot carry (%s); dropped and counted",
                            self.channel, c.name, why)
        elif kind == KIND_HELLO and c.node is None:
            self._hello(c, buf, off)
        elif kind == KIND_FILTERS and c.node is not None and c.pending is None:
            count, c.pending_gen = unpack_filters_head(buf, off)
            c.pending, c.pending_left = [], count
            if count == 0:
                self._apply_filters(c)
        elif kind == KIND_FILTER and c.pending is not None:
            c.pending.append(unpack_filter(buf, off))
            c.pending_left -= 1
            if c.pending_left == 0:
                self._apply_filters(c)
        else:
            raise ProtocolError(f"unexpected record kind {kind} from node {c.name}")

    def _enqueue(self, c: _Client, can_id: int, data: bytes, flags: int, now: int) -> None:
        """Queue a frame of ``c``'s; its first refused (a full TX queue, bus-off) is a warning, the rest counted."""
        if not self.model.enqueue(c.node, can_id, data, now, bool(flags & FLAG_EXTENDED), bool(flags & FLAG_FD),
                                  bool(flags & FLAG_BRS)):
            for _, text in self.model.take_refusals():
                LOG.warning("bus %s: %s", self.channel, text)

    def _frame_data(self, c: _Client, buf: bytes, off: int, now: int) -> None:
        """One FRAME_DATA record of a CAN FD frame above 8 bytes; the last one queues the frame."""
        head, records, keep = c.long
        records += buf[off:off + RECORD_SIZE]
        if len(records) >= frame_data_records(head.dlc) * RECORD_SIZE:
            c.long = None
            if keep:
                self._enqueue(c, head.can_id, join_frame(head, records).data, head.flags, now)

    def _hello(self, c: _Client, buf: bytes, off: int) -> None:
        hello = unpack_hello(buf, off)
        welcome = pack_welcome(self.model.bitrate, self.epoch0, c.cid,
                               fd_data_bitrate=self.model.data_bitrate if self.model.fd else 0)
        if hello.version != PROTOCOL_VERSION:
            try:
                c.sock.send(welcome)  # tells the node our version before we hang up
            except OSError:
                pass
            raise ProtocolError(f"node {hello.name} speaks protocol version {hello.version}, "
                                f"this server {PROTOCOL_VERSION}")
        c.name = hello.name
        c.receive_own = hello.receive_own
        c.node = self.model.attach(hello.name)
        self._by_node[c.node] = c
        self._rx_cache.clear()
        c.out += welcome
        self._dirty.add(c)
        LOG.info("bus %s: node %s (#%d) joined", self.channel, c.name, c.cid)

    def _apply_filters(self, c: _Client) -> None:
        c.filters = tuple(c.pending) if c.pending else None
        c.pending = None
        self._rx_cache.clear()
        c.out += pack_filters_ack(c.pending_gen)
        self._dirty.add(c)

    def _drop(self, c: _Client, why: str) -> None:
        """Disconnect a node: its queued frames are dropped and counted; a frame of it on the wire completes."""
        if c.closed:
            return
        c.closed = True
        self._sel.unregister(c.sock)
        c.sock.close()
        del self._clients[c.cid]
        self._rx_cache.clear()
        if c.node is not None:
            lost = self.model.detach(c.node)
            del self._by_node[c.node]
            LOG.log(logging.WARNING if lost else logging.INFO,  # frames lost: a warning
                    "bus %s: node %s (#%d) left (%s); %d queued frames dropped", self.channel, c.name, c.cid, why, lost)

    # ---- statistics
    @property
    def stats(self) -> BusServerStats:
        """A consistent snapshot (thread-safe)."""
        with self._lock:
            now = self._now()
            self._close_windows(now)
            up = max(now, 1) * 1e-9
            load = self.model.log.load
            clients = sum(c.node is not None for c in self._clients.values())
            return BusServerStats(
                self.channel, self.model.bitrate, up, clients,
                self._frames, self._frames / up, self._busy_ns / max(now, 1),
                load.last(1) if len(load) else None, self.model.log.frames_dropped, self._rejected, self._overruns,
                self._latency.quantile_s(0.5), self._latency.quantile_s(0.99),
                self._latency.max_ns * 1e-9 if self._latency.n else None,
                self._lateness.quantile_s(0.5), self._lateness.quantile_s(0.99),
                self._lateness.max_ns * 1e-9 if self._lateness.n else None,
                tcp_port=self.tcp_address[1] if self._tcp_listener is not None else None,
                eager_clients=clients, dropped_by_node=dict(self.model.log.dropped_by_node), **self._bad)  # (no lazy readers here: every client takes frames as they end)


if __name__ == "__main__":  # python -m tests.oracle.python_server: `hil bus-server` on this server (benchmarks)
    import sys

    from hil.runtime.realtime.command_line import bus_server_main

    sys.exit(bus_server_main(server_cls=PythonBusServer))
