"""Typed surface of the compiled frame engine (engine/src/py.rs). Times are integer ns unless named ``_s``."""
from collections.abc import Callable, Sequence
from os import PathLike
from pathlib import Path

VERSION: str
MAX_DATA: int  # bytes a frame can carry (CAN FD); classical frames carry at most 8
PROTOCOL: dict[str, int | float]  # the bus-server wire protocol's constants by name (engine/src/protocol.rs)

def frame_bits(can_id: int, data: bytes | bytearray, extended: bool = False) -> int:
    """Exact bits on the wire of a classical data frame, SOF through the 3-bit intermission."""

def frame_duration_ns(can_id: int, data: bytes | bytearray, nominal_bitrate: int, data_bitrate: int | None = None,
                      extended: bool = False, fd: bool = False, brs: bool = True) -> int:
    """Duration of a data frame at a nominal and a data bitrate; a CAN FD frame (``fd``) runs its data phase at the
    data rate when ``brs`` is set. An FD payload must have a CAN FD length (0..8, 12, 16, 20, 24, 32, 48, 64)."""

def fd_frame_bits(can_id: int, data: bytes | bytearray, extended: bool = False, brs: bool = True,
                  esi: bool = False) -> tuple[int, int]:
    """Exact bits of a CAN FD data frame (ISO 11898-1:2015), SOF through the intermission: (bits at the nominal
    rate, bits at the data rate; 0 without BRS)."""

def e2e_crc(data_id: int, payload: bytes | bytearray) -> int:
    """CRC-8 SAE J1850 over [data_id] + payload[1:]."""

def wire_bits(can_id: int, data: bytes | bytearray, extended: bool = False) -> bytes:
    """A classical data frame on the wire, SOF through EOF, one byte per bit (0 = dominant), as the error model
    corrupts it."""

def receive_wire(wire: Sequence[int] | bytes) -> tuple[str | None, int, int, bool, bytes]:
    """What CAN receivers make of ``wire``: (error "stuff"/"form"/"crc" or None, the bit it was found at, and for an
    accepted frame its ID, extended flag and data)."""

RngState = tuple[int, int]  # (state, inc) of a numpy PCG64 stream (``bit_generator.state["state"]``), continued here
# A bus event's kind and fields (hil.can.errors.event_text and hil.faults.guardian.guardian_text word them):
#   error_passive / error_active: node, tec, rec;  bus_off: node, tec, lost;  recovered: node, after_ns;
#   error_frame: error ("stuff", "form", "crc", "error flag"), frame_id, node (the first of an episode);
#   episode: start_ns, last_ns, by_error {kind: n};  babbling: frame_id, frames, busy_ns, allowance | None;  cleared: frame_id
BusEvent = tuple[int, str, dict]  # (t_ns, kind, fields)
BusFaultKind = str  # "corruption", "error_flags" or "drops"

SignalSpec = tuple[str, int, int, bool, float, float, int, int]  # name, start, length, signed, scale, offset, raw_min, raw_max

class MessageCodec:
    """One DBC message compiled for the hot path (built by ecu_sim.codec from cantools)."""

    name: str
    frame_id: int
    dlc: int
    data_id: int
    cycle_time_s: float
    signals: tuple[str, ...]
    units: tuple[str, ...]
    limits: tuple[tuple[float, float], ...]
    specs: list[SignalSpec]
    scales: list[float]
    saturations: dict[str, int]

    def __init__(self, name: str, frame_id: int, dlc: int, cycle_time_s: float, data_id: int,
                 specs: Sequence[SignalSpec], units: Sequence[str]) -> None: ...
    def encode(self, values: Sequence[float], counter: int) -> bytes:
        """Values in ``signals`` order -> bytes with alive counter and E2E CRC; saturates and counts, NaN raises."""
    def decode(self, data: bytes | bytearray) -> tuple[float, ...]: ...
    def counter_of(self, data: bytes | bytearray) -> int: ...
    def crc_ok(self, data: bytes | bytearray) -> bool: ...
    def index(self, signal: str) -> int: ...
    def reset_saturations(self) -> None: ...

