"""Exact classical CAN 2.0 data-frame timing: CRC-15, bit stuffing, frame length and duration.

The fast path (`frame_bits`) runs for every emulated frame; `frame_bits_reference` is the plain
bit-by-bit version the tests cross-check it against.
"""

from __future__ import annotations

import operator

import trainhil_engine as engine

CRC15_POLY = 0x4599  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1 (x^15 implicit)
_CRC_MASK = 0x7FFF
STD_ID_LIMIT = 1 << 11
EXT_ID_LIMIT = 1 << 29
MAX_DATA_BYTES = 8
TRAILER_BITS = 1 + 1 + 1 + 7 + 3  # CRC delimiter, ACK slot, ACK delimiter, EOF, IFS (never stuffed)
_STUFF_RUN = 5


def _int_field(value: object, name: str) -> int:
    """`value` as an int (numpy integers accepted; bool and float rejected), else ValueError naming it."""
    if isinstance(value, bool):
        raise ValueError(f"{name}={value!r} must be an integer, not bool")
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{name}={value!r} must be an integer") from None


def _crc15_byte_table() -> tuple[int, ...]:
    """T[b] = CRC-15 register after shifting byte b (MSB first) into a zero register."""
    table = []
    for b in range(256):
        reg = b << 7
        for _ in range(8):
            reg = ((reg << 1) ^ CRC15_POLY) if reg & 0x4000 else (reg << 1)
            reg &= _CRC_MASK
        table.append(reg)
    return tuple(table)


_CRC_T = _crc15_byte_table()


def _crc15_bytes(data: bytes, reg: int = 0) -> int:
    """Table-driven CRC-15 over whole bytes, MSB first, continuing from register `reg`."""
    for b in data:
        reg = ((reg << 8) & _CRC_MASK) ^ _CRC_T[(reg >> 7) ^ b]
    return reg


