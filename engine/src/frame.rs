//! Exact CAN frame timing: CRC-15, bit stuffing from the actual bits, frame length and duration.
//!
//! A classical data frame is counted from SOF through the 3-bit intermission: the stuffed part
//! (SOF..CRC sequence, stuff bits computed from the real ID, DLC, data and CRC bits) plus the
//! never-stuffed trailer (CRC delimiter, ACK slot, ACK delimiter, 7 EOF bits, 3 IFS bits).
//! CAN FD frames (ISO 11898-1:2015) are timed by `fd_frame_bits`: dynamic stuffing through the data field, the
//! stuff count and CRC-17/21 with fixed stuff bits, the arbitration and tail at the nominal rate and, with BRS,
//! the data phase at the data rate.

/// CRC-15 generator polynomial of classical CAN (x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1).
pub const CRC15_POLY: u16 = 0x4599;
/// Largest payload a frame can carry (CAN FD); classical frames carry at most 8.
pub const MAX_DATA: usize = 64;
/// Largest classical CAN payload.
pub const MAX_CLASSIC_DATA: usize = 8;
/// Never-stuffed bits after the CRC: CRC delimiter, ACK slot, ACK delimiter, EOF (7), IFS (3).
pub const TRAILER_BITS: u32 = 1 + 1 + 1 + 7 + 3;
const STD_ID_LIMIT: u32 = 1 << 11;
const EXT_ID_LIMIT: u32 = 1 << 29;

/// Why a frame cannot be timed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FrameError {
    IdOutOfRange { can_id: u32, extended: bool },
    TooLong { can_id: u32, len: usize, limit: usize },
    NotAnFdLength { can_id: u32, len: usize },
}

impl std::fmt::Display for FrameError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameError::IdOutOfRange { can_id, extended } => {
                let (kind, limit) = if *extended { ("extended (29-bit)", EXT_ID_LIMIT) } else { ("standard (11-bit)", STD_ID_LIMIT) };
                write!(f, "can_id={can_id:#x} out of range for a {kind} identifier (0..{:#x})", limit - 1)
            }
            FrameError::TooLong { can_id, len, limit } => {
                write!(f, "data length {len} > {limit} bytes (classical CAN) for can_id={can_id:#x}")
            }
            FrameError::NotAnFdLength { can_id, len } => {
                let pad = fd_padded_len(*len).map(|l| format!("pad it to {l}")).unwrap_or("at most 64".into());
                write!(f, "data length {len} is not a CAN FD length (0..8, 12, 16, 20, 24, 32, 48, 64) for \
                           can_id={can_id:#x}: {pad}")
            }
        }
    }
}

/// A sequence of bits, first bit on the wire first (0 = dominant).
#[derive(Default, Clone)]
pub struct Bits(pub Vec<u8>);

impl Bits {
    fn push(&mut self, value: u64, width: u32) {
        for i in (0..width).rev() {
            self.0.push(((value >> i) & 1) as u8);
        }
    }
}

/// CRC-15 of a bit sequence, exactly as the specification's shift register.
pub fn crc15(bits: &[u8]) -> u16 {
    let mut reg: u16 = 0;
    for &bit in bits {
        let next = bit ^ ((reg >> 14) & 1) as u8;
        reg = (reg << 1) & 0x7FFF;
        if next == 1 {
            reg ^= CRC15_POLY;
        }
    }
    reg
}

/// Check the identifier and the payload length of a classical frame.
pub fn validate(can_id: u32, len: usize, extended: bool) -> Result<(), FrameError> {
    validate_as(can_id, len, extended, false)
}

/// Check the identifier and the payload length of a classical or (`fd`) a CAN FD frame, before padding.
pub fn validate_as(can_id: u32, len: usize, extended: bool, fd: bool) -> Result<(), FrameError> {
    let limit = if extended { EXT_ID_LIMIT } else { STD_ID_LIMIT };
    if can_id >= limit {
        return Err(FrameError::IdOutOfRange { can_id, extended });
    }
    let max = if fd { MAX_DATA } else { MAX_CLASSIC_DATA };
    if len > max {
        return Err(FrameError::TooLong { can_id, len, limit: max });
    }
    Ok(())
}

