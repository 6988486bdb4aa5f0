//! The DBC frame codec: one compiled message layout (shifts, masks, scaling, raw limits), taken from cantools
//! at load time. Encoding saturates out-of-range values to the signal's raw limits and counts it (never wraps);
//! NaN is an error that names the signal. Decoding never checks the E2E header (receivers do).

use crate::e2e;
use crate::frame::MAX_DATA;

/// One little-endian (Intel) integer signal, as compiled from the DBC.
#[derive(Debug, Clone)]
pub struct SignalSpec {
    pub name: String,
    pub start: u32,
    pub length: u32,
    pub signed: bool,
    pub scale: f64,
    pub offset: f64,
    pub raw_min: i64,
    pub raw_max: i64,
}

/// Why a message cannot be encoded.
#[derive(Debug, Clone, PartialEq)]
pub enum CodecError {
    Nan { message: String, signal: String },
    Arity { message: String, expected: usize, got: usize },
    Counter { message: String, counter: i64 },
    Length { message: String, dlc: usize, got: usize },
}

impl std::fmt::Display for CodecError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CodecError::Nan { message, signal } => write!(f, "{message}.{signal}: cannot encode NaN"),
            CodecError::Arity { message, expected, got } => write!(f, "{message}: expected {expected} values, got {got}"),
            CodecError::Counter { message, counter } => write!(f, "{message}: alive counter {counter} is not in 0..15"),
            CodecError::Length { message, dlc, got } => write!(f, "{message}: frame has {got} bytes, DLC is {dlc}"),
        }
    }
}

/// A message layout: ID, DLC, E2E data ID and its payload signals (in start-bit order).
#[derive(Debug, Clone)]
pub struct MessageLayout {
    pub name: String,
    pub frame_id: u32,
    pub dlc: usize,
    pub data_id: u8,
    pub signals: Vec<SignalSpec>,
}

fn put_bits(buf: &mut [u8], start: u32, length: u32, raw: u64) {
    let mut value = if length == 64 { raw } else { raw & ((1u64 << length) - 1) };
    let (mut bit, mut left) = (start, length);
    while left > 0 {
        let byte = (bit / 8) as usize;
        let off = bit % 8;
        let take = (8 - off).min(left);
        let mask = (((1u16 << take) - 1) as u8) << off;
        buf[byte] = (buf[byte] & !mask) | (((value as u8) << off) & mask);
        value >>= take;
        bit += take;
        left -= take;
    }
}

fn get_bits(buf: &[u8], start: u32, length: u32) -> u64 {
    let (mut bit, mut left, mut shift, mut out) = (start, length, 0u32, 0u64);
    while left > 0 {
        let byte = (bit / 8) as usize;
        let off = bit % 8;
        let take = (8 - off).min(left);
        let chunk = ((buf[byte] >> off) as u64) & ((1u64 << take) - 1);
        out |= chunk << shift;
        shift += take;
        bit += take;
        left -= take;
    }
    out
}

impl MessageLayout {
    /// Physical values (in signal order) -> frame bytes with the alive counter and the E2E CRC.
    /// `saturations[i]` counts the values of signal i clipped to its range (beyond half an LSB).
    pub fn encode(&self, values: &[f64], counter: i64, saturations: &mut [u64], out: &mut [u8; MAX_DATA]) -> Result<usize, CodecError> {
        if values.len() != self.signals.len() {
            return Err(CodecError::Arity { message: self.name.clone(), expected: self.signals.len(), got: values.len() });
        }
        if !(0..16).contains(&counter) {
            return Err(CodecError::Counter { message: self.name.clone(), counter });
        }
        let dlc = self.dlc;
        out[..dlc].fill(0);
        out[1] = counter as u8;
        for (i, (s, &value)) in self.signals.iter().zip(values).enumerate() {
            let x = (value - s.offset) / s.scale;
            let (lo, hi) = (s.raw_min as f64, s.raw_max as f64);
            let raw = if lo <= x && x <= hi {
                x.round_ties_even() as i64 // Python's round(): ties to even
            } else {
                if x.is_nan() {
                    return Err(CodecError::Nan { message: self.name.clone(), signal: s.name.clone() });
                }
                if x > hi + 0.5 || x < lo - 0.5 {
                    saturations[i] += 1; // within half an LSB it is quantisation, not saturation
                }
                if x > hi { s.raw_max } else { s.raw_min }
            };
            put_bits(&mut out[..dlc], s.start, s.length, raw as u64);
        }
        out[0] = e2e::e2e_crc(self.data_id, &out[..dlc]);
        Ok(dlc)
    }

