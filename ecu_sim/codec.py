"""Fast per-message codecs compiled once from the train DBC (the DBC is the single source of truth).

cantools parses and models the DBC (``TrainDb.database``); each message is then compiled into a
``MessageCodec`` of the frame engine (``trainhil_engine``, Rust): bit positions, scaling and raw limits, so the
per-frame path never calls cantools. Encoding saturates out-of-range values (counted per signal) and fills the
E2E header; NaN is an error naming the signal.
A DBC that does not fit the firmware (missing or unknown messages, two messages on one ID, a signal too
short or too coarse for ``SIGNAL_NEEDS``, a bad E2E header or data ID) is a DbcMismatchError at load.

A CAN FD DBC (``dbc/train_fd.dbc``) may also define containers: FD messages whose ``ContainedMessages`` attribute
lists the messages they carry in byte order, and whose signals are those messages' signals at their offsets.
``TrainDb.packing`` turns them into the engine's frame packing (``trainhil_engine.Packing``).
"""
from __future__ import annotations

import io
import math
import re
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cantools

from trainhil_engine import MessageCodec, Packing

# The E2E header every message must carry: signal -> (start bit, length), unsigned, identity scaling.
E2E_HEADER = {"CRC": (0, 8), "AliveCounter": (8, 4)}
DATA_ID_ATTRIBUTE = "E2EDataID"
CONTAINED_ATTRIBUTE = "ContainedMessages"
MAX_CLASSIC_DLC = 8
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)

# What the firmware and the rig rely on: payload signal names in start-bit order per message family.
# Per-unit families are named <family>_U01 .. _U<max_units>; the rest are single messages.
UNIT_FAMILIES: dict[str, tuple[str, ...]] = {
    "TractionCmd": ("Mode", "Force"),
    "Sensor": ("Position", "Speed"),
    "AgentState": ("Position", "Speed"),
    "AgentAux": ("Accel", "Force"),
}
SINGLE_MESSAGES: dict[str, tuple[str, ...]] = {
    "Reference": ("Position", "Speed"),
    "ReferenceAux": ("Accel",),
    "RadioAheadState": ("Position", "Speed"),
    "RadioAheadAux": ("Accel", "Force"),
    "RadioBehindState": ("Position", "Speed"),
    "RadioBehindAux": ("Accel", "Force"),
}


# What each payload signal must carry for the firmware and the rig to work (a DBC that cannot is refused at load):
# name -> (physical range it must cover, largest LSB). Position: a 1000 km line at 1 mm (1 % of the 0.1 m
# coupler band); Speed: +-110 m/s (396 km/h, above every paper's speeds) at 0.5 mm/s; Accel: +-20 m/s^2 at
# 0.01 m/s^2; Force: +-500 kN (above the 300 kN actuator envelope) at 10 N; Mode: the BrakeMode values 0..2.
SIGNAL_NEEDS: dict[str, tuple[float, float, float]] = {
    "Position": (0.0, 1_000_000.0, 0.001),
    "Speed": (-110.0, 110.0, 0.0005),
    "Accel": (-20.0, 20.0, 0.01),
    "Force": (-500_000.0, 500_000.0, 10.0),
    "Mode": (0.0, 2.0, 1.0),
}


def default_dbc_path(name: str = "train.dbc") -> Path:
    """A packaged DBC (default dbc/train.dbc) of the source tree, else the copy a wheel installs under sys.prefix."""
    repo = Path(__file__).resolve().parents[1] / "dbc" / name
    installed = Path(sys.prefix) / "share" / "trainhil" / "dbc" / name
    for path in (repo, installed):
        if path.is_file():
            return path
    raise FileNotFoundError(f"DBC {name} not found: looked for {repo} and {installed}")


def fd_length(n: int) -> int | None:
    """The smallest CAN FD data length that holds n bytes (None above 64)."""
    return next((length for length in FD_LENGTHS if length >= n), None)


@dataclass(frozen=True)
class ContainerPart:
    """One message inside a container: its name, frame ID, first byte and length."""

    name: str
    frame_id: int
    offset: int
    length: int


@dataclass(frozen=True)
class Container:
    """A CAN FD container frame of the DBC and the messages it carries, in byte order."""

    name: str
    frame_id: int
    length: int
    parts: tuple[ContainerPart, ...]


