//! CAN errors on one bus: corrupted frames the receivers reject, error frames, retransmission, fault confinement,
//! and the fault injectors that need the wire (babbling node, frame drops, error flags). The same model as
//! `tests/oracle/bus_errors.py`, the Python oracle (its docstring has the whole description), decision for decision and draw for draw:
//!
//! * ISO 11898-1 fault confinement per controller: REC +1 for a receiver that detects an error, TEC +8 for the
//!   transmitter of a destroyed frame, -1 on each success (a REC above 127 set back to 127); error passive at
//!   128, bus-off above 255 TEC, and back error active after 128 sequences of 11 recessive bits.
//! * A corrupted classical frame has bits flipped as the receivers sample them; they destuff and parse it bit by
//!   bit (`receive`) and find a stuff, form or CRC error where a CAN controller would, which decides when the
//!   error frame (taken at its longest: 23 bits) starts. A corruption they miss is delivered as decoded
//!   (`undetected`), for the E2E CRC to catch. A corrupted CAN FD frame fails its CRC after the ACK delimiter.
//! * A destroyed frame goes back to its sender's queue with its queueing time (automatic retransmission).
//!
//! Random draws come from numpy streams handed over by state (`rng::Pcg64`), each drawn as `random()`: the hit
//! test `u < p`, a position `floor(u * n)`, corrupted bits by a partial Fisher-Yates shuffle.
//! The bit-level receiver is `wire.rs`; the bus's error path (the hooks `bus` calls where the Python model calls
//! its `BusErrors`) is `bus/error_path.rs`.

use crate::bus::{Item, Payload};
use crate::rng::Pcg64;

pub const ERROR_PASSIVE_AT: u32 = 128;
pub const BUS_OFF_ABOVE: u32 = 255;
pub const RECOVERY_SEQUENCES: i64 = 128;
pub const RECESSIVE_SEQUENCE_BITS: u64 = 11;
/// Error flag with the others' superposed flags (12), error delimiter (8), intermission (3).
pub const ERROR_TAIL_BITS: u64 = 12 + 8 + 3;
/// The end of an FD frame after its ACK delimiter: EOF and intermission.
pub(crate) const FD_EOF_IFS_BITS: u32 = 7 + 3;
/// Error frames less than this apart are one episode (one summary event).
pub(crate) const EPISODE_GAP_NS: i64 = 100_000_000;

/// What destroyed a frame: what the receivers found, or an injected error flag.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum ErrorKind {
    Crc,
    ErrorFlag,
    Form,
    Stuff,
}

impl ErrorKind {
    pub fn name(self) -> &'static str {
        match self {
            ErrorKind::Crc => "crc",
            ErrorKind::ErrorFlag => "error flag",
            ErrorKind::Form => "form",
            ErrorKind::Stuff => "stuff",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorState {
    Active,
    Passive,
    BusOff,
}

impl ErrorState {
    pub fn name(self) -> &'static str {
        match self {
            ErrorState::Active => "error_active",
            ErrorState::Passive => "error_passive",
            ErrorState::BusOff => "bus_off",
        }
    }
}

/// TEC and REC of one controller and the fault-confinement state they give.
#[derive(Debug, Clone, Copy)]
pub struct ErrorCounters {
    pub tec: u32,
    pub rec: u32,
    pub state: ErrorState,
    pub tec_max: u32,
    pub rec_max: u32,
    pub passive_count: u32,
    pub bus_off_count: u32,
}

impl Default for ErrorCounters {
    fn default() -> Self {
        ErrorCounters { tec: 0, rec: 0, state: ErrorState::Active, tec_max: 0, rec_max: 0, passive_count: 0, bus_off_count: 0 }
    }
}

impl ErrorCounters {
    /// Rule 3: the node's own frame was destroyed. Returns the new state if it changed.
    pub fn tx_error(&mut self) -> Option<ErrorState> {
        self.tec += 8;
        self.tec_max = self.tec_max.max(self.tec);
        self.update()
    }

    /// Rule 1: the node detected an error as a receiver.
    pub fn rx_error(&mut self) -> Option<ErrorState> {
        self.rec += 1;
        self.rec_max = self.rec_max.max(self.rec);
        self.update()
    }

    pub fn tx_ok(&mut self) -> Option<ErrorState> {
        self.tec = self.tec.saturating_sub(1);
        self.update()
    }

    pub fn rx_ok(&mut self) -> Option<ErrorState> {
        self.rec = if self.rec > 127 { 127 } else { self.rec.saturating_sub(1) };
        self.update()
    }

    /// Bus-off recovery complete: error active with both counters at zero.
    pub fn recover(&mut self) -> Option<ErrorState> {
        self.tec = 0;
        self.rec = 0;
        let old = std::mem::replace(&mut self.state, ErrorState::Active);
        (old != ErrorState::Active).then_some(ErrorState::Active)
    }

