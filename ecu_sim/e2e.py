"""End-to-end protection of train-bus frames: CRC-8 SAE J1850 and a 4-bit alive counter.

AUTOSAR profile-1 style header shared by every frame of dbc/train.dbc: byte 0 is the CRC over
[data ID] + bytes 1..end, the low nibble of byte 1 is the alive counter. The data ID is not sent,
so a frame checked against the wrong message type (wrong ID mapping) fails the CRC.

Receivers classify every frame (``E2EStatus``: OK, INITIAL, OK_SOME_LOST with the lost frames counted as LOST,
REPEATED, WRONG_SEQUENCE, CRC_ERROR) in the engine's mailboxes (engine/src/e2e.rs; its Python oracle is
``tests/oracle/e2e_checker.py``); TIMEOUT is counted by the receiver's freshness check
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