/// The unstuffed bits SOF..CRC sequence of a classical data frame (RTR = r0 = r1 = 0, SRR = IDE = 1).
pub fn unstuffed_bits(can_id: u32, data: &[u8], extended: bool) -> Bits {
    let mut b = Bits(Vec::with_capacity(160));
    b.push(0, 1); // SOF
    if extended {
        b.push((can_id >> 18) as u64, 11);
        b.push(0b11, 2); // SRR, IDE
        b.push((can_id & 0x3FFFF) as u64, 18);
        b.push(0, 3); // RTR, r1, r0
    } else {
        b.push(can_id as u64, 11);
        b.push(0, 3); // RTR, IDE, r0
    }
    b.push(data.len() as u64, 4);
    for &byte in data {
        b.push(byte as u64, 8);
    }
    let crc = crc15(&b.0);
    b.push(crc as u64, 15);
    b
}

/// Insert a complement bit after every 5 equal consecutive bits (the stuff bit starts the next run).
pub fn stuff(bits: &[u8]) -> Bits {
    let mut out = Vec::with_capacity(bits.len() + bits.len() / 4 + 1);
    let (mut last, mut run) = (2u8, 0u32);
    for &bit in bits {
        out.push(bit);
        if bit == last {
            run += 1;
        } else {
            last = bit;
            run = 1;
        }
        if run == 5 {
            last = 1 - bit;
            run = 1;
            out.push(last);
        }
    }
    Bits(out)
}

/// Number of stuff bits the sequence needs.
pub fn stuff_count(bits: &[u8]) -> u32 {
    (stuff(bits).0.len() - bits.len()) as u32
}

/// The stuffed part of a classical data frame as sent, SOF through the CRC sequence.
pub fn stuffed_bits(can_id: u32, data: &[u8], extended: bool) -> Bits {
    stuff(&unstuffed_bits(can_id, data, extended).0)
}

/// The header of a frame as it is sent, counted bit by bit: the CRC-15 register, the stuffing automaton's state
/// (`stuff_step`) and the stuff bits so far.
struct Header {
    crc: u16,
    st: u8,
    stuffed: u32,
    bits: u32,
}

impl Header {
    fn new() -> Header {
        Header { crc: 0, st: IDLE_STATE, stuffed: 0, bits: 0 }
    }

    /// Send `width` bits of `value`, MSB first, into the CRC and the stuffing.
    fn feed(&mut self, value: u64, width: u32) {
        for i in (0..width).rev() {
            let bit = ((value >> i) & 1) as u8;
            let next = bit ^ ((self.crc >> 14) & 1) as u8;
            self.crc = (self.crc << 1) & 0x7FFF;
            if next == 1 {
                self.crc ^= CRC15_POLY;
            }
            let (st, add) = stuff_step(self.st, bit);
            self.st = st;
            self.stuffed += add as u32;
        }
        self.bits += width;
    }
}

/// The stuffing state before SOF: the idle bus is recessive (last bit 1, run 1); the dominant SOF starts a fresh run.
const IDLE_STATE: u8 = 4;

/// Byte tables of the hot path: CRC-15 of a byte shifted into the register, and the stuffing automaton advanced
/// by a whole byte (the state between bits is the last bit and its run length 1..4: `last * 4 + run - 1`).
struct Tables {
    crc: [u16; 256],
    /// [state][byte] -> (next state, stuff bits inserted) for 8 bits, MSB first.
    stuff8: [[(u8, u8); 256]; 8],
    /// the same for the 7 low bits of a value (the CRC's last 7 bits).
    stuff7: [[(u8, u8); 128]; 8],
}

fn stuff_step(st: u8, bit: u8) -> (u8, u8) {
    let (last, run) = (st >> 2, (st & 3) + 1);
    let run = if bit == last { run + 1 } else { 1 };
    if run == 5 {
        ((1 - bit) * 4, 1) // the stuff bit starts a run of 1 of the other value
    } else {
        (bit * 4 + run - 1, 0)
    }
}

