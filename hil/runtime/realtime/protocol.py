"""Wire protocol between a bus server and its nodes: fixed-size 24-byte little-endian records over a unix stream socket.

Every record is ``RECORD_SIZE`` = 24 bytes and starts with a kind byte; a reader takes whole records off the
stream (keeping a partial tail for the next read). ``x`` is a zero pad byte.

======  ===============  ========  ==================================================================
kind    name             way       layout (struct, after the common "<")
======  ===============  ========  ==================================================================
1       FRAME            both      ``B B B x I d 8s``: kind, flags, dlc, -, can_id, timestamp, data
2       HELLO            c -> s    ``B B B x 20s``: kind, version, options, -, node name (UTF-8, NUL-padded)
3       WELCOME          s -> c    ``B B x x I d I I``: kind, version, -, -, bitrate, epoch0, client id, FD data bitrate
4       FILTERS          c -> s    ``B x H I 16x``: kind, -, count, generation; ``count`` FILTER records follow
5       FILTER           c -> s    ``B B x x I I 12x``: kind, match, -, -, can_id, can_mask
6       FILTERS_ACK      s -> c    ``B x x x I 16x``: kind, generation
7       AUTH             c -> s    ``B x x x 16s 4x``: kind, -, the run's token (16 bytes); TCP only, first record
10      READ_EVERY       c -> s    ``B B 6x d d``: kind, READ_TURNS or 0, first read time (epoch s), period (s; 0: one read); lazy only
11      SYNC             s -> c    ``B 7x d 8x``: kind, read time (epoch s): every frame that ended by then came before
13      DONE             c -> s    ``B 7x d 8x``: kind, read time (epoch s) of the node's turn it ends; lazy only
14      LEAST_DATA       c -> s    ``B B 22x``: kind, the fewest data bytes of any frame it will send; before its first
15      SENDER_NAME      c -> s    ``B B x x 20s``: kind, sender (FRAME byte 3), its bus node's name; before the first frame
======  ===============  ========  ==================================================================

FRAME: ``flags`` bits: EXTENDED (29-bit id), REMOTE, ERROR, ECHO (the node's own frame sent back because it
asked for its own messages; python-can ``is_rx=False``), FD (a CAN FD frame) and BRS (its data phase at the
data bitrate; only with FD). ``data`` is always 8 bytes, the first ``min(dlc, 8)`` count. A CAN FD frame with
more than 8 data bytes (``dlc`` = 12, 16, 20, 24, 32, 48 or 64, its payload length) is followed at once by
FRAME_DATA records (kind 9, ``B 23s``: kind, the next 23 payload bytes, zero-padded): 64 bytes take 4 records.
FRAME byte 3 (``x`` in ``FRAME``): from a node, which of its senders sends the frame (0..MAX_SENDERS-1; 0, the
node itself, is all python-can sends): the server keeps a bus node with its own TX queue per sender, so a process
hosting several ECUs queues each one's frames as its own controller would; from the server, 0.
From a node, ``timestamp`` is ignored (the frame is queued when the server reads it) unless the node is a lazy
reader, whose frames are queued at the epoch second they carry (kept between what the bus has run to and now);
from the server it is
the end of the frame's transmission (last bit of the intermission) in epoch seconds. Only classical data
frames are emulated: a node must not send REMOTE, ERROR or ECHO (the server counts and drops them); ERROR
frames are reserved for the server's fault hooks.

Lazy readers (HELLO options bit 1, OPTION_LAZY; the rig's ECU and plant nodes): the node says when it reads
(READ_EVERY, up to MAX_READ_SCHEDULES schedules), and the server hands its frames over only then: at each read
time, every frame for it that ended by then and a SYNC of that time, written at once. The server wakes at frame
ends only for eager nodes (python-can clients, the radio) and the error model; a lazy node blocks on its socket
until the SYNC of its read time, so it sees exactly the frames that ended by then (``link.rs``).

Quiet readers (HELLO options bit 2, OPTION_QUIET, with OPTION_LAZY; the rig's ECU and plant nodes on a server
that has a bell): what the node writes does not wake the server, which reads it at its next wake-up (a read time,
a frame end someone needs) and queues its frames at the instants they carry, as before. The node rings the bell,
a FIFO beside the socket (``<bus>.bell``, mode 0o600), when the server must see a record now: a READ_EVERY, a
frame the server hands over at its end. BELL records (kind 12) from the server say which frames those are:
``flags`` BELL_EVERY (every frame: an eager node, the error model or the guardian is on the bus) and BELL_RESET
(a new set starts), ``count`` IDs (u32, from byte 4) the radio takes; until the first, every frame rings.

Turns (READ_EVERY byte 1 = READ_TURNS; the rig's ECU and plant nodes with turns, ``hil run --turns``): each read time
of that schedule is the node's turn. After its SYNC the node acts as at the read time, however long its work
takes: its FRAME records carry that instant, and it ends the turn with DONE (after its frames, in the same write).
Until then the server runs its bus, and the buses of its radio, no further than just before the read time, and
reads the node's socket even if it is quiet; eager nodes' records wait meanwhile and are queued when taken. So
the frames of a turn compete for the bus at their instant, and a reader whose read time comes later has them, as
in virtual time. A turn without DONE is let go TURN_HOLD_MAX_S of wall time after its read time, and a bus already
further behind the wall clock than that at a read time lets its turn go at once (both counted: the server's
``turn_overruns``; the first kind by the node's name, ``turns_let_go``, the second as ``turns_behind``). After 20 of
the second kind within a second of wall time (TURNS_BEHIND_MAX) the server gives turns up for the rest of the run
(``turns_given_up_s``, when): the machine does not keep up with them, and holding for more would only put the bus
further behind, so the read times go on as plain reads. A DONE
stamped +inf says the node's turns are over (its run ended): its read times go on as plain reads.

Look-ahead: on an idle bus the server SYNCs at once every read time that no frame could end by, however soon one
were queued: those within the least frame any connection (or the radio, which forwards the frames of its buses'
connections) could still send. That is an empty frame (47 bits, without stuff bits) unless every connection said
it sends more (LEAST_DATA, before its first frame; the rig's ECU and plant nodes say what their DBC messages
carry). A node then acts on its SYNC before its read time, as at it. A frame shorter than its connection said is
refused and counted, as one the bus cannot carry; LEAST_DATA after a frame is a protocol error.

Session: the node sends HELLO (protocol version, options bit 0 = receive own messages, its name); the server
answers WELCOME (its version, the bitrate, ``epoch0`` = the epoch time of the bus's time zero, the node's id,
and on a CAN FD bus its data bitrate: 0 means a classical bus, where FD frames are refused).
A node replaces its acceptance filters with FILTERS (``count`` = 0: accept everything, the initial state;
``generation`` numbers the change) followed by ``count`` FILTER records; the server applies the set once
complete and answers FILTERS_ACK with that generation. A FILTER matches a frame when
``(frame_id ^ can_id) & can_mask == 0`` and the frame's format fits ``match`` (0 any, 1 standard only,
2 extended only): python-can's filter semantics. Any other record, or a version mismatch, ends the session.

Loopback TCP (optional, see ``sockets.listen_tcp``): a TCP client must send AUTH with the bus's per-run token as its
very first record, before HELLO; a missing or wrong token ends the connection at once. Unix-socket clients are
authenticated by the file system (owner-only run directory and socket) and never send AUTH.

The constants (kinds, flags, sizes, reasons, limits) are the engine's, defined once in engine/src/protocol.rs and
exported as ``trainhil_engine.PROTOCOL``.

``decode_record`` turns any 24 bytes into one typed record or a ProtocolError naming what is wrong: the
server's parser and the property tests rely on it never raising anything else.
"""
from __future__ import annotations

