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
//! The hooks are `Bus` methods called by `bus.rs` where the Python model calls its `BusErrors`.

use crate::bus::{Bus, Item, Payload, Transmission};
use crate::frame::{fd_frame_bits, stuffed_bits, FD_TAIL_BITS};
use crate::rng::Pcg64;

pub const ERROR_PASSIVE_AT: u32 = 128;
pub const BUS_OFF_ABOVE: u32 = 255;
pub const RECOVERY_SEQUENCES: i64 = 128;
pub const RECESSIVE_SEQUENCE_BITS: u64 = 11;
/// Error flag with the others' superposed flags (12), error delimiter (8), intermission (3).
pub const ERROR_TAIL_BITS: u64 = 12 + 8 + 3;
/// The end of an FD frame after its ACK delimiter: EOF and intermission.
const FD_EOF_IFS_BITS: u32 = 7 + 3;
/// Error frames less than this apart are one episode (one summary event).
const EPISODE_GAP_NS: i64 = 100_000_000;

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

// ------------------------------------------------------------------------------------------------ the wire

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
struct Episode {
    start_ns: i64,
    last_ns: i64,
    by_error: Vec<(ErrorKind, u64)>,
}

fn count_kind(counts: &mut Vec<(ErrorKind, u64)>, kind: ErrorKind) {
    match counts.iter_mut().find(|(k, _)| *k == kind) {
        Some((_, n)) => *n += 1,
        None => counts.push((kind, 1)),
    }
}

/// The error model's state on one bus (see the module docs); `Bus::enable_errors` attaches it.
#[derive(Debug)]
pub struct BusErrors {
    rng: Pcg64,
    pub corruptions: Vec<Selection>,
    pub error_flags: Vec<Selection>,
    pub drops: Vec<Selection>,
    pub babblers: Vec<Babbler>,
    /// Per node index; `order` is the order they were first needed (the Python model's dict order).
    counters: Vec<Option<ErrorCounters>>,
    order: Vec<usize>,
    /// Nodes with REC > 0 (a success lowers only theirs), in the order they got there.
    receiving: Vec<usize>,
    pub stats: ErrorStats,
    /// Error frames by kind, in the order the kinds first occurred.
    pub by_error: Vec<(ErrorKind, u64)>,
    pub undetected: Vec<Undetected>,
    seq_ns: i64,
    /// End of the last dominant bit on the bus (start of the current recessive run).
    run_start: i64,
    /// Complete 11-bit recessive sequences in the runs that have ended.
    sequences: i64,
    /// Bus-off nodes: (node, sequences at bus-off, time it went bus-off), in the order they went.
    bus_off: Vec<(usize, i64, i64)>,
    bus_off_ns: Vec<i64>,
    /// The queue entry of the transmission on the wire (put back when the frame is destroyed).
    pub(crate) item: Option<Item>,
    episode: Option<Episode>,
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