class CommandInbox:
    """One train bus's command inbox for a real-time plant: its TractionCmd frames checked (length, E2E CRC, a mode
    in ``valid_modes``) and decoded on receipt, as ``Network.attach_commands`` does on delivery, and the
    sensor-to-actuator latency closed by its AgentState frames (the arrival of the unit's last valid command minus
    the publication of the Sensor sample the AgentState is numbered with). Fed by ``FrameLink.route_commands`` or
    ``put``."""

    ids: list[int]
    def __init__(self, commands: Sequence[tuple[int, MessageCodec, int]], valid_modes: Sequence[int],
                 states: Sequence[tuple[int, int]], units: int) -> None:
        """``commands``: (frame_id, codec with signals (Mode, Force), unit); ``states``: (AgentState frame_id, unit);
        every unit in 0..units-1 (IndexError otherwise)."""
    def put(self, frame_id: int, data: bytes, t: float) -> bool:
        """A frame received at ``t`` (simulated s); whether it was one of ``ids``."""
    def published(self, t: float, samples: Sequence[tuple[int, int]]) -> None:
        """The Sensor samples published at ``t``: (unit, alive counter) each."""
    def take(self) -> tuple[list[tuple[int, float, int, float, int]], list[tuple[int, bytes, float]], list[tuple[float, float]]]:
        """Since the last call, in arrival order: the valid commands (unit, force, mode, t, alive counter), the
        refused frames (frame_id, data, t), and the latencies (command arrival t, latency s)."""

class Mailbox:
    """An ECU's input mailboxes: delivery keeps the latest frame of each stream, ``refresh`` checks it once per cycle."""

    unknown_frames: int
    malformed_frames: int

    def __init__(self) -> None: ...
    def add_slot(self, codec: MessageCodec, max_delta: int) -> int: ...
    def put(self, frame_id: int, data: bytes | bytearray, t: float) -> int:
        """0 stored, 1 unknown ID, 2 known ID of the wrong length (dropped, counted)."""
    def refresh(self) -> int:
        """Check and decode what arrived since the last call; returns the wrong-length frames counted so far."""
    def read(self, slot: int, t: float, timeout: float) -> tuple[bool, float, tuple[float, ...], int, float]:
        """(fresh, age s, values, alive counter, reception time of the last good frame); counts TIMEOUTs."""
    def values(self, slot: int) -> tuple[float, ...]: ...
    def counter(self, slot: int) -> int: ...
    def t_good(self, slot: int) -> float: ...
    def reset(self) -> None: ...
    def summary(self, slot: int) -> dict[str, int]: ...
    def count(self, slot: int, status: int) -> int: ...
    def ids(self) -> list[int]: ...
    def take_first_malformed(self) -> tuple[float, int, int] | None: ...

class Packing:
    """CAN FD frame packing: a sender's batch that holds every part of a container goes as that one frame, and
    receivers get its parts back as the frames they were (engine/src/packing.rs)."""

    def __init__(self, containers: Sequence[tuple[int, int, Sequence[tuple[int, int, int]]]]) -> None:
        """[(container_id, data_length, [(part_id, byte_offset, byte_length)])]; a ValueError says what is wrong."""
    def pack(self, frames: Sequence[tuple[int, bytes]]) -> list[tuple[int, bytes]]: ...
    def unpack(self, frame_id: int, data: bytes) -> list[tuple[int, bytes]] | None:
        """The parts of a container frame that lie within ``data``; None when ``frame_id`` is not a container."""
    def containers_of(self, ids: Sequence[int]) -> list[int]:
        """The containers carrying any of ``ids``: a receiver of ``ids`` accepts these too."""
    def parts(self, frame_id: int) -> list[tuple[int, int, int]] | None:
        """[(part_id, byte_offset, byte_length)] of a container; None when ``frame_id`` is not one."""

