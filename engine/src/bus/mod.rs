//! The CAN bus model: per-node TX queues, arbitration, exact frame durations, acceptance filters, load and
//! latency statistics. It is told the time by its driver (the virtual-time network, or a wall clock).
//!
//! When the bus goes idle every node offers the head of its TX queue (the lowest ID it holds under the
//! `Priority` policy, its oldest frame under `Fifo`) and the lowest arbitration key wins. A transmission ends
//! after its last bit including the 3-bit intermission, which is the time stamped on the received frame.

mod error_path;

use std::cmp::{Ordering, Reverse};
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::sync::Arc;

use crate::errors::{BusErrors, BusEvent, ErrorKind};
use crate::frame::{fd_padded_len, BitTiming, FrameError, MAX_CLASSIC_DATA, MAX_DATA};
use crate::guardian::Guardian;
use crate::packing::Packing;

/// Where a node's received frames go (resolved by the driver).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sink {
    /// A node that only sends.
    None,
    /// An ECU's mailboxes (index into the driver's mailboxes).
    Mailbox(usize),
    /// A queue the driver drains from Python.
    Inbox(usize),
    /// The plant's actuator commands: checked (length, E2E CRC, mode) and decoded on delivery.
    Commands(usize),
    /// The radio gateway's end on this bus.
    Gateway(usize),
}

/// The frame format: classical CAN 2.0, or CAN FD with or without the bit-rate switch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Format {
    #[default]
    Classical,
    Fd,
    FdBrs,
}

impl Format {
    /// Classical, or CAN FD with (`brs`) or without the bit-rate switch.
    pub fn of(fd: bool, brs: bool) -> Format {
        match (fd, brs) {
            (false, _) => Format::Classical,
            (true, false) => Format::Fd,
            (true, true) => Format::FdBrs,
        }
    }

    pub fn is_fd(self) -> bool {
        self != Format::Classical
    }
    pub fn brs(self) -> bool {
        self == Format::FdBrs
    }
    /// The largest payload of this format.
    pub fn max_data(self) -> usize {
        if self.is_fd() { MAX_DATA } else { MAX_CLASSIC_DATA }
    }
}

/// Queue policy of the TX queues.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Policy {
    Priority,
    Fifo,
}

/// A frame's payload: up to 64 bytes inline.
#[derive(Clone, Copy)]
pub struct Payload {
    pub len: u8,
    pub bytes: [u8; MAX_DATA],
}

impl Payload {
    pub fn new(data: &[u8]) -> Payload {
        let mut bytes = [0u8; MAX_DATA];
        bytes[..data.len()].copy_from_slice(data);
        Payload { len: data.len() as u8, bytes }
    }
    pub fn as_slice(&self) -> &[u8] {
        &self.bytes[..self.len as usize]
    }
}

impl std::fmt::Debug for Payload {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:02X?}", self.as_slice())
    }
}

/// A queued frame. Ordered by (arbitration key, bus-wide sequence number).
#[derive(Debug, Clone, Copy)]
pub struct Item {
    pub key: u64,
    pub seq: u64,
    pub node: usize,
    pub frame_id: u32,
    pub extended: bool,
    pub format: Format,
    pub t_enqueue: u64,
    pub data: Payload,
}

