"""E2E protection: CRC-8 SAE J1850 against independent implementations, counters, receiver checker."""
from __future__ import annotations

import random

import pytest
from crccheck.crc import Crc8SaeJ1850

from ecu_sim.e2e import E2EStatus, counter_of, crc_ok, e2e_crc
from tests.oracle.e2e_checker import E2EChecker, next_counter


def crc8_bitwise(data: bytes) -> int:
    """Reference CRC-8 SAE J1850 computed bit by bit (poly 0x1D, init 0xFF, xor-out 0xFF)."""
    crc = 0xFF
    for byte in data:
        for bit in range(7, -1, -1):
            top = (crc >> 7) ^ ((byte >> bit) & 1)
            crc = (crc << 1) & 0xFF
            if top:
                crc ^= 0x1D
    return crc ^ 0xFF


def make_frame(data_id: int, counter: int, payload: bytes = b"\x12\x34\x56") -> bytes:
    """Frame with header: byte 1 high nibble 0xA (payload bits), low nibble the counter."""
    body = bytes([0xA0 | counter]) + payload
    return bytes([e2e_crc(data_id, b"\x00" + body)]) + body


def test_crc_standard_check_value() -> None:
    # CRC-8/SAE-J1850 catalogue check value: CRC("123456789") = 0x4B. Byte 0 is skipped, the data ID leads.
    assert e2e_crc(ord("1"), b"\x00" + b"23456789") == 0x4B
    assert crc8_bitwise(b"123456789") == 0x4B


def test_crc_matches_crccheck_and_bitwise_reference() -> None:
    rng = random.Random(1)
    for _ in range(2000):
        data_id = rng.randrange(256)
        frame = bytes(rng.randrange(256) for _ in range(rng.randint(2, 8)))
        expected = Crc8SaeJ1850.calc(bytes([data_id]) + frame[1:])
        assert e2e_crc(data_id, frame) == expected
        assert crc8_bitwise(bytes([data_id]) + frame[1:]) == expected


def test_crc_ignores_byte0_and_accepts_buffer_types() -> None:
    frame = bytes([0x00, 1, 2, 3, 4, 5, 6, 7])
    other = bytes([0xFF]) + frame[1:]
    assert e2e_crc(6, frame) == e2e_crc(6, other) == e2e_crc(6, bytearray(frame)) == e2e_crc(6, memoryview(frame))


def test_crc_detects_every_single_bit_flip_and_any_data_id_change() -> None:
    frame = bytearray(make_frame(5, 9, b"\x00\x10\x20\x30\x40\x50"))
    assert crc_ok(5, frame)
    for i in range(len(frame) * 8):
        flipped = bytearray(frame)
        flipped[i // 8] ^= 1 << (i % 8)
        assert not crc_ok(5, flipped), f"bit {i} flip undetected"
    # The data ID -> CRC map is a bijection: a frame checked as another message type always fails.
    crcs = {e2e_crc(data_id, frame) for data_id in range(256)}
    assert len(crcs) == 256


def test_crc_rejects_bad_data_id() -> None:
    with pytest.raises(ValueError, match="256"):
        e2e_crc(256, b"\x00\x00")
    with pytest.raises(ValueError, match="-1"):
        e2e_crc(-1, b"\x00\x00")


def test_counter_helpers() -> None:
    assert [next_counter(c) for c in (0, 1, 14, 15)] == [1, 2, 15, 0]
    assert counter_of(bytes([0x00, 0xA7, 0x00])) == 7
    assert not crc_ok(1, b"\x00")  # too short to carry the header


def feed(checker: E2EChecker, counters: list[int], data_id: int = 5) -> list[E2EStatus]:
    return [checker.check(make_frame(data_id, c)) for c in counters]


def test_checker_profile1_sequence_default_max_delta() -> None:
    S = E2EStatus
    checker = E2EChecker(5, name="AgentState_U02")
    got = feed(checker, [0, 1, 2, 2, 4, 5, 8, 9, 15, 0, 1])
    # 2->4 loses one frame (allowed with max_delta 1); 5->8 loses two: wrong sequence, resync on 8.
    assert got == [S.INITIAL, S.OK, S.OK, S.REPEATED, S.OK_SOME_LOST, S.OK, S.WRONG_SEQUENCE, S.OK,
                   S.WRONG_SEQUENCE, S.OK, S.OK]
    assert checker.lost == 1
    assert checker.count(S.OK) == 6 and checker.count(S.WRONG_SEQUENCE) == 2 and checker.count(S.REPEATED) == 1
    assert checker.summary() == {
        "OK": 6, "INITIAL": 1, "OK_SOME_LOST": 1, "REPEATED": 1, "WRONG_SEQUENCE": 2, "LOST": 1,
    }


def test_checker_larger_window_counts_lost_frames_across_wrap() -> None:
    S = E2EStatus
    checker = E2EChecker(5, max_delta=3)
    # 13 -> 1 is delta 4 mod 16 (3 lost): accepted; 1 -> 6 is delta 5: rejected.
    assert feed(checker, [13, 1, 6, 7]) == [S.INITIAL, S.OK_SOME_LOST, S.WRONG_SEQUENCE, S.OK]
    assert checker.lost == 3
    zero = E2EChecker(5, max_delta=0)
    assert feed(zero, [3, 5]) == [S.INITIAL, S.WRONG_SEQUENCE]


def test_checker_crc_error_leaves_sequence_untouched() -> None:
    S = E2EStatus
    checker = E2EChecker(5)
    assert checker.check(make_frame(5, 3)) is S.INITIAL
    bad = bytearray(make_frame(5, 4))
    bad[3] ^= 0x01
    assert checker.check(bad) is S.CRC_ERROR
    assert checker.check(make_frame(6, 4)) is S.CRC_ERROR  # right counter, wrong data ID
    assert checker.check(make_frame(5, 4)) is S.OK  # 3 -> 4: the corrupted frames did not move the state
    assert checker.count(S.CRC_ERROR) == 2
    checker.reset()
    assert checker.check(make_frame(5, 11)) is S.INITIAL


def test_status_usable() -> None:
    assert {s for s in E2EStatus if s.usable} == {E2EStatus.OK, E2EStatus.INITIAL, E2EStatus.OK_SOME_LOST}


def test_checker_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="max_delta 15"):
        E2EChecker(5, max_delta=15)
    with pytest.raises(ValueError, match="300"):
        E2EChecker(300)
    with pytest.raises(ValueError, match="Reference.*1 bytes"):
        E2EChecker(2, name="Reference").check(b"\x00")