class Network:
    """Every train bus, the radio gateway and the mailboxes on one virtual-time event queue."""

    now: int
    busy_s: float  # wall time spent inside advance and send (the engine's own cost)

    def __init__(self) -> None: ...
    def add_bus(self, name: str, bitrate: int, policy_name: str = "priority", depth: int = 64, extended: bool = False,
                load_window_ns: int = 100_000_000, fd: bool = False, data_bitrate: int | None = None,
                brs: bool = True) -> int:
        """A bus; with ``fd`` its nodes send CAN FD frames (payloads padded up to an FD length), their data phase at
        ``data_bitrate`` (default: ``bitrate``; never below it) when ``brs`` is set."""
    def attach_sender(self, bus: int, name: str) -> int: ...
    def attach_mailbox(self, bus: int, name: str, mailbox: Mailbox) -> int: ...
    def attach_inbox(self, bus: int, name: str, rx_ids: Sequence[int] | None) -> tuple[int, int]: ...
    def attach_gateway(self, bus: int, name: str) -> int: ...
    def add_link(self, name: str, range_m: float, blackouts: Sequence[tuple[float, float]], latency_ns: int,
                 period_ns: int | None, loss_model: str, p: float, p_good_to_bad: float, p_bad_to_good: float,
                 loss_good: float, loss_bad: float, initially_bad: bool,
                 refill: Callable[[], tuple[list[float], list[float], list[int]]]) -> int: ...
    def add_route(self, src_bus: int, src_id: int, dst_bus: int, dst_id: int, link: int, reverse: int | None) -> None: ...
    def set_position_codec(self, codec: MessageCodec) -> None: ...
    def set_impairment(self, link: int, blackout: bool, losses: Sequence[float], extra_ns: int,
                       refill: Callable[[], list[float]]) -> None:
        """Injected faults on a radio link: a blackout, burst losses (one draw each, in order, from the one stream
        ``refill`` supplies in blocks), extra latency; all off: none."""
    def every(self, first_ns: int, period_ns: int) -> int:
        """A task due at first_ns and every period_ns after (0: once); returns the token ``advance`` reports."""
    def advance(self, until_ns: int) -> int | None:
        """Run the frame events before until_ns; the token of a due task (clock at its time), or None."""
    def send(self, bus: int, node: int, frame_id: int, data: bytes | bytearray) -> bool: ...
    def send_frames(self, bus: int, node: int, frames: Sequence[tuple[int, bytes]]) -> None:
        """One node's batch at the current time (packed into containers on a bus with ``set_packing``)."""
    def send_encoded(self, bus: int, node: int, outputs: Sequence[tuple[MessageCodec, Sequence[float], int]]) -> None:
        """One ECU cycle's outputs (message, values, alive counter) encoded and queued as ``send_frames`` does."""
    def set_packing(self, bus: int, packing: Packing) -> None:
        """Pack the batches sent on this CAN FD bus and unpack them at its receivers (ValueError on classical CAN)."""
    has_commands: bool  # commands or rejected frames wait for drain_commands

    def attach_commands(self, bus: int, name: str, commands: Sequence[tuple[int, MessageCodec, int]],
                        valid_modes: Sequence[int]) -> tuple[int, int]:
        """The plant's node: TractionCmd frames checked (length, CRC, mode) and decoded on delivery; (node, table)."""
    def drain_commands(self) -> tuple[list[tuple[int, float, int, float, int]], list[tuple[int, int, bytes, int]]]:
        """([(unit, force, mode, t_s, alive counter)] accepted, [(table, frame_id, data, t_end_ns)] rejected) since
        the last call."""
    def drain_inboxes(self) -> list[tuple[int, int, bytes, int]]:
        """(inbox, frame_id, data, t_end) of every frame delivered into an inbox since the last call, in order."""
    def take_stats(self, bus: int) -> tuple[bytes, bytes, int, int]:
        """(frame rows, load rows) as float64 bytes since the last call, and the totals (sent, dropped)."""
    def set_trace(self, bus: int, on: bool) -> None: ...
    def take_trace(self, bus: int) -> list[tuple[int, bytes, bool, int, int, int, int, bool, bool]]:
        """(frame_id, data, extended, t_enqueue, t_start, t_end, sender node, fd, brs) of each completed frame."""
    def finish(self, t_ns: int) -> None:
        """Close every bus's load windows and error model at ``t_ns`` (the end of a run)."""
    def enable_bus_errors(self, bus: int, rng_state: RngState) -> None:
        """CAN error confinement on a bus (engine/src/errors.rs); ``rng_state`` draws error flag and corruption bits."""
    def set_guardian(self, bus: int, allowances: dict[int, int], window_ns: int, share_ns: float) -> None:
        """Watch a bus for a babbling idiot: frames per window by ID (others 2), above which and above
        ``share_ns`` of bus time an ID is flagged."""
    def add_bus_fault(self, bus: int, fault: int, kind: BusFaultKind, rng_state: RngState, probability: float,
                      frame_ids: Sequence[int] | None, count: int | None, bits: int = 1) -> None:
        """Start fault ``fault``'s effect on the frames it selects (``probability`` each, ``frame_ids``, ``count``)."""
    def start_babbler(self, bus: int, fault: int, name: str, frame_id: int, data: bytes, extended: bool) -> int:
        """A babbling node joins the bus and queues its first frame now; returns its node."""
    def end_bus_fault(self, bus: int, fault: int) -> None: ...
    has_bus_events: bool
    def take_bus_events(self) -> list[tuple[int, int, str, dict]]:
        """(bus, t_ns, kind, fields) of every error-model and guardian event since the last call, in order."""
    def bus_errors(self, bus: int) -> dict | None:
        """The error model's counts, ``by_error``, ``nodes``, ``undetected_frames`` (t_ns, sent id, delivered id,
        delivered data, sent data, flipped bits) and ``babbling_detections``; None without an error model."""
    def link_stats(self, link: int) -> dict[str, int]: ...
    def nodes(self, bus: int) -> list[tuple[str, int, int, int]]: ...
    def dropped_by_node(self, bus: int) -> dict[str, int]:
        """The frames each node of a bus dropped (full TX queue, bus-off, queued when it left), by node name; nodes
        that dropped none left out."""
    def take_refusals(self, bus: int) -> list[tuple[int, str]]:
        """Each node's first frame refused on a bus (a full TX queue, bus-off) since the last call, as (t_ns, what
        happened); its later drops are counted only."""
    def detach(self, bus: int, node: int) -> int:
        """Take a node off its bus (its queued frames dropped and counted: how many); its index stays taken."""
    def attached(self, bus: int, node: int) -> bool: ...
    def gateway_ids(self, bus: int) -> list[int]: ...