    /// Frame bytes -> physical values in signal order (E2E header not checked).
    pub fn decode_into(&self, data: &[u8], out: &mut Vec<f64>) -> Result<(), CodecError> {
        if data.len() != self.dlc {
            return Err(CodecError::Length { message: self.name.clone(), dlc: self.dlc, got: data.len() });
        }
        out.clear();
        for s in &self.signals {
            let mut raw = get_bits(data, s.start, s.length) as i64;
            if s.signed && s.length < 64 && raw & (1i64 << (s.length - 1)) != 0 {
                raw -= 1i64 << s.length;
            }
            out.push(raw as f64 * s.scale + s.offset);
        }
        Ok(())
    }

    /// The first signal's physical value, if the frame has this message's length (the radio's position decoder).
    pub fn first_value(&self, data: &[u8]) -> Option<f64> {
        let s = self.signals.first()?;
        if data.len() != self.dlc {
            return None;
        }
        let mut raw = get_bits(data, s.start, s.length) as i64;
        if s.signed && s.length < 64 && raw & (1i64 << (s.length - 1)) != 0 {
            raw -= 1i64 << s.length;
        }
        Some(raw as f64 * s.scale + s.offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> MessageLayout {
        MessageLayout {
            name: "Sensor_U01".into(),
            frame_id: 0xC0,
            dlc: 8,
            data_id: 0x40,
            signals: vec![
                SignalSpec { name: "Position".into(), start: 12, length: 32, signed: false, scale: 0.001, offset: 0.0, raw_min: 0, raw_max: (1 << 32) - 1 },
                SignalSpec { name: "Speed".into(), start: 44, length: 20, signed: true, scale: 0.0005, offset: 0.0, raw_min: -(1 << 19), raw_max: (1 << 19) - 1 },
            ],
        }
    }

    #[test]
    fn round_trip_and_header() {
        let m = layout();
        let mut sat = [0u64; 2];
        let mut out = [0u8; MAX_DATA];
        let n = m.encode(&[108_800.001, -12.3455], 5, &mut sat, &mut out).unwrap();
        assert_eq!(n, 8);
        assert_eq!(out[1] & 0xF, 5);
        assert!(e2e::crc_ok(0x40, &out[..8]));
        let mut v = Vec::new();
        m.decode_into(&out[..8], &mut v).unwrap();
        assert!((v[0] - 108_800.001).abs() < 1e-6);
        assert!((v[1] + 12.3455).abs() < 1e-9);
        assert_eq!(sat, [0, 0]);
    }

    #[test]
    fn saturates_and_counts_never_wraps() {
        let m = layout();
        let mut sat = [0u64; 2];
        let mut out = [0u8; MAX_DATA];
        m.encode(&[-5.0, 1e9], 0, &mut sat, &mut out).unwrap();
        let mut v = Vec::new();
        m.decode_into(&out[..8], &mut v).unwrap();
        assert_eq!(v[0], 0.0);
        assert!((v[1] - ((1 << 19) - 1) as f64 * 0.0005).abs() < 1e-9);
        assert_eq!(sat, [1, 1]);
        let err = m.encode(&[f64::NAN, 0.0], 0, &mut sat, &mut out).unwrap_err();
        assert_eq!(err.to_string(), "Sensor_U01.Position: cannot encode NaN");
    }

    #[test]
    fn ties_round_to_even_like_python() {
        let mut m = layout();
        m.signals[1].scale = 1.0;
        let mut sat = [0u64; 2];
        let mut out = [0u8; MAX_DATA];
        let mut v = Vec::new();
        m.encode(&[0.0, 2.5], 0, &mut sat, &mut out).unwrap();
        m.decode_into(&out[..8], &mut v).unwrap();
        assert_eq!(v[1], 2.0);
        m.encode(&[0.0, -3.5], 0, &mut sat, &mut out).unwrap();
        m.decode_into(&out[..8], &mut v).unwrap();
        assert_eq!(v[1], -4.0);
    }
}