    fn add_bus_off_ns(&mut self, node: usize, ns: i64) {
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

impl Bus {
    /// Model CAN errors and fault confinement on this bus, drawing from `rng` (error flag and corruption positions).
    pub fn enable_errors(&mut self, rng: Pcg64) {
        self.errors = Some(Box::new(BusErrors::new(rng, self.timing.nominal_bit_ns)));
    }

    /// Run `f` with the error model taken out of the bus (so it can change the bus); nothing without one.
    fn with_errors<R: Default>(&mut self, f: impl FnOnce(&mut Bus, &mut BusErrors) -> R) -> R {
        let Some(mut e) = self.errors.take() else { return R::default() };
        let r = f(self, &mut e);
        self.errors = Some(e);
        r
    }

    fn event(&mut self, t_ns: i64, kind: EventKind) {
        self.events.push(BusEvent { t_ns, kind });
    }

    /// A bus-off node may queue again once it has recovered by t.
    pub(crate) fn admits(&mut self, node: usize, t: u64) -> bool {
        self.with_errors(|bus, e| bus.recoveries(e, t as i64));
        !self.nodes[node].bus_off
    }

    /// At a start of frame: recoveries due by now, then close the recessive run.
    pub(crate) fn before_arbitrate(&mut self, t: u64) {
        self.with_errors(|bus, e| {
            let t = t as i64;
            bus.recoveries(e, t);
            e.sequences += (t - e.run_start).max(0) / e.seq_ns;
            e.run_start = t;
        })
    }

    /// Frame drops: a hit frame vanishes from its sender's queue; the next pending frame competes instead.
    pub(crate) fn filter_winner(&mut self, mut won: Option<Item>) -> Option<Item> {
        let Some(mut e) = self.errors.take() else { return won };
        while let Some(item) = won {
            if e.drops.is_empty() || !e.drops.iter_mut().any(|d| d.hit(item.frame_id)) {
                break;
            }
            let n = &mut self.nodes[item.node];
            n.queued -= 1;
            n.dropped += 1;
            e.stats.dropped_by_fault += 1;
            won = self.pop_winner();
        }
        self.errors = Some(e);
        won
    }

    /// Decide what happens to the frame now on the wire (`current`): destroyed by an error flag, corrupted (the
    /// receivers judge it bit by bit), or clean. A destroyed frame ends early, its error frame included.
    pub(crate) fn on_start(&mut self, won: Item) {
        let Some(mut e) = self.errors.take() else { return };
        e.item = Some(won);
        let tx = self.current.expect("on_start without a transmission");
        for k in 0..e.babblers.len() {
            if e.babblers[k].node == tx.node {
                let b = &mut e.babblers[k];
                b.sent += 1;
                e.stats.babbled += 1;
                let (node, id, data, ext) = (b.node, b.frame_id, b.data, b.extended);
                self.enqueue_as(node, id, data.as_slice(), tx.t_start, Some(ext), tx.format); // keep it babbling
            }
        }
        let mut tx = tx;
        if e.error_flags.iter_mut().any(|s| s.hit(tx.frame_id)) {
            let n_bits = if tx.format.is_fd() {
                let b = self.fd_phases(&tx);
                b.0 + b.1 - 3
            } else {
                wire_bits(tx.frame_id, tx.data.as_slice(), tx.extended).len() as u32
            };
            let at = 1 + e.rng.below(n_bits - 8); // after SOF .. the ACK delimiter
            e.stats.injected_error_flags += 1;
            self.fail(&mut tx, ErrorKind::ErrorFlag, at);
        } else if let Some(k) = e.corruptions.iter_mut().position(|s| s.hit(tx.frame_id)) {
            let bits = e.corruptions[k].bits;
            self.corrupt_frame(&mut e, &mut tx, bits);
        }
        self.current = Some(tx);
        self.errors = Some(e);
    }

    fn fd_phases(&self, tx: &Transmission) -> (u32, u32) {
        let b = fd_frame_bits(tx.frame_id, tx.data.as_slice(), tx.extended, tx.format.brs(), false)
            .expect("a frame on the wire has a valid FD length");
        (b.nominal, b.data)
    }

    fn corrupt_frame(&mut self, e: &mut BusErrors, tx: &mut Transmission, bits: u32) {
        e.stats.corrupted += 1;
        if tx.format.is_fd() {
            // CRC-17/21 with the stuff count: found after the ACK delimiter, no residual error to model
            let (nominal, data) = self.fd_phases(tx);
            e.stats.rejected += 1;
            self.fail(tx, ErrorKind::Crc, nominal + data - FD_EOF_IFS_BITS - 1);
            return;
        }
        let wire = wire_bits(tx.frame_id, tx.data.as_slice(), tx.extended);
        let span = wire.len() as u32 - 10; // bits after SOF up to and including the CRC delimiter
        let flips = pick_positions(&mut e.rng, span, bits);
        let seen = receive(&corrupt(&wire, &flips));
        match seen.error {
            Some(error) => {
                e.stats.rejected += 1;
                self.fail(tx, error, seen.at);
            }
            None => {
                // CAN's residual error: delivered as decoded, for the E2E check to catch
                e.stats.undetected += 1;
                let delivered = Payload::new(&seen.data);
                e.undetected.push(Undetected { t_ns: tx.t_start, sent_id: tx.frame_id, delivered_id: seen.can_id, delivered,
                                               sent: tx.data, flipped: flips });
                tx.frame_id = seen.can_id;
                tx.data = delivered;
                tx.extended = seen.extended;
            }
        }
    }

    fn fail(&mut self, tx: &mut Transmission, error: ErrorKind, at: u32) {
        tx.error = Some(error);
        tx.t_end = tx.t_start + self.bits_ns(tx, at + 1) + ERROR_TAIL_BITS * self.timing.nominal_bit_ns;
        self.busy_until = tx.t_end;
    }

    /// The time of a frame's first `k` bits (CAN FD with BRS: the data phase at the data rate).
    fn bits_ns(&self, tx: &Transmission, k: u32) -> u64 {
        let bit = self.timing.nominal_bit_ns;
        if !tx.format.brs() {
            return k as u64 * bit;
        }
        let (nominal, data) = self.fd_phases(tx);
        let arbitration = nominal as i64 - FD_TAIL_BITS as i64;
        let fast = (k as i64 - arbitration).max(0).min(data as i64) as u64;
        (k as u64 - fast) * bit + fast * self.timing.data_bit_ns
    }

    /// End of a transmission: counters and events; a destroyed frame is requeued (false: do not deliver it).
    pub(crate) fn on_complete(&mut self, tx: &Transmission) -> bool {
        let Some(mut e) = self.errors.take() else { return true };
        let t_end = tx.t_end as i64;
        e.run_start = t_end - e.seq_ns; // every transmission ends with 11 recessive bits
        let item = e.item.take();
        let Some(error) = tx.error else {
            self.success(&mut e, tx);
            self.errors = Some(e);
            return true;
        };
        e.stats.error_frames += 1;
        count_kind(&mut e.by_error, error);
        self.log_error(&mut e, tx, error);
        for node in 0..self.nodes.len() {
            let n = &self.nodes[node];
            if node != tx.node && n.attached && !n.bus_off {
                if !e.receiving.contains(&node) {
                    e.receiving.push(node);
                }
                let new = e.counters_of(node).rx_error();
                self.changed(&mut e, node, new, t_end);
            }
        }
        let new = e.counters_of(tx.node).tx_error();
        self.changed(&mut e, tx.node, new, t_end);
        // a destroyed frame and its error frame occupy the bus: they count in the load
        self.close_windows(tx.t_end, false);
        self.window_busy += tx.t_end - tx.t_start;
        if self.nodes[tx.node].bus_off || !self.nodes[tx.node].attached {
            self.nodes[tx.node].dropped += 1;
            e.stats.dropped_bus_off += 1;
        } else if let Some(item) = item {
            self.requeue(item);
            e.stats.retransmissions += 1;
        }
        self.errors = Some(e);
        false
    }

    fn success(&mut self, e: &mut BusErrors, tx: &Transmission) {
        let t_end = tx.t_end as i64;
        if let Some(c) = e.counters.get_mut(tx.node).and_then(|c| c.as_mut()) {
            if c.tec > 0 {
                let new = c.tx_ok();
                self.changed(e, tx.node, new, t_end);
            }
        }
        if e.receiving.is_empty() {
            return;
        }
        for node in e.receiving.clone() {
            if node != tx.node && !self.nodes[node].bus_off {
                let c = e.counters[node].as_mut().expect("a receiving node has counters");
                let new = c.rx_ok();
                let rec = c.rec;
                self.changed(e, node, new, t_end);
                if rec == 0 {
                    e.receiving.retain(|&n| n != node);
                }
            }
        }
    }

    fn changed(&mut self, e: &mut BusErrors, node: usize, new: Option<ErrorState>, t: i64) {
        let Some(state) = new else { return };
        let c = *e.counters_of(node);
        match state {
            ErrorState::BusOff => {
                self.nodes[node].bus_off = true;
                let lost = self.drop_queued(node) as u64;
                e.stats.dropped_bus_off += lost;
                e.bus_off.push((node, e.sequences, t));
                self.refresh_receivers();
                self.event(t, EventKind::BusOff { node, tec: c.tec, lost });
            }
            _ => self.event(t, EventKind::State { node, state, tec: c.tec, rec: c.rec }),
        }
    }

    /// Bring back every bus-off node that has seen 128 recessive sequences by t (at the exact time it did).
    fn recoveries(&mut self, e: &mut BusErrors, t: i64) {
        if e.bus_off.is_empty() {
            return;
        }
        let idle = self.current.is_none();
        let mut i = 0;
        while i < e.bus_off.len() {
            let (node, seq0, t_off) = e.bus_off[i];
            let need = RECOVERY_SEQUENCES - (e.sequences - seq0);
            let t_rec = if need <= 0 {
                e.run_start // reached at the end of an earlier run: logged at the latest bound
            } else if idle && (t - e.run_start).div_euclid(e.seq_ns) >= need {
                e.run_start + need * e.seq_ns
            } else {
                i += 1;
                continue;
            };
            e.bus_off.remove(i);
            self.nodes[node].bus_off = false;
            e.add_bus_off_ns(node, t_rec - t_off);
            e.counters_of(node).recover();
            self.refresh_receivers();
            self.event(t_rec, EventKind::Recovered { node, after_ns: t_rec - t_off });
        }
    }

    fn log_error(&mut self, e: &mut BusErrors, tx: &Transmission, error: ErrorKind) {
        let t_end = tx.t_end as i64;
        if e.episode.as_ref().is_some_and(|ep| t_end - ep.last_ns > EPISODE_GAP_NS) {
            self.close_episode(e);
        }
        if e.episode.is_none() {
            e.episode = Some(Episode { start_ns: t_end, last_ns: t_end, by_error: Vec::new() });
            self.event(t_end, EventKind::ErrorFrame { error, frame_id: tx.frame_id, node: tx.node });
        }
        let ep = e.episode.as_mut().unwrap();
        ep.last_ns = t_end;
        count_kind(&mut ep.by_error, error);
    }

    fn close_episode(&mut self, e: &mut BusErrors) {
        if let Some(ep) = e.episode.take() {
            let mut by_error = ep.by_error;
            by_error.sort();
            self.event(ep.last_ns, EventKind::Episode { start_ns: ep.start_ns, last_ns: ep.last_ns, by_error });
        }
    }

    /// End of the run for the error model: recoveries due, the open episode, time still spent bus-off.
    pub(crate) fn finish_errors(&mut self, t: u64) {
        self.with_errors(|bus, e| {
            let t = t as i64;
            bus.recoveries(e, t);
            bus.close_episode(e);
            for k in 0..e.bus_off.len() {
                let (node, seq0, t_off) = e.bus_off[k];
                e.add_bus_off_ns(node, (t - t_off).max(0));
                e.bus_off[k] = (node, seq0, t);
            }
        })
    }

    /// Start a fault's selection effect (corruption, error flags, drops) on this bus's error model.
    pub fn add_effect(&mut self, effect: Effect, selection: Selection) {
        if let Some(e) = self.errors.as_mut() {
            e.effects(effect).push(selection);
        }
    }

    /// Attach a babbling node for fault `fault`; returns the node (the caller queues its first frame).
    pub fn start_babbler(&mut self, fault: u64, name: &str, frame_id: u32, data: &[u8], extended: bool) -> Option<usize> {
        self.errors.as_ref()?;
        let node = self.attach(name, crate::bus::Sink::None, None, false);
        let b = Babbler { fault, node, frame_id, data: Payload::new(data), extended, sent: 0 };
        self.errors.as_mut().unwrap().babblers.push(b);
        Some(node)
    }

    /// End fault `fault` on this bus (a babbler leaves the bus).
    pub fn end_fault(&mut self, fault: u64) {
        let node = self.errors.as_mut().and_then(|e| e.remove_fault(fault));
        if let Some(node) = node {
            if self.nodes[node].attached {
                self.detach(node);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::{Policy, Sink};
    use crate::frame::BitTiming;

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

    #[test]
    fn positions_are_distinct_and_sorted() {
        let mut g = Pcg64::from_state(1, 3);
        let p = pick_positions(&mut g, 10, 10);
        assert_eq!(p, (1..=10).collect::<Vec<_>>());
        let p = pick_positions(&mut g, 100, 5);
        assert!(p.windows(2).all(|w| w[0] < w[1]) && p.iter().all(|&x| (1..=100).contains(&x)));
    }

    fn error_bus() -> (Bus, usize, usize) {
        let mut b = Bus::new("b", BitTiming::new(500_000, 500_000).unwrap(), Policy::Priority, 8, false, 100_000_000);
        let a = b.attach("A", Sink::None, None, false);
        let r = b.attach("R", Sink::Inbox(0), None, false);
        b.enable_errors(Pcg64::from_state(7, 9));
        (b, a, r)
    }

    /// A frame destroyed by an error flag every time: TEC +8 per attempt, each retransmitted at once, error passive
    /// after 16, bus-off after 32 attempts (the queue dropped), back after 128 x 11 recessive bits of idle bus.
    #[test]
    fn a_node_whose_frames_are_always_destroyed_goes_passive_then_bus_off_then_recovers() {
        let (mut b, a, r) = error_bus();
        b.add_effect(Effect::ErrorFlags, Selection { fault: 1, rng: Pcg64::from_state(1, 1), probability: 1.0, frame_ids: None,
                                                     count: None, hits: 0, bits: 1 });
        b.enqueue(a, 0x10, &[1, 2], 0, None);
        b.enqueue(a, 0x11, &[1, 2], 0, None);
        let mut t = 0;
        let mut attempts = 0;
        while let Some(end) = b.arbitrate(t).unwrap() {
            let tx = b.complete();
            assert!(tx.error == Some(ErrorKind::ErrorFlag) && end < t + 200_000);
            attempts += 1;
            t = end;
        }
        assert_eq!(attempts, 32);
        let e = b.errors.as_ref().unwrap();
        let c = e.counters(a).unwrap();
        assert_eq!((c.state, c.tec, c.passive_count), (ErrorState::BusOff, 256, 1));
        assert_eq!(e.counters(r).unwrap().rec, 32);
        assert_eq!(e.stats.retransmissions, 31);
        assert_eq!((b.nodes[a].dropped, e.stats.dropped_bus_off), (2, 2)); // 0x11 at bus-off, 0x10 after its last attempt
        assert!(!b.enqueue(a, 0x12, &[], t + 1000, None)); // still bus-off: refused and counted
        assert_eq!(b.nodes[a].dropped, 3);
        // the error frame's last 11 recessive bits are the first sequence: back 127 sequences after it ended
        let back = t + 127 * 11 * 2000;
        assert!(!b.enqueue(a, 0x12, &[], back - 1, None));
        assert!(b.enqueue(a, 0x12, &[], back, None));
        assert!(b.events.iter().any(|ev| ev.kind == EventKind::Recovered { node: a, after_ns: 127 * 11 * 2000 }));
        assert!(b.events.iter().any(|ev| matches!(ev.kind, EventKind::State { node, state: ErrorState::Passive, .. } if node == a)));
    }

    #[test]
    fn a_babbler_keeps_its_frame_queued_and_leaves_at_the_end() {
        let (mut b, a, _) = error_bus();
        let n = b.start_babbler(5, "Babbler#5", 0x001, &[0xA5; 8], false).unwrap();
        b.enqueue(n, 0x001, &[0xA5; 8], 0, None);
        b.enqueue(a, 0x100, &[], 0, None);
        let mut t = 0;
        for _ in 0..10 {
            t = b.arbitrate(t).unwrap().unwrap();
            assert_eq!(b.complete().frame_id, 0x001); // 0x100 starves
        }
        b.end_fault(5);
        assert!(!b.nodes[n].attached);
        b.arbitrate(t).unwrap();
        assert_eq!(b.complete().frame_id, 0x100);
        assert_eq!(b.errors.as_ref().unwrap().stats.babbled, 10); // one per frame it started
    }
}