impl PartialEq for Item {
    fn eq(&self, other: &Self) -> bool {
        (self.key, self.seq) == (other.key, other.seq)
    }
}
impl Eq for Item {}
impl PartialOrd for Item {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Item {
    fn cmp(&self, other: &Self) -> Ordering {
        (self.key, self.seq).cmp(&(other.key, other.seq))
    }
}

/// The order arbitration on the wire decides: base ID, then SRR and IDE (a standard frame beats an extended
/// one with the same base ID), then the 18-bit ID extension.
pub fn arbitration_key(frame_id: u32, extended: bool) -> u64 {
    let id = frame_id as u64;
    if extended {
        ((id >> 18) << 20) | (0b11 << 18) | (id & 0x3FFFF)
    } else {
        id << 20
    }
}

/// A node's CAN controller: a bounded TX queue and an acceptance filter.
#[derive(Debug, Clone)]
pub struct Node {
    pub name: String,
    pub sink: Sink,
    /// Accepted IDs (None = everything).
    pub rx_ids: Option<Vec<u32>>,
    pub receive_own: bool,
    pub queued: usize,
    pub fifo: VecDeque<Item>,
    pub sent: u64,
    pub dropped: u64,
    /// False once the node left the bus (its index stays taken; it neither sends nor receives).
    pub attached: bool,
    /// Bus-off (fault confinement, `errors`): the node neither sends nor receives until it recovers.
    pub bus_off: bool,
    /// A frame of it was refused (a full TX queue, bus-off): its first is in `Bus::refusals`, the rest counted only.
    pub refused: bool,
}

/// A node's first frame refused at its TX queue (full, or the node bus-off), for the driver to report with its time:
/// where and when a loss began.
#[derive(Debug, Clone, PartialEq)]
pub struct Refusal {
    pub node: usize,
    pub frame_id: u32,
    pub t_ns: u64,
    pub bus_off: bool,
}

impl Node {
    /// The acceptance filter lets `frame_id` through.
    pub fn accepts(&self, frame_id: u32) -> bool {
        self.rx_ids.as_ref().is_none_or(|ids| ids.contains(&frame_id))
    }
}

/// A frame on the wire.
#[derive(Debug, Clone, Copy)]
pub struct Transmission {
    pub node: usize,
    pub frame_id: u32,
    pub extended: bool,
    pub format: Format,
    pub data: Payload,
    pub t_enqueue: u64,
    pub t_start: u64,
    pub t_end: u64,
    /// Set when the frame was destroyed (`errors`): not delivered, retransmitted.
    pub error: Option<ErrorKind>,
}

/// Statistics the run log takes over: one row per frame and one per load window.
#[derive(Debug, Default, Clone)]
pub struct BusStats {
    /// (t_end s, frame id, latency s = end - enqueue, queueing s = start - enqueue), flattened.
    pub frames: Vec<f64>,
    /// (window end s, load 0..1), flattened.
    pub load: Vec<f64>,
    pub frames_sent: u64,
}

/// One CAN bus.
#[derive(Debug)]
pub struct Bus {
    pub name: String,
    pub timing: BitTiming,
    pub policy: Policy,
    pub depth: usize,
    pub extended: bool,
    /// The format of the frames the bus's own nodes send (a server's clients say per frame).
    pub format: Format,
    pub nodes: Vec<Node>,
    heap: BinaryHeap<Reverse<Item>>,
    seq: u64,
    /// Receiver lists by frame ID (standard IDs indexed directly, extended ones hashed), built lazily.
    receivers_std: Vec<Option<Vec<usize>>>,
    receivers_ext: HashMap<u32, Vec<usize>>,
    pub busy_until: u64,
    pub current: Option<Transmission>,
    window_ns: u64,
    window_end: u64,
    pub(crate) window_busy: u64,
    pub stats: BusStats,
    /// When set, every completed transmission is also kept here for the driver (CAN logs, frame rows).
    pub trace: Option<Vec<Transmission>>,
    /// Container frames on this bus (CAN FD frame packing): a node accepting a part also receives its container.
    pub packing: Option<Arc<Packing>>,
    /// CAN error confinement and the bus fault injectors (None: the error-free fast path).
    pub errors: Option<Box<BusErrors>>,
    /// The babbling-idiot monitor, fed every delivered frame.
    pub guardian: Option<Guardian>,
    /// What the error model and the guardian reported, in order, for the driver to take.
    pub events: Vec<BusEvent>,
    /// Each node's first refused frame, in order, for the driver to take (`take_refusals`).
    pub refusals: Vec<Refusal>,
}

impl Bus {
    pub fn new(name: &str, timing: BitTiming, policy: Policy, depth: usize, extended: bool, load_window_ns: u64) -> Bus {
        Bus {
            name: name.to_string(), timing, policy, depth, extended, format: Format::Classical, nodes: Vec::new(), heap: BinaryHeap::new(), seq: 0,
            receivers_std: vec![None; 1 << 11], receivers_ext: HashMap::new(), busy_until: 0, current: None, window_ns: load_window_ns,
            window_end: load_window_ns, window_busy: 0, stats: BusStats::default(), trace: None, packing: None,
            errors: None, guardian: None, events: Vec::new(), refusals: Vec::new(),
        }
    }

    /// Call node `node` `name` from now on (its TX queue's drops, error state and refusals go by it).
    pub fn rename_node(&mut self, node: usize, name: &str) {
        self.nodes[node].name = name.to_string();
    }

    /// Attach a node; returns its index on this bus.
    pub fn attach(&mut self, name: &str, sink: Sink, rx_ids: Option<Vec<u32>>, receive_own: bool) -> usize {
        self.nodes.push(Node { name: name.to_string(), sink, rx_ids, receive_own, queued: 0, fifo: VecDeque::new(), sent: 0,
                               dropped: 0, attached: true, bus_off: false, refused: false });
        self.refresh_receivers();
        self.nodes.len() - 1
    }

    /// Forget the receiver lists (a node joined, left, went bus-off or recovered): they are built again.
    pub fn refresh_receivers(&mut self) {
        self.receivers_std.iter_mut().for_each(|r| *r = None);
        self.receivers_ext.clear();
    }

    fn find_receivers(nodes: &[Node], frame_id: u32, packing: Option<&Packing>) -> Vec<usize> {
        let parts = packing.and_then(|p| p.parts(frame_id)).unwrap_or(&[]);
        let wants = |ids: &Vec<u32>| ids.contains(&frame_id) || parts.iter().any(|p| ids.contains(&p.id));
        let listens = |n: &Node| n.sink != Sink::None && !n.bus_off;
        let mut found: Vec<usize> = (0..nodes.len())
            .filter(|&i| listens(&nodes[i]) && nodes[i].rx_ids.as_ref().is_some_and(wants))
            .collect();
        found.extend((0..nodes.len()).filter(|&i| listens(&nodes[i]) && nodes[i].rx_ids.is_none()));
        found
    }