__all__ = ["VERSION", "MAX_DATA", "PROTOCOL", "frame_bits", "frame_duration_ns", "fd_frame_bits", "e2e_crc", "wire_bits",
           "receive_wire", "MessageCodec", "CommandInbox", "Mailbox", "Network", "Packing", "BusServerCore", "ServingThread",
           "RadioHub", "FrameLink", "LinkGroup", "Series", "SERIES_FLUSH_ROWS", "wait_readable", "frame_error", "filters_accept"]

def wait_readable(fds: Sequence[int], timeout_s: float) -> bool:
    """Sleep until one of ``fds`` is readable or ``timeout_s`` (wall) passed, the GIL released (no fds: a sleep)."""

def frame_error(can_id: int, dlc: int, flags: int, fd_bus: bool = False) -> str | None:
    """Why a frame from a node cannot go on the emulated bus (None if it can), the bus server's own check; a CAN FD
    bus (``fd_bus``) carries both formats."""

def filters_accept(filters: Sequence[tuple[int, int, int]] | None, can_id: int, extended: bool) -> bool:
    """python-can's acceptance: no filters (None or empty) accept every frame, else any (can_id, can_mask, match)
    that matches the id and format does."""

class ServingThread:
    """A native thread serving several buses on one poll: an instant several buses need is one wake-up. Give it to
    each ``BusServerCore`` of a rig; it ends once dropped and its servers have shut down."""

    alive: bool
    native_id: int  # the thread's Linux TID (as threading.Thread.native_id), for setting its scheduling

    def __init__(self) -> None: ...

