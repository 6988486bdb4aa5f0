"""python-can interface ``trainhil``: a node on an emulated CAN bus served by a bus server (``hil.runtime.realtime.bus_server``).

    bus = can.Bus(interface="trainhil", channel="seed000/bus1")   # run "seed000", bus "bus1"
    bus = can.Bus(interface="trainhil", channel="/abs/path/bus1.sock")
    bus = can.Bus(interface="trainhil", channel="tcp:seed000/bus1")        # loopback TCP, token from the run dir
    bus = can.Bus(interface="trainhil", channel="tcp://127.0.0.1:40123", token="<32 hex digits>")

Channel: ``"<run>/<bus>"`` names the socket ``<runtime_root>/<run>/<bus>.sock`` (runtime root:
``$XDG_RUNTIME_DIR/trainhil`` or ``<tempdir>/trainhil-<uid>``, see ``hil.runtime.realtime.sockets``), or an absolute
path to a ``.sock`` file. Frames received carry the time their transmission ended on the emulated bus
(epoch seconds), and ``channel`` = the bus's 0-based index (bus1 -> 0; see ``bus_index``). Acceptance filters are applied by the server; until it confirms a new set, python-can
filters in software as well. Only classical data frames are emulated (no CAN FD, remote or error frames
from nodes). The bitrate is the server's; a ``bitrate`` argument that differs is logged and ignored.
"""
from __future__ import annotations

import itertools
import logging
import os
import re
import select
import socket
import stat
import threading
import time
from pathlib import Path
from typing import Any

from can import BusABC, CanInitializationError, CanOperationError, Message
from can.typechecking import AutoDetectedConfig

from hil.runtime.realtime.sockets import (
    InsecureRunDirError, bus_sockets, check_private_dir, check_private_socket, open_bell, parse_channel,
    parse_tcp_channel, read_token_file, socket_is_live,
)
from hil.runtime.realtime.protocol import (
    FLAG_BRS, FLAG_ECHO, FLAG_ERROR, FLAG_EXTENDED, FLAG_FD, FLAG_REMOTE, FRAME, KIND_FILTERS_ACK, KIND_FRAME,
    KIND_FRAME_DATA, MAX_DLC, PROTOCOL_VERSION, RECORD_SIZE, TOKEN_BYTES, Frame, ProtocolError, filter_from_python_can,
    frame_data_records, join_frame, pack_auth, pack_filters, pack_frame, pack_hello, refused_reason,
    unpack_filters_ack, unpack_welcome,
)

LOG = logging.getLogger(__name__)
INTERFACE = "trainhil"
_node_seq = itertools.count(1)


def bus_index(channel: str):
    """A received message's ``channel``: the bus's 0-based index (``.../bus1`` -> 0), as Vector and PCAN number their
    channels, so that python-can's log writers (which add 1) log busN as channel N, as the rig's own --can-log
    does; a bus not named ``bus<N>`` keeps its channel name."""
    m = re.search(r"bus(\d+)(?:\.sock)?$", channel)
    return int(m.group(1)) - 1 if m and int(m.group(1)) >= 1 else channel