import struct
import unicodedata
from typing import NamedTuple

import trainhil_engine as engine

from hil.can.frame import fd_pad

# The constants are the engine's (engine/src/protocol.rs, defined once for the server, FrameLink and this module).
_WIRE = engine.PROTOCOL


def _int(name: str) -> int:
    return int(_WIRE[name])


PROTOCOL_VERSION = _int("PROTOCOL_VERSION")
RECORD_SIZE = _int("RECORD_SIZE")
NAME_BYTES = _int("NAME_BYTES")
MAX_DLC = _int("MAX_DLC")  # data bytes in a FRAME record (and in a classical frame)
MAX_FILTERS = _int("MAX_FILTERS")

KIND_FRAME = _int("KIND_FRAME")
KIND_HELLO = _int("KIND_HELLO")
KIND_WELCOME = _int("KIND_WELCOME")
KIND_FILTERS = _int("KIND_FILTERS")
KIND_FILTER = _int("KIND_FILTER")
KIND_FILTERS_ACK = _int("KIND_FILTERS_ACK")
KIND_AUTH = _int("KIND_AUTH")
KIND_REFUSED = _int("KIND_REFUSED")  # server -> client, then it closes: byte 1 says why (REFUSED_REASONS)
KIND_FRAME_DATA = _int("KIND_FRAME_DATA")  # both ways: 23 more payload bytes of the CAN FD frame before it
FRAME_DATA_BYTES = _int("FRAME_DATA_BYTES")
MAX_FD_DLC = _int("MAX_FD_DLC")
TOKEN_BYTES = _int("TOKEN_BYTES")
REFUSED_FULL, REFUSED_TOKEN = _int("REFUSED_FULL"), _int("REFUSED_TOKEN")
REFUSED_WAITING, REFUSED_TIMEOUT = _int("REFUSED_WAITING"), _int("REFUSED_TIMEOUT")
REFUSED_REASONS = {
    REFUSED_FULL: "the bus server is full (max_clients connections)",
    REFUSED_TOKEN: "a missing or wrong token (TCP needs the run's token)",
    REFUSED_WAITING: "too many TCP connections are waiting to authenticate (someone may be holding them open)",
    REFUSED_TIMEOUT: "no token within the authentication deadline",
}
# TCP connections without the token yet: their own small budget and a short deadline, so that they never take
# the slots (max_clients) of authenticated or unix-socket nodes. The same values as the engine's server.rs.
MAX_UNAUTHENTICATED = _int("MAX_UNAUTHENTICATED")
AUTH_TIMEOUT_S = float(_WIRE["AUTH_TIMEOUT_S"])