/// The automaton after the `width` low bits of `v` (MSB first) from state `st`: (state, stuff bits inserted).
fn stuff_bits_of(st: u8, v: usize, width: u32) -> (u8, u8) {
    let (mut s, mut added) = (st, 0u8);
    for i in (0..width).rev() {
        let (next, add) = stuff_step(s, ((v >> i) & 1) as u8);
        s = next;
        added += add;
    }
    (s, added)
}

fn tables() -> &'static Tables {
    static TABLES: std::sync::OnceLock<Tables> = std::sync::OnceLock::new();
    TABLES.get_or_init(|| {
        let mut t = Tables { crc: [0; 256], stuff8: [[(0, 0); 256]; 8], stuff7: [[(0, 0); 128]; 8] };
        for b in 0..256usize {
            let mut reg = (b as u16) << 7;
            for _ in 0..8 {
                reg = if reg & 0x4000 != 0 { (reg << 1) ^ CRC15_POLY } else { reg << 1 } & 0x7FFF;
            }
            t.crc[b] = reg;
        }
        for st in 0..8u8 {
            for v in 0..256usize {
                t.stuff8[st as usize][v] = stuff_bits_of(st, v, 8);
                if v < 128 {
                    t.stuff7[st as usize][v] = stuff_bits_of(st, v, 7);
                }
            }
        }
        t
    })
}

/// Exact bits on the wire of a classical data frame, SOF through the intermission: the same count as stuffing
/// `unstuffed_bits` bit by bit (a unit test checks both), without building the bit list. The header goes bit by
/// bit, the data bytes and the CRC through byte tables.
pub fn frame_bits(can_id: u32, data: &[u8], extended: bool) -> Result<u32, FrameError> {
    validate(can_id, data.len(), extended)?;
    let mut c = Header::new();
    if extended {
        // SOF, base ID, SRR, IDE, ID extension, RTR, r1, r0
        c.feed(((can_id >> 18) as u64) << 2 | 0b11, 1 + 11 + 2);
        c.feed(((can_id & 0x3FFFF) as u64) << 3, 18 + 3);
    } else {
        c.feed((can_id as u64) << 3, 1 + 11 + 3); // SOF, ID, RTR, IDE, r0
    }
    c.feed(data.len() as u64, 4);
    let t = tables();
    let (mut st, mut reg, mut stuffed) = (c.st, c.crc, c.stuffed);
    for &byte in data {
        reg = ((reg << 8) & 0x7FFF) ^ t.crc[(((reg >> 7) as u8) ^ byte) as usize];
        let (next, add) = t.stuff8[st as usize][byte as usize];
        st = next;
        stuffed += add as u32;
    }
    let (next, add) = t.stuff8[st as usize][(reg >> 7) as usize];
    stuffed += add as u32;
    let (_, add) = t.stuff7[next as usize][(reg & 0x7F) as usize];
    stuffed += add as u32;
    Ok(c.bits + 8 * data.len() as u32 + 15 + stuffed + TRAILER_BITS)
}

// ------------------------------------------------------------------------------------------------ CAN FD

/// The payload lengths a CAN FD frame can carry, by DLC code 0..15 (ISO 11898-1:2015, table 5).
pub const FD_LENGTHS: [usize; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64];
/// Stuff count (3-bit Gray code + parity), CRC-17 and their 6 fixed stuff bits: payloads up to 16 bytes.
const FD_CRC17_FIELD: u32 = 4 + 17 + 6;
/// Stuff count, CRC-21 and their 7 fixed stuff bits: payloads above 16 bytes.
const FD_CRC21_FIELD: u32 = 4 + 21 + 7;
/// Nominal-rate bits after the data phase: ACK slot, ACK delimiter, EOF (7), IFS (3).
pub const FD_TAIL_BITS: u32 = 1 + 1 + 7 + 3;

/// The DLC code of a CAN FD payload length, or None if no DLC gives exactly that length (pad it first).
pub fn fd_dlc(len: usize) -> Option<u8> {
    FD_LENGTHS.iter().position(|&l| l == len).map(|d| d as u8)
}