class TrainhilBus(BusABC):
    """A python-can bus whose other end is an emulated CAN bus server (see the module docstring)."""

    def __init__(self, channel: Any, can_filters=None, receive_own_messages: bool = False,
                 node_name: str | None = None, connect_timeout: float = 2.0, token: str | bytes | None = None,
                 lazy_reader: bool = False, quiet: bool = False, **kwargs: Any) -> None:
        self.fd = bool(kwargs.get("fd", False))
        self._tcp: tuple[str, int, bytes] | None = None
        try:
            if str(channel).startswith("tcp:"):
                self.channel_name, self.path, self._tcp = self._tcp_endpoint(channel, token)
            else:
                self.channel_name, self.path = parse_channel(channel)
        except FileNotFoundError as exc:
            raise CanInitializationError(f"trainhil: no TCP bus server for channel {channel!r} ({exc.filename} does "
                                         "not exist); start one with tcp=True") from None
        except (ValueError, OSError) as exc:
            raise CanInitializationError(f"trainhil: {exc}") from exc
        name = node_name or f"pid{os.getpid()}.{next(_node_seq)}"
        # lazy_reader: for the rig's own nodes, whose engine FrameLink then reads at the node's read times only;
        # quiet: a lazy reader that rings the server's bell (FrameLink(bell=bell_fileno())), where it has one
        if quiet and not lazy_reader:
            raise CanInitializationError("trainhil: quiet=True is for a lazy reader (lazy_reader=True)")
        self._bell = self._open_bell() if quiet else None
        try:
            hello = pack_hello(name, receive_own_messages, lazy=lazy_reader, quiet=self._bell is not None)
            if self._tcp is not None:
                hello = pack_auth(self._tcp[2]) + hello  # the token goes first, or the server hangs up
            self._sock = self._connect_tcp(connect_timeout) if self._tcp is not None else self._connect(connect_timeout)
        except BaseException:
            self._close_bell()
            raise
        try:
            welcome = self._handshake(hello, connect_timeout)
        except BaseException:
            self._sock.close()
            self._close_bell()
            raise
        if self.fd and not welcome.fd_data_bitrate:
            self._sock.close()
            self._close_bell()
            raise CanInitializationError(f"trainhil: fd=True, but the bus {self.channel_name!r} is classical CAN "
                                         "(its scenario sets can.fd = false)")
        self.node_name = name
        self.bitrate = welcome.bitrate
        self.data_bitrate = welcome.fd_data_bitrate or None  # a CAN FD bus's data bitrate
        self.client_id = welcome.client_id
        wanted = kwargs.get("bitrate")
        if wanted is not None and int(wanted) != welcome.bitrate:
            LOG.warning("trainhil %s: bitrate %s requested, the emulated bus runs at %d bit/s",
                        self.channel_name, wanted, welcome.bitrate)
        rates = f"{welcome.bitrate} bit/s" + (f", CAN FD data {welcome.fd_data_bitrate} bit/s" if self.data_bitrate else "")
        self.channel_info = f"trainhil {self.channel_name} ({rates}, node {name})"
        self.channel_index = bus_index(self.channel_name)
        self._sock.setblocking(False)
        self._rbuf = bytearray(RECORD_SIZE)
        self._rview = memoryview(self._rbuf)
        self._rlen = 0
        self._long: bytes | None = None  # the FRAME record of a CAN FD frame whose FRAME_DATA records are due
        self._long_rest = bytearray()
        self._send_lock = threading.Lock()
        self._filter_gen = 0  # last filter set sent; the server acknowledges each
        self._acked_gen = 0
        super().__init__(channel, can_filters=can_filters, **kwargs)

    # ---- connection
    @staticmethod
    def _tcp_endpoint(channel: Any, token: str | bytes | None) -> tuple[str, Path | None, tuple[str, int, bytes]]:
        """(channel text, token file or None, (host, port, token)) of a "tcp:..." channel."""
        text, token_file, host, port = parse_tcp_channel(channel)
        if token_file is not None:
            for d in (token_file.parent.parent, token_file.parent):  # runtime root, run directory
                check_private_dir(d)
            host, port, found = read_token_file(token_file)
            return text, token_file, (host, port, found)
        if token is None:
            raise ValueError(f"channel {text!r}: a TCP bus needs the run's token (token=...), or use "
                             "\"tcp:<run>/<bus>\" to read it from the run directory")
        if isinstance(token, int) and not isinstance(token, bool):
            token = f"{token:032d}"  # python-can casts an all-digit hex string to int: undo it
        if not isinstance(token, (str, bytes, bytearray)):
            raise ValueError(f"channel {text!r}: token must be 32 hex digits or 16 bytes, got {type(token).__name__} "
                             "(python-can reads some strings as numbers: pass bytes.fromhex(...))")
        raw = bytes.fromhex(token) if isinstance(token, str) else bytes(token)
        if len(raw) != TOKEN_BYTES:
            raise ValueError(f"channel {text!r}: token must be {TOKEN_BYTES} bytes (32 hex digits), got {len(raw)}")
        assert host is not None and port is not None  # a "tcp://host:port" channel names both
        return text, None, (host, port, raw)

    def _connect_tcp(self, timeout: float) -> socket.socket:
        assert self._tcp is not None
        host, port, _ = self._tcp
        try:
            sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as exc:
            raise CanInitializationError(f"trainhil: no bus server accepts TCP connections on {host}:{port} "
                                         f"(channel {self.channel_name!r}): {exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def _connect(self, timeout: float) -> socket.socket:
        path = self.path
        assert path is not None  # a unix-socket channel has its path
        if "/" in self.channel_name and not os.path.isabs(self.channel_name):
            for d in (path.parent.parent, path.parent):  # runtime root, run directory
                try:
                    check_private_dir(d)
                except FileNotFoundError:
                    break  # reported as "no server" below
                except PermissionError as exc:
                    raise CanInitializationError(f"trainhil: {exc}") from exc
        try:
            if stat.S_ISSOCK(os.lstat(path).st_mode):
                check_private_socket(path)  # ours, owner-only: not a socket someone else planted
        except FileNotFoundError:
            pass  # reported as "no server" below
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
        buf = bytearray()
        deadline = time.monotonic() + timeout
        try:
            try:
                self._sock.sendall(hello)
            except BrokenPipeError:
                pass  # it closed on us before reading the hello: a REFUSED record it sent first may say why
            while len(buf) < RECORD_SIZE:
                self._sock.settimeout(max(deadline - time.monotonic(), 1e-3))
                chunk = self._sock.recv(RECORD_SIZE - len(buf))
                if not chunk:
                    break
                buf += chunk
        except TimeoutError:
            raise CanInitializationError(f"trainhil: the server at {self._where()} did not answer within "
                                         f"{timeout} s") from None
        except ConnectionError as exc:  # reset or broken pipe: it refused us; a REFUSED record may say why
            if len(buf) < RECORD_SIZE:
                raise CanInitializationError(f"trainhil: the server at {self._where()} refused the connection "
                                             f"during the handshake ({exc.strerror or exc})") from None
        if len(buf) < RECORD_SIZE:
            why = " (TCP: a missing or wrong token is refused)" if self._tcp is not None else ""
            raise CanInitializationError(f"trainhil: the server at {self._where()} closed the connection "
                                         f"during the handshake{why}")
        refused = refused_reason(buf)
        if refused is not None:
            raise CanInitializationError(f"trainhil: the server at {self._where()} refused the connection: {refused}")
        try:
            welcome = unpack_welcome(buf)
        except ProtocolError as exc:
            raise CanInitializationError(f"trainhil: {self._where()} does not speak the trainhil protocol: {exc}") from None
        if welcome.version != PROTOCOL_VERSION:
            raise CanInitializationError(f"trainhil: the server at {self._where()} speaks protocol version "
                                         f"{welcome.version}, this client {PROTOCOL_VERSION}")
        return welcome

    def _open_bell(self) -> int | None:
        """The server's bell (``<bus>.bell``) for a quiet lazy reader on a unix socket; None over TCP or where the
        server has none."""
        if self._tcp is not None or self.path is None:
            return None
        try:
            return open_bell(self.path)
        except InsecureRunDirError as exc:
            raise CanInitializationError(f"trainhil: {exc}") from exc

    def _close_bell(self) -> None:
        if self._bell is not None:
            os.close(self._bell)
            self._bell = None

    def bell_fileno(self) -> int | None:
        """The write end of the server's bell if this node is a quiet reader (its FrameLink rings it), else None."""
        return self._bell

    def _ring(self) -> None:
        """Wake the server for what this quiet node just wrote (a full FIFO already holds unread wake-ups)."""
        if self._bell is not None:
            try:
                os.write(self._bell, b"!")
            except BlockingIOError:
                pass

    def _where(self) -> str:
        return f"{self._tcp[0]}:{self._tcp[1]}" if self._tcp is not None else str(self.path)

    def fileno(self) -> int:
        """The socket: readable when a record waits (one record is read per message, so this stays exact)."""
        return self._sock.fileno()

    # ---- transmit
    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Queue ``msg`` in this node's TX queue on the emulated bus (a full queue drops it; the server counts)."""
        if msg.is_remote_frame or msg.is_error_frame:
            kind = "remote" if msg.is_remote_frame else "error"
            raise CanOperationError(f"trainhil: frame {msg.arbitration_id:#x} is a {kind} frame; "
                                    "only data frames are emulated")
        if msg.is_fd and not self.fd:
            raise CanOperationError(f"trainhil: frame {msg.arbitration_id:#x} is a CAN FD frame; open the bus "
                                    "with fd=True to send CAN FD frames (as with SocketCAN)")
        flags = (FLAG_EXTENDED if msg.is_extended_id else 0) | (
            (FLAG_FD | (FLAG_BRS if msg.bitrate_switch else 0)) if msg.is_fd else 0)
        record = pack_frame(msg.arbitration_id, bytes(msg.data), flags)  # ValueError names a bad id or length
        with self._send_lock:
            self._write(record, timeout)
            self._ring()

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
                if kind == KIND_FRAME and record[2] > MAX_DLC:  # a CAN FD frame: its FRAME_DATA records follow
                    self._long, self._long_rest = record, bytearray()
                    continue
                if kind == KIND_FRAME_DATA and self._long is not None:
                    self._long_rest += record
                    if len(self._long_rest) < frame_data_records(self._long[2]) * RECORD_SIZE:
                        continue
                    head, rest, self._long = self._long, bytes(self._long_rest), None
                    return self._message(head, rest), self._acked_gen == self._filter_gen
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
            raise CanOperationError(f"trainhil {self.channel_name}: the bus server at {self._where()} "
                                    "closed the connection")
        self._rlen += n
        if self._rlen < RECORD_SIZE:
            return None
        self._rlen = 0
        return bytes(self._rbuf)

    def _message(self, record: bytes, continuation: bytes = b"") -> Message:
        """The python-can message of a FRAME record (and the FRAME_DATA records of a CAN FD payload above 8 bytes)."""
        _, flags, dlc, can_id, timestamp, data = FRAME.unpack(record)
        if continuation:
            data = join_frame(Frame(can_id, data, flags, timestamp, dlc), continuation).data
        return Message(timestamp=timestamp, arbitration_id=can_id, is_extended_id=bool(flags & FLAG_EXTENDED),
                       is_remote_frame=bool(flags & FLAG_REMOTE), is_error_frame=bool(flags & FLAG_ERROR),
                       dlc=dlc, data=data[:dlc], is_rx=not flags & FLAG_ECHO, channel=self.channel_index,
                       is_fd=bool(flags & FLAG_FD), bitrate_switch=bool(flags & FLAG_BRS), check=False)

    # ---- filters, shutdown, discovery
    def _apply_filters(self, filters) -> None:
        """Send the set to the server; frames are filtered in software until it acknowledges."""
        parsed = [filter_from_python_can(f, i) for i, f in enumerate(filters or ())]
        if not parsed and self._filter_gen == 0:
            return  # the server starts with "accept everything"
        self._filter_gen = (self._filter_gen + 1) & 0xFFFFFFFF
        with self._send_lock:
            self._write(pack_filters(parsed, self._filter_gen), None)
            self._ring()

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._sock.close()
        self._close_bell()

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        """Every bus of every running rig under the runtime root (a socket that accepts a connection)."""
        return [AutoDetectedConfig(interface=INTERFACE, channel=channel)
                for channel, path in bus_sockets() if socket_is_live(path, 0.2)]
