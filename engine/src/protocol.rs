//! The wire protocol between a bus server and its nodes, defined once: record kinds, sizes, flags, refusal reasons
//! and limits, the record codec, the check of a node's frame and python-can's filter rule. The server
//! (`server.rs`) and a node's end (`link.rs`) use them; Python takes them from the engine
//! (`trainhil_engine.PROTOCOL`, `frame_error`, `filters_accept`, read by `hil/runtime/realtime/protocol.py`), so
//! both sides agree by construction. The record layouts are described in that Python module's docstring.

use std::time::Duration;

use crate::bus::Format;

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
/// HELLO options: bit 1, a lazy reader. It reads its frames only at its read times (READ_EVERY), so the server
/// hands them over then, with a SYNC record, rather than at each frame's end; its FRAME records carry the epoch
/// second they were sent, and are queued at that instant.
pub const OPTION_LAZY: u8 = 0x02;
/// A lazy reader's read times: the first (epoch s, bytes 8..16) and the period (s, bytes 16..24; 0: once).
pub const KIND_READ_EVERY: u8 = 10;
/// Server to a lazy reader: every frame for it that ended by the epoch second in bytes 8..16 came before this.
pub const KIND_SYNC: u8 = 11;
/// A SYNC within this of a read time is that read time's: epoch seconds in an f64 resolve about 0.24 µs.
pub const SYNC_TOLERANCE_S: f64 = 1e-6;
/// Senders one connection may have (FRAME byte 3): a node process hosting several ECUs sends each one's frames as
/// its own sender, and the server keeps a bus node, with its own TX queue, per sender, as separate CAN
/// controllers would have. Sender 0 is the connection's own node.
pub const MAX_SENDERS: usize = 64;
/// Read schedules one lazy reader may hold at once.
pub const MAX_READ_SCHEDULES: usize = 256;
/// HELLO options: bit 2, a quiet lazy reader (with OPTION_LAZY). Its records do not wake the server, which reads
/// them at its next wake-up and queues its frames at the instants they carry; the node rings the server's bell (a
/// FIFO beside the socket, `<bus>.bell`) when the server must see a record now: a READ_EVERY, a frame the server
/// hands over at its end (BELL records say which), anything else it writes.
pub const OPTION_QUIET: u8 = 0x04;
/// Server to a quiet reader: which of its frames it rings the bell for. Byte 1: BELL_EVERY (every frame) and
/// BELL_RESET (this record starts a new set: forget the IDs before); byte 2: how many IDs follow (up to
/// BELL_IDS_PER_RECORD, u32 from byte 4).
pub const KIND_BELL: u8 = 12;
pub const BELL_EVERY: u8 = 0x01;
pub const BELL_RESET: u8 = 0x02;
pub const BELL_IDS_PER_RECORD: usize = 5;
/// READ_EVERY byte 1: its read times are the node's turns. After the SYNC of such a read time the node acts as at
/// that instant (its FRAME records carry it, however late it sends) and ends its turn with DONE; meanwhile the
/// server runs its bus (and the buses of its radio) no further than just before that read time, so the frames of
/// the turn compete at their instant as in virtual time. A turn not ended within TURN_HOLD_MAX_S of wall time
/// after its read time is let go (counted: `turn_overruns`) and the bus goes on. A server whose bus keeps falling
/// further behind the wall clock than that (`server::TURNS_BEHIND_MAX` turns let go at once within a second) gives
/// turns up for the rest of the run (`turns_given_up_s`): the read times go on as plain reads.
pub const READ_TURNS: u8 = 0x01;
/// Node to server, after its turn: it sends nothing more stamped before its next read time (bytes 8..16: the read
/// time of the turn, epoch s). Stamped +inf: its turns are over (its run ended); its read times go on as plain
/// reads, and no turn of it holds the bus any more.
pub const KIND_DONE: u8 = 13;
/// The longest a turn holds the bus, in wall seconds after its read time.
pub const TURN_HOLD_MAX_S: f64 = 0.002;
/// Node to server, before its first frame: every frame the connection sends carries at least byte 1 data bytes
/// (at most the bus's largest payload). The server refuses a shorter one (dropped and counted, as a frame the bus cannot carry) and,
/// on an idle bus, SYNCs at once every read time that no frame of any possible sender could end by: the least
/// frame of the fewest bytes any connection declared (none: an empty frame) is the bus's horizon.
pub const KIND_LEAST_DATA: u8 = 14;
/// Node to server, before its first frame: the name of its sender byte 1 on the bus (bytes 4.. as HELLO's, NAME_BYTES
/// of UTF-8, NUL-padded), in place of "<node>.<k>" (sender 0: the node's own bus node, named by HELLO until then). A
/// process that hosts several ECUs names each unit's TX queue as the unit's own controller is named.
pub const KIND_SENDER_NAME: u8 = 15;
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
        ("MATCH_EXTENDED", MATCH_EXTENDED as f64), ("OPTION_LAZY", OPTION_LAZY as f64),
        ("KIND_READ_EVERY", KIND_READ_EVERY as f64), ("KIND_SYNC", KIND_SYNC as f64),
        ("MAX_READ_SCHEDULES", MAX_READ_SCHEDULES as f64), ("OPTION_QUIET", OPTION_QUIET as f64),
        ("KIND_BELL", KIND_BELL as f64), ("BELL_EVERY", BELL_EVERY as f64), ("BELL_RESET", BELL_RESET as f64),
        ("BELL_IDS_PER_RECORD", BELL_IDS_PER_RECORD as f64), ("MAX_SENDERS", MAX_SENDERS as f64),
        ("READ_TURNS", READ_TURNS as f64), ("KIND_DONE", KIND_DONE as f64), ("TURN_HOLD_MAX_S", TURN_HOLD_MAX_S),
        ("KIND_LEAST_DATA", KIND_LEAST_DATA as f64), ("KIND_SENDER_NAME", KIND_SENDER_NAME as f64),
    ]
}