def unit_message_name(family: str, unit0: int) -> str:
    """DBC name of a per-unit message: 0-based unit index -> slot suffix _U01, _U02, ..."""
    return f"{family}_U{unit0 + 1:02d}"


class DbcMismatchError(ValueError):
    """The DBC does not have the layout the firmware and rig are written against."""


class _FrameIdMap(dict):
    """frame id -> codec; a missing id raises KeyError naming it in hex."""

    def __missing__(self, frame_id: int) -> MessageCodec:
        raise KeyError(f"no message with frame id 0x{frame_id:03X} in the train DBC")


def _raw_limits(signal, where: str) -> tuple[int, int]:
    """Raw range of a signal: its bit range, narrowed by the DBC minimum/maximum when given."""
    if signal.is_signed:
        lo, hi = -(1 << (signal.length - 1)), (1 << (signal.length - 1)) - 1
    else:
        lo, hi = 0, (1 << signal.length) - 1
    if signal.minimum is not None:
        lo = max(lo, math.ceil((signal.minimum - signal.offset) / signal.scale - 1e-6))
    if signal.maximum is not None:
        hi = min(hi, math.floor((signal.maximum - signal.offset) / signal.scale + 1e-6))
    if lo > hi:
        raise DbcMismatchError(f"{where}: signal {signal.name} has an empty range [{signal.minimum}, {signal.maximum}]")
    return lo, hi


def _check_header(message, where: str) -> None:
    """Every message must carry CRC and AliveCounter where the E2E code reads them."""
    by_name = {s.name: s for s in message.signals}
    for name, (start, length) in E2E_HEADER.items():
        sig = by_name.get(name)
        if sig is None:
            raise DbcMismatchError(f"{where}: E2E signal {name} is missing")
        ok = (sig.start == start and sig.length == length and sig.byte_order == "little_endian"
              and not sig.is_signed and sig.scale == 1 and sig.offset == 0)
        if not ok:
            raise DbcMismatchError(
                f"{where}: {name} must be unsigned Intel at bit {start}, {length} bits, scale 1 "
                f"(is start {sig.start}, {sig.length} bits, {sig.byte_order}, signed={sig.is_signed}, "
                f"scale {sig.scale}, offset {sig.offset})"
            )


def _check_needs(signal, raw_lo: int, raw_hi: int, where: str) -> None:
    """The signal's range and resolution against SIGNAL_NEEDS (a too-short signal would saturate all the time)."""
    need = SIGNAL_NEEDS.get(signal.name)
    if need is None:
        return
    lo_needed, hi_needed, lsb_needed = need
    ends = sorted((raw_lo * signal.scale + signal.offset, raw_hi * signal.scale + signal.offset))
    eps = 1e-9 * max(1.0, abs(lo_needed), abs(hi_needed))
    if ends[0] > lo_needed + eps or ends[1] < hi_needed - eps or abs(signal.scale) > lsb_needed * (1 + 1e-9):
        raise DbcMismatchError(
            f"{where}: signal {signal.name} ({signal.length} bits, scale {signal.scale}) carries [{ends[0]:g}, {ends[1]:g}] "
            f"in steps of {abs(signal.scale):g}; the firmware needs at least [{lo_needed:g}, {hi_needed:g}] "
            f"in steps of {lsb_needed:g} or finer")