/// The smallest CAN FD payload length that carries `len` bytes (the frame is padded up to it), or None above 64.
pub fn fd_padded_len(len: usize) -> Option<usize> {
    FD_LENGTHS.iter().copied().find(|&l| l >= len)
}

/// A CAN FD frame's bits by phase: at the nominal rate (arbitration and the tail) and at the data rate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FdBits {
    pub nominal: u32,
    pub data: u32,
}

impl FdBits {
    pub fn total(&self) -> u32 {
        self.nominal + self.data
    }
}

/// Exact bits of a CAN FD data frame (ISO 11898-1:2015), SOF through the intermission, split by phase.
///
/// Dynamic stuffing covers SOF through the end of the data field. The stuff count and the CRC field use fixed
/// stuff bits (one before the stuff count and one after every 4 bits after it), so the CRC value and the stuff
/// count value do not change the length: only the CRC width does (17 bits up to 16 data bytes, 21 above). With
/// BRS the data rate runs from the sample point of BRS to the sample point of the CRC delimiter; counting BRS at
/// the nominal rate and the CRC delimiter at the data rate gives exactly that total, whatever the sample points.
/// Without BRS every bit is at the nominal rate (`data` is 0). `data` must have a length of `FD_LENGTHS`.
pub fn fd_frame_bits(can_id: u32, data: &[u8], extended: bool, brs: bool, esi: bool) -> Result<FdBits, FrameError> {
    let limit = if extended { EXT_ID_LIMIT } else { STD_ID_LIMIT };
    if can_id >= limit {
        return Err(FrameError::IdOutOfRange { can_id, extended });
    }
    let dlc = fd_dlc(data.len()).ok_or(FrameError::NotAnFdLength { can_id, len: data.len() })?;
    let mut c = Header::new();
    if extended {
        // SOF, base ID, SRR, IDE, ID extension, RRS, FDF, res
        c.feed(((can_id >> 18) as u64) << 2 | 0b11, 1 + 11 + 2);
        c.feed(((can_id & 0x3FFFF) as u64) << 3 | 0b010, 18 + 3);
    } else {
        c.feed((can_id as u64) << 4 | 0b0010, 1 + 11 + 4); // SOF, ID, RRS, IDE, FDF, res
    }
    let arbitration = c.bits + 1 + c.stuffed; // up to BRS; a stuff bit BRS itself triggers follows it, at the data rate
    c.feed(brs as u64, 1);
    c.feed(esi as u64, 1);
    c.feed(dlc as u64, 4);
    let t = tables();
    let (mut st, mut stuffed) = (c.st, c.stuffed);
    for &byte in data {
        let (next, add) = t.stuff8[st as usize][byte as usize];
        st = next;
        stuffed += add as u32;
    }
    let dynamic = c.bits + 8 * data.len() as u32 + stuffed;
    let crc_field = if data.len() <= 16 { FD_CRC17_FIELD } else { FD_CRC21_FIELD };
    let data_phase = dynamic - arbitration + crc_field + 1; // ... through the CRC delimiter
    Ok(if brs {
        FdBits { nominal: arbitration + FD_TAIL_BITS, data: data_phase }
    } else {
        FdBits { nominal: arbitration + data_phase + FD_TAIL_BITS, data: 0 }
    })
}

/// The unstuffed bits SOF..end of data of a CAN FD frame (the reference the fast count is checked against).
pub fn fd_unstuffed_bits(can_id: u32, data: &[u8], extended: bool, brs: bool, esi: bool) -> Bits {
    let mut b = Bits(Vec::with_capacity(600));
    b.push(0, 1);
    if extended {
        b.push((can_id >> 18) as u64, 11);
        b.push(0b11, 2);
        b.push((can_id & 0x3FFFF) as u64, 18);
        b.push(0b010, 3); // RRS, FDF, res
    } else {
        b.push(can_id as u64, 11);
        b.push(0b0010, 4); // RRS, IDE, FDF, res
    }
    b.push(brs as u64, 1);
    b.push(esi as u64, 1);
    b.push(fd_dlc(data.len()).unwrap_or(0) as u64, 4);
    for &byte in data {
        b.push(byte as u64, 8);
    }
    b
}

