"""python-can interface ``trainhil``: a node on an emulated CAN bus served by ``hil.realtime.busserver``.

    bus = can.Bus(interface="trainhil", channel="seed000/bus1")   # run "seed000", bus "bus1"
    bus = can.Bus(interface="trainhil", channel="/abs/path/bus1.sock")

Channel: ``"<run>/<bus>"`` names the socket ``<runtime_root>/<run>/<bus>.sock`` (runtime root:
``$XDG_RUNTIME_DIR/trainhil`` or ``<tempdir>/trainhil-<uid>``, see ``hil.realtime.paths``), or an absolute
path to a ``.sock`` file. Frames received carry the time their transmission ended on the emulated bus
(epoch seconds). Acceptance filters are applied by the server; until it confirms a new set, python-can
filters in software as well. Only classical data frames are emulated (no CAN FD, remote or error frames
from nodes). The bitrate is the server's; a ``bitrate`` argument that differs is logged and ignored.
"""
from __future__ import annotations

import itertools
import logging
import os
import select
import socket
import threading
import time
from typing import Any

from can import BusABC, CanInitializationError, CanInterfaceNotImplementedError, CanOperationError, Message

from hil.realtime.paths import bus_sockets, check_private_dir, parse_channel, socket_is_live
from hil.realtime.protocol import (
    FLAG_ECHO, FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, FRAME, KIND_FILTERS_ACK, KIND_FRAME, PROTOCOL_VERSION,
    RECORD_SIZE, ProtocolError, filter_from_python_can, pack_filters, pack_frame, pack_hello,
    unpack_filters_ack, unpack_welcome,
)

LOG = logging.getLogger(__name__)
INTERFACE = "trainhil"
_node_seq = itertools.count(1)


