//! A classical CAN frame on the wire, bit by bit, as the error model corrupts it and the receivers read it:
//! the sent bits, flipped bits, and a receiver that destuffs and parses them and finds a stuff, form or CRC error
//! where a CAN controller would.

use crate::errors::ErrorKind;
use crate::frame::stuffed_bits;
use crate::rng::Pcg64;

/// A classical data frame as sent, SOF to the end of EOF: stuffed SOF..CRC, CRC delimiter, ACK slot (dominant, as
/// the receivers drive it), ACK delimiter, 7 EOF bits. `len - 10` is the index of the CRC delimiter.
pub fn wire_bits(can_id: u32, data: &[u8], extended: bool) -> Vec<u8> {
    let mut bits = stuffed_bits(can_id, data, extended).0;
    bits.extend_from_slice(&[1, 0, 1, 1, 1, 1, 1, 1, 1, 1]);
    bits
}

/// What the receivers made of a frame: `error` (None: accepted) found at bit `at` (the error frame starts at
/// `at + 1`); an accepted frame's ID, format and data as they decoded them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reception {
    pub error: Option<ErrorKind>,
    pub at: u32,
    pub can_id: u32,
    pub extended: bool,
    pub data: Vec<u8>,
}

fn int(bits: &[u8]) -> u32 {
    bits.iter().fold(0, |v, &b| (v << 1) | b as u32)
}

/// A receiver's destuffing automaton over the wire (bits beyond it read recessive: an idle bus).
struct Destuffer<'a> {
    wire: &'a [u8],
    pos: usize,
    last: u8,
    run: u32,
    out: Vec<u8>,
}

impl Destuffer<'_> {
    fn bit(&self, at: usize) -> u8 {
        self.wire.get(at).copied().unwrap_or(1)
    }

    /// Read `count` data bits, checking every stuff bit; Err(position) at a stuff error.
    fn take(&mut self, mut count: usize) -> Result<(), u32> {
        while count > 0 {
            let bit = self.bit(self.pos);
            if self.run == 5 {
                if bit == self.last {
                    return Err(self.pos as u32);
                }
                self.last = bit;
                self.run = 1;
                self.pos += 1;
                continue;
            }
            self.run = if bit == self.last { self.run + 1 } else { 1 };
            self.last = bit;
            self.out.push(bit);
            self.pos += 1;
            count -= 1;
        }
        Ok(())
    }
}

/// Decode a frame as a CAN receiver does: destuff and check the stuffing, parse the header to know the length,
/// check the CRC-15 and the fixed-form delimiters.
pub fn receive(wire: &[u8]) -> Reception {
    let mut d = Destuffer { wire, pos: 1, last: 0, run: 1, out: vec![0] }; // SOF (dominant) already read
    let fail = |error, at| Reception { error: Some(error), at, can_id: 0, extended: false, data: Vec::new() };
    let parsed = (|| {
        d.take(13)?; // 11 ID bits, RTR/SRR, IDE
        let extended = d.out[13] == 1;
        d.take(if extended { 18 + 3 } else { 1 })?;
        d.take(4)?;
        let n = d.out.len();
        let dlc = int(&d.out[n - 4..]);
        let rtr = if extended { d.out[n - 7] } else { d.out[12] };
        let nbytes = if rtr == 1 { 0 } else { dlc.min(8) as usize };
        d.take(8 * nbytes)?;
        let body = d.out.len();
        d.take(15)?;
        if d.run == 5 {
            // a stuff bit follows five equal CRC bits
            if d.bit(d.pos) == d.last {
                return Err(d.pos as u32);
            }
            d.pos += 1;
        }
        Ok((extended, nbytes, body))
    })();
    let (extended, nbytes, body) = match parsed {
        Ok(p) => p,
        Err(at) => return fail(ErrorKind::Stuff, at),
    };
    let pos = d.pos;
    if d.bit(pos) == 0 {
        return fail(ErrorKind::Form, pos as u32); // the CRC delimiter must be recessive
    }
    if d.bit(pos + 2) == 0 {
        return fail(ErrorKind::Form, pos as u32 + 2); // the ACK delimiter too
    }
    let out = &d.out;
    if crate::frame::crc15(&out[..body]) as u32 != int(&out[body..body + 15]) {
        return fail(ErrorKind::Crc, pos as u32 + 2); // signalled from the bit after the ACK delimiter
    }
    let payload = &out[body - 8 * nbytes..body];
    let data = payload.chunks(8).map(|b| int(b) as u8).collect();
    let can_id = if extended { (int(&out[1..12]) << 18) | int(&out[14..32]) } else { int(&out[1..12]) };
    Reception { error: None, at: pos as u32 + 2, can_id, extended, data }
}