class BusServerCore:
    """One emulated CAN bus served in wall-clock time by a native thread (engine/src/server.rs).

    Takes over the listening sockets' fds (pass duplicates); hil.runtime.realtime.native_server wraps it."""

    epoch0_ns: int
    bitrate: int
    serving: bool

    def __init__(self, channel: str, listener_fd: int, tcp_fd: int | None, token: bytes | None, bitrate: int,
                 policy_name: str, depth: int, extended: bool, load_window_ns: int, pace: float, spin_ns: int,
                 max_clients: int, hello_timeout_s: float, keep_log: bool, fd: bool = False,
                 data_bitrate: int | None = None, radio: tuple[RadioHub, int] | None = None,
                 bell_fd: int | None = None, thread: ServingThread | None = None) -> None:
        """``fd``: a CAN FD bus (nodes send either format, each FRAME record says which), its data phase at
        ``data_bitrate`` (default: ``bitrate``); ``radio``: the rig's radio hub and this bus's index in it (the
        server joins the bus as node "RadioGW" and hands the hub every routed frame at its end); ``bell_fd``: the
        bus's bell FIFO opened read-write and non-blocking, which quiet readers ring (taken over, closed on error);
        ``thread``: the serving thread it shares with the rig's other buses (None: a thread of its own)."""
    def now_ns(self) -> int: ...
    def align_load_windows(self, origin_ns: int) -> None:
        """From now on the load windows end at model time ``origin_ns`` + k x the window (the run's zero); call it
        before that time."""
    def stats(self) -> dict[str, float | int | None | dict[str, int]]:
        """The server's counters and figures (``BusServerStats``); ``turns_let_go`` and ``dropped_by_node`` are
        counts by node name."""
    def take_log(self) -> tuple[bytes, bytes, int, int]: ...
    def dropped_by_node(self) -> dict[str, int]:
        """The frames each node dropped, by node name; nodes that dropped none left out."""
    def set_trace(self, on: bool) -> None: ...
    def take_trace(self) -> list[tuple[int, bytes, bool, int, int, int, bool, bool]]:
        """(frame_id, data, extended, t_enqueue, t_start, t_end, fd, brs) of each frame completed since the last call."""
    def take_messages(self) -> list[tuple[str, str, int]]:
        """(level, text, t_ns) of each log line since the last call; t_ns: the model time it happened (ns since the
        server's zero)."""
    def enable_bus_errors(self, rng_state: RngState) -> None: ...
    def set_guardian(self, allowances: dict[int, int], window_ns: int, share_ns: float) -> None: ...
    def add_bus_fault(self, fault: int, kind: BusFaultKind, rng_state: RngState, probability: float,
                      frame_ids: Sequence[int] | None, count: int | None, bits: int = 1) -> None: ...
    def start_babbler(self, fault: int, name: str, frame_id: int, data: bytes, extended: bool) -> int: ...
    def end_bus_fault(self, fault: int) -> None: ...
    def take_bus_events(self) -> list[BusEvent]:
        """(t_ns, kind, fields) of every error-model and guardian event since the last call (model time)."""
    def bus_errors(self) -> dict | None: ...
    def current(self) -> tuple[int, int] | None: ...
    def shutdown(self) -> None: ...

