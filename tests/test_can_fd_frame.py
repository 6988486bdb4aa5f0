"""CAN FD frame timing in the engine (ISO 11898-1:2015): against frames worked out by hand and
against an independent bit-by-bit count written here in Python (dynamic stuffing through the data field, the
stuff count and CRC-17/21 with their fixed stuff bits, the arbitration phase and the tail at the nominal rate)."""
from __future__ import annotations

import random

import pytest
import trainhil_engine as engine

FD_LENGTHS = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]


def bits(value: int, width: int) -> list[int]:
    return [(value >> i) & 1 for i in range(width - 1, -1, -1)]


def stuffed_length(seq: list[int]) -> int:
    """Length after dynamic stuffing: a complement bit after every 5 equal bits (it starts the next run)."""
    out, last, run = 0, None, 0
    for b in seq:
        out += 1
        run = run + 1 if b == last else 1
        last = b
        if run == 5:
            out += 1
            last, run = 1 - b, 1
    return out


def reference(can_id: int, data: bytes, extended: bool, brs: bool, esi: bool) -> tuple[int, int]:
    """(nominal, data-phase) bits of an FD frame, counted field by field."""
    if extended:
        head = [0] + bits(can_id >> 18, 11) + [1, 1] + bits(can_id & 0x3FFFF, 18) + [0, 1, 0]
    else:
        head = [0] + bits(can_id, 11) + [0, 0, 1, 0]  # SOF, ID, RRS, IDE, FDF, res
    arbitration = stuffed_length(head) + 1  # SOF..res with their stuff bits, then BRS (a stuff bit after BRS is data phase)
    dynamic = stuffed_length(head + [brs, esi] + bits(FD_LENGTHS.index(len(data)), 4)
                             + [b for byte in data for b in bits(byte, 8)])
    crc = 17 if len(data) <= 16 else 21
    fixed = -(-(4 + crc) // 4)  # one before the stuff count, one after every 4 bits of stuff count + CRC
    data_phase = dynamic - arbitration + 4 + crc + fixed + 1  # ... and the CRC delimiter
    tail = 1 + 1 + 7 + 3  # ACK slot, ACK delimiter, EOF, IFS
    return (arbitration + tail, data_phase) if brs else (arbitration + data_phase + tail, 0)


def test_frames_worked_out_by_hand():
    assert engine.fd_frame_bits(0, b"") == (31, 34)  # see engine/src/frame.rs, fd_empty_frame_by_hand
    assert engine.fd_frame_bits(0, b"", brs=False) == (65, 0)
    assert engine.fd_frame_bits(0x555, b"\x55" * 64) == (29, 550)
    assert engine.frame_duration_ns(0x555, b"\x55" * 64, 500_000, 2_000_000, fd=True) == 29 * 2000 + 550 * 500
    assert engine.frame_duration_ns(0x555, b"\x55" * 64, 500_000, 2_000_000, fd=True, brs=False) == 579 * 2000


def test_random_frames_match_an_independent_count():
    rng = random.Random(15)
    for _ in range(3000):
        extended = rng.random() < 0.5
        can_id = rng.randrange(1 << 29 if extended else 1 << 11)
        n = rng.choice(FD_LENGTHS)
        data = bytes(rng.choice((0, 0xFF, rng.randrange(256))) for _ in range(n))
        brs, esi = rng.random() < 0.7, rng.random() < 0.2
        assert engine.fd_frame_bits(can_id, data, extended, brs, esi) == reference(can_id, data, extended, brs, esi), \
            (hex(can_id), n, extended, brs, esi)


def test_lengths_that_are_not_fd_lengths_are_refused_with_the_padding_to_use():
    with pytest.raises(ValueError, match=r"data length 13 is not a CAN FD length .*pad it to 16"):
        engine.fd_frame_bits(0x100, bytes(13))
    with pytest.raises(ValueError, match="out of range"):
        engine.fd_frame_bits(0x800, b"")