    fn update(&mut self) -> Option<ErrorState> {
        if self.state == ErrorState::BusOff {
            return None; // only recover() leaves bus-off
        }
        let new = if self.tec > BUS_OFF_ABOVE {
            self.bus_off_count += 1;
            ErrorState::BusOff
        } else if self.tec >= ERROR_PASSIVE_AT || self.rec >= ERROR_PASSIVE_AT {
            ErrorState::Passive
        } else {
            ErrorState::Active
        };
        if new == self.state {
            return None;
        }
        if new == ErrorState::Passive {
            self.passive_count += 1;
        }
        self.state = new;
        Some(new)
    }
}

// ------------------------------------------------------------------------------------------------ injected effects

/// Which frames an effect hits: each with `probability`, only `frame_ids` if given, at most `count`.
#[derive(Debug, Clone)]
pub struct Selection {
    /// The fault it belongs to (to end it).
    pub fault: u64,
    pub rng: Pcg64,
    pub probability: f64,
    pub frame_ids: Option<Vec<u32>>,
    pub count: Option<u64>,
    pub hits: u64,
    /// Bits flipped per corrupted frame (corruptions only).
    pub bits: u32,
}

impl Selection {
    pub fn hit(&mut self, frame_id: u32) -> bool {
        if self.count.is_some_and(|c| self.hits >= c) {
            return false;
        }
        if self.frame_ids.as_ref().is_some_and(|ids| !ids.contains(&frame_id)) {
            return false;
        }
        if self.probability < 1.0 && self.rng.random() >= self.probability {
            return false;
        }
        self.hits += 1;
        true
    }
}

/// The kinds of selection effects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Effect {
    Corruption,
    ErrorFlags,
    Drops,
}

/// A node that keeps one frame of `frame_id` queued all the time: it wins every arbitration it can.
#[derive(Debug, Clone)]
pub struct Babbler {
    pub fault: u64,
    pub node: usize,
    pub frame_id: u32,
    pub data: Payload,
    pub extended: bool,
    pub sent: u64,
}

/// A corruption the receivers did not detect, delivered as they decoded it.
#[derive(Debug, Clone)]
pub struct Undetected {
    pub t_ns: u64,
    pub sent_id: u32,
    pub delivered_id: u32,
    pub delivered: Payload,
    pub sent: Payload,
    pub flipped: Vec<u32>,
}

/// The error model's counts (the keys of the Python model's `stats`, in its order).
#[derive(Debug, Default, Clone, Copy)]
pub struct ErrorStats {
    pub corrupted: u64,
    pub rejected: u64,
    pub undetected: u64,
    pub error_frames: u64,
    pub injected_error_flags: u64,
    pub retransmissions: u64,
    pub dropped_by_fault: u64,
    pub dropped_bus_off: u64,
    pub babbled: u64,
}

impl ErrorStats {
    pub fn items(&self) -> [(&'static str, u64); 9] {
        [("corrupted", self.corrupted), ("rejected", self.rejected), ("undetected", self.undetected),
         ("error_frames", self.error_frames), ("injected_error_flags", self.injected_error_flags),
         ("retransmissions", self.retransmissions), ("dropped_by_fault", self.dropped_by_fault),
         ("dropped_bus_off", self.dropped_bus_off), ("babbled", self.babbled)]
    }
}

/// What the error model and the guardian report, in bus time; the Python side words them.
#[derive(Debug, Clone, PartialEq)]
pub enum EventKind {
    /// A node's confinement state changed (error passive / active again).
    State { node: usize, state: ErrorState, tec: u32, rec: u32 },
    BusOff { node: usize, tec: u32, lost: u64 },
    Recovered { node: usize, after_ns: i64 },
    /// The first error frame of an episode.
    ErrorFrame { error: ErrorKind, frame_id: u32, node: usize },
    /// An episode closed: its error frames by kind.
    Episode { start_ns: i64, last_ns: i64, by_error: Vec<(ErrorKind, u64)> },
    /// The guardian flagged an ID (`allowance` None: not in the DBC).
    Babbling { frame_id: u32, frames: u32, busy_ns: u64, allowance: Option<u32> },
    Cleared { frame_id: u32 },
}

#[derive(Debug, Clone, PartialEq)]
pub struct BusEvent {
    pub t_ns: i64,
    pub kind: EventKind,
}

#[derive(Debug, Clone)]
pub(crate) struct Episode {
    pub(crate) start_ns: i64,
    pub(crate) last_ns: i64,
    pub(crate) by_error: Vec<(ErrorKind, u64)>,
}

pub(crate) fn count_kind(counts: &mut Vec<(ErrorKind, u64)>, kind: ErrorKind) {
    match counts.iter_mut().find(|(k, _)| *k == kind) {
        Some((_, n)) => *n += 1,
        None => counts.push((kind, 1)),
    }
}

/// The error model's state on one bus (see the module docs); `Bus::enable_errors` attaches it.
#[derive(Debug)]
pub struct BusErrors {
    pub(crate) rng: Pcg64,
    pub corruptions: Vec<Selection>,
    pub error_flags: Vec<Selection>,
    pub drops: Vec<Selection>,
    pub babblers: Vec<Babbler>,
    /// Per node index; `order` is the order they were first needed (the Python model's dict order).
    pub(crate) counters: Vec<Option<ErrorCounters>>,
    pub(crate) order: Vec<usize>,
    /// Nodes with REC > 0 (a success lowers only theirs), in the order they got there.
    pub(crate) receiving: Vec<usize>,
    pub stats: ErrorStats,
    /// Error frames by kind, in the order the kinds first occurred.
    pub by_error: Vec<(ErrorKind, u64)>,
    pub undetected: Vec<Undetected>,
    pub(crate) seq_ns: i64,
    /// End of the last dominant bit on the bus (start of the current recessive run).
    pub(crate) run_start: i64,
    /// Complete 11-bit recessive sequences in the runs that have ended.
    pub(crate) sequences: i64,
    /// Bus-off nodes: (node, sequences at bus-off, time it went bus-off), in the order they went.
    pub(crate) bus_off: Vec<(usize, i64, i64)>,
    pub(crate) bus_off_ns: Vec<i64>,
    /// The queue entry of the transmission on the wire (put back when the frame is destroyed).
    pub(crate) item: Option<Item>,
    pub(crate) episode: Option<Episode>,
}

impl BusErrors {
    pub fn new(rng: Pcg64, bit_ns: u64) -> BusErrors {
        BusErrors {
            rng, corruptions: Vec::new(), error_flags: Vec::new(), drops: Vec::new(), babblers: Vec::new(),
            counters: Vec::new(), order: Vec::new(), receiving: Vec::new(), stats: ErrorStats::default(),
            by_error: Vec::new(), undetected: Vec::new(), seq_ns: (RECESSIVE_SEQUENCE_BITS * bit_ns) as i64, run_start: 0,
            sequences: 0, bus_off: Vec::new(), bus_off_ns: Vec::new(), item: None, episode: None,
        }
    }