def _compile(message, expected: tuple[str, ...], where: str) -> MessageCodec:
    """Check one cantools message against what the code expects and build its codec."""
    if message.is_extended_frame or message.is_fd or message.length > MAX_CLASSIC_DLC:
        raise DbcMismatchError(f"{where}: must be a classical CAN frame with an 11-bit ID and DLC <= 8")
    _check_header(message, where)
    attr = message.dbc.attributes.get(DATA_ID_ATTRIBUTE) if message.dbc else None
    if attr is None:
        raise DbcMismatchError(f"{where}: no {DATA_ID_ATTRIBUTE} attribute")
    if not isinstance(attr.value, int) or not 0 <= attr.value <= 0xFF:
        raise DbcMismatchError(f"{where}: {DATA_ID_ATTRIBUTE} {attr.value!r} is not in 0..255 (one byte of the E2E CRC)")
    if message.cycle_time is None:
        raise DbcMismatchError(f"{where}: no GenMsgCycleTime attribute")
    payload = sorted((s for s in message.signals if s.name not in E2E_HEADER), key=lambda s: s.start)
    names = tuple(s.name for s in payload)
    if names != expected:
        raise DbcMismatchError(f"{where}: payload signals {names}, the code expects {expected}")
    specs = []
    for s in payload:
        if s.byte_order != "little_endian" or s.is_float or s.is_multiplexer or s.multiplexer_ids:
            raise DbcMismatchError(f"{where}: signal {s.name} must be a plain Intel integer signal")
        lo, hi = _raw_limits(s, where)
        _check_needs(s, lo, hi, where)
        specs.append((s.name, s.start, s.length, bool(s.is_signed), float(s.scale), float(s.offset), lo, hi))
    return MessageCodec(message.name, message.frame_id, message.length, message.cycle_time / 1000.0,
                        int(attr.value), specs, [s.unit or "" for s in payload])


_PARSED: dict[tuple[str, bytes], cantools.database.can.Database] = {}  # (suffix, contents) -> cantools' model
_PARSED_KEPT = 8
_PARSED_LOCK = threading.Lock()  # a sweep's threads load DBCs at once
DATABASE_FORMATS = ("dbc", "arxml", "kcd", "sym", "cdd")  # the file suffixes cantools loads a database by
_CP1252_FORMATS = ("dbc", "sym")  # cantools' load_file reads these as cp1252, every other format as UTF-8


def _parsed_dbc(path: Path) -> cantools.database.can.Database:
    """cantools' model of the DBC at ``path``, parsed once per process for each content (and file suffix, which
    cantools reads the format from): parsing takes about 0.1 s, and a run's checks, its rig and a test suite load the
    same DBC again and again, often copied. The model is shared, so it is read only (each ``TrainDb`` compiles its
    own codecs, with their own saturation counts)."""
    key = (path.suffix.lower(), path.read_bytes())
    with _PARSED_LOCK:
        database = _PARSED.get(key)
        if database is None:
            database = _parse(*key)
            if len(_PARSED) >= _PARSED_KEPT:
                del _PARSED[next(iter(_PARSED))]  # the oldest
            _PARSED[key] = database
    return database


def _parse(suffix: str, content: bytes) -> cantools.database.can.Database:
    """cantools' model of ``content``, read as its ``load_file`` reads a file of that suffix. Parsing the bytes
    already read means the model is always the content it is remembered by (a file saved anew meanwhile is parsed
    at its next load), and never goes through cantools' pickled disk cache, which ``CANTOOLS_CACHE_DIR`` would
    turn on and anyone who can write to that folder could fill."""
    database_format = suffix[1:]
    encoding = "cp1252" if database_format in _CP1252_FORMATS else "utf-8"
    text = io.TextIOWrapper(io.BytesIO(content), encoding=encoding, errors="replace").read()  # as open() reads it
    return cantools.database.load_string(text, database_format=database_format, strict=True)