    /// Nodes that receive `frame_id`: filtered nodes in attach order, then the catch-all ones.
    pub fn receivers(&mut self, frame_id: u32) -> &[usize] {
        let (nodes, packing) = (&self.nodes, self.packing.as_deref());
        if let Some(slot) = self.receivers_std.get_mut(frame_id as usize) {
            return slot.get_or_insert_with(|| Self::find_receivers(nodes, frame_id, packing));
        }
        self.receivers_ext.entry(frame_id).or_insert_with(|| Self::find_receivers(nodes, frame_id, packing))
    }

    /// Pack the frames of this bus's containers (see `packing`); the receiver lists are built again.
    pub fn set_packing(&mut self, packing: Option<Arc<Packing>>) {
        self.packing = packing;
        self.refresh_receivers();
    }

    /// Move the receiver list of `frame_id` out of the cache (no copy per frame); give it back with `put_receivers`.
    pub fn take_receivers(&mut self, frame_id: u32) -> Vec<usize> {
        self.receivers(frame_id);
        match self.receivers_std.get_mut(frame_id as usize) {
            Some(slot) => slot.take().unwrap_or_default(),
            None => self.receivers_ext.remove(&frame_id).unwrap_or_default(),
        }
    }

    pub fn put_receivers(&mut self, frame_id: u32, list: Vec<usize>) {
        match self.receivers_std.get_mut(frame_id as usize) {
            Some(slot) => *slot = Some(list),
            None => {
                self.receivers_ext.insert(frame_id, list);
            }
        }
    }

    /// The bus with its nodes sending `format` frames (CAN FD: payloads padded up to the next FD length).
    pub fn with_format(mut self, format: Format) -> Bus {
        self.format = format;
        self
    }

    /// Queue a frame at time t in the bus's format; false (and counted as a drop) when the node's queue is full.
    pub fn enqueue(&mut self, node: usize, frame_id: u32, data: &[u8], t: u64, extended: Option<bool>) -> bool {
        self.enqueue_as(node, frame_id, data, t, extended, self.format)
    }

    /// Queue a frame of the given format. A CAN FD payload whose length no DLC gives is padded with zeros up to
    /// the next one (12, 16, 20, 24, 32, 48, 64), as FD controllers do; what cannot be sent fails in `arbitrate`.
    pub fn enqueue_as(&mut self, node: usize, frame_id: u32, data: &[u8], t: u64, extended: Option<bool>, format: Format) -> bool {
        let n = &self.nodes[node];
        if n.queued >= self.depth || !n.attached || (n.bus_off && !self.admits(node, t)) {
            let n = &mut self.nodes[node];
            n.dropped += 1;
            if n.attached && !n.refused {
                n.refused = true;
                let bus_off = n.bus_off;
                self.refusals.push(Refusal { node, frame_id, t_ns: t, bus_off });
            }
            return false;
        }
        let n = &mut self.nodes[node];
        n.queued += 1;
        self.seq += 1;
        let ext = extended.unwrap_or(self.extended);
        let mut payload = Payload::new(&data[..data.len().min(MAX_DATA)]);
        if format.is_fd() {
            payload.len = fd_padded_len(data.len()).unwrap_or(data.len()) as u8;
        }
        let item = Item { key: arbitration_key(frame_id, ext), seq: self.seq, node, frame_id, extended: ext, format, t_enqueue: t,
                          data: payload };
        match self.policy {
            Policy::Priority => self.heap.push(Reverse(item)),
            Policy::Fifo => n.fifo.push_back(item),
        }
        true
    }

    /// Take the frame that wins arbitration at `t` among those queued by then. A frame queued after `t` is not
    /// there yet: only a frame put on a real-time bus from outside its turns (a fault's babbling node, queued at the
    /// wall clock's now) can be, while the server's lazy bus still runs events before that now; it won ahead of
    /// frames queued before it, and its wait came out negative (a u64 wrapped to 1.8e10 s).
    pub(crate) fn pop_winner(&mut self, t: u64) -> Option<Item> {
        match self.policy {
            Policy::Priority => {
                let mut later = Vec::new();
                let mut won = None;
                while let Some(Reverse(item)) = self.heap.pop() {
                    if item.t_enqueue <= t {
                        won = Some(item);
                        break;
                    }
                    later.push(Reverse(item));
                }
                self.heap.extend(later);
                won
            }
            Policy::Fifo => {
                let best = self.fifo_winner(|i| self.nodes[i].fifo.front().filter(|item| item.t_enqueue <= t));
                best.and_then(|b| self.nodes[b].fifo.pop_front())
            }
        }
    }

    /// The (frame ID, extended) of every queued frame, in no order.
    pub fn queued_ids(&self) -> impl Iterator<Item = (u32, bool)> + '_ {
        let heap = self.heap.iter().map(|Reverse(item)| (item.frame_id, item.extended));
        let fifos = self.nodes.iter().flat_map(|n| n.fifo.iter().map(|item| (item.frame_id, item.extended)));
        heap.chain(fifos)
    }