/// Worst-case classical frame length incl. the 3-bit IFS (Davis et al. 2007, eq. 1).
pub fn worst_case_frame_bits(dlc: u32, extended: bool) -> u32 {
    let g = if extended { 54 } else { 34 };
    g + 8 * dlc + 13 + (g + 8 * dlc - 1) / 4
}

/// The timing of one frame format on a bus: nominal bit time and (for CAN FD with BRS) the data-phase bit time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BitTiming {
    pub nominal_bit_ns: u64,
    pub data_bit_ns: u64,
}

impl BitTiming {
    /// Whole-nanosecond bit times of a nominal and a data bitrate; None when either is not a whole number of ns.
    pub fn new(nominal_bitrate: u64, data_bitrate: u64) -> Option<BitTiming> {
        let ns = |rate: u64| if rate > 0 && 1_000_000_000 % rate == 0 { Some(1_000_000_000 / rate) } else { None };
        Some(BitTiming { nominal_bit_ns: ns(nominal_bitrate)?, data_bit_ns: ns(data_bitrate)? })
    }

    /// Duration in ns of a data frame, SOF through the intermission. Classical frames run at the nominal rate
    /// throughout; `fd` frames switch to the data rate when `brs` is set (`fd_frame_bits`).
    pub fn frame_ns(&self, can_id: u32, data: &[u8], extended: bool, fd: bool, brs: bool) -> Result<u64, FrameError> {
        if fd {
            let b = fd_frame_bits(can_id, data, extended, brs, false)?;
            return Ok(b.nominal as u64 * self.nominal_bit_ns + b.data as u64 * self.data_bit_ns);
        }
        Ok(frame_bits(can_id, data, extended)? as u64 * self.nominal_bit_ns)
    }

    /// The fewest ns any data frame with at least `least_data` bytes can take on a bus of `fd` (classical frames
    /// as well; CAN FD ones with or without BRS) or classical frames only, SOF through the intermission: a lower
    /// bound for every identifier and payload, since it counts no stuff bits (`least_frame_bits`).
    pub fn least_frame_ns(&self, least_data: usize, fd: bool) -> u64 {
        let ns = |b: FdBits| b.nominal as u64 * self.nominal_bit_ns + b.data as u64 * self.data_bit_ns;
        let classical = (least_data <= MAX_CLASSIC_DATA).then(|| ns(least_frame_bits(least_data, false, false)));
        let fd_frames = fd.then(|| ns(least_frame_bits(least_data, true, true)).min(ns(least_frame_bits(least_data, true, false))));
        classical.into_iter().chain(fd_frames).min().unwrap_or(u64::MAX)
    }
}