class TrainDb:
    """The train DBC: cantools' object model plus one compiled codec per message."""

    def __init__(self, path: Path, database: cantools.database.can.Database, codecs: Sequence[MessageCodec],
                 max_units: int, containers: Sequence[Container] = ()) -> None:
        self.path = path
        self.database = database  # cantools object model (not used per frame; shared by loads of one content: read only)
        self.max_units = max_units
        self.containers: tuple[Container, ...] = tuple(containers)
        self.container_by_id: dict[int, Container] = {c.frame_id: c for c in containers}
        self.by_name: dict[str, MessageCodec] = {c.name: c for c in codecs}
        self.by_id: dict[int, MessageCodec] = _FrameIdMap((c.frame_id, c) for c in codecs)
        self._units = {f: tuple(self.by_name[unit_message_name(f, u)] for u in range(max_units)) for f in UNIT_FAMILIES}

    @classmethod
    def load(cls, path: Path | str | None = None) -> "TrainDb":
        """Load and check the DBC (default: :func:`default_dbc_path`), compile every message."""
        path = default_dbc_path() if path is None else Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"train DBC not found: {path}")
        if path.suffix.lower()[1:] not in DATABASE_FORMATS:  # cantools reads the format from the suffix
            raise DbcMismatchError(f"DBC {path}: cantools reads a database by its file name's suffix, one of "
                                   f"{', '.join('.' + f for f in DATABASE_FORMATS)}; this one has "
                                   f"{repr(path.suffix) if path.suffix else 'none'}")
        try:
            database = _parsed_dbc(path)
        except cantools.errors.Error as exc:
            raise DbcMismatchError(f"DBC {path}: cantools cannot load it: {exc}") from exc
        every = {m.name: m for m in database.messages}
        by_name = {n: m for n, m in every.items() if not _contained(m)}
        max_units = _count_unit_slots(by_name, path)
        expected = dict(SINGLE_MESSAGES)
        for family, signals in UNIT_FAMILIES.items():
            expected.update({unit_message_name(family, u): signals for u in range(max_units)})
        missing = [name for name in expected if name not in by_name]
        if missing:
            raise DbcMismatchError(f"DBC {path}: missing message(s) {', '.join(missing)}")
        extra = [name for name in by_name if name not in expected]
        if extra:
            raise DbcMismatchError(f"DBC {path}: message(s) the code does not know: {', '.join(extra)}")
        _check_unique_ids(every, path)
        codecs = [_compile(by_name[n], sig, f"DBC {path}: message {n}") for n, sig in expected.items()]
        containers = [_container(m, by_name, f"DBC {path}: container {n}") for n, m in every.items() if _contained(m)]
        return cls(path, database, codecs, max_units, containers)

    def cycle_times(self) -> dict[int, float]:
        """Frame ID -> DBC cycle time (s) of every message and container (a container's is its first part's)."""
        out = {fid: codec.cycle_time_s for fid, codec in self.by_id.items()}
        out.update({c.frame_id: out[c.parts[0].frame_id] for c in self.containers})
        return out

    def containers_for(self, units: int | None = None) -> list[Container]:
        """This DBC's containers for a train of ``units`` unit slots (default: all): parts of slots beyond it are
        left out (no sender would ever complete a container whose parts no one sends), and each container keeps
        its DBC length, the absent parts' bytes zero, so every frame on the wire decodes strictly with the DBC (a
        static container PDU has a fixed length; CANoe and cantools refuse a shorter frame)."""
        out, slots = [], self.max_units if units is None else units
        for c in self.containers:
            parts = tuple(p for p in c.parts if (_unit_slot(p.name) or 0) < slots)
            if parts:
                out.append(Container(c.name, c.frame_id, c.length, parts))
        return out

    def carriers(self, frame_id: int, units: int | None = None) -> list[Container]:
        """The containers (:meth:`containers_for` ``units``) that carry message ``frame_id``."""
        return [c for c in self.containers_for(units) if any(p.frame_id == frame_id for p in c.parts)]

    def packing(self, units: int | None = None) -> Packing | None:
        """The engine's frame packing of :meth:`containers_for` ``units``; None when the DBC has no containers."""
        spec = [(c.frame_id, c.length, [(p.frame_id, p.offset, p.length) for p in c.parts])
                for c in self.containers_for(units)]
        return Packing(spec) if spec else None

    def traction_cmd(self, unit0: int) -> MessageCodec:
        """TractionCmd codec of 0-based unit index ``unit0`` (slot _U{unit0 + 1:02d})."""
        return self._unit("TractionCmd", unit0)

    def sensor(self, unit0: int) -> MessageCodec:
        """Sensor codec of 0-based unit index ``unit0`` (slot _U{unit0 + 1:02d})."""
        return self._unit("Sensor", unit0)

    def agent_state(self, unit0: int) -> MessageCodec:
        """AgentState codec of 0-based unit index ``unit0`` (slot _U{unit0 + 1:02d})."""
        return self._unit("AgentState", unit0)

    def agent_aux(self, unit0: int) -> MessageCodec:
        """AgentAux codec of 0-based unit index ``unit0`` (slot _U{unit0 + 1:02d})."""
        return self._unit("AgentAux", unit0)

    def _unit(self, family: str, unit0: int) -> MessageCodec:
        if not 0 <= unit0 < self.max_units:
            raise IndexError(f"{family}: unit index {unit0!r} is not in 0..{self.max_units - 1}")
        return self._units[family][unit0]

    @property
    def reference(self) -> MessageCodec:
        return self.by_name["Reference"]

    @property
    def reference_aux(self) -> MessageCodec:
        return self.by_name["ReferenceAux"]

    @property
    def radio_ahead_state(self) -> MessageCodec:
        return self.by_name["RadioAheadState"]

    @property
    def radio_ahead_aux(self) -> MessageCodec:
        return self.by_name["RadioAheadAux"]

    @property
    def radio_behind_state(self) -> MessageCodec:
        return self.by_name["RadioBehindState"]

    @property
    def radio_behind_aux(self) -> MessageCodec:
        return self.by_name["RadioBehindAux"]

    def total_saturations(self) -> dict[str, int]:
        """Saturated encodes so far, keyed "Message.Signal" (non-zero entries only)."""
        return {f"{c.name}.{s}": n for c in self.by_name.values() for s, n in c.saturations.items() if n}

    def reset_saturations(self) -> None:
        """Zero the saturation counts of every codec."""
        for codec in self.by_name.values():
            codec.reset_saturations()