    /// Under `Policy::Fifo`, the node whose frame wins arbitration among the frames `head(node)` offers (each
    /// node's oldest queued frame; the lowest key, the first node on a tie).
    fn fifo_winner<'a>(&'a self, head: impl Fn(usize) -> Option<&'a Item>) -> Option<usize> {
        let mut best: Option<(u64, usize)> = None;
        for i in 0..self.nodes.len() {
            if let Some(item) = head(i) {
                if best.is_none_or(|(key, _)| item.key < key) {
                    best = Some((item.key, i));
                }
            }
        }
        best.map(|(_, i)| i)
    }

    /// The queued frames in the order they would go on the wire if no other frame came (arbitration by priority;
    /// under `Policy::Fifo`, among the heads of the nodes' queues).
    pub fn queue_order(&self) -> Vec<Item> {
        match self.policy {
            Policy::Priority => {
                let mut items: Vec<Item> = self.heap.iter().map(|Reverse(item)| *item).collect();
                items.sort();
                items
            }
            Policy::Fifo => {
                let mut heads = vec![0usize; self.nodes.len()];
                let mut out = Vec::new();
                while let Some(i) = self.fifo_winner(|i| self.nodes[i].fifo.get(heads[i])) {
                    out.push(self.nodes[i].fifo[heads[i]]);
                    heads[i] += 1;
                }
                out
            }
        }
    }

    /// The end of the first frame `wanted` accepts (the one on the wire, then the queued ones in `queue_order`),
    /// if no other frame came and none failed: the earliest it can end, since a frame that comes later can only
    /// win arbitration before it. None: no such frame.
    pub fn earliest_end(&self, mut wanted: impl FnMut(u32, bool) -> bool) -> Option<u64> {
        let tx = self.current?;
        if wanted(tx.frame_id, tx.extended) {
            return Some(tx.t_end);
        }
        let mut t = tx.t_end;
        for item in self.queue_order() {
            t += self.timing.frame_ns(item.frame_id, item.data.as_slice(), item.extended, item.format.is_fd(), item.format.brs()).ok()?;
            if wanted(item.frame_id, item.extended) {
                return Some(t);
            }
        }
        None
    }

    /// Whether any frame is queued.
    pub fn pending(&self) -> bool {
        match self.policy {
            Policy::Priority => !self.heap.is_empty(),
            Policy::Fifo => self.nodes.iter().any(|n| !n.fifo.is_empty()),
        }
    }

    /// If the bus is idle at t, start the winning pending frame and return its end time.
    pub fn arbitrate(&mut self, t: u64) -> Result<Option<u64>, FrameError> {
        if self.current.is_some() || t < self.busy_until {
            return Ok(None);
        }
        let errors = self.errors.is_some();
        if errors {
            self.before_arbitrate(t);
        }
        let mut won = self.pop_winner(t);
        if errors {
            won = self.filter_winner(won, t);
        }
        let Some(won) = won else { return Ok(None) };
        self.nodes[won.node].queued -= 1;
        let f = won.format;
        let t_end = t + self.timing.frame_ns(won.frame_id, won.data.as_slice(), won.extended, f.is_fd(), f.brs())?;
        self.current = Some(Transmission { node: won.node, frame_id: won.frame_id, extended: won.extended, format: f,
                                           data: won.data, t_enqueue: won.t_enqueue, t_start: t, t_end, error: None });
        self.busy_until = t_end;
        if errors {
            self.on_start(won); // may destroy the frame: it then ends with its error frame
        }
        Ok(self.current.map(|tx| tx.t_end))
    }

    /// End the current transmission and account for it; the driver delivers it to `receivers(frame_id)` unless
    /// it was destroyed (`error` set: the error model put it back in its sender's queue).
    pub fn complete(&mut self) -> Transmission {
        let tx = self.current.take().expect("complete() without a transmission");
        if self.errors.is_some() && !self.on_complete(&tx) {
            return tx;
        }
        self.nodes[tx.node].sent += 1;
        self.stats.frames_sent += 1;
        self.stats.frames.extend_from_slice(&[
            tx.t_end as f64 * 1e-9, tx.frame_id as f64, (tx.t_end - tx.t_enqueue) as f64 * 1e-9,
            (tx.t_start - tx.t_enqueue) as f64 * 1e-9,
        ]);
        self.account(tx.t_start, tx.t_end);
        if let Some(trace) = self.trace.as_mut() {
            trace.push(tx);
        }
        if let Some(g) = self.guardian.as_mut() {
            g.observe(&tx, &mut self.events);
        }
        tx
    }

    /// Put a destroyed frame back at its place in its node's queue (automatic retransmission).
    pub(crate) fn requeue(&mut self, item: Item) {
        self.nodes[item.node].queued += 1;
        match self.policy {
            Policy::Priority => self.heap.push(Reverse(item)),
            Policy::Fifo => self.nodes[item.node].fifo.push_front(item),
        }
    }

    /// Drop (and count) every frame a node has queued (it left the bus, or went bus-off); returns how many.
    pub(crate) fn drop_queued(&mut self, node: usize) -> usize {
        let lost = self.nodes[node].queued;
        if lost > 0 && self.policy == Policy::Priority {
            let items: Vec<Reverse<Item>> = std::mem::take(&mut self.heap).into_vec();
            self.heap = items.into_iter().filter(|Reverse(item)| item.node != node).collect();
        }
        let n = &mut self.nodes[node];
        n.fifo.clear();
        n.queued = 0;
        n.dropped += lost as u64;
        lost
    }

    /// Book a transmission's bus time in the load windows it spans, each its own part (a frame that straddles a
    /// boundary would otherwise put more than a window's length into the later one: a load above 1).
    fn account(&mut self, start: u64, end: u64) {
        while end > self.window_end {
            if start < self.window_end {
                self.window_busy += self.window_end - start.max(self.window_end - self.window_ns);
            }
            self.stats.load.push(self.window_end as f64 * 1e-9);
            self.stats.load.push(self.window_busy as f64 / self.window_ns as f64);
            self.window_busy = 0;
            self.window_end += self.window_ns;
        }
        // saturating: a frame that ended before the window began (only after `align_load_windows`) adds nothing
        self.window_busy += end.saturating_sub(start.max(self.window_end - self.window_ns));
    }

    /// From now on the load windows end at `origin_ns` + k x the window (a real-time bus server's at the run's
    /// time zero, as virtual time's end at k x the window). The bus time booked since the last window closed counts
    /// in the first aligned window, up to the part of that window that has passed, so no window reads above full;
    /// call it before the run's time zero, where no run's figure reads it.
    pub fn align_load_windows(&mut self, origin_ns: u64, now: u64) {
        self.close_windows(now, false);
        let w = self.window_ns as i128;
        let ahead = (origin_ns as i128 - now as i128).rem_euclid(w) as u64; // from now to the next aligned end
        self.window_end = now + if ahead == 0 { self.window_ns } else { ahead };
        self.window_busy = self.window_busy.min(now - (self.window_end - self.window_ns).min(now));
    }

    /// Where the load window in progress ends (model ns).
    #[cfg(test)]
    fn load_window_end(&self) -> u64 {
        self.window_end
    }

    /// Emit a load sample for every window that ended before t (at or before t if inclusive).
    pub(crate) fn close_windows(&mut self, t: u64, inclusive: bool) {
        while t > self.window_end || (inclusive && t == self.window_end) {
            self.stats.load.push(self.window_end as f64 * 1e-9);
            self.stats.load.push(self.window_busy as f64 / self.window_ns as f64);
            self.window_busy = 0;
            self.window_end += self.window_ns;
        }
    }

    /// Close the load windows up to t (the end of a run).
    pub fn finish(&mut self, t: u64) {
        if self.errors.is_some() {
            self.finish_errors(t);
        }
        self.close_windows(t, true);
    }

    /// Remove a node (it disconnected): its queued frames are dropped and counted, how many is returned; a frame
    /// of it already on the wire completes.
    pub fn detach(&mut self, node: usize) -> usize {
        let lost = self.drop_queued(node);
        let n = &mut self.nodes[node];
        n.attached = false;
        n.sink = Sink::None;
        n.rx_ids = Some(Vec::new());
        self.refresh_receivers();
        lost
    }

    /// The first refused frame of each node since the last call, each as (its time, what happened): "node N dropped
    /// frame 0x... (its TX queue of 64 is full); its later drops are only counted".
    pub fn take_refusals(&mut self) -> Vec<(u64, String)> {
        let refusals = std::mem::take(&mut self.refusals);
        refusals.into_iter().map(|r| {
            let why =
                if r.bus_off { "it is bus-off".to_string() } else { format!("its TX queue of {} is full", self.depth) };
            let name = &self.nodes[r.node].name;
            (r.t_ns, format!("node {name} dropped frame 0x{:X} ({why}); its later drops are only counted", r.frame_id))
        }).collect()
    }

    /// Frames dropped at full TX queues, over all nodes.
    pub fn frames_dropped(&self) -> u64 {
        self.nodes.iter().map(|n| n.dropped).sum()
    }

    /// The frames each node dropped (a full TX queue, bus-off, frames queued when it left), by node name in name
    /// order, nodes that dropped none left out: which controller lost frames. A name attached twice (a restarted
    /// ECU) is summed.
    pub fn dropped_by_node(&self) -> Vec<(String, u64)> {
        let mut by_name = std::collections::BTreeMap::new();
        for n in self.nodes.iter().filter(|n| n.dropped > 0) {
            *by_name.entry(n.name.clone()).or_insert(0) += n.dropped;
        }
        by_name.into_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bus(policy: Policy) -> Bus {
        Bus::new("bus1", BitTiming::new(500_000, 500_000).unwrap(), policy, 2, false, 100_000_000)
    }

    #[test]
    fn lowest_id_wins_and_duration_is_exact() {
        let mut b = bus(Policy::Priority);
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::Mailbox(0), Some(vec![0x100, 0x200]), false);
        assert!(b.enqueue(a, 0x200, &[1, 2], 0, None));
        assert!(b.enqueue(c, 0x100, &[3], 0, None));
        let end = b.arbitrate(0).unwrap().unwrap();
        assert_eq!(b.current.unwrap().frame_id, 0x100);
        assert_eq!(end, crate::frame::frame_bits(0x100, &[3], false).unwrap() as u64 * 2000);
        assert_eq!(b.arbitrate(10).unwrap(), None); // busy
        let tx = b.complete();
        assert_eq!(b.receivers(tx.frame_id), &[1]);
        assert_eq!(b.arbitrate(end).unwrap().map(|_| b.current.unwrap().frame_id), Some(0x200));
    }

    #[test]
    fn standard_beats_extended_with_same_base_id() {
        assert!(arbitration_key(0x100, false) < arbitration_key(0x100 << 18, true));
        assert!(arbitration_key((0x100 << 18) | 5, true) < arbitration_key(0x101, false));
    }

    #[test]
    fn fifo_offers_each_nodes_oldest_frame() {
        let mut b = bus(Policy::Fifo);
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::None, None, false);
        b.enqueue(a, 0x300, &[], 0, None);
        b.enqueue(a, 0x010, &[], 0, None);
        b.enqueue(c, 0x200, &[], 0, None);
        let mut order = Vec::new();
        let mut t = 0;
        while let Some(end) = b.arbitrate(t).unwrap() {
            order.push(b.complete().frame_id);
            t = end;
        }
        assert_eq!(order, vec![0x200, 0x300, 0x010]); // 0x010 waits behind A's 0x300: priority inversion
    }

    /// Run the bus with nothing more queued; the end of the first frame with `id`.
    fn end_of(b: &mut Bus, id: u32) -> u64 {
        loop {
            let tx = b.complete();
            if tx.frame_id == id {
                return tx.t_end;
            }
            b.arbitrate(tx.t_end).unwrap();
        }
    }

    /// Nodes A and C with three frames queued at 0 (A: 0x300 then 0x050; C: 0x200), the first on the wire.
    fn three_queued(policy: Policy) -> (Bus, usize) {
        let mut b = bus(policy);
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::None, None, false);
        b.enqueue(a, 0x300, &[1; 8], 0, None);
        b.enqueue(a, 0x050, &[2; 4], 0, None);
        b.enqueue(c, 0x200, &[3; 2], 0, None);
        b.arbitrate(0).unwrap();
        (b, c)
    }

    #[test]
    fn the_earliest_end_of_a_queued_frame_is_its_end_if_nothing_comes_and_a_bound_if_something_does() {
        for policy in [Policy::Priority, Policy::Fifo] {
            let (mut b, _) = three_queued(policy);
            let first = if policy == Policy::Priority { 0x050 } else { 0x200 }; // FIFO: A's 0x300 is before its 0x050
            assert_eq!(b.current.unwrap().frame_id, first);
            assert_eq!(b.earliest_end(|id, _| id == first), Some(b.busy_until));
            assert_eq!(b.earliest_end(|id, _| id == 0x7FF), None);
            let earliest = b.earliest_end(|id, _| id == 0x300).unwrap();
            assert_eq!(end_of(&mut b, 0x300), earliest, "{policy:?}: nothing else came");
            // the same queue, and a frame that comes later and wins arbitration before 0x300: it can only be later
            let (mut b, c) = three_queued(policy);
            b.enqueue(c, 0x010, &[4; 8], 1, None);
            assert!(end_of(&mut b, 0x300) > earliest, "{policy:?}: a later frame delays it");
        }
    }

    #[test]
    fn a_detached_node_loses_its_queue_but_not_the_frame_on_the_wire() {
        let mut b = bus(Policy::Priority);
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::None, None, false);
        b.enqueue(a, 1, &[], 0, None);
        b.enqueue(a, 2, &[], 0, None);
        b.enqueue(c, 3, &[], 0, None);
        b.arbitrate(0).unwrap();
        assert_eq!(b.detach(a), 1);
        assert_eq!(b.complete().frame_id, 1);
        let end = b.busy_until;
        b.arbitrate(end).unwrap();
        assert_eq!(b.complete().frame_id, 3);
        assert_eq!(b.frames_dropped(), 1);
        assert!(!b.pending());
    }

    #[test]
    fn an_fd_bus_times_frames_at_both_rates_and_pads_payloads() {
        let timing = BitTiming::new(1_000_000, 5_000_000).unwrap();
        let mut b = Bus::new("b", timing, Policy::Priority, 8, false, 100_000_000).with_format(Format::FdBrs);
        let a = b.attach("A", Sink::None, None, false);
        assert!(b.enqueue(a, 0x10, &[7; 10], 0, None)); // 10 bytes: padded to 12 (DLC 9)
        let end = b.arbitrate(0).unwrap().unwrap();
        let tx = b.complete();
        assert_eq!(tx.data.as_slice(), &[7, 7, 7, 7, 7, 7, 7, 7, 7, 7, 0, 0]);
        let bits = crate::frame::fd_frame_bits(0x10, tx.data.as_slice(), false, true, false).unwrap();
        assert_eq!(end, bits.nominal as u64 * 1000 + bits.data as u64 * 200);
    }

    #[test]
    fn classical_and_fd_frames_share_one_bus() {
        let timing = BitTiming::new(500_000, 2_000_000).unwrap();
        let mut b = Bus::new("b", timing, Policy::Priority, 8, false, 100_000_000);
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::None, None, false);
        b.enqueue_as(a, 0x20, &[1; 8], 0, None, Format::Classical);
        b.enqueue_as(c, 0x21, &[1; 8], 0, None, Format::FdBrs);
        let t1 = b.arbitrate(0).unwrap().unwrap();
        assert_eq!(b.complete().format, Format::Classical); // the lower ID wins whatever the format
        assert_eq!(t1, crate::frame::frame_bits(0x20, &[1; 8], false).unwrap() as u64 * 2000);
        let t2 = b.arbitrate(t1).unwrap().unwrap();
        assert_eq!(b.complete().format, Format::FdBrs);
        assert!(t2 - t1 < t1, "8 bytes with BRS at 4x the rate are shorter than the classical frame");
    }

    #[test]
    fn full_queue_drops_and_counts() {
        let mut b = bus(Policy::Priority);
        let a = b.attach("A", Sink::None, None, false);
        assert!(b.enqueue(a, 1, &[], 0, None));
        assert!(b.enqueue(a, 2, &[], 0, None));
        assert!(!b.enqueue(a, 3, &[], 0, None));
        assert_eq!(b.frames_dropped(), 1);
    }

    #[test]
    fn each_nodes_first_refused_frame_is_taken_once_with_its_time_and_cause() {
        let mut b = bus(Policy::Priority); // TX queues of two frames
        let a = b.attach("A", Sink::None, None, false);
        let c = b.attach("C", Sink::None, None, false);
        for (t, id) in [(10, 1), (10, 2), (10, 3), (20, 4)] {
            b.enqueue(a, id, &[], t, None); // 3 and 4 refused
        }
        b.enqueue(c, 5, &[], 30, None);
        let said = b.take_refusals();
        let text = "node A dropped frame 0x3 (its TX queue of 2 is full); its later drops are only counted";
        assert_eq!(said, vec![(10, text.to_string())]);
        b.enqueue(c, 6, &[], 40, None);
        b.enqueue(c, 7, &[], 50, None); // refused: C's first
        b.enqueue(a, 8, &[], 60, None); // refused: A's again, counted only
        let said = b.take_refusals();
        assert_eq!(said.len(), 1);
        assert!(said[0].0 == 50 && said[0].1.starts_with("node C dropped frame 0x7 "), "{said:?}");
        assert!(b.take_refusals().is_empty());
        assert_eq!(b.frames_dropped(), 4);
    }

    #[test]
    fn drops_are_named_by_node_and_summed_over_a_name_attached_twice() {
        let mut b = bus(Policy::Priority); // TX queues of two frames
        let plant = b.attach("Plant", Sink::None, None, false);
        let quiet = b.attach("ECU_U02", Sink::None, None, false);
        let first = b.attach("ECU_U01", Sink::None, None, false);
        assert!(b.enqueue(quiet, 9, &[], 0, None));
        for id in 1..=5 {
            b.enqueue(plant, id, &[], 0, None);
        }
        b.enqueue(first, 7, &[], 0, None);
        assert_eq!(b.detach(first), 1); // a crashed ECU loses its queued frame
        let again = b.attach("ECU_U01", Sink::None, None, false); // restarted as a new node of the same name
        for id in 10..=12 {
            b.enqueue(again, id, &[], 0, None);
        }
        assert_eq!(b.dropped_by_node(), vec![("ECU_U01".to_string(), 2), ("Plant".to_string(), 3)]);
        assert_eq!(b.frames_dropped(), 5);
    }

    #[test]
    fn load_windows_split_a_frame_that_spans_them() {
        let mut b = Bus::new("b", BitTiming::new(1_000_000, 1_000_000).unwrap(), Policy::Priority, 8, false, 1_000);
        let a = b.attach("A", Sink::None, None, false);
        b.enqueue(a, 0, &[], 0, None);
        let end = b.arbitrate(0).unwrap().unwrap(); // 53 us (the all-zero frame) over 53 windows of 1 us
        b.complete();
        b.finish(end);
        let loads: Vec<f64> = b.stats.load.chunks(2).map(|w| w[1]).collect();
        assert_eq!(loads.len() as u64, end / 1_000);
        assert!(loads.iter().all(|&l| l == 1.0), "{loads:?}"); // each window full, none above 1
    }

    #[test]
    fn a_frame_across_a_window_boundary_is_shared_by_both() {
        let mut b = Bus::new("b", BitTiming::new(1_000_000, 1_000_000).unwrap(), Policy::Priority, 8, false, 100_000);
        let a = b.attach("A", Sink::None, None, false);
        b.enqueue(a, 0, &[], 80_000, None);
        let end = b.arbitrate(80_000).unwrap().unwrap(); // 80 us .. 133 us: 20 us in the first window, 33 in the next
        b.complete();
        b.finish(200_000);
        let loads: Vec<f64> = b.stats.load.chunks(2).map(|w| w[1]).collect();
        assert_eq!(end, 133_000);
        assert_eq!(loads, vec![0.2, 0.33]);
    }

    /// A frame queued after the arbitration's instant (a real-time fault's babbler, queued at the wall clock's
    /// now while the server's lazy bus runs events before it) does not take part in it: the frames queued by then
    /// compete, and it waits for its own time. It took the bus before and its wait wrapped (t_start < t_enqueue).
    #[test]
    fn a_frame_queued_after_an_arbitration_s_instant_does_not_take_part_in_it() {
        for policy in [Policy::Priority, Policy::Fifo] {
            let mut b = Bus::new("b", BitTiming::new(500_000, 500_000).unwrap(), policy, 8, false, 100_000_000);
            let (a, c) = (b.attach("A", Sink::None, None, false), b.attach("C", Sink::None, None, false));
            assert!(b.enqueue(c, 0x000, &[0xFF; 8], 200_000, None)); // the babbler, queued at 200 us
            assert_eq!(b.arbitrate(150_000).unwrap(), None); // nothing was queued by 150 us
            assert!(b.enqueue(a, 0x300, &[1], 100_000, None)); // a turn's frame of 100 us, taken later
            let end = b.arbitrate(150_000).unwrap().unwrap();
            assert_eq!(b.current.unwrap().frame_id, 0x300, "{policy:?}");
            b.complete();
            assert!(b.arbitrate(end).unwrap().is_some());
            let tx = b.complete();
            assert_eq!((tx.frame_id, tx.t_start, tx.t_enqueue), (0x000, end, 200_000), "{policy:?}");
            let rows: Vec<f64> = b.stats.frames.chunks(4).map(|r| r[3]).collect(); // the waits
            assert!(rows.iter().all(|&w| (0.0..1.0).contains(&w)), "{rows:?}");
        }
    }

    /// The load rows (window end in ns, load).
    fn load_rows(b: &Bus) -> Vec<(u64, f64)> {
        b.stats.load.chunks(2).map(|w| ((w[0] * 1e9).round() as u64, w[1])).collect()
    }

    #[test]
    fn aligned_load_windows_end_at_the_origin_plus_whole_windows() {
        let mut b = Bus::new("b", BitTiming::new(1_000_000, 1_000_000).unwrap(), Policy::Priority, 8, false, 100_000);
        let a = b.attach("A", Sink::None, None, false);
        b.align_load_windows(1_030_000, 250_000); // the run's zero at 1.03 ms, in the future: the next end is 330 us
        assert_eq!(load_rows(&b), vec![(100_000, 0.0), (200_000, 0.0)]);
        assert_eq!(b.load_window_end(), 330_000);
        b.enqueue(a, 0, &[], 1_010_000, None);
        let end = b.arbitrate(1_010_000).unwrap().unwrap(); // 1010 .. 1063 us: 20 us before the zero, 33 after
        b.complete();
        b.finish(1_130_000);
        assert_eq!(end, 1_063_000);
        let rows = load_rows(&b);
        assert_eq!(rows[2..].iter().map(|r| r.0).collect::<Vec<_>>(), vec![330_000, 430_000, 530_000, 630_000, 730_000,
                                                                          830_000, 930_000, 1_030_000, 1_130_000]);
        assert_eq!(rows[rows.len() - 2..], [(1_030_000, 0.2), (1_130_000, 0.33)]);
    }

    #[test]
    fn aligning_keeps_no_window_above_full() {
        let mut b = Bus::new("b", BitTiming::new(1_000_000, 1_000_000).unwrap(), Policy::Priority, 8, false, 100_000);
        let a = b.attach("A", Sink::None, None, false);
        b.enqueue(a, 0, &[], 0, None);
        b.enqueue(a, 0, &[], 0, None);
        b.arbitrate(0).unwrap();
        b.complete(); // 0 .. 53 us booked in the window ending at 100 us
        b.align_load_windows(60_000, 70_000); // the window now in progress ends at 160 us and began at 60 us
        assert_eq!(b.load_window_end(), 160_000);
        let end = b.arbitrate(70_000).unwrap().unwrap(); // 70 .. 123 us
        b.complete();
        b.finish(160_000);
        assert_eq!(end, 123_000);
        // the 53 us booked before the call count as at most the 10 us of the new window that had passed
        assert_eq!(load_rows(&b), vec![(160_000, 0.63)]);
    }

    #[test]
    fn a_frame_that_ended_before_an_aligned_window_began_adds_nothing() {
        let mut b = Bus::new("b", BitTiming::new(1_000_000, 1_000_000).unwrap(), Policy::Priority, 8, false, 100_000);
        let a = b.attach("A", Sink::None, None, false);
        b.enqueue(a, 0, &[], 0, None);
        b.arbitrate(0).unwrap(); // 0 .. 53 us, completed only after the windows were moved
        b.align_load_windows(170_000, 90_000); // now in the window (70, 170] us
        b.complete();
        b.finish(170_000);
        assert_eq!(load_rows(&b), vec![(170_000, 0.0)]);
    }
}
