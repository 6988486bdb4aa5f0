//! The wire protocol between a bus server and its nodes, defined once: record kinds, sizes, flags, refusal reasons
//! and limits. The server (`server.rs`) and the node-side `FrameLink` (`py.rs`) use them; Python takes them from
//! the engine (`trainhil_engine.PROTOCOL`, read by `hil/runtime/realtime/protocol.py`), so both sides agree by
//! construction. The record layouts are described in that Python module's docstring.

use std::time::Duration;

pub const RECORD_SIZE: usize = 24;
pub const PROTOCOL_VERSION: u8 = 1;
pub const KIND_FRAME: u8 = 1;
pub const KIND_HELLO: u8 = 2;
pub const KIND_WELCOME: u8 = 3;
pub const KIND_FILTERS: u8 = 4;
pub const KIND_FILTER: u8 = 5;
pub const KIND_FILTERS_ACK: u8 = 6;
pub const KIND_AUTH: u8 = 7;
pub const KIND_REFUSED: u8 = 8;
/// The rest of a CAN FD payload above 8 bytes: byte 0 the kind, then 23 payload bytes (the FRAME record carries the
/// first 8). A 64-byte payload is a FRAME and 3 FRAME_DATA records.
pub const KIND_FRAME_DATA: u8 = 9;
pub const FRAME_DATA_BYTES: usize = RECORD_SIZE - 1;
/// The records of the longest frame: FRAME and 3 FRAME_DATA.
pub const MAX_FRAME_RECORDS: usize = 4;
/// Why a connection was refused (byte 1 of a REFUSED record; the client says it in its error).
pub const REFUSED_FULL: u8 = 1;
pub const REFUSED_TOKEN: u8 = 2;
pub const REFUSED_WAITING: u8 = 3;
pub const REFUSED_TIMEOUT: u8 = 4;
/// TCP connections that have not shown the token yet: their own small budget and a short deadline, so that they
/// can never take the slots of authenticated or unix-socket nodes (``max_clients``).
pub const MAX_UNAUTHENTICATED: usize = 16;
pub const AUTH_TIMEOUT: Duration = Duration::from_secs(1);
pub const FLAG_EXTENDED: u8 = 0x01;
pub const FLAG_REMOTE: u8 = 0x02;
pub const FLAG_ERROR: u8 = 0x04;
pub const FLAG_ECHO: u8 = 0x08;
/// A CAN FD frame (FDF set); with FLAG_BRS its data phase runs at the bus's data bitrate.
pub const FLAG_FD: u8 = 0x10;
pub const FLAG_BRS: u8 = 0x20;
pub const KNOWN_FLAGS: u8 = FLAG_EXTENDED | FLAG_REMOTE | FLAG_ERROR | FLAG_ECHO | FLAG_FD | FLAG_BRS;
pub const MAX_FILTERS: usize = 1024;
/// Bytes of a node's name in HELLO (UTF-8, NUL-padded).
pub const NAME_BYTES: usize = 20;
/// Data bytes a FRAME record carries itself (and a classical frame's most).
pub const MAX_DLC: usize = 8;
/// The longest CAN FD payload.
pub const MAX_FD_DLC: usize = 64;
/// The run's token (AUTH, TCP only).
pub const TOKEN_BYTES: usize = 16;
/// HELLO options: bit 0, the node hears its own frames back.
pub const OPTION_RECEIVE_OWN: u8 = 0x01;
/// A FILTER's format match: any, standard IDs only, extended IDs only.
pub const MATCH_ANY: u8 = 0;
pub const MATCH_STANDARD: u8 = 1;
pub const MATCH_EXTENDED: u8 = 2;

/// Every constant by its name, as Python sees them (`trainhil_engine.PROTOCOL`).
pub fn constants() -> Vec<(&'static str, f64)> {
    vec![
        ("PROTOCOL_VERSION", PROTOCOL_VERSION as f64), ("RECORD_SIZE", RECORD_SIZE as f64),
        ("NAME_BYTES", NAME_BYTES as f64), ("MAX_DLC", MAX_DLC as f64), ("MAX_FD_DLC", MAX_FD_DLC as f64),
        ("MAX_FILTERS", MAX_FILTERS as f64), ("TOKEN_BYTES", TOKEN_BYTES as f64),
        ("KIND_FRAME", KIND_FRAME as f64), ("KIND_HELLO", KIND_HELLO as f64), ("KIND_WELCOME", KIND_WELCOME as f64),
        ("KIND_FILTERS", KIND_FILTERS as f64), ("KIND_FILTER", KIND_FILTER as f64),
        ("KIND_FILTERS_ACK", KIND_FILTERS_ACK as f64), ("KIND_AUTH", KIND_AUTH as f64),
        ("KIND_REFUSED", KIND_REFUSED as f64), ("KIND_FRAME_DATA", KIND_FRAME_DATA as f64),
        ("FRAME_DATA_BYTES", FRAME_DATA_BYTES as f64),
        ("REFUSED_FULL", REFUSED_FULL as f64), ("REFUSED_TOKEN", REFUSED_TOKEN as f64),
        ("REFUSED_WAITING", REFUSED_WAITING as f64), ("REFUSED_TIMEOUT", REFUSED_TIMEOUT as f64),
        ("MAX_UNAUTHENTICATED", MAX_UNAUTHENTICATED as f64), ("AUTH_TIMEOUT_S", AUTH_TIMEOUT.as_secs_f64()),
        ("FLAG_EXTENDED", FLAG_EXTENDED as f64), ("FLAG_REMOTE", FLAG_REMOTE as f64),
        ("FLAG_ERROR", FLAG_ERROR as f64), ("FLAG_ECHO", FLAG_ECHO as f64), ("FLAG_FD", FLAG_FD as f64),
        ("FLAG_BRS", FLAG_BRS as f64), ("OPTION_RECEIVE_OWN", OPTION_RECEIVE_OWN as f64),
        ("MATCH_ANY", MATCH_ANY as f64), ("MATCH_STANDARD", MATCH_STANDARD as f64),
        ("MATCH_EXTENDED", MATCH_EXTENDED as f64),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_payload_fits_a_frame_and_its_frame_data_records() {
        assert_eq!(FRAME_DATA_BYTES, RECORD_SIZE - 1);
        assert!(MAX_DLC + (MAX_FRAME_RECORDS - 1) * FRAME_DATA_BYTES >= MAX_FD_DLC);
        assert!(MAX_DLC + (MAX_FRAME_RECORDS - 2) * FRAME_DATA_BYTES < MAX_FD_DLC);
    }

    #[test]
    fn kinds_and_flags_are_distinct() {
        let kinds = [KIND_FRAME, KIND_HELLO, KIND_WELCOME, KIND_FILTERS, KIND_FILTER, KIND_FILTERS_ACK, KIND_AUTH,
                     KIND_REFUSED, KIND_FRAME_DATA];
        let mut sorted = kinds.to_vec();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), kinds.len());
        let flags = [FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR, FLAG_ECHO, FLAG_FD, FLAG_BRS];
        assert_eq!(flags.iter().fold(0u8, |acc, f| { assert_eq!(acc & f, 0); acc | f }), KNOWN_FLAGS);
        assert_eq!(constants().len(), 33);
    }
}