/// The wire with the bits at `positions` flipped.
pub fn corrupt(wire: &[u8], positions: &[u32]) -> Vec<u8> {
    let mut out = wire.to_vec();
    for &p in positions {
        out[p as usize] ^= 1;
    }
    out
}

/// `k` distinct positions of 1..=span, sorted: a partial Fisher-Yates shuffle, one `random()` per position.
pub fn pick_positions(rng: &mut Pcg64, span: u32, k: u32) -> Vec<u32> {
    let mut pool: Vec<u32> = (1..=span).collect();
    let k = k.min(span) as usize;
    for i in 0..k {
        let j = i + rng.below(span - i as u32) as usize;
        pool.swap(i, j);
    }
    let mut picked = pool[..k].to_vec();
    picked.sort_unstable();
    picked
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_intact_frame_is_received_as_sent() {
        for (id, data, ext) in [(0x123, vec![1u8, 2, 3], false), (0x1ABC_DE01, vec![0; 8], true), (0, vec![], false)] {
            let r = receive(&wire_bits(id, &data, ext));
            assert_eq!(r, Reception { error: None, at: wire_bits(id, &data, ext).len() as u32 - 8, can_id: id, extended: ext, data });
        }
    }

    #[test]
    fn six_equal_bits_are_a_stuff_error_and_a_dominant_delimiter_a_form_error() {
        let wire = wire_bits(0, &[], false); // SOF and 4 ID bits are 5 zeros: a stuff bit (1) at index 5
        assert_eq!(wire[5], 1);
        assert_eq!(receive(&corrupt(&wire, &[5])), Reception { error: Some(ErrorKind::Stuff), at: 5, can_id: 0, extended: false,
                                                              data: vec![] });
        let wire = wire_bits(0x155, &[0x55], false);
        let crc_delimiter = wire.len() as u32 - 10;
        let r = receive(&corrupt(&wire, &[crc_delimiter]));
        assert_eq!((r.error, r.at), (Some(ErrorKind::Form), crc_delimiter));
        let r = receive(&corrupt(&wire, &[crc_delimiter + 2])); // the ACK delimiter
        assert_eq!((r.error, r.at), (Some(ErrorKind::Form), crc_delimiter + 2));
    }

    #[test]
    fn a_flipped_data_bit_is_a_crc_error_signalled_after_the_ack_delimiter() {
        let wire = wire_bits(0x155, &[0x55], false); // alternating bits: no stuff bits near the data
        let r = receive(&corrupt(&wire, &[20]));
        assert_eq!(r.error, Some(ErrorKind::Crc));
        assert_eq!(r.at as usize, wire.len() - 8);
    }

    #[test]
    fn positions_are_distinct_and_sorted() {
        let mut g = Pcg64::from_state(1, 3);
        let p = pick_positions(&mut g, 10, 10);
        assert_eq!(p, (1..=10).collect::<Vec<_>>());
        let p = pick_positions(&mut g, 100, 5);
        assert!(p.windows(2).all(|w| w[0] < w[1]) && p.iter().all(|&x| (1..=100).contains(&x)));
    }
}
