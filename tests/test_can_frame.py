"""Tests of hil.can.frame: CRC-15, exact stuffed frame length, worst-case bound, durations."""

from __future__ import annotations

import random
import re

import pytest
from crccheck.crc import Crc15Can  # independent CRC library (a cantools dependency)

from hil.can.frame import (
    crc15,
    frame_bits,
    frame_bits_reference,
    frame_duration_ns,
    worst_case_frame_bits,
)

_G = "1100010110011001"  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1 (0x4599 plus the x^15 term)


def crc_long_division(bits: str) -> int:
    """CRC-15 as the remainder of bits(x) * x^15 divided by G(x), on '0'/'1' strings."""
    rem = list(bits + "0" * 15)
    for i in range(len(bits)):
        if rem[i] == "1":
            for k, g in enumerate(_G):
                rem[i + k] = "1" if rem[i + k] != g else "0"
    return int("".join(rem[-15:]), 2)


def stuff_count(region: str) -> int:
    """Stuff bits by search in the growing output: after 5 equal bits insert the complement there."""
    out, pos, count = region, 0, 0
    run5 = re.compile("00000|11111")
    while (m := run5.search(out, pos)) is not None:
        end = m.end()
        out = out[:end] + ("1" if out[end - 1] == "0" else "0") + out[end:]
        pos, count = end, count + 1  # the stuff bit at `end` starts the next run
    return count


def std_region_without_crc(can_id: int, data: bytes) -> str:
    """SOF, 11-bit ID, RTR, IDE, r0, DLC, data as a bit string."""
    return "0" + f"{can_id:011b}" + "000" + f"{len(data):04b}" + "".join(f"{b:08b}" for b in data)


def ext_region_without_crc(can_id: int, data: bytes) -> str:
    """SOF, base ID, SRR=1, IDE=1, 18-bit ext ID, RTR, r1, r0, DLC, data as a bit string."""
    head = "0" + f"{can_id >> 18:011b}" + "11" + f"{can_id & 0x3FFFF:018b}" + "000" + f"{len(data):04b}"
    return head + "".join(f"{b:08b}" for b in data)


def independent_frame_bits(can_id: int, data: bytes, extended: bool) -> int:
    """Frame length from the string helpers above: stuffed (region + CRC) plus 13 fixed bits."""
    region = (ext_region_without_crc if extended else std_region_without_crc)(can_id, data)
    region += f"{crc_long_division(region):015b}"
    return len(region) + stuff_count(region) + 13


# ---------------------------------------------------------------- CRC-15


def test_crc15_published_check_value():
    # CRC catalogue check value of CRC-15/CAN: the ASCII string "123456789" gives 0x059E.
    assert crc15(int.from_bytes(b"123456789", "big"), 72) == 0x059E


def test_crc15_matches_long_division_and_crccheck():
    rng = random.Random(7)
    for _ in range(300):
        nbits = rng.randrange(1, 140)
        bits = rng.getrandbits(nbits)
        assert crc15(bits, nbits) == crc_long_division(f"{bits:0{nbits}b}")
    for _ in range(300):
        data = rng.randbytes(rng.randrange(1, 16))
        assert crc15(int.from_bytes(data, "big"), 8 * len(data)) == Crc15Can.calc(data)


def test_crc15_small_cases_by_hand():
    # A single 1 bit: x^0 * x^15 mod G = G - x^15 = 0x4599.  A single 0 bit: 0.
    assert crc15(1, 1) == 0x4599
    assert crc15(0, 1) == 0
    # Leading zeros do not change a zero-initialised CRC.
    assert crc15(1, 40) == 0x4599
    with pytest.raises(ValueError, match="nbits"):
        crc15(0b100, 2)


# ---------------------------------------------------------------- hand-computed frames


def test_frame_id0_eight_zero_bytes_by_hand():
    # ID 0x000, DLC 8, data 00 x 8 (standard frame). Unstuffed SOF..data (83 bits):
    #   SOF 0 | ID 00000000000 | RTR 0 IDE 0 r0 0 | DLC 1000 | 64 x 0
    # CRC: the only 1 is the DLC MSB, 67 bits before the end, so CRC = x^(67+15) mod G = x^82 mod G
    #   = 0x145B = 001010001011011 (checked by long division below).
    # Stuffing, left to right:
    #   15 zeros (SOF, ID, RTR, IDE, r0): stuff '1' after zeros 5, 10, 15          -> 3 stuff bits
    #   DLC '1' follows the third stuff bit '1' (run of 2 ones), then DLC '000' and
    #   64 data zeros = one run of 67 zeros: a stuff '1' after every 5th zero,
    #   floor(67/5) = 13, leaving a run of 2 zeros                                   -> 13 stuff bits
    #   CRC 00|1|0|1|000|1|0|11|0|11: its two leading zeros make the run 4, then a 1;
    #   no later run reaches 5                                                        -> 0 stuff bits
    # Total: 83 + 15 (CRC) + 16 stuff + 13 (CRC delim, ACK, ACK delim, EOF 7, IFS 3) = 127.
    region = std_region_without_crc(0x000, bytes(8))
    assert region == "0" * 15 + "1000" + "0" * 64
    assert crc_long_division(region) == 0x145B
    assert crc15(int(region, 2), len(region)) == 0x145B
    assert stuff_count(region + f"{0x145B:015b}") == 16
    assert frame_bits(0x000, bytes(8)) == 127
    assert frame_bits_reference(0x000, bytes(8)) == 127