FLAG_EXTENDED = _int("FLAG_EXTENDED")
FLAG_REMOTE = _int("FLAG_REMOTE")
FLAG_ERROR = _int("FLAG_ERROR")
FLAG_ECHO = _int("FLAG_ECHO")
FLAG_FD = _int("FLAG_FD")  # a CAN FD frame
FLAG_BRS = _int("FLAG_BRS")  # ... whose data phase runs at the data bitrate
KNOWN_FLAGS = FLAG_EXTENDED | FLAG_REMOTE | FLAG_ERROR | FLAG_ECHO | FLAG_FD | FLAG_BRS

OPTION_RECEIVE_OWN = _int("OPTION_RECEIVE_OWN")
OPTION_LAZY = _int("OPTION_LAZY")  # a lazy reader: its frames come at its read times (READ_EVERY), then a SYNC
KIND_READ_EVERY = _int("KIND_READ_EVERY")  # lazy reader -> server: first read time (epoch s), period (s; 0: once)
KIND_SYNC = _int("KIND_SYNC")  # server -> lazy reader: every frame that ended by this epoch second came before
OPTION_QUIET = _int("OPTION_QUIET")  # a quiet lazy reader: its records wait for the server's next wake-up
KIND_BELL = _int("KIND_BELL")  # server -> quiet reader: the frames it rings the bell for
MAX_SENDERS = _int("MAX_SENDERS")  # senders per connection (FRAME byte 3), each its own TX queue on the bus
READ_TURNS = _int("READ_TURNS")  # READ_EVERY byte 1: each read time is the node's turn, ended by DONE
KIND_DONE = _int("KIND_DONE")  # lazy reader -> server: its turn at this epoch second is over
TURN_HOLD_MAX_S = float(_WIRE["TURN_HOLD_MAX_S"])  # wall seconds after its read time a turn may hold the bus
KIND_LEAST_DATA = _int("KIND_LEAST_DATA")  # node -> server: its frames carry at least byte 1 data bytes
KIND_SENDER_NAME = _int("KIND_SENDER_NAME")  # node -> server: sender byte 1's bus node is called the name given

MATCH_ANY = _int("MATCH_ANY")
MATCH_STANDARD = _int("MATCH_STANDARD")
MATCH_EXTENDED = _int("MATCH_EXTENDED")

STD_ID_LIMIT = 1 << 11
EXT_ID_LIMIT = 1 << 29

FRAME = struct.Struct("<BBBxId8s")
HELLO = struct.Struct("<BBBx20s")
WELCOME = struct.Struct("<BBxxIdII")
FILTERS = struct.Struct("<BxHI16x")
FILTER = struct.Struct("<BBxxII12x")
FILTERS_ACK = struct.Struct("<BxxxI16x")
AUTH = struct.Struct("<Bxxx16s4x")
FRAME_DATA = struct.Struct("<B23s")
assert all(s.size == RECORD_SIZE for s in (FRAME, HELLO, WELCOME, FILTERS, FILTER, FILTERS_ACK, AUTH, FRAME_DATA))


