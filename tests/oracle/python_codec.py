"""The pure-Python message codec the engine's codec replaced, kept as a test oracle (tests/test_engine_differential.py).

It is the implementation the rig ran before the frame engine, unchanged, so the compiled codec is checked
against it byte for byte.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from ecu_sim.e2e import COUNTER_MASK, e2e_crc


@dataclass(frozen=True, slots=True)
class _SignalSpec:
    """Everything the hot path needs about one payload signal, taken from the DBC once."""

    name: str
    shift: int
    mask: int
    sign_bit: int  # 0 for unsigned signals
    scale: float
    offset: float
    raw_min: int
    raw_max: int


class MessageCodec:
    """Encoder/decoder of one message: physical values in ``signals`` order <-> frame bytes."""

    __slots__ = (
        "name", "frame_id", "dlc", "cycle_time_s", "data_id", "signals", "units", "limits",
        "saturations", "_specs", "_enc", "_dec",
    )

    def __init__(self, name: str, frame_id: int, dlc: int, cycle_time_s: float, data_id: int,
                 specs: Sequence[_SignalSpec], units: Sequence[str]) -> None:
        self.name = name
        self.frame_id = frame_id
        self.dlc = dlc
        self.cycle_time_s = cycle_time_s
        self.data_id = data_id
        self._specs = tuple(specs)
        self.signals: tuple[str, ...] = tuple(s.name for s in self._specs)
        self.units: tuple[str, ...] = tuple(units)
        # Physical range each signal can carry (what encode saturates to).
        self.limits: tuple[tuple[float, float], ...] = tuple(
            (s.raw_min * s.scale + s.offset, s.raw_max * s.scale + s.offset) for s in self._specs
        )
        self.saturations: dict[str, int] = {s.name: 0 for s in self._specs}
        self._enc = tuple((s.offset, s.scale, s.raw_min, s.raw_max, s.mask, s.shift) for s in self._specs)
        self._dec = tuple((s.shift, s.mask, s.sign_bit, s.scale, s.offset) for s in self._specs)

    def __repr__(self) -> str:
        return f"MessageCodec({self.name}, id=0x{self.frame_id:03X}, dlc={self.dlc}, signals={self.signals})"

    def index(self, signal: str) -> int:
        """Position of a payload signal in ``signals`` (the order of encode/decode values)."""
        try:
            return self.signals.index(signal)
        except ValueError:
            raise KeyError(f"message {self.name} has no payload signal {signal!r} (has {self.signals})") from None

    def encode(self, values: Sequence[float], counter: int) -> bytes:
        """Physical values (in ``signals`` order) -> frame bytes with alive counter and E2E CRC."""
        if len(values) != len(self._enc):
            raise ValueError(f"{self.name}: expected {len(self._enc)} values {self.signals}, got {len(values)}")
        if not 0 <= counter <= COUNTER_MASK:
            raise ValueError(f"{self.name}: alive counter {counter!r} is not in 0..{COUNTER_MASK}")
        word = int(counter) << 8
        i = 0
        for value, (offset, scale, lo, hi, mask, shift) in zip(values, self._enc):
            x = (value - offset) / scale
            raw = round(x) if lo <= x <= hi else self._saturate(i, x, lo, hi)
            word |= (raw & mask) << shift
            i += 1
        dlc = self.dlc
        return (word | e2e_crc(self.data_id, word.to_bytes(dlc, "little"))).to_bytes(dlc, "little")

    def _saturate(self, i: int, x: float, lo: int, hi: int) -> int:
        """Raw value of an out-of-range (or NaN) scaled value: the nearest extreme, counted."""
        name = self.signals[i]
        if math.isnan(x):
            raise ValueError(f"{self.name}.{name}: cannot encode NaN")
        # Within half an LSB of the extreme it is plain quantisation, not saturation.
        if x > hi + 0.5 or x < lo - 0.5:
            self.saturations[name] += 1
        return hi if x > hi else lo

    def decode(self, data: bytes | bytearray | memoryview) -> tuple[float, ...]:
        """Frame bytes -> physical values in ``signals`` order (E2E header not checked here)."""
        if len(data) != self.dlc:
            raise ValueError(f"{self.name}: frame has {len(data)} bytes, DLC is {self.dlc}")
        word = int.from_bytes(data, "little")
        out = []
        for shift, mask, sign_bit, scale, offset in self._dec:
            raw = (word >> shift) & mask
            if raw & sign_bit:
                raw -= mask + 1
            out.append(raw * scale + offset)
        return tuple(out)

    def counter_of(self, data: bytes | bytearray | memoryview) -> int:
        """Alive counter carried in the frame."""
        self._check_length(data)
        return data[1] & COUNTER_MASK

    def crc_ok(self, data: bytes | bytearray | memoryview) -> bool:
        """True when the frame's CRC byte matches this message's data ID and payload."""
        self._check_length(data)
        return data[0] == e2e_crc(self.data_id, data)

    def _check_length(self, data: bytes | bytearray | memoryview) -> None:
        if len(data) != self.dlc:
            raise ValueError(f"{self.name}: frame has {len(data)} bytes, DLC is {self.dlc}")

    def reset_saturations(self) -> None:
        """Zero the saturation counts (e.g. between runs sharing one database)."""
        for name in self.saturations:
            self.saturations[name] = 0


def oracle_codec(codec) -> MessageCodec:
    """The Python codec of the same message as an engine codec, built from the DBC through cantools."""
    from ecu_sim.codec import TrainDb, _raw_limits

    db = TrainDb.load()
    message = db.database.get_message_by_name(codec.name)
    specs = []
    for s in sorted((s for s in message.signals if s.name in codec.signals), key=lambda s: s.start):
        lo, hi = _raw_limits(s, codec.name)
        specs.append(_SignalSpec(s.name, s.start, (1 << s.length) - 1, 1 << (s.length - 1) if s.is_signed else 0,
                                 float(s.scale), float(s.offset), lo, hi))
    return MessageCodec(codec.name, codec.frame_id, codec.dlc, codec.cycle_time_s, codec.data_id, specs, codec.units)
