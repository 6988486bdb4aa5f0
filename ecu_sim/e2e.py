"""End-to-end protection of train-bus frames: CRC-8 SAE J1850 and a 4-bit alive counter.

AUTOSAR profile-1 style header shared by every frame of dbc/train.dbc: byte 0 is the CRC over
[data ID] + bytes 1..end, the low nibble of byte 1 is the alive counter. The data ID is not sent,
so a frame checked against the wrong message type (wrong ID mapping) fails the CRC.

Receivers classify every frame (``E2EStatus``: OK, INITIAL, OK_SOME_LOST with the lost frames counted as LOST,
REPEATED, WRONG_SEQUENCE, CRC_ERROR); TIMEOUT is counted by the receiver's freshness check
(``ecu_sim.runtime.InputSlot.fresh``) each time a stream that had been fresh goes stale.
"""
from __future__ import annotations

from enum import IntEnum

CRC_POLY = 0x1D  # SAE J1850: x^8 + x^4 + x^3 + x^2 + 1
CRC_INIT = 0xFF
CRC_XOR_OUT = 0xFF
COUNTER_MODULO = 16  # 4-bit alive counter
COUNTER_MASK = COUNTER_MODULO - 1
HEADER_BYTES = 2  # CRC byte + the byte holding the counter


def _crc8_table(poly: int) -> tuple[int, ...]:
    """Byte-wise lookup table of an MSB-first (non-reflected) CRC-8."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _crc8_table(CRC_POLY)


def e2e_crc(data_id: int, payload: bytes | bytearray | memoryview) -> int:
    """CRC-8 SAE J1850 over [data_id] + payload[1:] (byte 0, the CRC slot itself, is skipped)."""
    if not 0 <= data_id <= 0xFF:
        raise ValueError(f"E2E data ID {data_id!r} is not in 0..255")
    table = _TABLE
    crc = table[CRC_INIT ^ data_id]
    for byte in payload[1:]:
        crc = table[crc ^ byte]
    return crc ^ CRC_XOR_OUT


def next_counter(counter: int) -> int:
    """The alive counter value of the next transmission."""
    return (counter + 1) % COUNTER_MODULO


def counter_of(data: bytes | bytearray | memoryview) -> int:
    """Alive counter carried in a frame (low nibble of byte 1)."""
    return data[1] & COUNTER_MASK


def crc_ok(data_id: int, data: bytes | bytearray | memoryview) -> bool:
    """True when byte 0 of the frame is the E2E CRC of the rest under ``data_id``."""
    return len(data) >= HEADER_BYTES and data[0] == e2e_crc(data_id, data)


class E2EStatus(IntEnum):
    """Receiver verdict on one frame (AUTOSAR E2E profile-1 check status)."""

    OK = 0  # counter advanced by exactly 1
    INITIAL = 1  # first valid frame of the stream (or after reset): nothing to compare with
    OK_SOME_LOST = 2  # counter advanced by 2..max_delta+1: usable, some frames lost
    REPEATED = 3  # same counter as the last valid frame: stale, do not use
    WRONG_SEQUENCE = 4  # counter jumped further than allowed: do not use; the stream resyncs on it
    CRC_ERROR = 5  # CRC mismatch (corruption or wrong data ID): do not use, state untouched

    @property
    def usable(self) -> bool:
        """Whether the frame's data may be used by the application."""
        return self in (E2EStatus.OK, E2EStatus.INITIAL, E2EStatus.OK_SOME_LOST)


class E2EChecker:
    """Receiver-side check of one message stream: CRC, then alive-counter sequence.

    Profile-1 semantics with counter modulo 16: delta 1 -> OK, 0 -> REPEATED,
    2..max_delta+1 -> OK_SOME_LOST (max_delta frames may be lost in a row), larger -> WRONG_SEQUENCE.
    Deviation from AUTOSAR (which widens the window on every call): a WRONG_SEQUENCE frame becomes
    the new reference, so after a long outage exactly one frame is rejected before the stream is OK.
    """

    __slots__ = ("data_id", "max_delta", "name", "last_counter", "counts", "lost", "timeouts")

    def __init__(self, data_id: int, max_delta: int = 1, name: str = "") -> None:
        if not 0 <= data_id <= 0xFF:
            raise ValueError(f"E2EChecker {name!r}: data ID {data_id!r} is not in 0..255")
        if not 0 <= max_delta <= COUNTER_MODULO - 2:
            raise ValueError(f"E2EChecker {name!r}: max_delta {max_delta!r} is not in 0..{COUNTER_MODULO - 2}")
        self.data_id = data_id
        self.max_delta = max_delta
        self.name = name
        self.last_counter: int | None = None
        self.counts = [0] * len(E2EStatus)  # indexed by E2EStatus
        self.lost = 0  # frames known lost from OK_SOME_LOST gaps
        self.timeouts = 0  # times the stream went stale (counted by the receiver's freshness check)

    def reset(self) -> None:
        """Forget the sequence (next valid frame is INITIAL); keeps the statistics."""
        self.last_counter = None

    def check(self, data: bytes | bytearray | memoryview) -> E2EStatus:
        """Classify one received frame and update the sequence state and the counts."""
        if len(data) < HEADER_BYTES:
            raise ValueError(f"E2E stream {self.name!r}: frame of {len(data)} bytes has no E2E header")
        status = self._classify(data)
        self.counts[status] += 1
        return status

    def _classify(self, data: bytes | bytearray | memoryview) -> E2EStatus:
        if data[0] != e2e_crc(self.data_id, data):
            return E2EStatus.CRC_ERROR
        counter = data[1] & COUNTER_MASK
        last = self.last_counter
        self.last_counter = counter
        if last is None:
            return E2EStatus.INITIAL
        delta = (counter - last) % COUNTER_MODULO
        if delta == 1:
            return E2EStatus.OK
        if delta == 0:
            return E2EStatus.REPEATED
        if delta <= self.max_delta + 1:
            self.lost += delta - 1
            return E2EStatus.OK_SOME_LOST
        return E2EStatus.WRONG_SEQUENCE

    def count(self, status: E2EStatus) -> int:
        """Frames classified with ``status`` so far."""
        return self.counts[status]

    def summary(self) -> dict[str, int]:
        """Non-zero counts by status name, plus the number of lost frames and of timeouts."""
        out = {s.name: self.counts[s] for s in E2EStatus if self.counts[s]}
        if self.lost:
            out["LOST"] = self.lost
        if self.timeouts:
            out["TIMEOUT"] = self.timeouts
        return out
