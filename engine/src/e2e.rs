//! End-to-end protection: CRC-8 SAE J1850 over a data ID and the payload, and the alive-counter check.
//!
//! AUTOSAR profile-1 style header: byte 0 is the CRC over [data ID] + bytes 1..end, the low nibble of
//! byte 1 is the 4-bit alive counter. Receivers classify every frame they read (`Status`).

const POLY: u8 = 0x1D;
const INIT: u8 = 0xFF;
const XOR_OUT: u8 = 0xFF;
pub const COUNTER_MODULO: u8 = 16;
pub const HEADER_BYTES: usize = 2;

const fn table() -> [u8; 256] {
    let mut t = [0u8; 256];
    let mut b = 0;
    while b < 256 {
        let mut crc = b as u8;
        let mut i = 0;
        while i < 8 {
            crc = if crc & 0x80 != 0 { (crc << 1) ^ POLY } else { crc << 1 };
            i += 1;
        }
        t[b] = crc;
        b += 1;
    }
    t
}

static TABLE: [u8; 256] = table();

/// CRC-8 SAE J1850 over [data_id] + payload[1..] (byte 0, the CRC slot itself, is skipped).
pub fn e2e_crc(data_id: u8, payload: &[u8]) -> u8 {
    let mut crc = TABLE[(INIT ^ data_id) as usize];
    for &byte in payload.iter().skip(1) {
        crc = TABLE[(crc ^ byte) as usize];
    }
    crc ^ XOR_OUT
}

/// The alive counter a frame carries (low nibble of byte 1); 0 for a frame too short to hold one.
pub fn counter_of(data: &[u8]) -> u8 {
    data.get(1).map_or(0, |b| b & (COUNTER_MODULO - 1))
}

/// Whether byte 0 of the frame is the CRC of the rest under `data_id`.
pub fn crc_ok(data_id: u8, data: &[u8]) -> bool {
    data.len() >= HEADER_BYTES && data[0] == e2e_crc(data_id, data)
}

/// Receiver verdict on one frame (AUTOSAR E2E profile-1 check status); the order is the Python enum's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Status {
    Ok = 0,
    Initial = 1,
    OkSomeLost = 2,
    Repeated = 3,
    WrongSequence = 4,
    CrcError = 5,
}

pub const STATUS_NAMES: [&str; 6] = ["OK", "INITIAL", "OK_SOME_LOST", "REPEATED", "WRONG_SEQUENCE", "CRC_ERROR"];

impl Status {
    /// Whether the application may use the frame's data.
    pub fn usable(self) -> bool {
        matches!(self, Status::Ok | Status::Initial | Status::OkSomeLost)
    }
}

/// Receiver-side check of one stream: CRC, then the alive-counter sequence (delta 1 OK, 0 REPEATED,
/// 2..max_delta+1 OK_SOME_LOST, larger WRONG_SEQUENCE, which becomes the new reference).
#[derive(Debug, Clone)]
pub struct Checker {
    pub data_id: u8,
    pub max_delta: u8,
    pub last_counter: Option<u8>,
    pub counts: [u64; 6],
    pub lost: u64,
    pub timeouts: u64,
}

impl Checker {
    pub fn new(data_id: u8, max_delta: u8) -> Checker {
        Checker { data_id, max_delta, last_counter: None, counts: [0; 6], lost: 0, timeouts: 0 }
    }

    /// Classify one frame (at least HEADER_BYTES long) and count the verdict.
    pub fn check(&mut self, data: &[u8]) -> Status {
        let status = self.classify(data);
        self.counts[status as usize] += 1;
        status
    }

    fn classify(&mut self, data: &[u8]) -> Status {
        if data[0] != e2e_crc(self.data_id, data) {
            return Status::CrcError;
        }
        let counter = data[1] & (COUNTER_MODULO - 1);
        let last = self.last_counter.replace(counter);
        let Some(last) = last else { return Status::Initial };
        let delta = (counter + COUNTER_MODULO - last) % COUNTER_MODULO;
        if delta == 1 {
            Status::Ok
        } else if delta == 0 {
            Status::Repeated
        } else if delta <= self.max_delta + 1 {
            self.lost += (delta - 1) as u64;
            Status::OkSomeLost
        } else {
            Status::WrongSequence
        }
    }

    /// Forget the sequence (the next valid frame is INITIAL); keeps the statistics.
    pub fn reset(&mut self) {
        self.last_counter = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_alive_counter_is_the_low_nibble_of_byte_1() {
        assert_eq!(counter_of(&[0x12, 0xA7, 0xFF]), 7);
        assert_eq!(counter_of(&[0x12, 0x0F]), 15);
        assert_eq!(counter_of(&[0x12]), 0); // too short to carry one
    }

    #[test]
    fn crc8_j1850_check_value() {
        // CRC-8/SAE-J1850 of "123456789" is 0x4B; here the first byte is the data ID and byte 0 of the payload is skipped.
        let payload = [0u8, b'2', b'3', b'4', b'5', b'6', b'7', b'8', b'9'];
        assert_eq!(e2e_crc(b'1', &payload), 0x4B);
    }

    fn frame(data_id: u8, counter: u8) -> [u8; 4] {
        let mut f = [0, counter, 0x12, 0x34];
        f[0] = e2e_crc(data_id, &f);
        f
    }

    #[test]
    fn sequence_classification() {
        let mut c = Checker::new(7, 2);
        assert_eq!(c.check(&frame(7, 3)), Status::Initial);
        assert_eq!(c.check(&frame(7, 4)), Status::Ok);
        assert_eq!(c.check(&frame(7, 4)), Status::Repeated);
        assert_eq!(c.check(&frame(7, 7)), Status::OkSomeLost);
        assert_eq!(c.lost, 2);
        assert_eq!(c.check(&frame(7, 15)), Status::WrongSequence);
        assert_eq!(c.check(&frame(7, 0)), Status::Ok); // wraps; the wrong-sequence frame became the reference
        assert_eq!(c.check(&frame(8, 1)), Status::CrcError); // wrong data ID
        assert_eq!(c.counts, [2, 1, 1, 1, 1, 1]);
    }
}