    pub fn counters_of(&mut self, node: usize) -> &mut ErrorCounters {
        if self.counters.len() <= node {
            self.counters.resize(node + 1, None);
        }
        if self.counters[node].is_none() {
            self.counters[node] = Some(ErrorCounters::default());
            self.order.push(node);
        }
        self.counters[node].as_mut().unwrap()
    }

    pub fn counters(&self, node: usize) -> Option<&ErrorCounters> {
        self.counters.get(node).and_then(|c| c.as_ref())
    }

    /// Nodes with counters that ever moved, in order: (node, counters, time spent bus-off in ns).
    pub fn nodes(&self) -> Vec<(usize, ErrorCounters, i64)> {
        self.order.iter().filter_map(|&n| {
            let c = self.counters[n]?;
            (c.tec_max > 0 || c.rec_max > 0).then(|| (n, c, self.bus_off_ns.get(n).copied().unwrap_or(0)))
        }).collect()
    }

    pub(crate) fn add_bus_off_ns(&mut self, node: usize, ns: i64) {
        if self.bus_off_ns.len() <= node {
            self.bus_off_ns.resize(node + 1, 0);
        }
        self.bus_off_ns[node] += ns;
    }

    /// The list a selection effect lives in.
    pub fn effects(&mut self, effect: Effect) -> &mut Vec<Selection> {
        match effect {
            Effect::Corruption => &mut self.corruptions,
            Effect::ErrorFlags => &mut self.error_flags,
            Effect::Drops => &mut self.drops,
        }
    }

    /// End a fault's effect (a selection or a babbler); returns the babbler's node if it was one.
    pub fn remove_fault(&mut self, fault: u64) -> Option<usize> {
        for list in [&mut self.corruptions, &mut self.error_flags, &mut self.drops] {
            list.retain(|s| s.fault != fault);
        }
        let at = self.babblers.iter().position(|b| b.fault == fault)?;
        Some(self.babblers.remove(at).node)
    }
}

// ------------------------------------------------------------------------------------------------ the hooks
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counters_follow_the_confinement_rules() {
        let mut c = ErrorCounters::default();
        for _ in 0..15 {
            assert_eq!(c.tx_error(), None);
        }
        assert_eq!(c.tx_error(), Some(ErrorState::Passive)); // TEC 128
        for _ in 0..15 {
            c.tx_error();
        }
        assert_eq!(c.tec, 248);
        assert_eq!(c.tx_error(), Some(ErrorState::BusOff)); // 256 > 255
        assert_eq!(c.tx_ok(), None); // only recovery leaves bus-off
        assert_eq!(c.recover(), Some(ErrorState::Active));
        assert_eq!((c.tec, c.rec, c.passive_count, c.bus_off_count), (0, 0, 1, 1));
        c.rec = 140;
        c.rx_ok();
        assert_eq!(c.rec, 127);
    }
}