/// python-can acceptance filter: matches when (id ^ can_id) & can_mask == 0 and the format fits `matching`
/// (0 any, 1 standard only, 2 extended only).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Filter {
    pub can_id: u32,
    pub can_mask: u32,
    pub matching: u8,
}

pub fn filters_accept(filters: &Option<Vec<Filter>>, can_id: u32, extended: bool) -> bool {
    let Some(filters) = filters else { return true };
    filters.iter().any(|f| (f.matching == 0 || (f.matching == 2) == extended) && (can_id ^ f.can_id) & f.can_mask == 0)
}

/// The format a FRAME record's flags give.
pub fn record_format(flags: u8) -> Format {
    Format::of(flags & FLAG_FD != 0, flags & FLAG_BRS != 0)
}

/// The FRAME record flags of a transmission.
pub fn format_flags(format: Format) -> u8 {
    match format {
        Format::Classical => 0,
        Format::Fd => FLAG_FD,
        Format::FdBrs => FLAG_FD | FLAG_BRS,
    }
}

/// Why a frame from a node cannot go on the emulated bus (`fd_bus`: a CAN FD bus, which carries both formats).
pub fn frame_error(can_id: u32, dlc: u8, flags: u8, fd_bus: bool) -> Option<String> {
    if flags & !KNOWN_FLAGS != 0 {
        return Some(format!("flags {flags:#04x}: unknown flag bits"));
    }
    if flags & (FLAG_REMOTE | FLAG_ERROR | FLAG_ECHO) != 0 {
        return Some(format!("flags {flags:#04x}: only data frames can be sent (no remote, error or echo frames)"));
    }
    if flags & FLAG_BRS != 0 && flags & FLAG_FD == 0 {
        return Some(format!("flags {flags:#04x}: a bit-rate switch without the FD flag"));
    }
    if flags & FLAG_FD != 0 && !fd_bus {
        return Some("a CAN FD frame on a classical CAN bus".to_string());
    }
    if dlc > 8 && flags & FLAG_FD == 0 {
        return Some(format!("dlc {dlc} > 8 in a classical frame (set the FD flag for CAN FD payloads up to 64 bytes)"));
    }
    if dlc as usize > crate::frame::MAX_DATA || (dlc > 8 && crate::frame::fd_dlc(dlc as usize).is_none()) {
        return Some(format!("length {dlc} is not a CAN FD payload length (0..8, 12, 16, 20, 24, 32, 48, 64)"));
    }
    let extended = flags & FLAG_EXTENDED != 0;
    let limit = if extended { 1u32 << 29 } else { 1u32 << 11 };
    if can_id >= limit {
        return Some(format!("can_id {can_id:#x} out of range for a {}-bit identifier", if extended { 29 } else { 11 }));
    }
    None
}