def test_frame_0x555_alternating_data_by_hand():
    # ID 0x555, DLC 8, data 55 x 8. Unstuffed SOF..data:
    #   SOF 0 | ID 10101010101 | 000 | DLC 1000 | 01010101 x 8
    # Longest run before the CRC: DLC '000' + the first data '0' = 4 zeros -> no stuff bit.
    # CRC = 0x1B04 = 00110110 00001 00 (long division below). After the last data bit '1':
    #   0 0 1 1 0 1 1 [0 0 0 0 0] -> stuff '1' -> 1 0 0: the stuff '1' and the next CRC '1'
    #   make a run of only 2                                                           -> 1 stuff bit
    # Total: 83 + 15 + 1 + 13 = 112.
    data = b"\x55" * 8
    region = std_region_without_crc(0x555, data)
    assert crc_long_division(region) == 0x1B04
    assert stuff_count(region) == 0
    assert stuff_count(region + f"{0x1B04:015b}") == 1
    assert frame_bits(0x555, data) == 112
    assert frame_bits_reference(0x555, data) == 112


def test_frame_empty_data_by_hand():
    # ID 0x000, DLC 0: SOF..DLC is 19 zeros and the CRC of an all-zero message is 0, so the stuffed
    # region is 34 zeros: a stuff '1' after every 5th zero, floor(34/5) = 6. 34 + 6 + 13 = 53.
    assert crc15(0, 19) == 0
    assert frame_bits(0x000, b"") == 53
    # ID 0x7FF, DLC 0: 0 11111 11111 1 000 0000, CRC 0x272F = 010011100101111.
    #   ID ones: stuff '0' after ones 5 and 10 (the stuff '0' breaks each run)         -> 2
    #   11th one, then RTR IDE r0 + DLC = 7 zeros: stuff '1' after 5, 2 zeros remain;
    #   CRC '0' makes 3, then '1'; CRC runs after that are at most 4 (the final 1111)    -> 1
    # 34 + 3 + 13 = 50.
    assert crc_long_division(std_region_without_crc(0x7FF, b"")) == 0x272F
    assert frame_bits(0x7FF, b"") == 50


def test_minimal_std_frame_is_47_bits_plus_stuffing():
    # Without stuffing a standard 0-byte frame is 44 bits + 3 IFS = 47; every ID adds its own stuff.
    for can_id in range(1 << 11):
        region = std_region_without_crc(can_id, b"")
        region += f"{crc_long_division(region):015b}"
        assert len(region) + 13 == 47
        assert frame_bits(can_id, b"") == 47 + stuff_count(region)
    # RTR, IDE, r0 and DLC 0000 are 7 dominant bits in a row, so a 0-byte data frame always has a stuff bit.
    assert min(frame_bits(i, b"") for i in range(1 << 11)) >= 48


# ---------------------------------------------------------------- fast path == reference


def _adversarial_bytes(rng: random.Random, n: int) -> bytes:
    """Bytes built from long runs, where stuffing is densest and the fast path's carries matter."""
    return bytes(rng.choice((0x00, 0xFF, 0x0F, 0xF0, 0x87, 0x78, 0xC3, 0x3C, 0xE1, 0x1E, 0x55)) for _ in range(n))


def test_fast_equals_reference_on_random_frames():
    rng = random.Random(2024)
    for i in range(6000):
        extended = bool(i & 1)
        can_id = rng.getrandbits(29 if extended else 11)
        if i % 7 == 0:
            can_id = rng.choice((0, 0x555, 0x2AA, (1 << (29 if extended else 11)) - 1))
        n = rng.randrange(9)
        data = _adversarial_bytes(rng, n) if i % 3 == 0 else rng.randbytes(n)
        expected = frame_bits_reference(can_id, data, extended)
        assert frame_bits(can_id, data, extended) == expected, (hex(can_id), data.hex(), extended)