/// The bits of the shortest data frame with at least `least_data` bytes (a standard identifier and no dynamic stuff
/// bit; a CAN FD payload padded to its length), by phase as in `fd_frame_bits`: no frame of that many bytes or
/// more is shorter. Classical: SOF, ID, RTR, IDE, r0, DLC (19), the data, the CRC (15) and `TRAILER_BITS`.
pub fn least_frame_bits(least_data: usize, fd: bool, brs: bool) -> FdBits {
    if !fd {
        return FdBits { nominal: 19 + 8 * least_data as u32 + 15 + TRAILER_BITS, data: 0 };
    }
    let len = fd_padded_len(least_data).unwrap_or(MAX_DATA) as u32;
    let crc_field = if len <= 16 { FD_CRC17_FIELD } else { FD_CRC21_FIELD };
    let arbitration = 1 + 11 + 4 + 1; // SOF, ID, RRS, IDE, FDF, res, BRS
    let data_phase = 1 + 4 + 8 * len + crc_field + 1; // ESI, DLC, the data, stuff count and CRC, CRC delimiter
    if brs {
        FdBits { nominal: arbitration + FD_TAIL_BITS, data: data_phase }
    } else {
        FdBits { nominal: arbitration + data_phase + FD_TAIL_BITS, data: 0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A CAN FD frame worked out by hand: ID 0x000, no data, BRS, ESI = 0. SOF, 11 ID bits, RRS and IDE are 14
    /// zeros: stuff bits after the 5th and the 10th. Then FDF 1, res 0, BRS 1 (arbitration ends: 17 bits + 2 stuff),
    /// ESI 0 and DLC 0000 make 5 zeros: one stuff bit, in the data phase. Data phase: ESI, DLC, that stuff bit, the
    /// stuff count and CRC-17 with 6 fixed stuff bits (27), the CRC delimiter: 1 + 4 + 1 + 27 + 1 = 34. Nominal:
    /// 19 + ACK slot, ACK delimiter, EOF, IFS (12) = 31.
    #[test]
    fn fd_empty_frame_by_hand() {
        assert_eq!(fd_frame_bits(0, &[], false, true, false).unwrap(), FdBits { nominal: 31, data: 34 });
        assert_eq!(fd_frame_bits(0, &[], false, false, false).unwrap(), FdBits { nominal: 65, data: 0 });
        let t = BitTiming::new(500_000, 2_000_000).unwrap();
        assert_eq!(t.frame_ns(0, &[], false, true, true).unwrap(), 31 * 2000 + 34 * 500);
    }

    /// No data frame is shorter than `least_frame_bits` of its length, whatever its identifier and payload, and
    /// the bound is met or nearly (within a stuff bit): every standard ID with a range of payloads, classical
    /// and CAN FD, with and without BRS, and a sample of extended IDs.
    #[test]
    fn no_frame_is_shorter_than_the_least_frame_of_its_length() {
        let patterns = [0x00u8, 0xFF, 0x55, 0xAA, 0x0F, 0x33, 0xC3, 0x84];
        for len in 0..=MAX_CLASSIC_DATA {
            let least = least_frame_bits(len, false, false).nominal;
            let mut shortest = u32::MAX;
            for id in 0..STD_ID_LIMIT {
                for &p in &patterns {
                    let bits = frame_bits(id, &vec![p; len], false).unwrap();
                    assert!(bits >= least, "id {id:#x}, {len} bytes of {p:#x}: {bits} bits < {least}");
                    shortest = shortest.min(bits);
                }
            }
            for id in (0..EXT_ID_LIMIT).step_by(65_537) {
                assert!(frame_bits(id, &vec![0x55; len], true).unwrap() >= least);
            }
            assert!(shortest <= least + 1, "{len} bytes: the shortest frame has {shortest} bits, the bound {least}");
        }
        for &len in FD_LENGTHS.iter() {
            for brs in [false, true] {
                let least = least_frame_bits(len, true, brs);
                for id in (0..STD_ID_LIMIT).step_by(7) {
                    for &p in &patterns {
                        let b = fd_frame_bits(id, &vec![p; len], false, brs, false).unwrap();
                        assert!(b.nominal >= least.nominal && b.data >= least.data, "FD id {id:#x} {len} bytes: {b:?} < {least:?}");
                    }
                }
            }
        }
        // ID 0x555 with 0x55 bytes has no stuff bit at all: the bound is that frame (`fd_64_byte_frame_by_hand`)
        assert_eq!(least_frame_bits(64, true, true), fd_frame_bits(0x555, &[0x55; 64], false, true, false).unwrap());
        // a payload between CAN FD lengths is padded: 9 bytes go as 12
        assert_eq!(least_frame_bits(9, true, true), least_frame_bits(12, true, true));
    }

    /// The least frame a bus can carry: classical 47 bits (an empty frame without stuff bits; `frame_ns(0, &[])`,
    /// with its stuff bits, is 53); on a CAN FD bus the empty FD frame with BRS when that is shorter; more than 8
    /// bytes only as CAN FD.
    #[test]
    fn the_least_frame_of_a_bus() {
        let classical = BitTiming::new(500_000, 500_000).unwrap();
        assert_eq!(classical.least_frame_ns(0, false), 47 * 2000);
        assert_eq!(classical.least_frame_ns(5, false), (47 + 40) * 2000);
        assert_eq!(classical.least_frame_ns(12, false), u64::MAX); // no classical frame carries 12 bytes
        let fd = BitTiming::new(500_000, 2_000_000).unwrap();
        assert_eq!(fd.least_frame_ns(0, true), (29 * 2000 + 33 * 500).min(47 * 2000));
        assert_eq!(fd.least_frame_ns(12, true), 29 * 2000 + (1 + 4 + 96 + 27 + 1) * 500);
    }

    /// 64 bytes of 0x55 (alternating bits: no dynamic stuffing in the data), ID 0x555, BRS: the header
    /// 0 10101010101 0010 1 0 1111 has no run of five, so no stuff bits at all. Arbitration: SOF, ID, RRS, IDE,
    /// FDF, res, BRS = 17; data phase: ESI 1 + DLC 4 + 512 data + stuff count and CRC-21 with 7 fixed stuff bits
    /// (32) + CRC delimiter 1 = 550; nominal 17 + 12 = 29.
    #[test]
    fn fd_64_byte_frame_by_hand() {
        let b = fd_frame_bits(0x555, &[0x55; 64], false, true, false).unwrap();
        assert_eq!(b, FdBits { nominal: 29, data: 550 });
        assert_eq!(stuff_count(&fd_unstuffed_bits(0x555, &[0x55; 64], false, true, false).0), 0);
    }

    #[test]
    fn fd_fast_count_equals_bit_by_bit_stuffing() {
        let mut seed = 0x2545F4914F6CDD1Du64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for _ in 0..5000 {
            let extended = next() % 2 == 0;
            let id = (next() as u32) % if extended { EXT_ID_LIMIT } else { STD_ID_LIMIT };
            let len = FD_LENGTHS[(next() % 16) as usize];
            let data: Vec<u8> = (0..len).map(|_| if next() % 3 == 0 { 0 } else { next() as u8 }).collect();
            let (brs, esi) = (next() % 2 == 0, next() % 5 == 0);
            let raw = fd_unstuffed_bits(id, &data, extended, brs, esi);
            let crc_field = if len <= 16 { FD_CRC17_FIELD } else { FD_CRC21_FIELD };
            let expected = stuff(&raw.0).0.len() as u32 + crc_field + 1 + FD_TAIL_BITS;
            let got = fd_frame_bits(id, &data, extended, brs, esi).unwrap();
            assert_eq!(got.total(), expected, "id {id:#x} len {len} brs {brs}");
            // the arbitration phase: SOF..BRS and the stuff bits among them (a stuff bit after BRS is data phase)
            let head = if extended { 1 + 11 + 2 + 18 + 3 + 1 } else { 1 + 11 + 4 + 1 };
            let arb = stuff(&raw.0[..head - 1]).0.len() as u32 + 1;
            if brs {
                assert_eq!(got.nominal, arb + FD_TAIL_BITS);
            }
        }
    }

    #[test]
    fn fd_lengths_and_padding() {
        assert_eq!(fd_dlc(12), Some(9));
        assert_eq!(fd_dlc(64), Some(15));
        assert_eq!(fd_dlc(13), None);
        assert_eq!(fd_padded_len(13), Some(16));
        assert_eq!(fd_padded_len(65), None);
        assert!(matches!(fd_frame_bits(1, &[0; 13], false, true, false), Err(FrameError::NotAnFdLength { len: 13, .. })));
        assert!(matches!(fd_frame_bits(0x800, &[], false, true, false), Err(FrameError::IdOutOfRange { .. })));
    }

    /// A frame worked out by hand: ID 0x000, DLC 0. Bits SOF..DLC are 19 zeros and the CRC of zeros is zero, so
    /// the stuffed part is 34 zeros with a 1 after every fifth (each stuff bit ends the run): 6 stuff bits.
    #[test]
    fn all_zero_frame_by_hand() {
        let raw = unstuffed_bits(0, &[], false);
        assert_eq!(raw.0.len(), 34);
        assert!(raw.0.iter().all(|&b| b == 0));
        assert_eq!(stuff_count(&raw.0), 6);
        assert_eq!(frame_bits(0, &[], false).unwrap(), 34 + 6 + 13);
    }

    /// ID 0x7FF DLC 0: SOF 0, then 11 ones (stuffed after 5 and 10 of them: 2 bits), then 000 + 0000.
    #[test]
    fn all_ones_id_by_hand() {
        let raw = unstuffed_bits(0x7FF, &[], false);
        let crc = crc15(&raw.0[..19]);
        assert_eq!(crc, crc15(&raw.0[..19])); // deterministic
        let stuffed = stuffed_bits(0x7FF, &[], false);
        // SOF(0) 11111 [0] 11111 [0] 1 then RTR IDE r0 DLC = 0000000 -> run of 7 zeros after the '1': one stuff bit
        assert_eq!(&stuffed.0[..14], &[0, 1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 0, 1]);
        assert_eq!(stuffed.0.len() as u32 - 34, stuff_count(&raw.0));
    }

    #[test]
    fn fast_count_equals_bit_by_bit_stuffing() {
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        for k in 0..20_000u32 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let extended = k % 3 == 0;
            let id = if extended { (x >> 7) as u32 & 0x1FFF_FFFF } else { (x >> 11) as u32 & 0x7FF };
            let len = (x % 9) as usize;
            let data: Vec<u8> = (0..len).map(|i| (x >> (8 * i)) as u8).collect();
            let reference = stuffed_bits(id, &data, extended).0.len() as u32 + TRAILER_BITS;
            assert_eq!(frame_bits(id, &data, extended).unwrap(), reference, "id {id:#x} data {data:02X?}");
        }
    }

    #[test]
    fn crc15_known_value() {
        // CRC-15/CAN of the ASCII bytes "123456789" is 0x059E (the standard check value).
        let mut bits = Bits::default();
        for &c in b"123456789" {
            bits.push(c as u64, 8);
        }
        assert_eq!(crc15(&bits.0), 0x059E);
    }

    #[test]
    fn stuffing_worst_case_never_exceeded() {
        // The worst-case bound holds for every 1-byte payload of a few IDs, and is reached for some frame.
        for dlc in 0..=8u32 {
            let bound = worst_case_frame_bits(dlc, false);
            for id in [0u32, 0x0F0, 0x3C3, 0x555, 0x7FF] {
                for fill in [0x00u8, 0xFF, 0x0F, 0xF0, 0x3C, 0xAA] {
                    let data = vec![fill; dlc as usize];
                    assert!(frame_bits(id, &data, false).unwrap() <= bound);
                }
            }
        }
        assert_eq!(worst_case_frame_bits(8, false), 135);
        assert_eq!(worst_case_frame_bits(8, true), 160);
    }

    #[test]
    fn stuff_bit_starts_the_next_run() {
        // 0000011111: stuff after the 5 zeros (a 1), which starts a run of ones: 1 + 4 ones -> stuff again after 4.
        let s = stuff(&[0, 0, 0, 0, 0, 1, 1, 1, 1, 1]);
        assert_eq!(s.0, vec![0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 0, 1]);
    }

    #[test]
    fn bad_frames_are_refused() {
        assert!(matches!(frame_bits(0x800, &[], false), Err(FrameError::IdOutOfRange { .. })));
        assert!(frame_bits(0x800, &[], true).is_ok());
        assert!(matches!(frame_bits(1, &[0; 9], false), Err(FrameError::TooLong { .. })));
        let t = BitTiming::new(500_000, 500_000).unwrap();
        assert_eq!(t.frame_ns(0, &[], false, false, false).unwrap(), 53 * 2000);
        assert!(matches!(t.frame_ns(0, &[0; 9], false, true, true), Err(FrameError::NotAnFdLength { .. })));
        assert!(BitTiming::new(300_000, 300_000).is_none());
    }

    #[test]
    fn extended_header_layout() {
        let raw = unstuffed_bits(0x1234_5678 & 0x1FFF_FFFF, &[], true);
        assert_eq!(raw.0.len(), 39 + 15);
        assert_eq!(raw.0[12], 1); // SRR
        assert_eq!(raw.0[13], 1); // IDE
    }
}