/// A FRAME record as the server sends it: the first 8 data bytes (`dlc` says how many there are in all).
pub fn pack_frame(can_id: u32, data: &[u8], flags: u8, stamp: f64) -> [u8; RECORD_SIZE] {
    pack_frame_from(can_id, data, flags, stamp, 0)
}

/// A FRAME record from one of the connection's senders (see MAX_SENDERS).
pub fn pack_frame_from(can_id: u32, data: &[u8], flags: u8, stamp: f64, sender: u8) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_FRAME;
    r[1] = flags;
    r[2] = data.len() as u8;
    r[3] = sender;
    r[4..8].copy_from_slice(&can_id.to_le_bytes());
    r[8..16].copy_from_slice(&stamp.to_le_bytes());
    let head = data.len().min(8);
    r[16..16 + head].copy_from_slice(&data[..head]);
    r
}

/// A frame as records: its FRAME record, then FRAME_DATA records for a payload above 8 bytes.
pub fn pack_frame_records(can_id: u32, data: &[u8], flags: u8, stamp: f64, out: &mut Vec<u8>) {
    pack_frame_records_from(can_id, data, flags, stamp, 0, out);
}

/// `pack_frame_records` from one of the connection's senders (see MAX_SENDERS).
pub fn pack_frame_records_from(can_id: u32, data: &[u8], flags: u8, stamp: f64, sender: u8, out: &mut Vec<u8>) {
    out.extend_from_slice(&pack_frame_from(can_id, data, flags, stamp, sender));
    for chunk in data.get(8..).unwrap_or(&[]).chunks(FRAME_DATA_BYTES) {
        let mut r = [0u8; RECORD_SIZE];
        r[0] = KIND_FRAME_DATA;
        r[1..1 + chunk.len()].copy_from_slice(chunk);
        out.extend_from_slice(&r);
    }
}

/// How many FRAME_DATA records follow a FRAME record of `dlc` data bytes.
pub fn frame_data_records(dlc: usize) -> usize {
    dlc.saturating_sub(8).div_ceil(FRAME_DATA_BYTES)
}

/// The WELCOME record: the bitrate, the bus's epoch, the client's ID and, on a CAN FD bus, its data bitrate
/// (0: a classical bus).
pub fn pack_welcome(bitrate: u32, epoch0: f64, client_id: u32, fd_data_bitrate: u32) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_WELCOME;
    r[1] = PROTOCOL_VERSION;
    r[4..8].copy_from_slice(&bitrate.to_le_bytes());
    r[8..16].copy_from_slice(&epoch0.to_le_bytes());
    r[16..20].copy_from_slice(&client_id.to_le_bytes());
    r[20..24].copy_from_slice(&fd_data_bitrate.to_le_bytes());
    r
}

/// The record a refused connection gets before the server closes it.
pub fn pack_refused(why: u8) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_REFUSED;
    r[1] = why;
    r
}

pub fn pack_filters_ack(generation: u32) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_FILTERS_ACK;
    r[4..8].copy_from_slice(&generation.to_le_bytes());
    r
}

pub fn u32_at(r: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(r[at..at + 4].try_into().unwrap())
}