def _contained(message) -> str:
    """The ContainedMessages attribute of a message ("" for an ordinary message)."""
    attr = message.dbc.attributes.get(CONTAINED_ATTRIBUTE) if message.dbc else None
    return str(attr.value).strip() if attr is not None else ""


def _unit_slot(name: str) -> int | None:
    """0-based unit slot of a per-unit message name (TractionCmd_U03 -> 2), None for the others."""
    m = re.fullmatch(r"(\w+)_U(\d\d)", name)
    return int(m.group(2)) - 1 if m and m.group(1) in UNIT_FAMILIES else None


def _signal_key(signal, shift: int = 0) -> tuple:
    return (signal.start + shift, signal.length, signal.byte_order, bool(signal.is_signed), float(signal.scale),
            float(signal.offset))


def _container(message, messages: dict, where: str) -> Container:
    """Check a container (an FD frame whose signals are its parts' signals at their byte offsets) and describe it."""
    if not message.is_fd or message.is_extended_frame:
        raise DbcMismatchError(f"{where}: a container must be a CAN FD frame with an 11-bit ID (VFrameFormat StandardCAN_FD)")
    parts, offset = [], 0
    for name in _contained(message).split():
        part = messages.get(name)
        if part is None:
            raise DbcMismatchError(f"{where}: {CONTAINED_ATTRIBUTE} names {name}, which is not a message of the DBC")
        parts.append(ContainerPart(name, part.frame_id, offset, part.length))
        offset += part.length
    if message.length != fd_length(offset):
        raise DbcMismatchError(f"{where}: its parts take {offset} bytes, so its length must be {fd_length(offset)}, "
                               f"not {message.length}")
    expected = sorted(_signal_key(s, 8 * p.offset) for p in parts for s in messages[p.name].signals)
    if sorted(_signal_key(s) for s in message.signals) != expected:
        raise DbcMismatchError(f"{where}: its signals must be its parts' signals at their byte offsets "
                               f"({', '.join(f'{p.name} at byte {p.offset}' for p in parts)})")
    return Container(message.name, message.frame_id, message.length, tuple(parts))


def _check_unique_ids(by_name: dict, path: Path) -> None:
    """Two messages on one frame ID cannot be told apart by any receiver (cantools only warns)."""
    seen: dict[int, str] = {}
    for name, message in by_name.items():
        other = seen.setdefault(message.frame_id, name)
        if other != name:
            raise DbcMismatchError(f"DBC {path}: messages {other} and {name} share the frame ID 0x{message.frame_id:03X}")


def _count_unit_slots(by_name: dict, path: Path) -> int:
    """Number of unit slots: TractionCmd_U01.. consecutive from 1 (other families are checked against it)."""
    n = 0
    while unit_message_name("TractionCmd", n) in by_name:
        n += 1
    if n == 0:
        raise DbcMismatchError(f"DBC {path}: missing message(s) {unit_message_name('TractionCmd', 0)}")
    return n