class ProtocolError(ValueError):
    """A record that breaks the protocol (unknown kind, bad field): the session ends."""


class Frame(NamedTuple):
    can_id: int
    data: bytes  # the record's bytes: the first min(dlc, 8); join_frame adds the rest of a longer CAN FD payload
    flags: int = 0
    timestamp: float = 0.0
    dlc: int | None = None  # the payload length the FRAME record announced (None: len(data))


class Hello(NamedTuple):
    name: str
    receive_own: bool
    version: int = PROTOCOL_VERSION


class Welcome(NamedTuple):
    bitrate: int
    epoch0: float
    client_id: int
    version: int = PROTOCOL_VERSION
    fd_data_bitrate: int = 0  # a CAN FD bus's data bitrate; 0: classical CAN


class Filter(NamedTuple):
    can_id: int
    can_mask: int
    match: int = MATCH_ANY


def frame_error(can_id: int, dlc: int, flags: int, fd_bus: bool = False) -> str | None:
    """Why a frame from a node cannot go on the emulated bus (None if it can); a CAN FD bus carries both formats.
    The bus server's own check (``protocol::frame_error`` in the engine), so both sides say the same."""
    return engine.frame_error(can_id, dlc, flags, fd_bus)


def frame_data_records(dlc: int) -> int:
    """How many FRAME_DATA records follow a FRAME record of ``dlc`` data bytes."""
    return max(0, -(-(dlc - MAX_DLC) // FRAME_DATA_BYTES))


def pack_frame(can_id: int, data: bytes, flags: int = 0, timestamp: float = 0.0) -> bytes:
    """A FRAME record, and for a CAN FD payload above 8 bytes its FRAME_DATA records (padded to an FD length);
    ValueError naming the id if it or the data do not fit."""
    if len(data) > MAX_DLC:
        if not flags & FLAG_FD:
            raise ValueError(f"frame {can_id:#x}: {len(data)} data bytes > {MAX_DLC} in a classical frame")
        if len(data) > MAX_FD_DLC:
            raise ValueError(f"frame {can_id:#x}: {len(data)} data bytes > {MAX_FD_DLC} (CAN FD)")
        data = fd_pad(bytes(data))
    limit = EXT_ID_LIMIT if flags & FLAG_EXTENDED else STD_ID_LIMIT
    if not 0 <= can_id < limit:
        raise ValueError(f"frame id {can_id:#x} out of range for a "
                         f"{'29' if flags & FLAG_EXTENDED else '11'}-bit identifier (0..{limit - 1:#x})")
    head = FRAME.pack(KIND_FRAME, flags, len(data), can_id, timestamp, data[:MAX_DLC])
    rest = data[MAX_DLC:]
    return head + b"".join(FRAME_DATA.pack(KIND_FRAME_DATA, rest[k:k + FRAME_DATA_BYTES])
                           for k in range(0, len(rest), FRAME_DATA_BYTES))


def join_frame(head: Frame, continuation: bytes | memoryview) -> Frame:
    """A frame whose FRAME record said ``dlc`` > 8, completed with its FRAME_DATA records; ProtocolError if one is not."""
    out = bytearray(head.data)
    for off in range(0, len(continuation), RECORD_SIZE):
        if continuation[off] != KIND_FRAME_DATA:
            raise ProtocolError(f"frame {head.can_id:#x}: record kind {continuation[off]} where its FRAME_DATA was due")
        out += continuation[off + 1:off + RECORD_SIZE]
    return head._replace(data=bytes(out[:head.dlc]))


def unpack_frame(record: bytes | bytearray | memoryview, offset: int = 0) -> Frame:
    """The FRAME record at ``offset``; ProtocolError if it is another kind or its dlc exceeds 8."""
    kind, flags, dlc, can_id, timestamp, data = FRAME.unpack_from(record, offset)
    if kind != KIND_FRAME:
        raise ProtocolError(f"record kind {kind} is not a FRAME ({KIND_FRAME})")
    if dlc > MAX_FD_DLC:
        raise ProtocolError(f"frame {can_id:#x}: dlc {dlc} > {MAX_FD_DLC}")
    return Frame(can_id, data[:min(dlc, MAX_DLC)], flags, timestamp, dlc)


def pack_hello(name: str, receive_own: bool = False, version: int = PROTOCOL_VERSION, lazy: bool = False,
               quiet: bool = False) -> bytes:
    """HELLO: the node's name and options (``receive_own``; ``lazy``: a lazy reader, see OPTION_LAZY; ``quiet``: a
    quiet one, see OPTION_QUIET)."""
    raw = name.encode()
    if not raw or len(raw) > NAME_BYTES or b"\0" in raw:
        raise ValueError(f"node name {name!r}: must be 1-{NAME_BYTES} bytes of UTF-8 without NUL")
    if quiet and not lazy:
        raise ValueError("a quiet node must be a lazy reader")
    options = (OPTION_RECEIVE_OWN if receive_own else 0) | (OPTION_LAZY if lazy else 0) | (OPTION_QUIET if quiet else 0)
    return HELLO.pack(KIND_HELLO, version, options, raw)


def unpack_hello(record: bytes | bytearray | memoryview, offset: int = 0) -> Hello:
    kind, version, options, raw = HELLO.unpack_from(record, offset)
    if kind != KIND_HELLO:
        raise ProtocolError(f"record kind {kind} is not a HELLO ({KIND_HELLO})")
    try:
        name = raw.rstrip(b"\0").decode()
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"HELLO: node name {raw!r} is not UTF-8") from exc
    return Hello(loggable(name) or "?", bool(options & OPTION_RECEIVE_OWN), version)


def loggable(name: str) -> str:
    """A node name as it goes into logs: control characters (newlines, escapes) become '?', so no node can forge a
    log line (the engine's server does the same)."""
    return "".join("?" if unicodedata.category(c) == "Cc" else c for c in name)


def pack_welcome(bitrate: int, epoch0: float, client_id: int, version: int = PROTOCOL_VERSION,
                 fd_data_bitrate: int = 0) -> bytes:
    return WELCOME.pack(KIND_WELCOME, version, bitrate, epoch0, client_id, fd_data_bitrate)


def unpack_welcome(record: bytes | bytearray | memoryview, offset: int = 0) -> Welcome:
    kind, version, bitrate, epoch0, client_id, fd_data_bitrate = WELCOME.unpack_from(record, offset)
    if kind != KIND_WELCOME:
        raise ProtocolError(f"record kind {kind} is not a WELCOME ({KIND_WELCOME})")
    return Welcome(bitrate, epoch0, client_id, version, fd_data_bitrate)


def filter_from_python_can(f: dict, index: int = 0) -> Filter:
    """A python-can filter dict {"can_id", "can_mask"[, "extended"]} -> Filter; ValueError naming the entry."""
    try:
        can_id, can_mask = int(f["can_id"]), int(f["can_mask"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"can_filters[{index}] = {f!r}: needs integer 'can_id' and 'can_mask'") from exc
    if not (0 <= can_id < 1 << 32 and 0 <= can_mask < 1 << 32):
        raise ValueError(f"can_filters[{index}] = {f!r}: can_id and can_mask must fit in 32 bits")
    ext = f.get("extended")
    match = MATCH_ANY if ext is None else (MATCH_EXTENDED if ext else MATCH_STANDARD)
    return Filter(can_id, can_mask, match)


def pack_filters(filters: list[Filter], generation: int) -> bytes:
    """FILTERS plus one FILTER record per entry (an empty list accepts every frame)."""
    if len(filters) > MAX_FILTERS:
        raise ValueError(f"{len(filters)} acceptance filters > {MAX_FILTERS}")
    head = FILTERS.pack(KIND_FILTERS, len(filters), generation & 0xFFFFFFFF)
    return head + b"".join(FILTER.pack(KIND_FILTER, f.match, f.can_id, f.can_mask) for f in filters)


def unpack_filters_head(record: bytes | bytearray | memoryview, offset: int = 0) -> tuple[int, int]:
    """(count, generation) of a FILTERS record."""
    kind, count, generation = FILTERS.unpack_from(record, offset)
    if kind != KIND_FILTERS:
        raise ProtocolError(f"record kind {kind} is not FILTERS ({KIND_FILTERS})")
    if count > MAX_FILTERS:
        raise ProtocolError(f"FILTERS: {count} filters > {MAX_FILTERS}")
    return count, generation


def unpack_filter(record: bytes | bytearray | memoryview, offset: int = 0) -> Filter:
    kind, match, can_id, can_mask = FILTER.unpack_from(record, offset)
    if kind != KIND_FILTER:
        raise ProtocolError(f"record kind {kind} is not a FILTER ({KIND_FILTER})")
    if match not in (MATCH_ANY, MATCH_STANDARD, MATCH_EXTENDED):
        raise ProtocolError(f"FILTER: match {match} is not 0, 1 or 2")
    return Filter(can_id, can_mask, match)


def pack_refused(why: int) -> bytes:
    """The record a refused connection gets before the server closes it."""
    return bytes([KIND_REFUSED, why]) + bytes(RECORD_SIZE - 2)


def refused_reason(record: bytes | bytearray | memoryview) -> str | None:
    """Why the server refused us, if ``record`` is a REFUSED record (else None)."""
    if record[0] != KIND_REFUSED:
        return None
    return REFUSED_REASONS.get(record[1], f"refused (reason code {record[1]})")


def pack_filters_ack(generation: int) -> bytes:
    return FILTERS_ACK.pack(KIND_FILTERS_ACK, generation & 0xFFFFFFFF)


def unpack_filters_ack(record: bytes | bytearray | memoryview, offset: int = 0) -> int:
    kind, generation = FILTERS_ACK.unpack_from(record, offset)
    if kind != KIND_FILTERS_ACK:
        raise ProtocolError(f"record kind {kind} is not FILTERS_ACK ({KIND_FILTERS_ACK})")
    return generation


def filters_accept(filters: tuple[Filter, ...] | None, can_id: int, extended: bool) -> bool:
    """python-can semantics: no filters accept everything, else any filter that matches the id and format (the
    bus server's own rule, ``protocol::filters_accept`` in the engine)."""
    return engine.filters_accept(filters, can_id, extended)


def pack_auth(token: bytes) -> bytes:
    """The AUTH record carrying a bus's per-run token (TCP clients send it first)."""
    if len(token) != TOKEN_BYTES:
        raise ValueError(f"a bus token is {TOKEN_BYTES} bytes, got {len(token)}")
    return AUTH.pack(KIND_AUTH, token)


def unpack_auth(record: bytes | bytearray | memoryview, offset: int = 0) -> bytes:
    kind, token = AUTH.unpack_from(record, offset)
    if kind != KIND_AUTH:
        raise ProtocolError(f"record kind {kind} is not AUTH ({KIND_AUTH})")
    return token


class FiltersHead(NamedTuple):
    count: int  # type: ignore[assignment]  # the field shadows tuple.count, as the wire names it
    generation: int


class FiltersAck(NamedTuple):
    generation: int


class Auth(NamedTuple):
    token: bytes


class FrameData(NamedTuple):
    """23 more payload bytes of the CAN FD frame before it."""

    data: bytes


Record = Frame | Hello | Welcome | FiltersHead | Filter | FiltersAck | Auth | FrameData


def decode_record(record: bytes | bytearray | memoryview) -> Record:
    """Any 24 bytes -> the typed record, or ProtocolError saying what is wrong (never another exception).

    A FRAME that decodes but could not go on the bus (bad dlc, flags or id) is still a Frame: ``frame_error``
    judges it, as the server does (counted and dropped, the session goes on)."""
    if len(record) != RECORD_SIZE:
        raise ProtocolError(f"a record is {RECORD_SIZE} bytes, got {len(record)}")
    kind = record[0]
    if kind == KIND_FRAME:
        _, flags, dlc, can_id, timestamp, data = FRAME.unpack_from(record)
        return Frame(can_id, data[:min(dlc, MAX_DLC)], flags, timestamp, dlc)
    if kind == KIND_FRAME_DATA:
        return FrameData(bytes(record[1:]))
    if kind == KIND_HELLO:
        return unpack_hello(record)
    if kind == KIND_WELCOME:
        return unpack_welcome(record)
    if kind == KIND_FILTERS:
        return FiltersHead(*unpack_filters_head(record))
    if kind == KIND_FILTER:
        return unpack_filter(record)
    if kind == KIND_FILTERS_ACK:
        return FiltersAck(unpack_filters_ack(record))
    if kind == KIND_AUTH:
        return Auth(unpack_auth(record))
    raise ProtocolError(f"unknown record kind {kind} (first bytes {bytes(record[:4]).hex()})")