/// A lazy reader's READ_EVERY record: read at `first` (epoch s), then every `period` s (0: once); `turns`: each
/// read time is a turn (READ_TURNS).
pub fn pack_read_every(first: f64, period: f64, turns: bool) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_READ_EVERY;
    r[1] = if turns { READ_TURNS } else { 0 };
    r[8..16].copy_from_slice(&first.to_le_bytes());
    r[16..24].copy_from_slice(&period.to_le_bytes());
    r
}

/// The DONE record that ends a node's turn at read time `stamp` (epoch s).
pub fn pack_done(stamp: f64) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_DONE;
    r[8..16].copy_from_slice(&stamp.to_le_bytes());
    r
}

/// The LEAST_DATA record: every frame of this connection carries at least `bytes` data bytes.
pub fn pack_least_data(bytes: u8) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_LEAST_DATA;
    r[1] = bytes;
    r
}

/// The SENDER_NAME record: sender `sender`'s bus node is called `name` (at most NAME_BYTES of it, cut at a character).
pub fn pack_sender_name(sender: u8, name: &str) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_SENDER_NAME;
    r[1] = sender;
    let mut end = name.len().min(NAME_BYTES);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    r[4..4 + end].copy_from_slice(&name.as_bytes()[..end]);
    r
}

/// The SYNC record a lazy reader gets at its read time `stamp` (epoch s).
pub fn pack_sync(stamp: f64) -> [u8; RECORD_SIZE] {
    let mut r = [0u8; RECORD_SIZE];
    r[0] = KIND_SYNC;
    r[8..16].copy_from_slice(&stamp.to_le_bytes());
    r
}

/// The BELL records of a set: ring for every frame (`every`), else for the frames of `ids`.
pub fn pack_bell(every: bool, ids: &[u32]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut chunks: Vec<&[u32]> = ids.chunks(BELL_IDS_PER_RECORD).collect();
    if chunks.is_empty() {
        chunks.push(&[]);
    }
    for (k, chunk) in chunks.iter().enumerate() {
        let mut r = [0u8; RECORD_SIZE];
        r[0] = KIND_BELL;
        r[1] = if every { BELL_EVERY } else { 0 } | if k == 0 { BELL_RESET } else { 0 };
        r[2] = chunk.len() as u8;
        for (j, id) in chunk.iter().enumerate() {
            r[4 + 4 * j..8 + 4 * j].copy_from_slice(&id.to_le_bytes());
        }
        out.extend_from_slice(&r);
    }
    out
}

/// A quiet reader's view of when to ring its server's bell (the BELL records read so far): for every frame until
/// the server has said otherwise.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BellSet {
    pub every: bool,
    pub ids: std::collections::HashSet<u32>,
}

impl Default for BellSet {
    fn default() -> Self {
        BellSet { every: true, ids: Default::default() }
    }
}

impl BellSet {
    /// Take one BELL record in.
    pub fn apply(&mut self, r: &[u8]) {
        if r[1] & BELL_RESET != 0 {
            self.ids.clear();
            self.every = false;
        }
        self.every |= r[1] & BELL_EVERY != 0;
        for j in 0..(r[2] as usize).min(BELL_IDS_PER_RECORD) {
            self.ids.insert(u32_at(r, 4 + 4 * j));
        }
    }

    /// Whether a frame of `can_id` must ring the bell.
    pub fn rings(&self, can_id: u32) -> bool {
        self.every || self.ids.contains(&can_id)
    }
}

/// The f64 in bytes 8..16 of a record (a FRAME's stamp, a SYNC's or READ_EVERY's time).
pub fn stamp_of(r: &[u8]) -> f64 {
    f64::from_le_bytes(r[8..16].try_into().unwrap())
}