def test_fast_equals_string_based_length():
    # A third, independent implementation (string search stuffing, long-division CRC).
    rng = random.Random(99)
    for i in range(600):
        extended = bool(i & 1)
        can_id = rng.getrandbits(29 if extended else 11)
        data = _adversarial_bytes(rng, rng.randrange(9)) if i % 2 else rng.randbytes(rng.randrange(9))
        assert frame_bits(can_id, data, extended) == independent_frame_bits(can_id, data, extended)


def test_bytes_like_data_and_repeated_ids():
    data = bytes([0x12, 0x00, 0x00, 0xFF, 0xFF, 0x80])
    expected = frame_bits_reference(0x321, data)
    assert frame_bits(0x321, bytearray(data)) == expected
    assert frame_bits(0x321, memoryview(data)) == expected
    # Same ID and DLC, different data: the per-(ID, DLC) cache must not leak data-dependent state.
    assert frame_bits(0x321, bytes(6)) == frame_bits_reference(0x321, bytes(6))
    assert frame_bits(0x321, data) == expected


# ---------------------------------------------------------------- worst-case bound


def test_worst_case_formula_values():
    # Davis et al. (2007) eq. (1): std 8 bytes 34+64+13+floor(97/4) = 135; ext 54+64+13+floor(117/4) = 160.
    assert worst_case_frame_bits(8) == 135
    assert worst_case_frame_bits(8, extended=True) == 160
    assert worst_case_frame_bits(0) == 34 + 13 + 33 // 4  # 55
    assert [worst_case_frame_bits(s) for s in range(9)] == [55 + 10 * s for s in range(9)]
    assert [worst_case_frame_bits(s, True) for s in range(9)] == [80 + 10 * s for s in range(9)]


def test_densest_frames_close_to_bound():
    # Densest frames found by a search over IDs with data 3C x 8 (runs of 4 that chain stuff bits):
    # std 131 bits = 111 + 20 stuff, ext 156 bits = 131 + 25 stuff; the bound allows 24 and 29.
    cases = [(0x02F, False, 131), (0xC0000, True, 156)]
    for can_id, extended, bits in cases:
        data = b"\x3c" * 8
        assert frame_bits(can_id, data, extended) == bits
        assert frame_bits_reference(can_id, data, extended) == bits
        assert independent_frame_bits(can_id, data, extended) == bits
        assert bits <= worst_case_frame_bits(8, extended)


def test_frames_never_exceed_worst_case():
    rng = random.Random(5)
    for i in range(4000):
        extended = bool(i & 1)
        n = rng.randrange(9)
        can_id = rng.getrandbits(29 if extended else 11)
        data = _adversarial_bytes(rng, n) if i % 2 else rng.randbytes(n)
        bits = frame_bits(can_id, data, extended)
        assert 47 + 8 * n + (20 if extended else 0) <= bits <= worst_case_frame_bits(n, extended)


# ---------------------------------------------------------------- durations and validation


@pytest.mark.parametrize(
    ("bitrate", "ns_per_bit"), [(125_000, 8000), (250_000, 4000), (500_000, 2000), (1_000_000, 1000)]
)
def test_frame_duration_ns(bitrate: int, ns_per_bit: int):
    assert frame_duration_ns(1, bitrate) == ns_per_bit
    assert frame_duration_ns(135, bitrate) == 135 * ns_per_bit  # 1.08 ms at 125 kbit/s, 135 us at 1 Mbit/s
    assert frame_duration_ns(0, bitrate) == 0


def test_frame_duration_rejects_inexact_bitrate():
    with pytest.raises(ValueError, match="bitrate=333333"):
        frame_duration_ns(100, 333_333)
    with pytest.raises(ValueError, match="bitrate"):
        frame_duration_ns(100, 0)
    with pytest.raises(ValueError, match="bits"):
        frame_duration_ns(-1, 500_000)


@pytest.mark.parametrize(
    ("can_id", "data", "extended", "match"),
    [
        (0x800, b"", False, "can_id=0x800"),
        (-1, b"", False, "can_id=-0x1"),
        (1 << 29, b"", True, "can_id=0x20000000"),
        (0x10, bytes(9), False, "data length 9"),
        (1.0, b"", False, "can_id=1.0"),
        (True, b"", False, "can_id=True"),
    ],
)
def test_frame_bits_rejects_bad_input(can_id, data, extended, match):
    with pytest.raises(ValueError, match=match):
        frame_bits(can_id, data, extended)
    with pytest.raises(ValueError, match=match):
        frame_bits_reference(can_id, data, extended)


def test_worst_case_rejects_bad_dlc():
    with pytest.raises(ValueError, match="dlc=9"):
        worst_case_frame_bits(9)
    with pytest.raises(ValueError, match="dlc=-1"):
        worst_case_frame_bits(-1)