class TrainhilBus(BusABC):
    """A python-can bus whose other end is an emulated CAN bus server (see the module docstring)."""

    def __init__(self, channel: Any, can_filters=None, receive_own_messages: bool = False,
                 node_name: str | None = None, connect_timeout: float = 2.0, **kwargs: Any) -> None:
        if kwargs.get("fd"):
            raise CanInterfaceNotImplementedError("trainhil: CAN FD is not emulated (classical CAN only)")
        try:
            self.channel_name, self.path = parse_channel(channel)
        except ValueError as exc:
            raise CanInitializationError(f"trainhil: {exc}") from exc
        name = node_name or f"pid{os.getpid()}.{next(_node_seq)}"
        hello = pack_hello(name, receive_own_messages)  # ValueError names a bad node name
        self._sock = self._connect(connect_timeout)
        try:
            welcome = self._handshake(hello, connect_timeout)
        except BaseException:
            self._sock.close()
            raise
        self.node_name = name
        self.bitrate = welcome.bitrate
        self.client_id = welcome.client_id
        wanted = kwargs.get("bitrate")
        if wanted is not None and int(wanted) != welcome.bitrate:
            LOG.warning("trainhil %s: bitrate %s requested, the emulated bus runs at %d bit/s",
                        self.channel_name, wanted, welcome.bitrate)
        self.channel_info = f"trainhil {self.channel_name} ({welcome.bitrate} bit/s, node {name})"
        self._sock.setblocking(False)
        self._rbuf = bytearray(RECORD_SIZE)
        self._rview = memoryview(self._rbuf)
        self._rlen = 0
        self._send_lock = threading.Lock()
        self._filter_gen = 0  # last filter set sent; the server acknowledges each
        self._acked_gen = 0
        super().__init__(channel, can_filters=can_filters, **kwargs)

    # ---- connection
    def _connect(self, timeout: float) -> socket.socket:
        if "/" in self.channel_name and not os.path.isabs(self.channel_name):
            for d in (self.path.parent.parent, self.path.parent):  # runtime root, run directory
                try:
                    check_private_dir(d)
                except FileNotFoundError:
                    break  # reported as "no server" below
                except PermissionError as exc:
                    raise CanInitializationError(f"trainhil: {exc}") from exc
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(timeout)
        try:
            sock.connect(str(self.path))
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            sock.close()
            raise CanInitializationError(
                f"trainhil: no bus server is running at {self.path} (channel {self.channel_name!r}: "
                f"{exc.strerror}); start one with `hil bus-server --run RUN --bus BUS`") from None
        except OSError as exc:
            sock.close()
            raise CanInitializationError(f"trainhil: cannot connect to {self.path}: {exc}") from exc
        return sock

    def _handshake(self, hello: bytes, timeout: float):
        self._sock.sendall(hello)
        buf = bytearray()
        deadline = time.monotonic() + timeout
        while len(buf) < RECORD_SIZE:
            self._sock.settimeout(max(deadline - time.monotonic(), 1e-3))
            try:
                chunk = self._sock.recv(RECORD_SIZE - len(buf))
            except TimeoutError:
                raise CanInitializationError(f"trainhil: the server at {self.path} did not answer within "
                                             f"{timeout} s") from None
            if not chunk:
                raise CanInitializationError(f"trainhil: the server at {self.path} closed the connection "
                                             "during the handshake")
            buf += chunk
        try:
            welcome = unpack_welcome(buf)
        except ProtocolError as exc:
            raise CanInitializationError(f"trainhil: {self.path} does not speak the trainhil protocol: {exc}") from None
        if welcome.version != PROTOCOL_VERSION:
            raise CanInitializationError(f"trainhil: the server at {self.path} speaks protocol version "
                                         f"{welcome.version}, this client {PROTOCOL_VERSION}")
        return welcome

    def fileno(self) -> int:
        """The socket: readable when a record waits (one record is read per message, so this stays exact)."""
        return self._sock.fileno()

    # ---- transmit
    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Queue ``msg`` in this node's TX queue on the emulated bus (a full queue drops it; the server counts)."""
        if msg.is_fd or msg.is_remote_frame or msg.is_error_frame:
            kind = "CAN FD" if msg.is_fd else "remote" if msg.is_remote_frame else "error"
            raise CanOperationError(f"trainhil: frame {msg.arbitration_id:#x} is a {kind} frame; "
                                    "only classical data frames are emulated")
        flags = FLAG_EXTENDED if msg.is_extended_id else 0
        record = pack_frame(msg.arbitration_id, bytes(msg.data), flags)  # ValueError names a bad id or length
        with self._send_lock:
            self._write(record, timeout)

    def _write(self, record: bytes, timeout: float | None) -> None:
        """Write whole records; ``timeout`` only bounds the wait before the first byte (a started record is
        always finished, or the stream would lose its framing)."""
        view = memoryview(record)
        deadline = None if timeout is None else time.monotonic() + timeout
        while view:
            try:
                n = self._sock.send(view)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                raise CanOperationError(f"trainhil {self.channel_name}: send failed: {exc}") from exc
            view = view[n:]
            if not view:
                return
            wait = None
            if deadline is not None and len(view) == len(record):
                wait = deadline - time.monotonic()
                if wait <= 0:
                    raise CanOperationError(f"trainhil {self.channel_name}: send timed out after {timeout} s "
                                            "(the bus server is not reading)")
            select.select([], [self._sock], [], wait)

    # ---- receive
    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            record = self._read_record()
            if record is not None:
                kind = record[0]
                if kind == KIND_FRAME:
                    return self._message(record), self._acked_gen == self._filter_gen
                if kind == KIND_FILTERS_ACK:
                    self._acked_gen = unpack_filters_ack(record)
                    continue
                raise CanOperationError(f"trainhil {self.channel_name}: unexpected record kind {kind} from the server")
            wait = None
            if deadline is not None:
                wait = deadline - time.monotonic()
                if wait <= 0:
                    return None, True
            if not select.select([self._sock], [], [], wait)[0]:
                return None, True

    def _read_record(self) -> bytes | None:
        """One whole record, or None if none is complete yet (a partial one is kept)."""
        try:
            n = self._sock.recv_into(self._rview[self._rlen:], RECORD_SIZE - self._rlen)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as exc:
            raise CanOperationError(f"trainhil {self.channel_name}: receive failed: {exc}") from exc
        if n == 0:
            raise CanOperationError(f"trainhil {self.channel_name}: the bus server at {self.path} "
                                    "closed the connection")
        self._rlen += n
        if self._rlen < RECORD_SIZE:
            return None
        self._rlen = 0
        return bytes(self._rbuf)

    def _message(self, record: bytes) -> Message:
        _, flags, dlc, can_id, timestamp, data = FRAME.unpack(record)
        return Message(timestamp=timestamp, arbitration_id=can_id, is_extended_id=bool(flags & FLAG_EXTENDED),
                       is_remote_frame=bool(flags & FLAG_REMOTE), is_error_frame=bool(flags & FLAG_ERROR),
                       dlc=dlc, data=data[:dlc], is_rx=not flags & FLAG_ECHO, channel=self.channel_name, check=False)

    # ---- filters, shutdown, discovery
    def _apply_filters(self, filters) -> None:
        """Send the set to the server; frames are filtered in software until it acknowledges."""
        parsed = [filter_from_python_can(f, i) for i, f in enumerate(filters or ())]
        if not parsed and self._filter_gen == 0:
            return  # the server starts with "accept everything"
        self._filter_gen = (self._filter_gen + 1) & 0xFFFFFFFF
        with self._send_lock:
            self._write(pack_filters(parsed, self._filter_gen), None)

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._sock.close()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        """Every bus of every running rig under the runtime root (a socket that accepts a connection)."""
        return [{"interface": INTERFACE, "channel": channel}
                for channel, path in bus_sockets() if socket_is_live(path, 0.2)]