/// Reads the whole frames at the start of `buf`, a stream of records from a bus server, and calls
/// `each(can_id, flags, stamp, data)` for each; returns the bytes used. A SYNC record sets `synced` to its time;
/// once `synced` reaches `horizon` (a lazy reader's read time; an eager reader passes infinity), reading stops at
/// the next FRAME or SYNC. A BELL record goes into `bell` even then (a lazy connection that never reads still
/// learns which frames must ring); other records are skipped; a CAN FD frame whose FRAME_DATA records are not all
/// in `buf` yet waits.
pub fn read_frames(buf: &[u8], horizon: f64, synced: &mut f64, bell: &mut BellSet,
                   mut each: impl FnMut(u32, u8, f64, &[u8])) -> usize {
    let mut off = 0;
    let mut data = [0u8; MAX_FD_DLC];
    while off + RECORD_SIZE <= buf.len() {
        let r = &buf[off..off + RECORD_SIZE];
        let past_horizon = *synced >= horizon - SYNC_TOLERANCE_S;
        if past_horizon && (r[0] == KIND_FRAME || r[0] == KIND_SYNC) {
            break; // held back for a later read time; a BELL record is taken in at once
        }
        if r[0] != KIND_FRAME {
            if r[0] == KIND_SYNC {
                *synced = synced.max(stamp_of(r));
            } else if r[0] == KIND_BELL {
                bell.apply(r);
            }
            off += RECORD_SIZE; // FILTERS_ACK and the like: no frame
            continue;
        }
        let dlc = (r[2] as usize).min(MAX_FD_DLC);
        let extra = frame_data_records(dlc);
        if off + (1 + extra) * RECORD_SIZE > buf.len() {
            break; // the rest of a long frame is still on its way
        }
        let head = dlc.min(MAX_DLC);
        data[..head].copy_from_slice(&r[16..16 + head]);
        for k in 0..extra {
            let at = MAX_DLC + k * FRAME_DATA_BYTES;
            let take = (dlc - at).min(FRAME_DATA_BYTES);
            let rec = off + (1 + k) * RECORD_SIZE;
            data[at..at + take].copy_from_slice(&buf[rec + 1..rec + 1 + take]);
        }
        each(u32_at(r, 4), r[1], stamp_of(r), &data[..dlc]);
        off += (1 + extra) * RECORD_SIZE;
    }
    off
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
                     KIND_REFUSED, KIND_FRAME_DATA, KIND_READ_EVERY, KIND_SYNC, KIND_BELL, KIND_DONE, KIND_LEAST_DATA,
                     KIND_SENDER_NAME];
        let mut sorted = kinds.to_vec();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), kinds.len());
        let flags = [FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR, FLAG_ECHO, FLAG_FD, FLAG_BRS];
        assert_eq!(flags.iter().fold(0u8, |acc, f| { assert_eq!(acc & f, 0); acc | f }), KNOWN_FLAGS);
        assert_eq!(constants().len(), 48);
    }

    #[test]
    fn a_quiet_reader_rings_for_every_frame_until_bell_records_name_a_set_and_a_reset_replaces_it() {
        let mut bell = BellSet::default();
        assert!(bell.rings(0x123));
        let ids: Vec<u32> = (0x100..0x107).collect(); // two records: 5 and 2 IDs
        let stream = pack_bell(false, &ids);
        assert_eq!(stream.len(), 2 * RECORD_SIZE);
        let mut synced = f64::NEG_INFINITY;
        let used = read_frames(&stream, f64::INFINITY, &mut synced, &mut bell, |_, _, _, _| panic!("no frame"));
        assert_eq!(used, stream.len());
        assert!(bell.rings(0x100) && bell.rings(0x106) && !bell.rings(0x107) && !bell.rings(0x123));
        for r in pack_bell(true, &[]).chunks(RECORD_SIZE) {
            bell.apply(r);
        }
        assert!(bell.rings(0x123) && bell.ids.is_empty()); // every frame, the old set forgotten
        for r in pack_bell(false, &[0x7FF]).chunks(RECORD_SIZE) {
            bell.apply(r);
        }
        assert_eq!(bell, BellSet { every: false, ids: [0x7FF].into() });
    }

    #[test]
    fn python_can_filter_semantics() {
        let f = Some(vec![Filter { can_id: 0x100, can_mask: 0x7F0, matching: 1 }]);
        assert!(filters_accept(&f, 0x10F, false));
        assert!(!filters_accept(&f, 0x10F, true)); // standard only
        assert!(!filters_accept(&f, 0x110, false));
        assert!(filters_accept(&None, 0x123, true));
    }

    #[test]
    fn frames_the_bus_cannot_carry_are_named() {
        assert!(frame_error(0x800, 8, 0, false).unwrap().contains("11-bit"));
        assert!(frame_error(0x100, 9, 0, true).unwrap().contains("in a classical frame"));
        assert!(frame_error(0x100, 9, FLAG_FD, true).unwrap().contains("not a CAN FD payload length"));
        assert!(frame_error(0x100, 64, FLAG_FD, true).is_none());
        assert!(frame_error(0x100, 8, FLAG_REMOTE, false).is_some());
        assert!(frame_error(0x1FFF_FFFF, 8, FLAG_EXTENDED, false).is_none());
        assert!(frame_error(0x100, 8, FLAG_FD, false).unwrap().contains("classical CAN bus"));
        assert!(frame_error(0x100, 8, FLAG_BRS, true).unwrap().contains("without the FD flag"));
        assert!(frame_error(0x100, 8, FLAG_FD | FLAG_BRS, true).is_none());
        assert!(frame_error(0x100, 8, 0, true).is_none()); // a classical frame on an FD bus
        assert_eq!(record_format(FLAG_FD | FLAG_BRS | FLAG_EXTENDED), Format::FdBrs);
        assert_eq!(format_flags(record_format(FLAG_FD)), FLAG_FD);
    }

    #[test]
    fn frames_are_read_whole_from_a_stream_of_records() {
        let long: Vec<u8> = (0..64).collect();
        let mut stream = Vec::new();
        pack_frame_records(0x123, &[1, 2, 3], 0, 1.5, &mut stream);
        stream.extend_from_slice(&pack_filters_ack(7));
        pack_frame_records(0x1ABCDEF, &long, FLAG_FD | FLAG_BRS | FLAG_EXTENDED, 2.5, &mut stream);
        let mut seen = Vec::new();
        let mut synced = f64::NEG_INFINITY;
        // Everything but the last record: the long frame waits.
        let used = read_frames(&stream[..stream.len() - RECORD_SIZE], f64::INFINITY, &mut synced, &mut BellSet::default(),
                               |id, flags, t, d| seen.push((id, flags, t, d.to_vec())));
        assert_eq!(used, 2 * RECORD_SIZE);
        assert_eq!(seen, vec![(0x123, 0, 1.5, vec![1, 2, 3])]);
        let used = read_frames(&stream[used..], f64::INFINITY, &mut synced, &mut BellSet::default(), |id, flags, t, d| seen.push((id, flags, t, d.to_vec())));
        assert_eq!(used, MAX_FRAME_RECORDS * RECORD_SIZE);
        assert_eq!(seen[1], (0x1ABCDEF, FLAG_FD | FLAG_BRS | FLAG_EXTENDED, 2.5, long));
    }

    #[test]
    fn a_lazy_reader_reads_up_to_the_sync_of_its_read_time_and_no_further() {
        let mut stream = Vec::new();
        pack_frame_records(0x10, &[1], 0, 1.0, &mut stream);
        stream.extend_from_slice(&pack_sync(1.5));
        pack_frame_records(0x11, &[2], 0, 1.7, &mut stream);
        stream.extend_from_slice(&pack_sync(2.0));
        let (mut synced, mut seen) = (f64::NEG_INFINITY, Vec::new());
        let used = read_frames(&stream, 1.5, &mut synced, &mut BellSet::default(), |id, _, _, _| seen.push(id));
        assert_eq!((used, synced, seen.clone()), (2 * RECORD_SIZE, 1.5, vec![0x10]));
        assert_eq!(read_frames(&stream[used..], 1.5, &mut synced, &mut BellSet::default(), |id, _, _, _| seen.push(id)), 0); // reached
        let used = read_frames(&stream[used..], 2.0, &mut synced, &mut BellSet::default(), |id, _, _, _| seen.push(id));
        assert_eq!((used, synced, seen), (2 * RECORD_SIZE, 2.0, vec![0x10, 0x11]));
    }
}