class RadioHub:
    """The radio between a real-time rig's bus servers (engine/src/radio_hub.rs): links and routes as ``Network``'s,
    frames forwarded by the servers' threads; the links' draws are queued ahead in blocks by ``top_up``."""

    RESERVE_BLOCKS: int  # blocks of draws top_up keeps queued per link (and for the injected faults)
    starved: int  # frames dropped because a link's draws ran out (top_up not called often enough)

    def __init__(self, pace: float, packing: Packing | None = None) -> None: ...
    def add_link(self, name: str, range_m: float, blackouts: Sequence[tuple[float, float]], latency_ns: int,
                 period_ns: int | None, loss_model: str, p: float, p_good_to_bad: float, p_bad_to_good: float,
                 loss_good: float, loss_bad: float, initially_bad: bool,
                 refill: Callable[[], tuple[list[float], list[float], list[int]]]) -> int: ...
    def add_route(self, src_bus: int, src_id: int, dst_bus: int, dst_id: int, link: int, reverse: int | None) -> None: ...
    def set_position_codec(self, codec: MessageCodec) -> None: ...
    def set_impairment(self, link: int, blackout: bool, losses: Sequence[float], extra_ns: int,
                       refill: Callable[[], list[float]]) -> None: ...
    def top_up(self) -> int:
        """Queue blocks of draws (each link's ``refill``, the faults' refill) until each has ``RESERVE_BLOCKS``
        waiting; returns the most blocks any one of them had used since the last top-up."""
    def link_stats(self, link: int) -> dict[str, int]: ...

class FrameLink:
    """A node's bus socket read and written by the engine: frames go straight into routed mailboxes."""

    fd: int
    received: int
    synced: float
    in_turn: bool  # a turn is open (``act_at`` on a link of turns, not ended yet)

    def __init__(self, fd: int, t0: float, pace: float, keep: bool = False, lazy: bool = False,
                 bell: int | None = None) -> None:
        """``lazy``: the connection said OPTION_LAZY; frames come in at ``sync_to``, sent frames carry their time.
        ``bell``: it also said OPTION_QUIET; the write end of the server's bell FIFO (kept open by the caller), rung
        when the server must see a record now (a read request, a frame its BELL records name)."""
    def read_every(self, first: float, period: float, turns: bool = False) -> None:
        """A lazy link's read times: ``first`` (epoch s), then every ``period`` s (0: once); ``turns``: from now on
        each of its read times is a turn (protocol READ_TURNS)."""
    def sends_at_least(self, bytes: int) -> None:
        """Every frame this link will send carries at least ``bytes`` data bytes (protocol LEAST_DATA), said before
        its first frame: the server need not wait for shorter frames before it SYNCs, and refuses one."""
    def name_sender(self, sender: int, name: str) -> None:
        """Name sender ``sender``'s bus node ``name`` (protocol SENDER_NAME, 1 to 20 bytes), said before the link's
        first frame: that sender's TX queue, drops and error state go by it."""
    def act_at(self, t: float) -> None:
        """The node acts at read time ``t`` (epoch s), perhaps synced to it before it comes: frames sent from now
        on carry ``t`` while it is still ahead (the server queues them then), else the instant they are sent; on a
        link of turns, ``t`` until ``end_turn``, however late (the server holds its bus for the turn)."""
    def end_turn(self) -> None:
        """End the open turn (a DONE record); nothing without one."""
    def sync_to(self, t: float, timeout_s: float) -> bool:
        """Hand over every frame that ended by read time ``t`` (epoch s), waiting up to ``timeout_s`` (wall) for the
        server's SYNC of it; whether it came."""
    def route(self, frame_id: int, mailbox: Mailbox) -> None: ...
    def route_commands(self, inbox: CommandInbox) -> None:
        """Deliver the frames of ``inbox.ids`` into ``inbox`` (an ID routed to mailboxes goes only to them)."""
    def set_packing(self, packing: Packing) -> None:
        """Pack each ``send`` batch into containers; unpack the containers received into their parts."""
    def pump(self) -> int: ...
    def take(self, pump: bool = True) -> list[tuple[int, bytes, float]]:
        """The kept frames received since the last call: [(frame_id, data, t_sim)]; ``pump``: read the socket first
        (not needed by a lazy link just synced)."""
    def send(self, frames: Sequence[tuple[int, bytes]], extended: bool = False, fd: bool = False,
             brs: bool = True, sender: int = 0, end_turn: bool = False) -> None:
        """FRAME records of [(frame_id, data)]: 29-bit IDs with ``extended``, CAN FD frames with ``fd`` (and BRS);
        ``sender``: which of the connection's senders (0..MAX_SENDERS-1) sends them: each has its own TX queue on
        the bus, as a separate CAN controller (a process hosting several ECUs sends each as its own).
        ``end_turn``: they end the open turn (``end_turn`` after them, in the same write)."""
    def send_encoded(self, outputs: Sequence[tuple[MessageCodec, Sequence[float], int]], extended: bool = False,
                     fd: bool = False, brs: bool = True, sender: int = 0, end_turn: bool = False) -> None:
        """One ECU cycle's outputs (message, values, alive counter), encoded and sent as ``send`` does, in one call."""