def crc15(bits: int, nbits: int) -> int:
    """CAN CRC-15 (poly 0x4599, init 0) of the `nbits`-bit string `bits`, first bit = MSB.

    Leading zero bits do not change a zero-initialised CRC, so the string is left-padded to whole
    bytes and run through the byte table.
    """
    if _int_field(nbits, "nbits") < 0 or _int_field(bits, "bits") < 0 or bits >> nbits:
        raise ValueError(f"crc15: bits={bits:#x} does not fit in nbits={nbits}")
    return _crc15_bytes(bits.to_bytes((nbits + 7) // 8, "big"))


# Bit-stuffing automaton. State between bits: the value of the last bit on the wire and its run
# length 1..4 (a run of 5 always gets a stuff bit, which starts a run of 1 of the other value):
# st = last * 4 + run - 1. The fast path also carries the stuff count in the state, premultiplied
# so that a byte can be OR-ed in: s = ((count << 3) | st) << 8, and one lookup advances a whole byte.
_MAX_STUFF_COUNT = 40  # > floor((54 + 64 + 15 - 1) / 4) = 33, the most a frame can hold


def _stuff_step(st: int, bit: int) -> tuple[int, int]:
    """Advance the stuffing automaton by one bit: (new state, stuff bits inserted)."""
    last, run = st >> 2, (st & 3) + 1
    run = run + 1 if bit == last else 1
    if run == _STUFF_RUN:
        return (1 - bit) * 4, 1
    return bit * 4 + run - 1, 0


def _stuff_table(width: int) -> tuple[int, ...]:
    """Lookup s | v -> next s for a chunk v of `width` bits (MSB first), s as described above."""
    chunk = []
    for st in range(8):
        for v in range(256):
            s, added = st, 0
            for i in range(width - 1, -1, -1):
                s, inc = _stuff_step(s, (v >> i) & 1)
                added += inc
            chunk.append((added, s))
    return tuple(
        (((count + added) << 3) | s) << 8
        for count in range(_MAX_STUFF_COUNT + 1)
        for added, s in chunk
    )


_STUFF8 = _stuff_table(8)
_STUFF7 = _stuff_table(7)  # for the last 7 CRC bits (only entries with v < 128 are used)


def _header(can_id: int, dlc: int, extended: bool) -> tuple[int, int]:
    """(bits SOF..DLC as an int, their count) for a data frame (RTR = r0 = r1 = 0, SRR = IDE = 1)."""
    if extended:
        base, ext = can_id >> 18, can_id & 0x3FFFF
        # SOF(0) base(11) SRR(1) IDE(1) ext(18) RTR(0) r1(0) r0(0) DLC(4)
        return (base << 27) | (0b11 << 25) | (ext << 7) | dlc, 39
    # SOF(0) ID(11) RTR(0) IDE(0) r0(0) DLC(4)
    return (can_id << 7) | dlc, 19


def _validate(can_id: int, data: bytes, extended: bool) -> None:
    """Raise ValueError naming the bad field and value."""
    limit = EXT_ID_LIMIT if extended else STD_ID_LIMIT
    if not 0 <= _int_field(can_id, "can_id") < limit:
        kind = "extended (29-bit)" if extended else "standard (11-bit)"
        raise ValueError(f"can_id={can_id:#x} out of range for a {kind} identifier (0..{limit - 1:#x})")
    if len(data) > MAX_DATA_BYTES:
        raise ValueError(f"data length {len(data)} > {MAX_DATA_BYTES} bytes (classical CAN) for can_id={can_id:#x}")


_IDLE_STATE = 4  # before SOF the bus idles recessive: last bit 1, run 1 (SOF then starts a fresh run)

# Per (can_id, dlc, extended): (CRC register after the header, stuffing state after the header,
# bits of the frame that do not depend on the data values).
_HEADER_CACHE: dict[tuple[int, int, bool], tuple[int, int, int]] = {}
_HEADER_CACHE_MAX = 1 << 14


def _header_entry(can_id: int, dlc: int, extended: bool) -> tuple[int, int, int]:
    """CRC and stuffing state after SOF..DLC, computed bit by bit once per identifier and DLC."""
    hdr, nhdr = _header(can_id, dlc, extended)
    st, count = _IDLE_STATE, 0
    for i in range(nhdr - 1, -1, -1):
        st, inc = _stuff_step(st, (hdr >> i) & 1)
        count += inc
    entry = (crc15(hdr, nhdr), ((count << 3) | st) << 8, nhdr + 8 * dlc + 15 + TRAILER_BITS)
    if len(_HEADER_CACHE) >= _HEADER_CACHE_MAX:
        _HEADER_CACHE.clear()
    _HEADER_CACHE[(can_id, dlc, extended)] = entry
    return entry


def frame_bits(can_id: int, data: bytes, extended: bool = False) -> int:
    """Exact bits on the wire of a classical CAN data frame, SOF through the 3-bit intermission.

    Header CRC and stuffing state are cached per (id, DLC); the data bytes and the CRC go through
    byte tables, so a call costs one dict lookup plus about ten table lookups.
    """
    entry = _HEADER_CACHE.get((can_id, len(data), extended))
    if entry is None or type(can_id) is not int:  # 1.0 or True would hit the entry of 1
        _validate(can_id, data, extended)
        entry = _header_entry(can_id, len(data), extended)
    reg, s, nbits = entry
    crc_t, stuff8 = _CRC_T, _STUFF8
    for b in data:
        reg = ((reg << 8) & 0x7FFF) ^ crc_t[(reg >> 7) ^ b]
        s = stuff8[s | b]
    s = _STUFF7[stuff8[s | (reg >> 7)] | (reg & 0x7F)]
    return nbits + (s >> 11)


def _bits_of(value: int, width: int) -> list[int]:
    """`value` as a list of `width` bits, MSB first."""
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _crc15_bitwise(bits: list[int]) -> int:
    """CRC-15 exactly as the CAN specification's shift-register description."""
    reg = 0
    for bit in bits:
        crc_next = bit ^ ((reg >> 14) & 1)
        reg = (reg << 1) & _CRC_MASK
        if crc_next:
            reg ^= CRC15_POLY
    return reg


def _stuff(bits: list[int]) -> list[int]:
    """Insert a complement bit after every 5 equal consecutive bits; the stuff bit starts the next run."""
    out: list[int] = []
    last, run = -1, 0
    for bit in bits:
        out.append(bit)
        run = run + 1 if bit == last else 1
        last = bit
        if run == _STUFF_RUN:
            last, run = 1 - bit, 1
            out.append(last)
    return out


def stuffed_bits(can_id: int, data: bytes, extended: bool = False) -> list[int]:
    """The stuffed part of a data frame as sent, SOF through the CRC sequence, bit by bit (0 = dominant)."""
    if extended:
        head = [0] + _bits_of(can_id >> 18, 11) + [1, 1] + _bits_of(can_id & 0x3FFFF, 18) + [0, 0, 0]
    else:
        head = [0] + _bits_of(can_id, 11) + [0, 0, 0]
    head += _bits_of(len(data), 4)
    for byte in data:
        head += _bits_of(byte, 8)
    return _stuff(head + _bits_of(_crc15_bitwise(head), 15))


def frame_bits_reference(can_id: int, data: bytes, extended: bool = False) -> int:
    """Bit-by-bit reference for `frame_bits`: build the frame, stuff it, count the bits."""
    _validate(can_id, data, extended)
    stuffed = stuffed_bits(can_id, data, extended)
    trailer = [1] + [0] + [1] + [1] * 7 + [1] * 3  # CRC delim, ACK (acknowledged), ACK delim, EOF, IFS
    return len(stuffed) + len(trailer)


def worst_case_frame_bits(dlc: int, extended: bool = False) -> int:
    """Worst-case frame length incl. 3-bit IFS (Davis et al. 2007, eq. 1): g + 8s + 13 + floor((g+8s-1)/4)."""
    if not 0 <= _int_field(dlc, "dlc") <= MAX_DATA_BYTES:
        raise ValueError(f"dlc={dlc!r} out of range 0..{MAX_DATA_BYTES}")
    g = 54 if extended else 34
    return g + 8 * dlc + 13 + (g + 8 * dlc - 1) // 4


def bit_time_ns(bitrate: int) -> int:
    """Whole nanoseconds per bit; ValueError if the bitrate does not give a whole number."""
    if _int_field(bitrate, "bitrate") <= 0:
        raise ValueError(f"bitrate={bitrate!r} must be a positive integer (bit/s)")
    if 1_000_000_000 % bitrate:
        raise ValueError(f"bitrate={bitrate} bit/s: bit time {1e9 / bitrate} ns is not a whole number of ns")
    return 1_000_000_000 // bitrate


def frame_duration_ns(bits: int, bitrate: int) -> int:
    """Exact duration in integer nanoseconds of `bits` bits at `bitrate` bit/s."""
    if _int_field(bits, "bits") < 0:
        raise ValueError(f"bits={bits!r} must be a non-negative integer")
    return bits * bit_time_ns(bitrate)


# ---- CAN FD (ISO 11898-1:2015); the exact count per frame is the engine's (engine/src/frame.rs)
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)  # payload length by DLC code 0..15
MAX_FD_DATA_BYTES = 64
_FD_ARBITRATION_BITS = {False: 1 + 11 + 1 + 1 + 1 + 1 + 1, True: 1 + 11 + 2 + 18 + 1 + 1 + 1 + 1}  # SOF..BRS
_FD_CONTROL_BITS = 1 + 4  # ESI, DLC: the data phase's dynamically stuffed bits before the data field
FD_TAIL_BITS = 1 + 1 + 7 + 3  # after the CRC delimiter: ACK slot, ACK delimiter, EOF, IFS (nominal rate)


def fd_padded_len(length: int) -> int:
    """The smallest CAN FD payload length that carries ``length`` bytes (FD frames are padded up to it)."""
    for n in FD_LENGTHS:
        if n >= length:
            return n
    raise ValueError(f"{length} data bytes exceed the {MAX_FD_DATA_BYTES} of a CAN FD frame")


def fd_pad(data: bytes) -> bytes:
    """``data`` padded with zero bytes up to the next CAN FD length."""
    return data + bytes(fd_padded_len(len(data)) - len(data))


def fd_frame_bits(can_id: int, data: bytes, extended: bool = False, brs: bool = True) -> tuple[int, int]:
    """Exact bits of a CAN FD data frame: (at the nominal rate, at the data rate; 0 without BRS)."""
    return engine.fd_frame_bits(can_id, data, extended, brs)


def _fd_crc_field_bits(length: int) -> int:
    """Stuff count (4), CRC-17 or CRC-21, their fixed stuff bits, and the CRC delimiter."""
    return (4 + 17 + 6 if length <= 16 else 4 + 21 + 7) + 1


def best_case_fd_frame_bits(length: int, extended: bool = False, brs: bool = True) -> tuple[int, int]:
    """The fewest bits a CAN FD frame of ``length`` data bytes can take (no dynamic stuff bits), as (nominal, data)."""
    if length not in FD_LENGTHS:
        raise ValueError(f"length={length!r} is not a CAN FD payload length {FD_LENGTHS}")
    arbitration = _FD_ARBITRATION_BITS[bool(extended)]
    data_phase = _FD_CONTROL_BITS + 8 * length + _fd_crc_field_bits(length)
    nominal = arbitration + FD_TAIL_BITS
    return (nominal, data_phase) if brs else (nominal + data_phase, 0)


def worst_case_fd_frame_bits(length: int, extended: bool = False, brs: bool = True) -> tuple[int, int]:
    """An upper bound on the bits of a CAN FD frame of ``length`` data bytes, as (nominal, data) like
    :func:`fd_frame_bits`. Dynamic stuffing adds at most one bit per 4 after the first of SOF..data; the bound
    puts as many of them as can fall there in the (slower) arbitration phase. The CRC field's stuffing is fixed."""
    if length not in FD_LENGTHS:
        raise ValueError(f"length={length!r} is not a CAN FD payload length {FD_LENGTHS}")
    arbitration = _FD_ARBITRATION_BITS[bool(extended)]
    dynamic = arbitration + _FD_CONTROL_BITS + 8 * length
    stuff_total = (dynamic - 1) // 4
    stuff_arbitration = min((arbitration - 1) // 4, stuff_total)
    nominal = arbitration + stuff_arbitration + FD_TAIL_BITS
    data_phase = dynamic - arbitration + stuff_total - stuff_arbitration + _fd_crc_field_bits(length)
    return (nominal, data_phase) if brs else (nominal + data_phase, 0)