class Series:
    """A real-time node's (t, value) rows: appended to ``path`` as native float64 pairs every SERIES_FLUSH_ROWS rows
    and at ``flush`` (created 0600; None: kept in memory), the values counted in 1 µs bins."""

    path: Path | None
    n: int  # finite values added
    max: float  # the largest finite value (-inf before any)

    def __init__(self, path: str | PathLike[str] | None = None) -> None: ...
    def add(self, t: float, value: float) -> None:
        """One row; a non-finite value is recorded but not counted. OSError when the file cannot take the rows."""
    def extend(self, rows: Sequence[tuple[float, float]]) -> None:
        """Rows [(t, value)] in order, as ``add`` each."""
    def flush(self) -> None: ...
    def close(self) -> None:
        """Flush and close the file; rows added later stay in memory."""
    def percentile(self, q: float) -> float | None:
        """As ``np.percentile(values, q)`` over the values rounded to the microsecond; None without values."""
    def pending_bytes(self) -> bytes:
        """The rows not written yet (all without a path), t and value interleaved, native float64."""


SERIES_FLUSH_ROWS: int


class LinkGroup:
    """A lazy reader's links, one per bus: its wait for a read time on all of them in a few calls."""

    def __init__(self, links: Sequence[FrameLink]) -> None: ...
    def read_every(self, bus: int, first: float, period: float, turns: bool = False) -> None:
        """Read times ``first + k * period`` (simulated s) on ``bus``, told to its server (0: a single read);
        ``turns``: they are the node's turns (``FrameLink.read_every``)."""
    def end_turn(self, buses: Sequence[int] | None = None) -> None:
        """End the open turns of the links of ``buses`` (default: every bus; ``FrameLink.end_turn``). A turn still
        open when the node next waits for a later instant ends then, as do the turns of read times it skipped."""
    def end_turns_for_good(self) -> None:
        """The node's turns are over (its run ended): a DONE stamped +inf on every link, after which its servers hold
        their buses for none of its read times, though it may still wait for them."""
    def begin_wait(self, sim_t: float) -> list[int]:
        """Start waiting for read time ``sim_t`` (simulated s) on the buses that have it among their read times, or,
        at an instant none foresaw, on every bus not yet synced to it, asked once. The buses still without a SYNC."""
    def wait_more(self, sim_t: float, timeout_s: float) -> list[int]:
        """Sleep up to ``timeout_s`` (wall) for a bus still waited for, take what came; the buses still without a SYNC."""
    def finish(self, sim_t: float) -> list[tuple[int, list[tuple[int, bytes, float]]]]:
        """Every link acts at ``sim_t``; the frames each kept, read off its socket first unless it was just synced:
        [(bus, [(frame_id, data, t_sim)])], only buses with some."""
