//! The real-time bus server: one emulated CAN bus in wall-clock time, served by a native thread (no Python
//! interpreter lock), its own or one it shares with the rig's other buses (`serving_thread.rs`), with the
//! unix-socket protocol of `hil/runtime/realtime/protocol.py` (24-byte records).
//!
//! Each turn: wait (`poll_wait.rs`: epoll, nanosecond timeout, timer slack 1 ns) until the frame on the wire ends
//! (when someone must have it then), a read time comes, or a node writes (a quiet reader's records wait for the
//! next turn); read the nodes' records (HELLO, FILTERS, FRAME; AUTH first on TCP), then run the bus's events to now
//! in time order (`settle`; with the other buses of its radio on the same thread, `turn_together`): complete every
//! transmission that ended, hand it to every node whose acceptance filters take it (python-can semantics, applied
//! here), queue the records and the radio's deliveries at their times, arbitrate, SYNC lazy readers; write the
//! output.
//! The last `spin_ns` before an end are polled, not slept.
//! Bad input never stops the server: frames the bus cannot carry are counted and dropped, a record that breaks
//! the protocol disconnects that node, and both are counted and reported (the first few of each kind).
//! The listening sockets are made (owner-only paths, loopback TCP, token file) by the Python side.

use std::collections::{BTreeMap, HashMap};
use std::io::{ErrorKind, Read, Write};
use std::net::TcpListener;
use std::os::fd::{AsRawFd, FromRawFd, RawFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::bus::{Bus, Format, Policy, Sink, Transmission};
use crate::frame::BitTiming;

use crate::histogram::Histogram;
use crate::poll_wait::{descriptors_changed, PollWait};
use crate::protocol::*;
use crate::radio_hub::{Delivery, RadioHub};
use crate::serving_thread::ServingThread;

const READ_RECORDS: usize = 32; // per node and turn: a babbling node cannot stall the loop
const OUT_CAP_BYTES: usize = 1 << 20; // a node that stops reading loses frames beyond this (overruns)
const LOG_FIRST: u64 = 10;
/// The poll set: the wake-up pipe, the unix listener, the TCP listener, the bell, then one per client.
const FIRST_CLIENT_FD: usize = 4;
/// Turns let go at once within one TURNS_BEHIND_WINDOW_S of wall time, the bus further behind the wall clock than a
/// turn may hold it, at which its server gives turns up for the rest of the run (`turns_given_up_s`): the machine
/// does not keep up with them, and holding the bus for more would only put it further behind. Fewer are a moment's
/// stall (the nodes' first cycles at the start of a run let one go on each bus), after which the turns keep the
/// frames at their instants. Seed000 at pace 10 in a slow hour: 6-56 % of the plant's publications late with turns
/// held on, 0.07-0.31 % with this rule, 0.01-0.06 % given up at the first such turn (which would also end the turns
/// of runs that keep up after their start), 0.2-0.3 % after 100 in all (docs/realtime-performance.md, "Turns given
/// up").
pub const TURNS_BEHIND_MAX: u64 = 20;
/// The window TURNS_BEHIND_MAX is counted in, in wall seconds (a window starts at the first turn let go at once).
pub const TURNS_BEHIND_WINDOW_S: f64 = 1.0;
/// How far behind now (wall seconds) a lazy reader's backlog may hold a turn's bus time (`backlog_limit`): a host
/// that held the server this long, or a node whose stamps lag further, has its frames queued when read. A node that
/// keeps its socket full of stamps just inside it can keep its bus that far behind the wall clock, no more (any
/// node can starve a CAN bus with frames of a low ID).
const BACKLOG_MAX_S: f64 = 1.0;

/// Read and forget the bytes that woke the loop (its own wake-up pipe, the bell).
pub(crate) fn drain_wake_ups(source: &mut impl Read) {
    let mut buf = [0u8; 64];
    while let Ok(n) = source.read(&mut buf) {
        if n == 0 {
            break;
        }
    }
}

/// A CAN FD frame whose FRAME_DATA records are still coming.
#[derive(Debug, Clone)]
struct LongFrame {
    can_id: u32,
    flags: u8,
    len: usize,
    data: Vec<u8>,
    /// False for a refused frame: its FRAME_DATA records are read and dropped.
    keep: bool,
    /// When it was queued (bus ns).
    t: u64,
    /// The bus node it is queued as (the connection's sender).
    node: usize,
}

/// Settings of one server.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    pub channel: String,
    pub bitrate: u64,
    /// The data-phase bitrate of CAN FD frames with BRS (the nominal bitrate on a classical bus).
    pub data_bitrate: u64,
    /// Classical: clients may send classical frames only; an FD format: both (each frame says which).
    pub format: Format,
    pub policy: Policy,
    pub depth: usize,
    pub extended: bool,
    pub load_window_ns: u64,
    pub pace: f64,
    pub spin_ns: u64,
    pub max_clients: usize,
    pub hello_timeout: Duration,
    pub keep_log: bool,
    pub token: Option<[u8; 16]>,
}

/// Counters of bad input, by kind.
#[derive(Debug, Default, Clone, Copy)]
pub struct BadInput {
    pub protocol_errors: u64,
    pub truncated_records: u64,
    pub auth_failures: u64,
    pub clients_refused: u64,
}

/// What the serving thread shares with its owner (under one lock, taken once per loop turn).
pub struct Shared {
    pub bus: Bus,
    pub frames: u64,
    pub busy_ns: u64,
    pub rejected: u64,
    pub overruns: u64,
    pub latency: Histogram,
    pub lateness: Histogram,
    pub bad: BadInput,
    pub clients: usize,
    /// Of `clients`, those that take their frames as they end (not lazy readers): python-can programs and devices,
    /// not the rig's own nodes, which read lazily. The rig waits for an external unit's before its clock starts.
    pub eager_clients: usize,
    /// Turns of the serving loop so far (each one a wake-up of its thread).
    pub turns: u64,
    /// Nodes' turns (READ_TURNS) the bus waited for: their read time came before their DONE.
    pub turns_held: u64,
    /// Turns let go: after TURN_HOLD_MAX_S without their DONE (the bus went on without the rest of the turn), or at
    /// once on a bus already further behind the wall clock than that (`turns_behind`).
    pub turn_overruns: u64,
    /// Of `turn_overruns`, those held TURN_HOLD_MAX_S without their DONE, by the node's name: who was late.
    pub turns_let_go: BTreeMap<String, u64>,
    /// Of `turn_overruns`, those let go at once because the bus itself was behind the wall clock.
    pub turns_behind: u64,
    /// The read time (epoch s) at which the server gave turns up, having let TURNS_BEHIND_MAX go at once within
    /// TURNS_BEHIND_WINDOW_S (None: it takes them still): from then on its nodes' read times are plain reads.
    pub turns_given_up_s: Option<f64>,
    /// Log lines for the owner to report (bad input, joins and leaves).
    pub messages: Vec<LogLine>,
}

/// A line of a server's log: its level ("INFO" or "WARNING"), its text, and the model time at which it happened (ns
/// since the server's zero), so the owner can time it exactly however late it reports it.
#[derive(Clone, Debug, PartialEq)]
pub struct LogLine {
    pub level: &'static str,
    pub text: String,
    pub t_ns: u64,
}

enum Stream {
    Unix(UnixStream),
    Tcp(std::net::TcpStream),
}

impl Stream {
    fn fd(&self) -> RawFd {
        match self {
            Stream::Unix(s) => s.as_raw_fd(),
            Stream::Tcp(s) => s.as_raw_fd(),
        }
    }
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self {
            Stream::Unix(s) => s.read(buf),
            Stream::Tcp(s) => s.read(buf),
        }
    }
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Stream::Unix(s) => s.write(buf),
            Stream::Tcp(s) => s.write(buf),
        }
    }
}

struct Client {
    stream: Stream,
    cid: u32,
    name: String,
    node: Option<usize>,
    rx: Vec<u8>,
    out: Vec<u8>,
    closed: bool,
    receive_own: bool,
    filters: Option<Vec<Filter>>,
    pending: Option<Vec<Filter>>,
    pending_left: usize,
    pending_gen: u32,
    rejected: u64,
    authed: bool,
    t_open: Instant,
    long: Option<LongFrame>,
    /// Records of `rx` already processed this turn.
    rx_off: usize,
    /// Bytes at the front of `out` to write now (a lazy reader's frames wait for its next SYNC).
    flush_to: usize,
    /// A lazy reader (`OPTION_LAZY`): its frames go out at its read times, its FRAME records carry their times.
    lazy: bool,
    /// Its read times: (next, period, turn) in bus ns, period 0 for a single read; `turn`: each is a turn
    /// (READ_TURNS).
    reads: Vec<(u64, u64, bool)>,
    /// Its open turns: the read times (bus ns) it was synced to and has not ended with DONE (a DONE ends every
    /// turn up to its stamp), and whether the bus has waited for each yet (counted once in `turns_held`).
    turns: Vec<(u64, bool)>,
    /// The latest read time (bus ns) it was synced to: its frames since carry that instant or a later one.
    synced_to: u64,
    /// A quiet lazy reader (`OPTION_QUIET`): its records do not wake the loop (it rings the bell when they must).
    quiet: bool,
    /// The bus nodes of its senders 1, 2, ... (FRAME byte 3; sender 0 is `node`), attached at their first frame.
    senders: Vec<usize>,
    /// The names its senders 1, 2, ... were given (SENDER_NAME) before their first frame, by sender.
    sender_names: HashMap<usize, String>,
    /// The fewest data bytes any of its frames carries (LEAST_DATA; 0 until it says), and whether it sent a frame
    /// (after which it may no longer say).
    least_data: u8,
    sent: bool,
}

impl Client {
    /// Whether bus node `node` is one of this connection's (its own or a sender's).
    fn owns(&self, node: usize) -> bool {
        self.node == Some(node) || self.senders.contains(&node)
    }

    /// Queue bytes the node must get now (handshake answers), with everything before them.
    fn push_now(&mut self, bytes: &[u8]) {
        self.out.extend_from_slice(bytes);
        self.flush_to = self.out.len();
    }

    /// A node that takes its frames as they end (not a lazy reader): a python-can program or device.
    fn is_eager_node(&self) -> bool {
        !self.lazy && self.node.is_some() && !self.closed
    }

    fn next_read(&self) -> Option<u64> {
        if self.closed || self.node.is_none() {
            return None;
        }
        self.reads.iter().map(|&(next, _, _)| next).min()
    }

    /// The latest turn it ended (DONE's stamp, epoch s) among the whole records it sent that the server has not
    /// taken yet: a turn ends when its DONE comes, though the records before it take effect at their instants.
    fn done_waiting(&self) -> Option<f64> {
        let whole = (self.rx.len() - self.rx_off) / RECORD_SIZE * RECORD_SIZE;
        self.rx[self.rx_off..self.rx_off + whole].chunks_exact(RECORD_SIZE)
            .filter(|rec| rec[0] == KIND_DONE).map(stamp_of).reduce(f64::max)
    }
}

enum Fault {
    Protocol(String),
    Refused(String),
}

/// The serving loop (runs in its own thread; see the module docstring).
pub struct Server {
    cfg: ServerConfig,
    shared: Arc<Mutex<Shared>>,
    stop: Arc<AtomicBool>,
    listener: UnixListener,
    tcp: Option<TcpListener>,
    wake: UnixStream,
    clients: Vec<Client>,
    next_cid: u32,
    mono0: Instant,
    epoch0_ns: u64,
    next_window: u64,
    ended: Vec<u64>,
    rx_cache: std::collections::HashMap<(u32, bool), Vec<usize>>,
    /// Bus time up to which the bus has been run: arrivals are queued at or after it.
    floor: u64,
    /// A frame was queued on an idle bus at this time: arbitrate there.
    arbitrate_at: Option<u64>,
    /// The least frame any sender could still put on this bus (see `anticipate`): an empty one, unless every
    /// connection said more (LEAST_DATA); set at each turn (`least_frame`).
    least_frame_ns: u64,
    /// The bus's bit timing, for that.
    timing: BitTiming,
    /// About the longest (see `max_ahead_ns`).
    longest_frame_ns: u64,
    /// The rig's radio, when this bus is one of its trains' buses.
    radio: Option<RadioPort>,
    /// The bell quiet readers ring (the read end of `<bus>.bell`, a FIFO): without one, no reader is quiet.
    bell: Option<std::fs::File>,
    /// What the quiet readers were last told to ring for: every frame (true), or the radio's routes (if
    /// `bell_routes`: they must reach the hub at their ends), or nothing.
    bell_every: bool,
    bell_routes: bool,
    /// A quiet reader wrote more than one turn reads: turn again at once.
    more_waiting: bool,
    /// The last instant a lazy reader's records read this turn reach (bus ns), when it sent more than one turn
    /// reads: the bus runs no further this turn, so the rest are queued at their stamps (`backlog_limit`).
    backlog_at: Option<u64>,
    /// The lazy readers' sockets, looked at without waiting in each turn (`lazy_readable`).
    lazy_wait: PollWait,
    /// The turns let go at once in the current window of TURNS_BEHIND_WINDOW_S: (its start, bus ns; how many).
    behind_window: (u64, u64),
    /// The earliest open turn (READ_TURNS) whose read time this turn's now has reached (bus ns), if any.
    turn_hold: Option<u64>,
    /// Whether this turn's now was held back for a node's turn (on this bus or another of its radio): eager nodes'
    /// records then wait, and the loop wakes for the turn's DONE or its end (TURN_HOLD_MAX_S).
    held: bool,
    /// Set once the server has finished (its nodes disconnected, its log closed): its handle's `shutdown` waits.
    done: Arc<AtomicBool>,
}

/// A server's end of the rig's radio (engine/src/radio_hub.rs).
pub struct RadioPort {
    hub: Arc<RadioHub>,
    /// This bus's index among the hub's buses.
    bus: usize,
    /// How far this bus's zero lies after the hub's (model ns): the servers of one radio order their events by it.
    origin_ns: i64,
    /// The radio's node on this bus ("RadioGW"), which sends the frames it delivers.
    node: usize,
    /// IDs whose ends the hub must see (the gateway's routes from this bus).
    routed: std::collections::HashSet<u32>,
    /// Deliveries taken from the hub, not yet queued (their time is still to come), oldest first.
    pending: std::collections::VecDeque<Delivery>,
    /// Whether the hub must wake this server for a delivery (kept up to date each turn; see `radio_hub::Port`).
    eager: Arc<AtomicBool>,
    /// Whether the routed frames must be handed to the hub at their ends (`HubCore::needs_ends`; each turn).
    needs_ends: bool,
}

/// A handle to a running server: stop it, read its state.
pub struct ServerHandle {
    pub shared: Arc<Mutex<Shared>>,
    pub stop: Arc<AtomicBool>,
    wake: UnixStream,
    /// The thread that serves it (with other buses' servers, or alone).
    thread: Arc<ServingThread>,
    /// Whether that thread is this server's alone (closed with it).
    own_thread: bool,
    done: Arc<AtomicBool>,
    pub epoch0_ns: u64,
    pub mono0: Instant,
    pub pace: f64,
}

impl ServerHandle {
    /// Model time now (ns since the server's zero): wall time x pace.
    pub fn now_ns(&self) -> u64 {
        (self.mono0.elapsed().as_nanos() as f64 * self.pace) as u64
    }

    /// Whether it is served (not finished, its thread alive).
    pub fn running(&self) -> bool {
        !self.done.load(Ordering::SeqCst) && self.thread.alive()
    }

    /// Wake the serving loop (something changed under the lock that it must act on now).
    pub fn wake(&self) {
        let _ = (&self.wake).write(b"x");
    }

    /// Stop serving it and wait until it has finished (its nodes disconnected); a thread of its own ends too.
    pub fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        let _ = (&self.wake).write(b"x");
        while !self.done.load(Ordering::SeqCst) && self.thread.alive() {
            std::thread::sleep(Duration::from_micros(200));
        }
        if self.own_thread {
            self.thread.close();
        }
    }
}

pub(crate) fn set_timer_slack() {
    // SAFETY: prctl(PR_SET_TIMERSLACK) only changes this thread's timer slack.
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0);
    }
}

/// About the longest frame a bus can carry: a full extended one of zero bits (stuffed the most), on a CAN FD bus
/// 64 bytes without the faster data phase.
fn longest_frame_ns(timing: &BitTiming, format: Format) -> u64 {
    let classical = timing.frame_ns(0, &[0; 8], true, false, false).unwrap_or(0);
    if format.is_fd() { classical.max(timing.frame_ns(0, &[0; 64], true, true, false).unwrap_or(0)) } else { classical }
}

/// Start serving on already-listening sockets (raw fds the server takes ownership of).
/// `bell`: the bus's bell FIFO (quiet readers ring it), opened read-write and non-blocking; `radio`: the rig's
/// radio hub and this bus's index in it (the server joins it as node "RadioGW"); `thread`: the serving thread it
/// shares with other buses' servers (None: a thread of its own).
pub fn start(cfg: ServerConfig, listener_fd: RawFd, tcp_fd: Option<RawFd>, bell: Option<std::fs::File>,
             radio: Option<(Arc<RadioHub>, usize)>, thread: Option<Arc<ServingThread>>) -> std::io::Result<ServerHandle> {
    let timing = BitTiming::new(cfg.bitrate, cfg.data_bitrate).ok_or_else(|| {
        std::io::Error::new(ErrorKind::InvalidInput, format!("bitrate {} (data {}) has no whole-ns bit time", cfg.bitrate, cfg.data_bitrate))
    })?;
    // SAFETY: the caller hands over fds of listening sockets it no longer uses.
    let listener = unsafe { UnixListener::from_raw_fd(listener_fd) };
    listener.set_nonblocking(true)?;
    let tcp = match tcp_fd {
        // SAFETY: as above.
        Some(fd) => {
            let l = unsafe { TcpListener::from_raw_fd(fd) };
            l.set_nonblocking(true)?;
            Some(l)
        }
        None => None,
    };
    let (wake_r, wake_w) = UnixStream::pair()?;
    wake_r.set_nonblocking(true)?;
    wake_w.set_nonblocking(true)?;
    let least_frame_ns = timing.least_frame_ns(0, cfg.format.is_fd());
    let longest_frame_ns = longest_frame_ns(&timing, cfg.format);
    let mut bus = Bus::new(&cfg.channel, timing, cfg.policy, cfg.depth, cfg.extended, cfg.load_window_ns).with_format(cfg.format);
    let mono0 = Instant::now(); // and the same instant on the epoch clock: records carry epoch times
    let epoch0_ns = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0);
    let radio_wake = if radio.is_some() { Some(wake_w.try_clone()?) } else { None };
    let (thread, own_thread) = match thread {
        Some(t) => (t, false),
        None => (ServingThread::start(&format!("bus-server {}", cfg.channel))?, true),
    };
    let radio = match (radio, radio_wake) {
        (Some((hub, index)), Some(wake)) => {
            let eager = Arc::new(AtomicBool::new(true));
            hub.register(index, mono0, wake, eager.clone(), Arc::as_ptr(&thread) as usize);
            let (routed, origin_ns) = {
                let core = hub.core.lock().unwrap();
                (core.routed_ids(index), core.origin_of(index))
            };
            let node = bus.attach("RadioGW", Sink::None, None, false);
            Some(RadioPort { hub, bus: index, origin_ns, node, routed, pending: Default::default(), eager, needs_ends: true })
        }
        _ => None,
    };
    let shared = Arc::new(Mutex::new(Shared {
        bus, frames: 0, busy_ns: 0, rejected: 0, overruns: 0, latency: Histogram::default(), lateness: Histogram::default(),
        bad: BadInput::default(), clients: 0, eager_clients: 0, turns: 0, turns_held: 0, turn_overruns: 0,
        turns_let_go: BTreeMap::new(), turns_behind: 0, turns_given_up_s: None, messages: Vec::new(),
    }));
    let stop = Arc::new(AtomicBool::new(false));
    let pace = cfg.pace;
    let done = Arc::new(AtomicBool::new(false));
    let server = Server {
        next_window: cfg.load_window_ns, cfg, shared: shared.clone(), stop: stop.clone(), listener, tcp, wake: wake_r,
        clients: Vec::new(), next_cid: 1, mono0, epoch0_ns, ended: Vec::new(), rx_cache: Default::default(),
        floor: 0, arbitrate_at: None, least_frame_ns, timing, longest_frame_ns, radio, bell, bell_every: true, bell_routes: true,
        more_waiting: false, backlog_at: None, behind_window: (0, 0), turn_hold: None, held: false,
        lazy_wait: PollWait::new(),
        done: done.clone(),
    };
    descriptors_changed();
    thread.add(server);
    Ok(ServerHandle { shared, stop, wake: wake_w, thread, own_thread, done, epoch0_ns, mono0, pace })
}

impl Server {
    fn now(&self) -> u64 {
        let wall = self.mono0.elapsed().as_nanos() as u64;
        if self.cfg.pace == 1.0 { wall } else { (wall as f64 * self.cfg.pace) as u64 }
    }

    /// Whether its handle asked it to stop.
    pub(crate) fn stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// The last turn: every node gets what is still for it and is disconnected, the load windows are closed.
    pub(crate) fn finish(&mut self) {
        let shared_arc = self.shared.clone();
        let mut shared = shared_arc.lock().unwrap();
        for c in self.clients.iter_mut() {
            c.flush_to = c.out.len(); // a lazy reader's last frames too
        }
        self.flush(&mut shared);
        self.say_refusals(&mut shared);
        for i in 0..self.clients.len() {
            self.drop_client(&mut shared, i, "server closing");
        }
        let now = self.now();
        Self::close_windows(&mut shared, now, self.cfg.keep_log);
        descriptors_changed(); // the server and its connections close as it is dropped
        self.done.store(true, Ordering::SeqCst);
    }

    /// How long to sleep: to the end of the frame on the wire when someone must have it then (an eager node,
    /// or the error model, which acts at every frame), to the next read time of a lazy reader, else the end of the
    /// load window.
    /// A radio delivery or a frame sent ahead of its time wakes the loop only when someone takes frames as they
    /// end (`prompt`); else the next wake-up queues it at its time, before anyone can see past it.
    fn timeout_ns(&mut self, shared: &Shared) -> i64 {
        if std::mem::take(&mut self.more_waiting) {
            return 0;
        }
        let now = self.now();
        if self.held { // nothing can run until the turn ends: its DONE wakes the loop (poll_set), or its time is up
            let end = match self.turn_hold { // its own turn's end, or (held for another bus's) at most the longest
                Some(r) => (r + self.turn_hold_ns()).max(now + 1),
                None => now + self.turn_hold_ns(),
            };
            return ((end - now) as f64 / self.cfg.pace) as i64;
        }
        let mut wake = self.next_window.max(now); // not now + a window: each earlier wake-up would push it on
        if let Some(end) = self.frame_end_wake(shared) {
            wake = wake.min(end.saturating_sub(self.cfg.spin_ns));
        }
        if let Some(r) = self.next_read() {
            wake = wake.min(self.sync_wake(shared, r));
        }
        if self.prompt(shared) {
            if let Some(d) = self.radio.as_ref().and_then(|r| r.pending.front()) {
                wake = wake.min(d.t_ns);
            }
            if let Some(t) = self.next_pending_record(now) {
                wake = wake.min(t);
            }
        }
        (wake.saturating_sub(now) as f64 / self.cfg.pace) as i64
    }

    /// Whether someone must have frames as they end: `every_end_needed`, or the radio's routed frames must reach
    /// the hub at their ends (`routes_need_ends`).
    fn prompt(&self, shared: &Shared) -> bool {
        self.every_end_needed(shared) || self.routes_need_ends()
    }

    /// Whether this bus's routed frames must reach the radio hub at their ends (`HubCore::needs_ends`).
    fn routes_need_ends(&self) -> bool {
        self.radio.as_ref().is_some_and(|r| r.needs_ends && !r.routed.is_empty())
    }

    /// How far ahead of now a lazy reader's FRAME may be stamped: its SYNC comes up to one frame before its read
    /// time (`anticipate`), and it sends at that read time; a millisecond more for the clocks' rounding.
    fn max_ahead_ns(&self) -> u64 {
        self.longest_frame_ns + 1_000_000
    }

    /// The earliest time a record already read waits for (a FRAME sent ahead of its time), if any.
    fn next_pending_record(&self, now: u64) -> Option<u64> {
        (0..self.clients.len()).filter_map(|i| self.due_record_time(i, now)).filter(|&t| t > now).min()
    }

    /// When the loop can give the SYNC of read time `r` (see `anticipate`): one least frame before it, or when
    /// the frame on the wire ends if it ends by `r` (until then the SYNC must wait for it; the loop sleeps to it).
    fn sync_wake(&self, shared: &Shared, r: u64) -> u64 {
        let early = (r + 1).saturating_sub(self.least_frame_ns);
        match shared.bus.current {
            Some(tx) if tx.t_end <= r => early.max(tx.t_end),
            _ => early,
        }
    }

    /// When the loop must wake for a frame's end (None: no frame needs it). A frame needs its end when a node
    /// takes it as it ends (an eager node; the radio's routes when `routes_need_ends`) or the bus has an error model
    /// or guardian (they act at every frame): at the earliest such a frame can end (`Bus::earliest_end`), not at
    /// every end of the frames before it; whatever the loop did not wake for, `settle` runs in time order at the
    /// next wake-up.
    fn frame_end_wake(&mut self, shared: &Shared) -> Option<u64> {
        let tx = shared.bus.current?;
        if shared.bus.errors.is_some() || shared.bus.guardian.is_some() || !self.clients.iter().any(|c| c.lazy) {
            return Some(tx.t_end);
        }
        if !self.routes_need_ends() && !self.has_eager_node() {
            return None;
        }
        shared.bus.earliest_end(|id, ext| self.needs_end((id, ext)))
    }

    /// Whether a frame of `key` must be handed over at its end: an eager node takes it, or the radio routes it
    /// and needs it then.
    fn needs_end(&mut self, key: (u32, bool)) -> bool {
        self.receivers(key);
        self.rx_cache[&key].iter().any(|&i| !self.clients[i].lazy) || (self.routed(key.0) && self.routes_need_ends())
    }

    /// Cache the clients whose filters take frames of `key` (in `rx_cache`, until the clients or their filters
    /// change).
    fn receivers(&mut self, key: (u32, bool)) {
        if !self.rx_cache.contains_key(&key) {
            let found: Vec<usize> = (0..self.clients.len())
                .filter(|&i| self.clients[i].node.is_some() && !self.clients[i].closed
                        && filters_accept(&self.clients[i].filters, key.0, key.1))
                .collect();
            self.rx_cache.insert(key, found);
        }
    }

    fn next_read(&self) -> Option<u64> {
        self.clients.iter().filter_map(Client::next_read).min()
    }

    /// Remove the closed clients. The others' indices shift, so the receivers cached by index are forgotten (a
    /// frame that ended in the turn a node left cached them with the old indices).
    fn remove_closed(&mut self) {
        let before = self.clients.len();
        self.clients.retain(|c| !c.closed);
        if self.clients.len() != before {
            self.rx_cache.clear();
            descriptors_changed(); // their numbers may come back with the next connections
        }
    }

    /// Whether frames of `frame_id` go to the radio at their end.
    fn routed(&self, frame_id: u32) -> bool {
        self.radio.as_ref().is_some_and(|r| r.routed.contains(&frame_id))
    }

    /// Move the radio's deliveries for this bus from the hub to the local queue (in time order).
    fn take_radio(&mut self) {
        if let Some(r) = self.radio.as_mut() {
            let new = r.hub.core.lock().unwrap().take(r.bus);
            if !new.is_empty() {
                r.pending.extend(new);
                r.pending.make_contiguous().sort_by_key(|d| d.t_ns);
            }
        }
    }

    /// Queue the radio's next delivery on the bus as its node, at its time (not before the floor).
    fn radio_send(&mut self, shared: &mut Shared, t: u64) {
        let Some(r) = self.radio.as_mut() else { return };
        let Some(d) = r.pending.pop_front() else { return };
        let format = shared.bus.format;
        if shared.bus.enqueue_as(r.node, d.frame_id, d.data.as_slice(), t, None, format) && shared.bus.current.is_none() {
            self.arbitrate_at.get_or_insert(t);
        }
    }

    /// Each node's first frame its TX queue refused since the last call (from its records, the radio or a babbler)
    /// as a warning at its time and with its cause (`Bus::take_refusals`), so a run's loss can be found on its
    /// timeline.
    fn say_refusals(&self, shared: &mut Shared) {
        if shared.bus.refusals.is_empty() {
            return;
        }
        for (t_ns, text) in shared.bus.take_refusals() {
            let text = format!("bus {}: {text}", self.cfg.channel);
            shared.messages.push(LogLine { level: "WARNING", text, t_ns });
        }
    }

    /// Before a turn: its descriptors onto the serving thread's poll set (FIRST_CLIENT_FD of its own, then one per
    /// client), and how long it may sleep (wall ns).
    pub(crate) fn poll_set(&mut self, fds: &mut Vec<libc::pollfd>) -> i64 {
        let timeout = {
            let shared_arc = self.shared.clone();
            let shared = shared_arc.lock().unwrap();
            self.timeout_ns(&shared)
        };
        fds.push(libc::pollfd { fd: self.wake.as_raw_fd(), events: libc::POLLIN, revents: 0 });
        fds.push(libc::pollfd { fd: self.listener.as_raw_fd(), events: libc::POLLIN, revents: 0 });
        fds.push(libc::pollfd { fd: self.tcp.as_ref().map_or(-1, |l| l.as_raw_fd()), events: libc::POLLIN, revents: 0 });
        fds.push(libc::pollfd { fd: self.bell.as_ref().map_or(-1, |b| b.as_raw_fd()), events: libc::POLLIN, revents: 0 });
        for c in &self.clients {
            // a quiet reader's records wait for the next wake-up (a hang-up or error is reported all the same),
            // unless the bus is held for its turn: its DONE must wake the loop
            let listen = !c.quiet || (self.held && !c.turns.is_empty());
            let events = if listen { libc::POLLIN } else { 0 } | if c.flush_to == 0 { 0 } else { libc::POLLOUT };
            fds.push(libc::pollfd { fd: c.stream.fd(), events, revents: 0 });
        }
        timeout
    }

    /// The first part of a turn: read what came (`fds`: its own part of the poll set, as `poll_set` made it) and
    /// take the radio's deliveries. Returns now (bus ns), read after the sockets: an eager node's frame is queued at
    /// now, which must not come before it was sent (the thread may be preempted between the two).
    fn take_input(&mut self, shared: &mut Shared, fds: &[libc::pollfd]) -> u64 {
        shared.turns += 1;
        if fds[0].revents != 0 {
            drain_wake_ups(&mut self.wake);
        }
        if fds[3].revents != 0 {
            if let Some(bell) = self.bell.as_mut() {
                drain_wake_ups(bell);
            }
        }
        let n_clients = self.clients.len();
        let lazy_ready = self.lazy_readable();
        let mut full = Vec::new();
        for (k, pfd) in fds.iter().enumerate().skip(FIRST_CLIENT_FD).take(n_clients) {
            let i = k - FIRST_CLIENT_FD;
            let readable = pfd.revents & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) != 0 || lazy_ready[i];
            if readable && !self.clients[i].closed && self.receive(shared, i) && self.clients[i].lazy {
                full.push(i);
            }
        }
        if fds[1].revents != 0 {
            self.accept(shared, false);
        }
        if fds[2].revents != 0 {
            self.accept(shared, true);
        }
        let now = self.now();
        self.backlog_at = self.backlog_limit(&full, now);
        self.more_waiting |= self.backlog_at.is_some(); // the rest of the backlog: turn again at once
        self.take_radio();
        if let Some(r) = &self.radio {
            // before any server of the radio looks ahead this turn (`least_frame`): a new connection counts at once
            r.hub.core.lock().unwrap().set_least_data(r.bus, self.own_least_data());
        }
        self.turn_hold = self.open_turn(shared, now);
        now
    }

    /// The fewest data bytes a frame of this bus's connections carries (LEAST_DATA; None: no connection).
    fn own_least_data(&self) -> Option<u8> {
        self.clients.iter().filter(|c| !c.closed).map(|c| c.least_data).min()
    }

    /// The least frame any sender could still put on this bus (ns): one of the fewest data bytes its connections
    /// said they send and, with a radio, those of every bus of the radio (it forwards their frames); an empty
    /// frame when one did not say.
    fn least_frame(&self) -> u64 {
        let mut least = self.own_least_data();
        if let Some(r) = &self.radio {
            let forwarded = r.hub.core.lock().unwrap().least_data();
            least = least.into_iter().chain(forwarded).min();
        }
        self.timing.least_frame_ns(least.unwrap_or(0) as usize, self.cfg.format.is_fd())
    }

    /// Whether a node's turn opened at read time `t` (its SYNC just went out).
    fn turn_opened_at(&self, t: u64) -> bool {
        self.clients.iter().any(|c| c.turns.contains(&(t, false)))
    }

    /// The longest a turn holds the bus (bus ns): TURN_HOLD_MAX_S of wall time.
    fn turn_hold_ns(&self) -> u64 {
        (TURN_HOLD_MAX_S * 1e9 * self.cfg.pace) as u64
    }

    /// The earliest open turn whose read time `now` has reached, if any: the bus must not run past it until the
    /// node's DONE. The turns a DONE that came ends are closed; one held longer than TURN_HOLD_MAX_S is let go and
    /// counted.
    fn open_turn(&mut self, shared: &mut Shared, now: u64) -> Option<u64> {
        let limit = self.turn_hold_ns();
        let mut earliest: Option<u64> = None;
        for i in 0..self.clients.len() {
            if self.clients[i].turns.is_empty() {
                continue;
            }
            let ended = self.clients[i].done_waiting()
                .and_then(|done| if done == f64::INFINITY { Some(u64::MAX) } else { self.bus_ns(done + SYNC_TOLERANCE_S) });
            let c = &mut self.clients[i];
            let closed = c.closed;
            c.turns.retain_mut(|(r, waited)| {
                if closed || ended.is_some_and(|t| t >= *r) {
                    return false;
                }
                if now > *r + limit {
                    shared.turn_overruns += 1;
                    *shared.turns_let_go.entry(c.name.clone()).or_default() += 1;
                    return false;
                }
                if *r <= now {
                    if !*waited {
                        shared.turns_held += 1;
                        *waited = true;
                    }
                    earliest = Some(earliest.map_or(*r, |e| e.min(*r)));
                }
                true
            });
        }
        earliest
    }

    /// Which clients are lazy readers with something to read now. Their frames carry their time, so what came since
    /// the turn's poll is read too (fewer are late); a quiet reader is not in that poll at all. One poll of their
    /// sockets without waiting (`lazy_wait`, registered between turns), rather than a read of each: most turns,
    /// most of them sent nothing.
    fn lazy_readable(&mut self) -> Vec<bool> {
        let mut ready = vec![false; self.clients.len()];
        let lazy: Vec<usize> = (0..self.clients.len()).filter(|&i| self.clients[i].lazy && !self.clients[i].closed).collect();
        if lazy.is_empty() {
            return ready;
        }
        let mut pfds: Vec<libc::pollfd> = lazy.iter()
            .map(|&i| libc::pollfd { fd: self.clients[i].stream.fd(), events: libc::POLLIN, revents: 0 })
            .collect();
        let polled = self.lazy_wait.wait(&mut pfds, 0);
        for (&i, pfd) in lazy.iter().zip(&pfds) {
            ready[i] = polled < 0 || pfd.revents != 0; // the poll failed (interrupted): read each, as without it
        }
        ready
    }

    /// The last part of a turn, after the bus has run to `now`: the SYNCs it settles, write what is due, close
    /// the load windows, and tell the hub and the quiet readers what this bus needs now.
    fn end_turn(&mut self, shared: &mut Shared, now: u64) {
        self.least_frame_ns = self.least_frame();
        self.anticipate(shared, now);
        if shared.bus.current.is_none() {
            let _ = shared.bus.arbitrate(now);
        }
        self.flush(shared);
        self.say_refusals(shared);
        self.remove_closed();
        if now >= self.next_window {
            Self::close_windows(shared, now, self.cfg.keep_log);
            self.next_window = (now / self.cfg.load_window_ns + 1) * self.cfg.load_window_ns;
            self.expire_handshakes(shared);
            self.remove_closed();
        }
        shared.clients = self.clients.iter().filter(|c| c.node.is_some()).count();
        shared.eager_clients = self.clients.iter().filter(|c| c.is_eager_node()).count();
        let every_end = self.every_end_needed(shared);
        if let Some(r) = self.radio.as_mut() {
            r.eager.store(every_end, Ordering::Relaxed);
            r.needs_ends = r.hub.core.lock().unwrap().needs_ends();
        }
        let routes = self.routes_need_ends();
        if (every_end, routes) != (self.bell_every, self.bell_routes) {
            (self.bell_every, self.bell_routes) = (every_end, routes);
            self.tell_bell();
        }
    }

    /// Whether someone takes every frame at its end: an eager node, the error model or the guardian (they act at
    /// every frame). Then the radio wakes this server for its deliveries and quiet readers ring for every frame.
    fn every_end_needed(&self, shared: &Shared) -> bool {
        shared.bus.errors.is_some() || shared.bus.guardian.is_some() || self.has_eager_node()
    }

    /// Whether a node that takes its frames as they end (not a lazy reader) is on the bus.
    fn has_eager_node(&self) -> bool {
        self.clients.iter().any(Client::is_eager_node)
    }

    /// The BELL records of what quiet readers must ring for now: every frame, or those the radio takes at their
    /// ends, or none.
    fn bell_records(&self) -> Vec<u8> {
        let mut routed: Vec<u32> = match self.radio.as_ref().filter(|_| self.bell_routes) {
            Some(r) => r.routed.iter().copied().collect(),
            None => Vec::new(),
        };
        routed.sort_unstable();
        pack_bell(self.bell_every, &routed)
    }

    /// Tell every quiet reader what to ring for (the set changed).
    fn tell_bell(&mut self) {
        let records = self.bell_records();
        for c in self.clients.iter_mut().filter(|c| c.quiet && !c.closed) {
            c.push_now(&records);
        }
    }

    /// Run the bus alone up to `until` (its events before it): its own events only (`next_step`), not the nodes'
    /// records or the radio's deliveries.
    fn advance_before(&mut self, shared: &mut Shared, until: u64) {
        while let Some((t, kind)) = self.next_step(shared, until, false).filter(|&(t, _)| t < until) {
            self.step(shared, until, t, kind);
        }
        self.floor = self.floor.max(until);
        self.rearm(shared, until);
    }

    /// This server's next event by `now` (bus ns) and its kind: the end of the frame on the wire, an
    /// arbitration, a read time, and with `inputs` a node's record or a radio delivery.
    fn next_step(&self, shared: &Shared, now: u64, inputs: bool) -> Option<(u64, Step)> {
        let bus = match shared.bus.current {
            Some(tx) => Some((tx.t_end, Step::End)),
            None => self.arbitrate_at.map(|ta| (ta.max(shared.bus.busy_until), Step::Arbitrate)),
        };
        let input = if inputs { self.next_input_time(now).map(|t| (t, Step::Input)) } else { None };
        let read = self.next_read().map(|r| (r, Step::Read));
        [bus, input, read].into_iter().flatten().filter(|&(t, _)| t <= now).min()
    }

    /// Take the event `(t, kind)` that `next_step` gave: complete the frame that ended and hand it over
    /// (whatever is queued then competes at its end, after the other events of that instant), take one record
    /// or delivery, arbitrate, or SYNC the lazy readers of read time `t`. Returns whether the radio hub got a
    /// frame (the other buses then have deliveries to take).
    fn step(&mut self, shared: &mut Shared, now: u64, t: u64, kind: Step) -> bool {
        self.floor = self.floor.max(t);
        let mut offered = false;
        match kind {
            Step::End => {
                let done = shared.bus.complete();
                if done.error.is_none() {
                    offered = self.deliver(shared, &done); // a frame destroyed by an error frame is not delivered
                }
                self.arbitrate_at = shared.bus.pending().then_some(t);
            }
            Step::Input => self.take_one_input(shared, now, t),
            Step::Arbitrate => {
                self.arbitrate_at = None;
                let _ = shared.bus.arbitrate(t);
            }
            Step::Read => self.sync_readers(shared, t),
        }
        offered
    }

    /// An idle bus with frames queued and no arbitration to come (e.g. after an error frame): arbitrate at
    /// `until` or when the bus is free.
    fn rearm(&mut self, shared: &Shared, until: u64) {
        if shared.bus.current.is_none() && shared.bus.pending() && self.arbitrate_at.is_none() {
            self.arbitrate_at = Some(until.max(shared.bus.busy_until));
        }
    }

    /// The time of the earliest record or radio delivery due by `now`: a lazy reader's FRAME at the time it
    /// carries (not before the bus's floor; one sent ahead of its time waits for it), anyone else's when read.
    fn next_input_time(&self, now: u64) -> Option<u64> {
        let record = (0..self.clients.len()).filter_map(|i| self.due_record_time(i, now)).min();
        self.next_delivery_time(now).into_iter().chain(record).filter(|&t| t <= now).min()
    }

    /// When the radio's next delivery is queued: at its time, not before the bus's floor.
    fn next_delivery_time(&self, now: u64) -> Option<u64> {
        self.radio.as_ref().and_then(|r| r.pending.front()).map(|d| d.t_ns.max(self.floor.min(now)))
    }

    /// Take the earliest input due by `now` (at `t`): the radio's delivery before a record of the same time,
    /// among the records the first node's.
    fn take_one_input(&mut self, shared: &mut Shared, now: u64, t: u64) {
        let mut record: Option<(u64, usize)> = None;
        for i in 0..self.clients.len() {
            if let Some(ti) = self.due_record_time(i, now).filter(|&ti| ti <= now && record.is_none_or(|(b, _)| ti < b)) {
                record = Some((ti, i));
            }
        }
        match (self.next_delivery_time(now), record) {
            (Some(d), r) if r.is_none_or(|(tr, _)| d <= tr) => self.radio_send(shared, t),
            (_, Some((_, i))) => self.process_one(shared, i, t),
            _ => {}
        }
    }

    /// After the servers of a turn have run to their nows: forget the records taken, keep the bus armed.
    fn settled(&mut self, shared: &Shared, now: u64) {
        for c in self.clients.iter_mut() {
            c.rx.drain(..c.rx_off.min(c.rx.len()));
            c.rx_off = 0;
        }
        self.floor = self.floor.max(now);
        self.rearm(shared, now);
    }

    /// Which radio hub this server is on (None: none): the servers of one hub on one thread turn together.
    pub(crate) fn radio_key(&self) -> Option<usize> {
        self.radio.as_ref().map(|r| Arc::as_ptr(&r.hub) as usize)
    }

    /// How far this bus's zero lies after its radio hub's (0 without a radio): its time plus this is the hub's.
    fn origin_ns(&self) -> i64 {
        self.radio.as_ref().map_or(0, |r| r.origin_ns)
    }

    /// SYNC the read times that the bus's state settles now, so that every frame that ends by them has been
    /// handed over: while a frame is on the wire, every read time before its end (no other frame can end before
    /// it); on an idle bus, those less than the least frame any sender could still send away (`least_frame`: a
    /// frame not yet on the wire cannot end by then). A read time after the end of the frame on the wire waits for
    /// it. The lazy reader has its SYNC before its read time and acts at once, so it does not wait for this loop's
    /// wake-up at that time.
    fn anticipate(&mut self, shared: &mut Shared, now: u64) {
        let horizon = now.saturating_add(self.least_frame_ns);
        while let Some(r) = self.next_read() {
            let settled = match shared.bus.current {
                Some(tx) => tx.t_end > r,
                None => r < horizon,
            };
            if !settled {
                return;
            }
            self.sync_readers(shared, r);
        }
    }

    /// Read time `r` of lazy readers: a SYNC after the frames that ended by then, written out now; a turn opened for
    /// each whose read is a turn, unless the bus is too far behind (let go at once) or the server gave turns up.
    fn sync_readers(&mut self, shared: &mut Shared, r: u64) {
        let stamp = self.epoch_s(r);
        // a bus already further behind the wall clock than a turn may hold it does not wait: it catches up first
        let now = self.now();
        let on_time = now <= r + self.turn_hold_ns();
        let window_ns = (TURNS_BEHIND_WINDOW_S * 1e9 * self.cfg.pace) as u64;
        for c in self.clients.iter_mut().filter(|c| c.next_read() == Some(r)) {
            c.push_now(&pack_sync(stamp));
            c.synced_to = r;
            if shared.turns_given_up_s.is_none() && c.reads.iter().any(|&(next, _, turn)| turn && next <= r) {
                if on_time {
                    c.turns.push((r, false));
                } else {
                    shared.turn_overruns += 1; // not held: let go at once
                    shared.turns_behind += 1;
                    if Self::falls_behind(&mut self.behind_window, now, window_ns) {
                        shared.turns_given_up_s = Some(stamp);
                    }
                }
            }
            c.reads.retain_mut(|(next, period, _)| {
                if *next > r {
                    return true;
                }
                if *period == 0 {
                    return false;
                }
                *next += (r - *next) / *period * *period + *period; // the first read after r
                true
            });
        }
    }

    /// One more turn let go at once at `now` (bus ns), counted in `window` (its start, how many) of `window_ns`:
    /// whether that makes TURNS_BEHIND_MAX in one window (the server then gives turns up).
    fn falls_behind(window: &mut (u64, u64), now: u64, window_ns: u64) -> bool {
        if window.1 == 0 || now >= window.0 + window_ns {
            *window = (now, 0);
        }
        window.1 += 1;
        window.1 >= TURNS_BEHIND_MAX
    }

    /// READ_EVERY from a lazy reader: its read times from `first` (epoch s) every `period` s (0: once).
    fn read_every(&mut self, i: usize, r: &[u8], now: u64) -> Result<(), Fault> {
        let (first, period, turns) = (stamp_of(r), f64::from_le_bytes(r[16..24].try_into().unwrap()), r[1] & READ_TURNS != 0);
        let c = &self.clients[i];
        if !(first.is_finite() && period.is_finite() && period >= 0.0) {
            return Err(Fault::Protocol(format!("READ_EVERY: first {first}, period {period} s from node {}", c.name)));
        }
        if c.reads.len() >= MAX_READ_SCHEDULES {
            return Err(Fault::Protocol(format!("READ_EVERY: more than {MAX_READ_SCHEDULES} read schedules from node {}", c.name)));
        }
        let period_ns = (period * 1e9 * self.cfg.pace) as u64;
        if period > 0.0 && period_ns < 10_000 {
            return Err(Fault::Protocol(format!("READ_EVERY: a period of {period} s (bus time) is below 10 µs")));
        }
        let mut next = self.bus_ns(first).unwrap_or(0);
        if period_ns > 0 && next < now {
            next += (now - next).div_ceil(period_ns) * period_ns; // the first read time still to come
        }
        self.clients[i].reads.push((next.max(self.floor), period_ns, turns));
        Ok(())
    }

    /// A bus time (ns) in epoch seconds, as records carry it; `bus_ns` is its inverse.
    fn epoch_s(&self, t: u64) -> f64 {
        (self.epoch0_ns as f64 + t as f64 / self.cfg.pace) / 1e9
    }

    /// An epoch second in bus ns (None before the bus's zero or not finite).
    fn bus_ns(&self, epoch_s: f64) -> Option<u64> {
        let ns = (epoch_s * 1e9 - self.epoch0_ns as f64) * self.cfg.pace;
        (ns.is_finite() && ns >= 0.0).then_some(ns as u64)
    }

    /// Hand a frame that ended to its receivers (a lazy reader's wait for its next SYNC) and, if routed, to the
    /// radio hub; returns whether the hub got it.
    fn deliver(&mut self, shared: &mut Shared, tx: &Transmission) -> bool {
        let flags = if tx.extended { FLAG_EXTENDED } else { 0 } | format_flags(tx.format);
        let stamp = self.epoch_s(tx.t_end);
        let mut packed = Vec::with_capacity(MAX_FRAME_RECORDS * RECORD_SIZE);
        pack_frame_records(tx.frame_id, tx.data.as_slice(), flags, stamp, &mut packed);
        let mut record = [0u8; MAX_FRAME_RECORDS * RECORD_SIZE]; // copied per receiver without allocating
        let size = packed.len();
        record[..size].copy_from_slice(&packed);
        let key = (tx.frame_id, tx.extended);
        self.receivers(key);
        let receivers = self.rx_cache.remove(&key).unwrap_or_default();
        let mut eager = false;
        for &i in &receivers {
            let c = &mut self.clients[i];
            let mut rec = record;
            if c.owns(tx.node) {
                if !c.receive_own {
                    continue;
                }
                rec[1] |= FLAG_ECHO;
            }
            if c.out.len() >= OUT_CAP_BYTES {
                shared.overruns += 1;
                continue;
            }
            c.out.extend_from_slice(&rec[..size]);
            if !c.lazy {
                c.flush_to = c.out.len();
                eager = true;
            }
        }
        self.rx_cache.insert(key, receivers);
        let routed = self.radio.as_ref().filter(|r| r.routed.contains(&tx.frame_id));
        if let Some(r) = routed {
            r.hub.core.lock().unwrap().offer(r.bus, tx.frame_id, tx.data.as_slice(), tx.t_end);
        }
        shared.frames += 1;
        shared.busy_ns += tx.t_end - tx.t_start;
        shared.latency.add((tx.t_end - tx.t_enqueue) as i64);
        if eager {
            self.ended.push(tx.t_end); // delivery lateness: of the frames handed over at their end
        }
        routed.is_some()
    }

    fn flush(&mut self, shared: &mut Shared) {
        for i in 0..self.clients.len() {
            if self.clients[i].closed || self.clients[i].flush_to == 0 {
                continue;
            }
            let c = &mut self.clients[i];
            match c.stream.write(&c.out[..c.flush_to]) {
                Ok(n) => {
                    c.out.drain(..n);
                    c.flush_to -= n;
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock || e.kind() == ErrorKind::Interrupted => {}
                Err(e) => self.drop_client(shared, i, &format!("send failed: {e}")),
            }
        }
        if !self.ended.is_empty() {
            let t = self.now() as i64;
            for &t_end in &self.ended {
                shared.lateness.add(((t - t_end as i64) as f64 / self.cfg.pace) as i64);
            }
            self.ended.clear();
        }
    }

    fn close_windows(shared: &mut Shared, now: u64, keep_log: bool) {
        let t = match shared.bus.current {
            None => now,
            Some(tx) => now.min(tx.t_end.saturating_sub(1)),
        };
        shared.bus.finish(t);
        if !keep_log && shared.bus.stats.frames.len() >= 4 << 16 {
            shared.bus.stats.frames.clear(); // bounded memory: the histograms keep the statistics
        }
    }

    /// A line for the owner's log, stamped with the model time now.
    fn say(&self, shared: &mut Shared, level: &'static str, text: String) {
        shared.messages.push(LogLine { level, text, t_ns: self.now() });
    }

    fn bad_input(&self, shared: &mut Shared, kind: &str, text: String) {
        let counter = match kind {
            "protocol_errors" => &mut shared.bad.protocol_errors,
            "truncated_records" => &mut shared.bad.truncated_records,
            "auth_failures" => &mut shared.bad.auth_failures,
            _ => &mut shared.bad.clients_refused,
        };
        *counter += 1;
        let n = *counter;
        if n <= LOG_FIRST || n % 1000 == 0 {
            self.say(shared, "WARNING", format!("bus {}: {text} ({kind} #{n})", self.cfg.channel));
        }
    }

    fn accept(&mut self, shared: &mut Shared, tcp: bool) {
        loop {
            let accepted = if tcp {
                match self.tcp.as_ref().unwrap().accept() {
                    Ok((s, addr)) => Ok((Stream::Tcp(s), Some(addr.ip()))),
                    Err(e) => Err(e),
                }
            } else {
                self.listener.accept().map(|(s, _)| (Stream::Unix(s), None))
            };
            let (stream, ip) = match accepted {
                Ok(x) => x,
                Err(e) if e.kind() == ErrorKind::WouldBlock || e.kind() == ErrorKind::Interrupted => return,
                Err(e) => {
                    self.bad_input(shared, "clients_refused", format!("accept failed: {e}"));
                    return;
                }
            };
            let waiting = self.clients.iter().filter(|c| !c.closed && !c.authed).count();
            let why = if ip.is_some_and(|ip| !ip.is_loopback() && ip.to_string() != "::ffff:127.0.0.1") {
                Some((0, format!("TCP peer {} is not loopback", ip.unwrap())))
            } else if tcp && waiting >= MAX_UNAUTHENTICATED {
                Some((REFUSED_WAITING, format!("{MAX_UNAUTHENTICATED} TCP connections are already waiting to authenticate")))
            } else if !tcp && self.authenticated() >= self.cfg.max_clients {
                Some((REFUSED_FULL, format!("more than {} connections", self.cfg.max_clients)))
            } else {
                None
            };
            if let Some((code, why)) = why {
                let mut stream = stream;
                if code != 0 {
                    let _ = stream.write(&pack_refused(code));
                }
                drop(stream);
                self.bad_input(shared, "clients_refused", format!("connection refused: {why}"));
                continue;
            }
            match &stream {
                Stream::Unix(s) => {
                    let _ = s.set_nonblocking(true);
                }
                Stream::Tcp(s) => {
                    let _ = s.set_nonblocking(true);
                    let _ = s.set_nodelay(true);
                }
            }
            let cid = self.next_cid;
            self.next_cid += 1;
            descriptors_changed();
            self.clients.push(Client {
                stream, cid, name: format!("#{cid}"), node: None, rx: Vec::new(), out: Vec::new(), closed: false,
                receive_own: false, filters: None, pending: None, pending_left: 0, pending_gen: 0, rejected: 0,
                authed: !tcp, t_open: Instant::now(), long: None, rx_off: 0, flush_to: 0, lazy: false, reads: Vec::new(),
                turns: Vec::new(), synced_to: 0, quiet: false, senders: Vec::new(), sender_names: HashMap::new(),
                least_data: 0, sent: false,
            });
        }
    }

    /// Open connections that count against ``max_clients``: unix sockets, and TCP ones that showed the token.
    fn authenticated(&self) -> usize {
        self.clients.iter().filter(|c| !c.closed && c.authed).count()
    }

    fn expire_handshakes(&mut self, shared: &mut Shared) {
        let limit = self.cfg.hello_timeout;
        for i in 0..self.clients.len() {
            let c = &mut self.clients[i];
            if !c.closed && !c.authed && c.t_open.elapsed() > AUTH_TIMEOUT {
                let _ = c.stream.write(&pack_refused(REFUSED_TIMEOUT));
                let text = format!("TCP connection #{} sent no token within {} s", c.cid, AUTH_TIMEOUT.as_secs_f64());
                self.bad_input(shared, "auth_failures", text);
                self.drop_client(shared, i, "authentication timeout");
                continue;
            }
            let c = &self.clients[i];
            if !c.closed && c.node.is_none() && c.t_open.elapsed() > limit {
                let text = format!("connection #{} sent no HELLO within {} s", c.cid, limit.as_secs_f64());
                self.bad_input(shared, "protocol_errors", text);
                self.drop_client(shared, i, "handshake timeout");
            }
        }
    }

    /// Read what a node sent into its buffer (at most READ_RECORDS records a turn: a babbling node cannot stall
    /// the loop); a closed connection drops it. Returns whether it read that many (the node may have sent more).
    fn receive(&mut self, shared: &mut Shared, i: usize) -> bool {
        let mut chunk = [0u8; READ_RECORDS * RECORD_SIZE];
        let n = match self.clients[i].stream.read(&mut chunk) {
            Ok(n) => n,
            Err(e) if e.kind() == ErrorKind::WouldBlock || e.kind() == ErrorKind::Interrupted => return false,
            Err(e) => {
                self.drop_client(shared, i, &format!("receive failed: {e}"));
                return false;
            }
        };
        if n == 0 {
            let c = &self.clients[i];
            let partial = c.rx.len() % RECORD_SIZE;
            if partial != 0 {
                let text = format!("node {} (#{}) disconnected inside a record ({partial} of {RECORD_SIZE} bytes, discarded)",
                                   c.name, c.cid);
                self.bad_input(shared, "truncated_records", text);
            }
            self.process_client(shared, i); // its whole records still count
            self.drop_client(shared, i, "disconnected");
            return false;
        }
        self.clients[i].rx.extend_from_slice(&chunk[..n]);
        if n == chunk.len() && self.clients[i].quiet {
            self.more_waiting = true; // the rest would otherwise wait for a wake-up it does not cause
        }
        n == chunk.len()
    }

    /// How far the bus may run this turn for the lazy readers that sent more than it read (`full`): to the last
    /// stamp among their FRAME records read, the earliest of those. The records still in their sockets come at or
    /// after it; past it they would be queued at the floor, all at once, rather than at their stamps (a server
    /// held up by the host finds a node's records of that while). A stamp at or before the floor holds nothing
    /// (those frames are late whatever the bus does), nor one further from now than `max_ahead_ns` ahead or
    /// BACKLOG_MAX_S behind (not believed).
    fn backlog_limit(&self, full: &[usize], now: u64) -> Option<u64> {
        let behind_max = (BACKLOG_MAX_S * 1e9 * self.cfg.pace) as u64;
        full.iter().filter_map(|&i| {
            let c = &self.clients[i];
            let whole = (c.rx.len() - c.rx_off) / RECORD_SIZE * RECORD_SIZE;
            let last = c.rx[c.rx_off..c.rx_off + whole].chunks_exact(RECORD_SIZE).rev().find(|r| r[0] == KIND_FRAME)?;
            let t = self.bus_ns(stamp_of(last))?;
            (t > self.floor && t <= now + self.max_ahead_ns() && t + behind_max >= now).then_some(t)
        }).min()
    }

    /// Every whole record of one node, at once (a node that is leaving).
    fn process_client(&mut self, shared: &mut Shared, i: usize) {
        let now = self.now();
        while let Some(t) = self.next_record_time(i, now).map(|t| t.min(now)) {
            self.advance_before(shared, t);
            self.process_one(shared, i, t);
        }
    }

    fn process_one(&mut self, shared: &mut Shared, i: usize, t: u64) {
        let off = self.clients[i].rx_off;
        let mut r = [0u8; RECORD_SIZE];
        r.copy_from_slice(&self.clients[i].rx[off..off + RECORD_SIZE]);
        self.clients[i].rx_off += RECORD_SIZE;
        if let Err(fault) = self.record(shared, i, &r, t) {
            match fault {
                Fault::Protocol(why) => {
                    let c = &self.clients[i];
                    let text = format!("node {} (#{}) dropped: {why}", c.name, c.cid);
                    self.bad_input(shared, "protocol_errors", text);
                    self.drop_client(shared, i, &format!("protocol error: {why}"));
                }
                Fault::Refused(why) => self.drop_client(shared, i, &format!("refused: {why}")),
            }
            let c = &mut self.clients[i];
            c.rx.clear();
            c.rx_off = 0;
        }
    }

    /// `next_record_time`, but none for an eager node while the bus is held for a turn: its records wait for the
    /// turn's end and are queued when taken, never before they came.
    fn due_record_time(&self, i: usize, now: u64) -> Option<u64> {
        if self.held && !self.clients[i].lazy {
            return None;
        }
        self.next_record_time(i, now)
    }

    /// When node `i`'s next whole record takes effect (None: it has none, or it is closed).
    fn next_record_time(&self, i: usize, now: u64) -> Option<u64> {
        let c = &self.clients[i];
        if c.closed || c.rx.len() - c.rx_off < RECORD_SIZE {
            return None;
        }
        Some(self.record_time(c, &c.rx[c.rx_off..c.rx_off + RECORD_SIZE], now))
    }

    /// When a record takes effect: a lazy reader's FRAME at its stamp (not before the floor; up to `max_ahead_ns`
    /// after now, as a reader synced early sends at its read time), a FRAME_DATA with its FRAME, anything else
    /// now or, for a lazy reader, as soon as possible.
    fn record_time(&self, c: &Client, r: &[u8], now: u64) -> u64 {
        let floor = self.floor.min(now);
        match r[0] {
            KIND_FRAME if c.lazy => match self.bus_ns(stamp_of(r)) {
                Some(t) if t <= now + self.max_ahead_ns() => self.at_read_time(c, t).max(floor),
                _ => now, // further ahead than a node synced early can be: not believed, taken as read
            },
            KIND_FRAME_DATA if c.long.is_some() => c.long.as_ref().unwrap().t,
            _ if c.lazy => floor,
            _ => now,
        }
    }

    /// A lazy reader's frame time `t` (bus ns, from its epoch stamp): the read time it was synced to when `t` is
    /// within SYNC_TOLERANCE_S before it. The node acts at that read time and stamps its frames with the SYNC's own
    /// epoch seconds, whose float (a quarter of a microsecond apart at today's epoch) may convert back to just
    /// before it: such a frame would be queued before a turn's instant, ahead of the frames of the other turns of
    /// that instant it must compete with (a plant's sensor frames beat its wayside's Reference).
    fn at_read_time(&self, c: &Client, t: u64) -> u64 {
        let tolerance = (SYNC_TOLERANCE_S * 1e9 * self.cfg.pace) as u64;
        if t < c.synced_to && c.synced_to - t <= tolerance { c.synced_to } else { t }
    }

    fn record(&mut self, shared: &mut Shared, i: usize, r: &[u8], now: u64) -> Result<(), Fault> {
        let kind = r[0];
        if !self.clients[i].authed {
            let ok = kind == KIND_AUTH && self.cfg.token.is_some_and(|t| constant_time_eq(&r[4..20], &t));
            if !ok {
                let why = if kind == KIND_AUTH { "a wrong token" } else { "no token" };
                let text = format!("TCP connection #{} refused: {why}", self.clients[i].cid);
                self.bad_input(shared, "auth_failures", text);
                let _ = self.clients[i].stream.write(&pack_refused(REFUSED_TOKEN));
                return Err(Fault::Refused(why.into()));
            }
            if self.authenticated() >= self.cfg.max_clients {
                let text = format!("TCP connection #{} refused: more than {} connections", self.clients[i].cid,
                                   self.cfg.max_clients);
                self.bad_input(shared, "clients_refused", text);
                let _ = self.clients[i].stream.write(&pack_refused(REFUSED_FULL));
                return Err(Fault::Refused("the bus is full".into()));
            }
            self.clients[i].authed = true;
            return Ok(());
        }
        let has_node = self.clients[i].node.is_some();
        match kind {
            KIND_FRAME if has_node && self.clients[i].long.is_some() => {
                Err(Fault::Protocol(format!("FRAME before the FRAME_DATA records of the last one from node {}", self.clients[i].name)))
            }
            KIND_FRAME_DATA if self.clients[i].long.is_some() => {
                let long = self.clients[i].long.as_mut().unwrap();
                let take = (long.len - long.data.len()).min(FRAME_DATA_BYTES);
                long.data.extend_from_slice(&r[1..1 + take]);
                if long.data.len() == long.len {
                    let long = self.clients[i].long.take().unwrap();
                    if !long.keep {
                        return Ok(());
                    }
                    let ext = Some(long.flags & FLAG_EXTENDED != 0);
                    shared.bus.enqueue_as(long.node, long.can_id, &long.data, long.t, ext, record_format(long.flags));
                    if shared.bus.current.is_none() {
                        self.arbitrate_at.get_or_insert(long.t); // else it competes at the end of the frame on the wire
                    }
                }
                Ok(())
            }
            KIND_FRAME if has_node => {
                let (flags, dlc, can_id) = (r[1], r[2], u32_at(r, 4));
                let node = self.sender_node(shared, i, r[3] as usize)?;
                let least = self.clients[i].least_data;
                self.clients[i].sent = true;
                let short = (dlc < least).then(|| format!("{dlc} data bytes, fewer than the {least} its connection said (LEAST_DATA)"));
                match frame_error(can_id, dlc, flags, shared.bus.format.is_fd()).or(short) {
                    None if dlc > 8 => {
                        self.clients[i].long = Some(LongFrame { can_id, flags, len: dlc as usize, data: r[16..24].to_vec(), keep: true, t: now, node });
                    }
                    None => {
                        let ext = Some(flags & FLAG_EXTENDED != 0);
                        shared.bus.enqueue_as(node, can_id, &r[16..16 + dlc as usize], now, ext, record_format(flags));
                        if shared.bus.current.is_none() {
                            self.arbitrate_at.get_or_insert(now);
                        }
                    }
                    Some(why) => {
                        let c = &mut self.clients[i];
                        if dlc > 8 {
                            c.long = Some(LongFrame { can_id, flags, len: dlc as usize, data: r[16..24].to_vec(), keep: false, t: now, node });
                        }
                        c.rejected += 1;
                        shared.rejected += 1;
                        if c.rejected == 1 {
                            let text = format!("bus {}: node {} sent a frame the bus cannot carry ({why}); dropped and \
                                                counted", self.cfg.channel, c.name);
                            self.say(shared, "WARNING", text);
                        }
                    }
                }
                Ok(())
            }
            KIND_HELLO if !has_node => self.hello(shared, i, r),
            KIND_READ_EVERY if has_node && self.clients[i].lazy => self.read_every(i, r, now),
            KIND_DONE if has_node && self.clients[i].lazy => {
                // its turns ended when it came (`open_turn`); stamped +inf, its turns are over (its run ended): its
                // read times go on as plain reads, which hold the bus for nothing
                if stamp_of(r) == f64::INFINITY {
                    let c = &mut self.clients[i];
                    c.turns.clear();
                    c.reads.iter_mut().for_each(|read| read.2 = false);
                }
                Ok(())
            }
            KIND_SENDER_NAME if has_node => self.sender_name(shared, i, r),
            KIND_LEAST_DATA if has_node => {
                let (c, bytes, most) = (&mut self.clients[i], r[1], shared.bus.format.max_data());
                if c.sent {
                    return Err(Fault::Protocol(format!("LEAST_DATA from node {} after its first frame", c.name)));
                }
                if bytes as usize > most {
                    return Err(Fault::Protocol(format!("LEAST_DATA: {bytes} data bytes > {most}, the most a frame of this bus carries")));
                }
                c.least_data = bytes;
                Ok(())
            }
            KIND_FILTERS if has_node && self.clients[i].pending.is_none() => {
                let count = u16::from_le_bytes([r[2], r[3]]) as usize;
                if count > MAX_FILTERS {
                    return Err(Fault::Protocol(format!("FILTERS: {count} filters > {MAX_FILTERS}")));
                }
                let c = &mut self.clients[i];
                c.pending_gen = u32_at(r, 4);
                c.pending = Some(Vec::new());
                c.pending_left = count;
                if count == 0 {
                    self.apply_filters(i);
                }
                Ok(())
            }
            KIND_FILTER if self.clients[i].pending.is_some() => {
                let matching = r[1];
                if matching > 2 {
                    return Err(Fault::Protocol(format!("FILTER: match {matching} is not 0, 1 or 2")));
                }
                let c = &mut self.clients[i];
                c.pending.as_mut().unwrap().push(Filter { can_id: u32_at(r, 4), can_mask: u32_at(r, 8), matching });
                c.pending_left -= 1;
                if c.pending_left == 0 {
                    self.apply_filters(i);
                }
                Ok(())
            }
            _ => Err(Fault::Protocol(format!("unexpected record kind {kind} from node {}", self.clients[i].name))),
        }
    }

    /// SENDER_NAME: sender k's bus node is called by the name given (before the connection's first frame).
    fn sender_name(&mut self, shared: &mut Shared, i: usize, r: &[u8]) -> Result<(), Fault> {
        let (k, name) = (r[1] as usize, record_name(r, "SENDER_NAME")?);
        let c = &mut self.clients[i];
        if c.sent {
            return Err(Fault::Protocol(format!("SENDER_NAME from node {} after its first frame", c.name)));
        }
        if k >= MAX_SENDERS {
            return Err(Fault::Protocol(format!("SENDER_NAME for sender {k} of node {}: senders are 0..{}", c.name,
                                               MAX_SENDERS - 1)));
        }
        if k == 0 {
            shared.bus.rename_node(c.node.expect("a SENDER_NAME is taken after HELLO"), &name);
        } else {
            c.sender_names.insert(k, name);
        }
        Ok(())
    }

    fn hello(&mut self, shared: &mut Shared, i: usize, r: &[u8]) -> Result<(), Fault> {
        let (version, options) = (r[1], r[2]);
        let name = record_name(r, "HELLO")?;
        let fd_rate = if self.cfg.format.is_fd() { self.cfg.data_bitrate as u32 } else { 0 };
        let welcome = pack_welcome(self.cfg.bitrate as u32, self.epoch0_ns as f64 * 1e-9, self.clients[i].cid, fd_rate);
        if version != PROTOCOL_VERSION {
            let _ = self.clients[i].stream.write(&welcome); // tells the node our version before we hang up
            return Err(Fault::Protocol(format!("node {name} speaks protocol version {version}, this server {PROTOCOL_VERSION}")));
        }
        let node = shared.bus.attach(&name, Sink::None, None, false);
        let c = &mut self.clients[i];
        c.name = name;
        c.receive_own = options & OPTION_RECEIVE_OWN != 0;
        c.lazy = options & OPTION_LAZY != 0;
        c.quiet = c.lazy && options & OPTION_QUIET != 0 && self.bell.is_some();
        c.node = Some(node);
        c.push_now(&welcome);
        if c.quiet {
            let records = self.bell_records();
            self.clients[i].push_now(&records);
        }
        let c = &self.clients[i];
        self.rx_cache.clear();
        let text = format!("bus {}: node {} (#{}) joined", self.cfg.channel, c.name, c.cid);
        self.say(shared, "INFO", text);
        Ok(())
    }

    /// The bus node of node `i`'s sender `k` (FRAME byte 3), attached as "<name>.<k>" at its first frame: its own
    /// TX queue, as a separate controller has.
    fn sender_node(&mut self, shared: &mut Shared, i: usize, k: usize) -> Result<usize, Fault> {
        let c = &mut self.clients[i];
        if k == 0 {
            return Ok(c.node.expect("a FRAME is taken after HELLO"));
        }
        if k >= MAX_SENDERS {
            return Err(Fault::Protocol(format!("FRAME from sender {k} of node {}: senders are 0..{}", c.name, MAX_SENDERS - 1)));
        }
        while c.senders.len() < k {
            let k = c.senders.len() + 1;
            let name = c.sender_names.remove(&k).unwrap_or_else(|| format!("{}.{}", c.name, k));
            c.senders.push(shared.bus.attach(&name, Sink::None, None, false));
        }
        Ok(c.senders[k - 1])
    }

    fn apply_filters(&mut self, i: usize) {
        let c = &mut self.clients[i];
        let set = c.pending.take().unwrap_or_default();
        c.filters = if set.is_empty() { None } else { Some(set) };
        c.push_now(&pack_filters_ack(c.pending_gen));
        self.rx_cache.clear();
    }

    fn drop_client(&mut self, shared: &mut Shared, i: usize, why: &str) {
        let c = &mut self.clients[i];
        if c.closed {
            return;
        }
        c.closed = true;
        // SAFETY: shutting down our own socket; the stream is dropped when the client is removed.
        unsafe {
            libc::shutdown(c.stream.fd(), libc::SHUT_RDWR);
        }
        self.rx_cache.clear();
        if let Some(node) = c.node {
            let lost = shared.bus.detach(node) + c.senders.iter().map(|&n| shared.bus.detach(n)).sum::<usize>();
            let level = if lost > 0 { "WARNING" } else { "INFO" }; // frames lost: a warning the rig records
            let text = format!("bus {}: node {} (#{}) left ({why}); {lost} queued frames dropped", self.cfg.channel,
                               c.name, c.cid);
            self.say(shared, level, text);
        }
    }
}

/// The kinds of a server's events, in the order those of one instant are taken, across the servers of one radio
/// too: frame ends (and the radio deliveries they make), the nodes' records and the deliveries, arbitrations,
/// read times.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Step {
    End,
    Input,
    Arbitrate,
    Read,
}

/// One turn of servers that run together (the buses of one radio on one serving thread, or a server alone), each
/// with its part of the poll set: each reads what came, then their events up to now run in time order across them
/// (`settle`), so a frame the radio takes reaches the next bus before anyone there can see past its delivery time
/// and no wake-up is needed at its end; then each writes what is due.
pub(crate) fn turn_together(turns: &mut [(&mut Server, &[libc::pollfd])]) {
    let arcs: Vec<Arc<Mutex<Shared>>> = turns.iter().map(|(s, _)| s.shared.clone()).collect();
    let mut shared: Vec<_> = arcs.iter().map(|a| a.lock().unwrap()).collect();
    let walls: Vec<u64> = turns.iter_mut().zip(shared.iter_mut()).map(|((s, fds), sh)| s.take_input(sh, fds)).collect();
    let nows = hold_for_turns(turns, &walls);
    let nows = settle(turns, &mut shared, &nows);
    for (((s, _), sh), &now) in turns.iter_mut().zip(shared.iter_mut()).zip(&nows) {
        s.end_turn(sh, now);
    }
}

/// The servers' nows (`walls`: their wall-clock bus times) held back to just before the earliest open turn among
/// them, or to the end of a node's backlog read so far (`backlog_at`), in the radio's time (their buses run
/// together, so one node's turn holds them all); each is told whether it is held.
fn hold_for_turns(turns: &mut [(&mut Server, &[libc::pollfd])], walls: &[u64]) -> Vec<u64> {
    let turn = turns.iter().filter_map(|(s, _)| s.turn_hold.map(|r| r as i64 + s.origin_ns() - 1));
    let backlog = turns.iter().filter_map(|(s, _)| s.backlog_at.map(|t| t as i64 + s.origin_ns()));
    let hold = turn.chain(backlog).min();
    turns.iter_mut().zip(walls).map(|((s, _), &wall)| {
        let now = hold.map_or(wall, |h| wall.min((h - s.origin_ns()).max(0) as u64));
        s.held = now < wall;
        now
    }).collect()
}

/// Run the servers' events up to their nows, the earliest first across them (in the radio hub's time; see
/// `Step` for one instant's order). A routed frame's end hands it to the hub, and the other servers take its
/// deliveries before their next event.
fn settle(turns: &mut [(&mut Server, &[libc::pollfd])], shared: &mut [std::sync::MutexGuard<'_, Shared>], nows: &[u64]) -> Vec<u64> {
    let mut nows = nows.to_vec();
    loop {
        let mut best: Option<((i64, Step), usize, u64)> = None;
        for (k, (s, _)) in turns.iter().enumerate() {
            if let Some((t, kind)) = s.next_step(&shared[k], nows[k], true) {
                let key = (t as i64 + s.origin_ns(), kind);
                if best.is_none_or(|(b, _, _)| key < b) {
                    best = Some((key, k, t));
                }
            }
        }
        let Some(((_, kind), k, t)) = best else { break };
        if turns[k].0.step(&mut shared[k], nows[k], t, kind) && turns.len() > 1 {
            for (s, _) in turns.iter_mut() {
                s.take_radio();
            }
        }
        if kind == Step::Read && turns[k].0.turn_opened_at(t) {
            hold_from(turns, &mut nows, t as i64 + turns[k].0.origin_ns());
        }
    }
    for (k, (s, _)) in turns.iter_mut().enumerate() {
        s.settled(&shared[k], nows[k]);
    }
    nows
}

/// A turn begins at `h` (the radio's time) while the servers run: none of them runs past it before its DONE.
fn hold_from(turns: &mut [(&mut Server, &[libc::pollfd])], nows: &mut [u64], h: i64) {
    for ((s, _), now) in turns.iter_mut().zip(nows.iter_mut()) {
        let cap = (h - s.origin_ns()).max(0) as u64;
        if cap < *now {
            *now = cap;
            s.held = true;
        }
    }
}

/// The node name of a HELLO or SENDER_NAME record (bytes 4..24, UTF-8, NUL-padded), as it goes into logs; "?" when
/// empty.
fn record_name(r: &[u8], kind: &str) -> Result<String, Fault> {
    let raw = &r[4..24];
    let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
    let name = std::str::from_utf8(&raw[..end])
        .map_err(|_| Fault::Protocol(format!("{kind}: node name {:?} is not UTF-8", &raw[..end])))?;
    Ok(if name.is_empty() { "?".to_string() } else { loggable(name) })
}

/// A node name as it goes into logs: control characters (newlines, escapes) become '?', so no node can forge a
/// log line (the Python server's ``loggable`` does the same).
fn loggable(name: &str) -> String {
    name.chars().map(|c| if c.is_control() { '?' } else { c }).collect()
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A server on a socket in its own temporary directory: (handle, socket path, directory).
    fn serve(tag: &str, bitrate: u64, data_bitrate: u64, format: Format) -> (ServerHandle, std::path::PathBuf, std::path::PathBuf) {
        serve_with(tag, bitrate, data_bitrate, format, Policy::Priority, 100_000_000, None, None)
    }

    /// `serve` with a load window and a bell (the read end of a socket pair standing for the FIFO).
    #[allow(clippy::too_many_arguments)]
    fn serve_with(tag: &str, bitrate: u64, data_bitrate: u64, format: Format, policy: Policy, load_window_ns: u64,
                  bell: Option<std::fs::File>, thread: Option<Arc<ServingThread>>)
                  -> (ServerHandle, std::path::PathBuf, std::path::PathBuf) {
        let (fd, path, dir) = listen(tag);
        let cfg = ServerConfig {
            channel: "t/b".into(), bitrate, data_bitrate, format, policy, depth: 8, extended: false,
            load_window_ns, pace: 1.0, spin_ns: 0, max_clients: 8, hello_timeout: Duration::from_secs(5),
            keep_log: true, token: None,
        };
        (start(cfg, fd, None, bell, None, thread).unwrap(), path, dir)
    }

    /// A listening unix socket in its own temporary directory: (its fd, to hand over; its path; the directory).
    fn listen(tag: &str) -> (RawFd, std::path::PathBuf, std::path::PathBuf) {
        use std::os::fd::IntoRawFd;
        let dir = std::env::temp_dir().join(format!("th-srv-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("b.sock");
        let _ = std::fs::remove_file(&path);
        (UnixListener::bind(&path).unwrap().into_raw_fd(), path, dir)
    }

    /// A server on bus `index` of `hub` (the radio), served by `thread`, at 10 kbit/s with 1 s load windows.
    fn serve_radio(tag: &str, hub: &Arc<RadioHub>, index: usize, thread: &Arc<ServingThread>)
                   -> (ServerHandle, std::path::PathBuf, std::path::PathBuf) {
        let (fd, path, dir) = listen(tag);
        let cfg = ServerConfig {
            channel: format!("t/{tag}"), bitrate: 10_000, data_bitrate: 10_000, format: Format::Classical,
            policy: Policy::Priority, depth: 8, extended: false, load_window_ns: 1_000_000_000, pace: 1.0, spin_ns: 0,
            max_clients: 8, hello_timeout: Duration::from_secs(5), keep_log: true, token: None,
        };
        (start(cfg, fd, None, None, Some((hub.clone(), index)), Some(thread.clone())).unwrap(), path, dir)
    }

    /// Two buses of one radio hub on one serving thread, at 10 kbit/s: frames 0x100 on the first go to the second
    /// as 0x300, latency 0. Returns the thread and the two servers (handle, socket path, directory).
    fn radio_pair(tag: &str) -> (Arc<ServingThread>, Vec<(ServerHandle, std::path::PathBuf, std::path::PathBuf)>) {
        use crate::radio::{Draws, Hop, Link, Loss};
        let hub = Arc::new(RadioHub::new(None, 1.0));
        let link = hub.add_link(Link::new("1>2", 1e9, vec![], 0, None, Loss::None, false));
        hub.core.lock().unwrap().gateway.add_route(0, 0x100, Hop { dst_bus: 1, dst_id: 0x300, link, reverse: None });
        hub.push_draws(link, Draws { u_step: vec![0.5; 4], u_loss: vec![0.5; 4], jitter_ns: vec![0; 4], next: 0 });
        let thread = ServingThread::start("radio test").unwrap();
        let servers = (0..2).map(|i| serve_radio(&format!("{tag}{i}"), &hub, i, &thread)).collect();
        (thread, servers)
    }

    /// Stop `radio_pair`'s servers, remove their directories, close their thread.
    fn close_radio_pair(thread: Arc<ServingThread>, mut servers: Vec<(ServerHandle, std::path::PathBuf, std::path::PathBuf)>) {
        for (handle, _, dir) in servers.iter_mut() {
            handle.shutdown();
            let _ = std::fs::remove_dir_all(dir);
        }
        thread.close();
    }

    /// The times on the wire of the routed frame of `radio_pair`, on the first bus and on the second (s).
    fn routed_frame_times() -> (f64, f64) {
        let timing = BitTiming::new(10_000, 10_000).unwrap();
        let on = |id| timing.frame_ns(id, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
        (on(0x100), on(0x300))
    }

    /// The buses of one radio on one serving thread run together in time order: a lazy node's routed frame is on
    /// the next bus from the instant it ends (radio latency 0), with no wake-up at that end; the next bus's reader
    /// has it, stamped with its end there, before its SYNC.
    #[test]
    fn a_routed_frame_crosses_to_the_next_bus_at_its_end_without_a_wake_up_there() {
        let (thread, servers) = radio_pair("radio");
        let (mut sender, mut reader) = (connect_node(&servers[0].1, "S", OPTION_LAZY), connect_node(&servers[1].1, "R", OPTION_LAZY));
        let a = &servers[0].0;
        let epoch0 = a.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + a.now_ns() as f64 * 1e-9;
        let (on_a, on_b) = routed_frame_times();
        let t_read = now() + 0.01 + on_a + on_b + 0.01;
        reader.write_all(&pack_read_every(t_read, 0.0, false)).unwrap();
        std::thread::sleep(Duration::from_millis(10));
        let turns_before = turns(a);
        let t_send = now();
        sender.write_all(&pack_frame(0x100, &[1; 8], 0, t_send)).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        reader.read_exact(&mut rec).unwrap();
        assert_eq!((rec[0], u32_at(&rec, 4)), (KIND_FRAME, 0x300));
        assert!((stamp_of(&rec) - (t_send + on_a + on_b)).abs() < 2e-6, "ended {:.6} s after the send", stamp_of(&rec) - t_send);
        reader.read_exact(&mut rec).unwrap();
        assert_eq!(rec[0], KIND_SYNC);
        // one turn for the sender's write, one for the reader's SYNC: none at the frame's end on either bus
        assert_eq!(turns(a) - turns_before, 2);
        close_radio_pair(thread, servers);
    }

    /// With an eager node on the next bus, the routed frame is handed over at its ends again (`needs_ends`): the
    /// node has it at once, not at the loop's next wake-up (a load window, 1 s away).
    #[test]
    fn an_eager_node_on_the_next_bus_has_the_routed_frame_as_it_ends() {
        let (thread, servers) = radio_pair("radioeager");
        let (mut sender, mut eager) = (connect_node(&servers[0].1, "S", OPTION_LAZY), connect_node(&servers[1].1, "E", 0));
        let a = &servers[0].0;
        let epoch0 = a.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + a.now_ns() as f64 * 1e-9;
        let (on_a, on_b) = routed_frame_times();
        std::thread::sleep(Duration::from_millis(10)); // the eager node's first turn: the hub now needs ends
        let t_send = now();
        sender.write_all(&pack_frame(0x100, &[1; 8], 0, t_send)).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        eager.read_exact(&mut rec).unwrap();
        let got = now();
        assert_eq!((rec[0], u32_at(&rec, 4)), (KIND_FRAME, 0x300));
        assert!((stamp_of(&rec) - (t_send + on_a + on_b)).abs() < 2e-6, "ended {:.6} s after the send", stamp_of(&rec) - t_send);
        assert!(got - stamp_of(&rec) < 0.1, "handed over {:.3} s after its end", got - stamp_of(&rec));
        close_radio_pair(thread, servers);
    }

    /// One connection's frames from two senders wait in two TX queues, as two controllers' would: on a FIFO bus
    /// the second sender's frame competes with the first's head at once (one queue would send it after).
    #[test]
    fn each_sender_of_a_connection_has_its_own_tx_queue() {
        let (mut handle, path, dir) = serve_with("senders", 10_000, 10_000, Format::Classical, Policy::Fifo, 100_000_000, None, None);
        let connect = |name: &str| connect_node(&path, name, 0);
        let (mut host, mut reader) = (connect("H"), connect("R"));
        host.write_all(&pack_frame(0x400, &[1; 8], 0, 0.0)).unwrap(); // on the wire for about 13 ms at 10 kbit/s
        std::thread::sleep(Duration::from_millis(2));
        let mut batch = Vec::new();
        batch.extend_from_slice(&pack_frame(0x300, &[2], 0, 0.0));
        batch.extend_from_slice(&pack_frame_from(0x100, &[3], 0, 0.0, 1));
        host.write_all(&batch).unwrap();
        let mut order = Vec::new();
        let mut rec = [0u8; RECORD_SIZE];
        while order.len() < 3 {
            reader.read_exact(&mut rec).unwrap();
            order.push(u32_at(&rec, 4));
        }
        assert_eq!(order, vec![0x400, 0x100, 0x300]);
        let mut bad = pack_frame(0x100, &[3], 0, 0.0);
        bad[3] = MAX_SENDERS as u8;
        host.write_all(&bad).unwrap();
        assert_eq!(host.read(&mut rec).unwrap_or(0), 0, "a sender beyond MAX_SENDERS ends the session");
        assert_eq!(handle.shared.lock().unwrap().bad.protocol_errors, 1);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Two buses on one serving thread: each carries its own nodes' frames; one shut down, the other goes on; the
    /// thread ends once closed and both have finished.
    #[test]
    fn two_buses_share_a_serving_thread_and_each_stops_on_its_own() {
        let thread = ServingThread::start("bus-servers test").unwrap();
        let mut buses: Vec<_> = ["share1", "share2"].iter()
            .map(|tag| serve_with(tag, 500_000, 500_000, Format::Classical, Policy::Priority, 100_000_000, None, Some(thread.clone())))
            .collect();
        let connect = |path: &std::path::Path, name: &str| connect_node(path, name, 0);
        let exchange = |path: &std::path::Path, id: u32| {
            let (mut a, mut b) = (connect(path, "A"), connect(path, "B"));
            a.write_all(&pack_frame(id, &[1; 8], 0, 0.0)).unwrap();
            let mut rec = [0u8; RECORD_SIZE];
            b.read_exact(&mut rec).unwrap();
            assert_eq!((rec[0], u32_at(&rec, 4)), (KIND_FRAME, id));
        };
        exchange(&buses[0].1, 0x101);
        exchange(&buses[1].1, 0x202);
        buses[0].0.shutdown();
        assert!(!buses[0].0.running() && buses[1].0.running());
        exchange(&buses[1].1, 0x203);
        thread.close();
        assert!(buses[1].0.running(), "closing the thread does not stop the servers it has");
        buses[1].0.shutdown();
        for _ in 0..100 {
            if !thread.alive() {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(!thread.alive());
        for (_, _, dir) in buses {
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// A server with nothing to do still turns at the end of each load window (it closes the window's statistics
    /// and takes what quiet readers sent). It never did with windows longer than the serving thread's idle sleep
    /// (100 ms): the wake-up was reckoned from each look, so it moved on at every one.
    #[test]
    fn an_idle_server_turns_at_the_end_of_each_load_window() {
        let (mut handle, _path, dir) = serve_with("windows", 500_000, 500_000, Format::Classical, Policy::Priority,
                                                   200_000_000, None, None);
        std::thread::sleep(Duration::from_millis(50));
        let before = turns(&handle);
        std::thread::sleep(Duration::from_millis(700));
        assert!(turns(&handle) - before >= 3, "{} turns in 700 ms", turns(&handle) - before);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn turns(handle: &ServerHandle) -> u64 {
        handle.shared.lock().unwrap().turns
    }

    /// (clients, eager clients) of `handle` once they equal `want`, or as they are after 2 s.
    fn clients_settled(handle: &ServerHandle, want: (usize, usize)) -> (usize, usize) {
        let deadline = Instant::now() + Duration::from_secs(2);
        loop {
            let got = { let s = handle.shared.lock().unwrap(); (s.clients, s.eager_clients) };
            if got == want || Instant::now() > deadline {
                return got;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// The rig's own nodes read lazily; a python-can program or device does not. The server counts the latter
    /// apart (the rig waits for an external unit's before its clock starts), and forgets one that left.
    #[test]
    fn eager_clients_are_counted_apart_from_lazy_readers() {
        let (mut handle, path, dir) = serve("eagercount", 10_000, 10_000, Format::Classical);
        let _lazy = connect_node(&path, "Plant", OPTION_LAZY);
        assert_eq!(clients_settled(&handle, (1, 0)), (1, 0));
        let eager = connect_node(&path, "device", 0);
        assert_eq!(clients_settled(&handle, (2, 1)), (2, 1));
        drop(eager);
        assert_eq!(clients_settled(&handle, (1, 0)), (1, 0));
        handle.shutdown();
        let _ = std::fs::remove_dir_all(dir);
    }

    /// A quiet node's frame does not wake the server; the server reads it at its next wake-up (here a reader's
    /// SYNC) and queues it at the instant it carries, so the reader gets it with its exact end. Its bell does wake
    /// the server.
    #[test]
    fn a_quiet_nodes_frame_waits_for_the_next_wake_up_and_keeps_its_instant_and_its_bell_wakes_the_server() {
        let (bell_w, bell_r) = UnixStream::pair().unwrap();
        bell_r.set_nonblocking(true).unwrap();
        let (mut handle, path, dir) = serve_with("quiet", 500_000, 500_000, Format::Classical, Policy::Priority, 1_000_000_000,
                                                 Some(std::fs::File::from(std::os::fd::OwnedFd::from(bell_r))), None);
        let connect = |name: &str, options: u8| connect_node(&path, name, options);
        let mut quiet = connect("Q", OPTION_LAZY | OPTION_QUIET);
        let mut rec = [0u8; RECORD_SIZE];
        quiet.read_exact(&mut rec).unwrap();
        assert_eq!((rec[0], rec[1] & BELL_EVERY, rec[2]), (KIND_BELL, 0, 0)); // nothing to ring for: no radio, no eager node
        let mut reader = connect("R", OPTION_LAZY);
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + handle.now_ns() as f64 * 1e-9;
        let t_read = now() + 0.03;
        reader.write_all(&pack_read_every(t_read, 0.0, false)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        let before = turns(&handle);
        let t_send = now();
        quiet.write_all(&pack_frame(0x100, &[1; 8], 0, t_send)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(turns(&handle), before, "a quiet node's frame woke the server");
        let mut got = Vec::new();
        while got.len() < 2 {
            reader.read_exact(&mut rec).unwrap();
            got.push((rec[0], stamp_of(&rec)));
        }
        let one_frame = BitTiming::new(500_000, 500_000).unwrap().frame_ns(0x100, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
        assert_eq!((got[0].0, got[1].0), (KIND_FRAME, KIND_SYNC));
        assert!((got[0].1 - (t_send + one_frame)).abs() < 2e-6, "{got:?}"); // ended one frame after its instant
        std::thread::sleep(Duration::from_millis(2));
        let before = turns(&handle);
        (&bell_w).write_all(b"!").unwrap();
        std::thread::sleep(Duration::from_millis(5));
        assert!(turns(&handle) > before, "the bell did not wake the server");
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A lazy reader synced early acts at its read time: a frame it stamps a little ahead of now waits for its
    /// stamp (an eager node hears it end one frame after it); one stamped further ahead is taken when read.
    #[test]
    fn a_lazy_nodes_frame_stamped_ahead_of_now_goes_on_the_bus_at_its_stamp() {
        let (mut handle, path, dir) = serve("ahead", 10_000, 10_000, Format::Classical); // frames of about 5-11 ms
        let connect = |name: &str, options: u8| connect_node(&path, name, options);
        let mut sender = connect("S", OPTION_LAZY);
        let mut eager = connect("E", 0);
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + handle.now_ns() as f64 * 1e-9;
        let timing = BitTiming::new(10_000, 10_000).unwrap();
        let one_frame = timing.frame_ns(0x100, &[1], false, false, false).unwrap() as f64 * 1e-9;
        let shortest = timing.least_frame_ns(0, false) as f64 * 1e-9;
        std::thread::sleep(Duration::from_millis(5));
        let t_send = now() + shortest; // as a node synced one least frame early would stamp it
        sender.write_all(&pack_frame(0x100, &[1], 0, t_send)).unwrap();
        let frame_of = |s: &mut UnixStream| loop {
            let mut rec = [0u8; RECORD_SIZE];
            s.read_exact(&mut rec).unwrap();
            if rec[0] == KIND_FRAME {
                return stamp_of(&rec);
            }
        };
        let end = frame_of(&mut eager);
        assert!((end - (t_send + one_frame)).abs() < 2e-6, "ended {:.6} s after its stamp", end - t_send);
        let written = now();
        sender.write_all(&pack_frame(0x101, &[1], 0, written + 60.0)).unwrap(); // a minute ahead: not believed
        let end = frame_of(&mut eager);
        assert!(end < written + one_frame + 0.01, "held {:.3} s", end - written); // taken when read
        let _ = sender.flush();
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// While a frame is on the wire no other can end, so a read time before its end is settled at once: the
    /// reader has its SYNC as soon as the frame is queued, not one shortest frame before its read time.
    #[test]
    fn a_read_time_before_the_end_of_the_frame_on_the_wire_is_synced_at_once() {
        let (mut handle, path, dir) = serve("settled", 10_000, 10_000, Format::Classical); // frames of about 5-13 ms
        let connect = |name: &str| connect_node(&path, name, OPTION_LAZY);
        let (mut sender, mut reader) = (connect("S"), connect("R"));
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + handle.now_ns() as f64 * 1e-9;
        let timing = BitTiming::new(10_000, 10_000).unwrap();
        let one_frame = timing.frame_ns(0x100, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
        let shortest = timing.least_frame_ns(0, false) as f64 * 1e-9;
        let t_read = now() + 0.005 + one_frame - 0.0005; // while the frame sent in 5 ms is on the wire
        reader.write_all(&pack_read_every(t_read, 0.0, false)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        sender.write_all(&pack_frame(0x100, &[1; 8], 0, now())).unwrap(); // queued when the server reads it
        let mut rec = [0u8; RECORD_SIZE];
        reader.read_exact(&mut rec).unwrap();
        let got = now();
        assert_eq!(rec[0], KIND_SYNC); // no frame: the one on the wire ends after it
        assert!((stamp_of(&rec) - t_read).abs() < 2e-6);
        assert!(got < t_read - shortest - 0.002, "synced {:.4} s before its read time", t_read - got);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// On an idle bus a read time is SYNCed at once when no frame any connection could still send would end by
    /// it: within the least frame of the fewest data bytes they said (LEAST_DATA). A connection that did not say
    /// may send an empty frame, so the next read waits until one empty frame (47 bits, no stuff bit) before it.
    /// A frame shorter than its connection said is refused, and saying it after a frame is a protocol error.
    #[test]
    fn a_read_time_within_the_least_frame_the_connections_said_is_synced_at_once() {
        let (mut handle, path, dir) = serve("least", 5_000, 5_000, Format::Classical); // 200 µs a bit
        let timing = BitTiming::new(5_000, 5_000).unwrap();
        let (empty, eight) = (timing.least_frame_ns(0, false) as f64 * 1e-9, timing.least_frame_ns(8, false) as f64 * 1e-9);
        assert_eq!((empty, eight), (0.0094, 0.0222));
        let (mut sender, mut reader) = (connect_node(&path, "S", OPTION_LAZY), connect_node(&path, "R", OPTION_LAZY));
        sender.write_all(&pack_least_data(8)).unwrap();
        reader.write_all(&pack_least_data(8)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + handle.now_ns() as f64 * 1e-9;
        let mut rec = [0u8; RECORD_SIZE];
        let mut sync_lead = |reader: &mut UnixStream| {
            let t_read = now() + 0.020;
            reader.write_all(&pack_read_every(t_read, 0.0, false)).unwrap();
            reader.read_exact(&mut rec).unwrap();
            assert_eq!((rec[0], (stamp_of(&rec) - t_read).abs() < 2e-6), (KIND_SYNC, true));
            t_read - now()
        };
        let lead = sync_lead(&mut reader);
        assert!(lead > 0.015, "synced {lead:.4} s before its read time, not at once");
        let _other = connect_node(&path, "O", OPTION_LAZY); // says nothing
        std::thread::sleep(Duration::from_millis(5));
        let lead = sync_lead(&mut reader);
        assert!(lead <= empty + 0.0005, "synced {lead:.4} s before its read time, more than an empty frame");
        sender.write_all(&pack_frame(0x100, &[1; 2], 0, now())).unwrap(); // 2 bytes: fewer than it said
        std::thread::sleep(Duration::from_millis(50));
        let (rejected, frames) = { let shared = handle.shared.lock().unwrap(); (shared.rejected, shared.frames) };
        assert_eq!((rejected, frames), (1, 0));
        sender.write_all(&pack_least_data(1)).unwrap(); // too late: it sent a frame
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(handle.shared.lock().unwrap().bad.protocol_errors, 1);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A node's connection to the server at `path`: its HELLO with `options` said, the WELCOME read, reads that
    /// time out after 2 s.
    fn connect_node(path: &std::path::Path, name: &str, options: u8) -> UnixStream {
        let mut s = UnixStream::connect(path).unwrap();
        let mut r = hello(name);
        r[2] = options;
        s.write_all(&r).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        s.read_exact(&mut rec).unwrap();
        assert_eq!(rec[0], KIND_WELCOME);
        s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        s
    }

    fn hello(name: &str) -> [u8; RECORD_SIZE] {
        let mut r = [0u8; RECORD_SIZE];
        r[0] = KIND_HELLO;
        r[1] = PROTOCOL_VERSION;
        r[4..4 + name.len()].copy_from_slice(name.as_bytes());
        r
    }

    /// Two lazy nodes send at the same instant (their frames carry it); a lazy reader asks to read 20 ms on. The
    /// lower ID wins, the other ends exactly one frame later, and the reader gets both then, before its SYNC.
    #[test]
    fn a_lazy_reader_gets_the_frames_that_ended_by_its_read_time_with_a_sync() {
        let (mut handle, path, dir) = serve("lazy", 500_000, 500_000, Format::Classical);
        let lazy_hello = |name: &str| { let mut r = hello(name); r[2] = OPTION_LAZY; r };
        let mut socks: Vec<UnixStream> = ["A", "B", "R"].iter().map(|n| {
            let mut s = UnixStream::connect(&path).unwrap();
            s.write_all(&lazy_hello(n)).unwrap();
            let mut rec = [0u8; RECORD_SIZE];
            s.read_exact(&mut rec).unwrap();
            assert_eq!(rec[0], KIND_WELCOME);
            s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
            s
        }).collect();
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let t_send = epoch0 + handle.now_ns() as f64 * 1e-9 + 0.005;
        socks[2].write_all(&pack_read_every(t_send + 0.02, 0.0, false)).unwrap();
        std::thread::sleep(Duration::from_millis(10));
        {
            let _hold = handle.shared.lock().unwrap(); // the loop reads both before it runs the bus
            socks[1].write_all(&pack_frame(0x200, &[2; 8], 0, t_send)).unwrap();
            socks[0].write_all(&pack_frame(0x100, &[1; 8], 0, t_send)).unwrap();
        }
        let mut got = Vec::new();
        let mut rec = [0u8; RECORD_SIZE];
        while got.len() < 3 {
            socks[2].read_exact(&mut rec).unwrap();
            got.push((rec[0], u32_at(&rec, 4), stamp_of(&rec)));
        }
        let timing = BitTiming::new(500_000, 500_000).unwrap();
        let one_frame = timing.frame_ns(0x100, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
        let other = timing.frame_ns(0x200, &[2; 8], false, false, false).unwrap() as f64 * 1e-9;
        assert_eq!((got[0].0, got[0].1, got[1].0, got[1].1, got[2].0), (KIND_FRAME, 0x100, KIND_FRAME, 0x200, KIND_SYNC));
        assert!((got[0].2 - (t_send + one_frame)).abs() < 2e-6, "{got:?}"); // queued at the instant it carries
        assert!((got[1].2 - got[0].2 - other).abs() < 2e-6, "{got:?}"); // it waited for the winner, then ran
        assert!((got[2].2 - (t_send + 0.02)).abs() < 2e-6, "{got:?}");
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A node whose turns are over (DONE stamped +inf: its run ended) holds its bus for none of its later read
    /// times, which still SYNC it; without that each is let go, counted under the node's name.
    #[test]
    fn a_done_stamped_infinity_ends_a_nodes_turns_for_good_and_the_let_go_ones_name_their_node() {
        for for_good in [true, false] {
            let (mut handle, path, dir) = serve(if for_good { "good" } else { "goodx" }, 500_000, 500_000, Format::Classical);
            let mut node = connect_node(&path, "P", OPTION_LAZY);
            let epoch0 = handle.epoch0_ns as f64 * 1e-9;
            let first = epoch0 + handle.now_ns() as f64 * 1e-9 + 0.005;
            node.write_all(&pack_read_every(first, 0.005, true)).unwrap();
            let mut rec = [0u8; RECORD_SIZE];
            node.read_exact(&mut rec).unwrap();
            assert_eq!(rec[0], KIND_SYNC);
            // its first turn over; then either its turns for good, or nothing more (each later turn is let go)
            node.write_all(&pack_done(stamp_of(&rec))).unwrap();
            if for_good {
                node.write_all(&pack_done(f64::INFINITY)).unwrap();
            }
            let mut syncs = 0;
            while syncs < 5 { // its read times go on either way
                node.read_exact(&mut rec).unwrap();
                syncs += (rec[0] == KIND_SYNC) as usize;
            }
            std::thread::sleep(Duration::from_secs_f64(2.0 * TURN_HOLD_MAX_S)); // the last one's hold over
            let (overruns, by_node, behind) = {
                let shared = handle.shared.lock().unwrap();
                (shared.turn_overruns, shared.turns_let_go.clone(), shared.turns_behind)
            };
            if for_good {
                assert_eq!((overruns, by_node.len(), behind), (0, 0, 0), "{by_node:?}");
            } else {
                assert!(by_node.get("P").is_some_and(|&n| n >= 1), "{by_node:?}");
                assert_eq!(overruns, by_node["P"] + behind);
            }
            handle.shutdown();
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// A bus that falls further behind the wall clock than a turn may hold it lets its turns go at once
    /// (`turns_behind`). A moment's stall lets a few go and the turns go on; TURNS_BEHIND_MAX in one window and its
    /// server takes no more: the node's later read times are plain reads, and none is held or let go.
    #[test]
    fn a_server_that_falls_behind_its_turns_gives_them_up_and_holds_the_bus_no_more() {
        let (mut handle, path, dir) = serve("giveup", 500_000, 500_000, Format::Classical);
        let mut node = connect_node(&path, "P", OPTION_LAZY);
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = |h: &ServerHandle| epoch0 + h.now_ns() as f64 * 1e-9;
        let first = now(&handle) + 0.005;
        node.write_all(&pack_read_every(first, 0.001, true)).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        node.read_exact(&mut rec).unwrap();
        node.write_all(&pack_done(stamp_of(&rec))).unwrap(); // its first turn, ended
        let stall = |h: &ServerHandle, ms: u64| { // the serving thread stalls: read times meanwhile are synced late
            let _held = h.shared.lock().unwrap();
            std::thread::sleep(Duration::from_millis(ms));
        };
        stall(&handle, 6); // a moment's: a few let go at once
        std::thread::sleep(Duration::from_millis(20));
        let (behind, given_up) = { let s = handle.shared.lock().unwrap(); (s.turns_behind, s.turns_given_up_s) };
        assert!(behind >= 1 && behind < TURNS_BEHIND_MAX && given_up.is_none(), "{behind} {given_up:?}");
        let stalled = std::time::Instant::now();
        stall(&handle, 150); // the machine fell behind
        let given_up = loop {
            let given_up = handle.shared.lock().unwrap().turns_given_up_s;
            if let Some(t) = given_up {
                break t;
            }
            assert!(stalled.elapsed() < Duration::from_secs(2), "turns not given up");
            std::thread::sleep(Duration::from_millis(5));
        };
        assert!(given_up > first && given_up < now(&handle), "given up at {given_up}");
        let counts = |h: &ServerHandle| {
            let shared = h.shared.lock().unwrap();
            (shared.turns_behind, shared.turn_overruns, shared.turns_held)
        };
        let before = counts(&handle);
        assert!(before.0 >= TURNS_BEHIND_MAX && before.0 < TURNS_BEHIND_MAX + 10, "{before:?}");
        // the node never ends another turn: past the SYNCs of the stall, its read times go on, none of them held
        while !(rec[0] == KIND_SYNC && stamp_of(&rec) > now(&handle) - 0.001) {
            node.read_exact(&mut rec).unwrap();
        }
        let mut syncs = 0;
        while syncs < 20 {
            node.read_exact(&mut rec).unwrap();
            syncs += (rec[0] == KIND_SYNC) as usize;
        }
        std::thread::sleep(Duration::from_secs_f64(2.0 * TURN_HOLD_MAX_S));
        assert_eq!(counts(&handle), before, "turns held or let go after they were given up");
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A node's turn (READ_TURNS) that takes longer than the read after it: its frame, sent late but stamped with
    /// its read time, still goes on the bus at that instant, and the later reader's SYNC waits for the turn's DONE,
    /// so that reader has the frame as in virtual time. Without DONE the turn is let go after TURN_HOLD_MAX_S.
    #[test]
    fn a_turn_holds_the_bus_at_its_read_time_until_the_node_ends_it() {
        for ends in [true, false] {
            let (mut handle, path, dir) = serve(if ends { "turn" } else { "turnx" }, 500_000, 500_000, Format::Classical);
            let (mut node, mut reader) = (connect_node(&path, "P", OPTION_LAZY), connect_node(&path, "R", OPTION_LAZY));
            let epoch0 = handle.epoch0_ns as f64 * 1e-9;
            let t_turn = epoch0 + handle.now_ns() as f64 * 1e-9 + 0.01;
            let t_read = t_turn + 0.0004; // after one frame's end, long before the node's turn is over
            node.write_all(&pack_read_every(t_turn, 0.0, true)).unwrap();
            reader.write_all(&pack_read_every(t_read, 0.0, false)).unwrap();
            let mut rec = [0u8; RECORD_SIZE];
            node.read_exact(&mut rec).unwrap();
            assert_eq!(rec[0], KIND_SYNC);
            std::thread::sleep(Duration::from_millis(1)); // the node's work: past the reader's read time
            let mut out = pack_frame(0x100, &[1; 8], 0, t_turn).to_vec();
            if ends {
                out.extend_from_slice(&pack_done(t_turn));
            }
            node.write_all(&out).unwrap();
            let mut got = Vec::new();
            while got.last().is_none_or(|&(kind, _)| kind != KIND_SYNC) {
                reader.read_exact(&mut rec).unwrap();
                got.push((rec[0], stamp_of(&rec)));
            }
            let synced_wall = epoch0 + handle.now_ns() as f64 * 1e-9;
            let one_frame = BitTiming::new(500_000, 500_000).unwrap().frame_ns(0x100, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
            let stats = {
                let shared = handle.shared.lock().unwrap();
                (shared.turns_held, shared.turn_overruns)
            };
            if ends {
                assert_eq!(got.len(), 2, "{got:?}");
                assert_eq!(got[0].0, KIND_FRAME);
                assert!((got[0].1 - (t_turn + one_frame)).abs() < 2e-6, "ended {:.6} s after its turn", got[0].1 - t_turn);
                assert!((got[1].1 - t_read).abs() < 2e-6);
                // not let go; held once, unless a loaded machine woke the loop only after the DONE had come
                assert!(stats.0 <= 1 && stats.1 == 0, "{stats:?}");
            } else {
                assert!(synced_wall - t_turn > TURN_HOLD_MAX_S, "the reader waited {:.6} s", synced_wall - t_turn);
                assert_eq!(stats.1, 1, "let go once");
            }
            handle.shutdown();
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// Two nodes' turns at one read time: the frames both queue at it compete there, however late the second's
    /// come (a plant's sensor frames and its wayside's Reference frames, on two connections of one process). Each
    /// stamps its frames with the SYNC's epoch seconds, which may convert back to just before the read time (the
    /// float's rounding: made certain here by one step down): they still act at the read time.
    #[test]
    fn frames_of_two_turns_at_one_instant_are_arbitrated_together() {
        let (mut handle, path, dir) = serve("turn2", 500_000, 500_000, Format::Classical);
        let (mut a, mut b) = (connect_node(&path, "A", OPTION_LAZY), connect_node(&path, "B", OPTION_LAZY));
        let mut reader = connect_node(&path, "R", 0);
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let t_turn = epoch0 + handle.now_ns() as f64 * 1e-9 + 0.01;
        a.write_all(&pack_read_every(t_turn, 0.0, true)).unwrap();
        b.write_all(&pack_read_every(t_turn, 0.0, true)).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        let mut act = |node: &mut UnixStream, id: u32, work: Duration| {
            node.read_exact(&mut rec).unwrap();
            assert_eq!(rec[0], KIND_SYNC);
            let stamp = stamp_of(&rec);
            let just_before = f64::from_bits(stamp.to_bits() - 1); // the SYNC's stamp, a rounding step down
            assert!(just_before < stamp);
            std::thread::sleep(work);
            let mut out = pack_frame(id, &[1; 8], 0, just_before).to_vec();
            out.extend_from_slice(&pack_done(stamp));
            node.write_all(&out).unwrap();
        };
        act(&mut a, 0x200, Duration::ZERO); // A's turn is over at once
        act(&mut b, 0x100, Duration::from_millis(1)); // B's work: its frame comes after A's DONE
        let mut ids = Vec::new();
        while ids.len() < 2 {
            reader.read_exact(&mut rec).unwrap();
            if rec[0] == KIND_FRAME {
                ids.push(u32::from_le_bytes(rec[4..8].try_into().unwrap()));
            }
        }
        assert_eq!(ids, vec![0x100, 0x200]); // 0x100 won the arbitration at the turn's instant
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A process hosting several ECUs names each sender's bus node as the unit's own controller (SENDER_NAME),
    /// before its first frame: sender 0 renamed, sender 2 named, sender 1 left "<node>.1"; a name after the first
    /// frame is a protocol error.
    #[test]
    fn a_node_names_its_senders_before_its_first_frame() {
        let (mut handle, path, dir) = serve("names", 500_000, 500_000, Format::Classical);
        let mut node = connect_node(&path, "ECU_T1_U01x3", 0);
        let mut out = pack_sender_name(0, "ECU_U01").to_vec();
        out.extend_from_slice(&pack_sender_name(2, "ECU_U03"));
        for k in [2u8, 0] {
            let mut f = pack_frame(0x100 + k as u32, &[1; 8], 0, 0.0);
            f[3] = k;
            out.extend_from_slice(&f);
        }
        node.write_all(&out).unwrap();
        let deadline = Instant::now() + Duration::from_secs(2);
        let names = loop {
            let names: Vec<String> = handle.shared.lock().unwrap().bus.nodes.iter().map(|n| n.name.clone()).collect();
            if names.len() >= 3 || Instant::now() > deadline {
                break names;
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        assert_eq!(names, ["ECU_U01", "ECU_T1_U01x3.1", "ECU_U03"]);
        node.write_all(&pack_sender_name(1, "late")).unwrap(); // after its first frame
        let mut rec = [0u8; RECORD_SIZE];
        assert!(matches!(node.read(&mut rec), Ok(0) | Err(_)), "the server hangs up on a late SENDER_NAME");
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A node leaves in the turn in which a frame ends: the receivers of that frame, found after it left, must
    /// not point past the clients once the closed one is removed (the server panicked on the next frame).
    #[test]
    fn a_node_that_leaves_as_a_frame_ends_does_not_confuse_the_receivers_of_later_frames() {
        let (mut handle, path, dir) = serve("leave", 10_000, 10_000, Format::Classical);
        let mut socks: Vec<UnixStream> = ["A", "S", "C"].iter().map(|n| {
            let mut s = UnixStream::connect(&path).unwrap();
            let mut r = hello(n);
            if *n == "A" {
                r[2] = OPTION_LAZY; // its socket is read every turn, even one the poll did not wake for it
            }
            s.write_all(&r).unwrap();
            let mut rec = [0u8; RECORD_SIZE];
            s.read_exact(&mut rec).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
            s
        }).collect();
        socks[1].write_all(&pack_frame(0x100, &[1; 8], 0, 0.0)).unwrap(); // about 11 ms on the wire at 10 kbit/s
        std::thread::sleep(Duration::from_millis(8));
        {
            let _hold = handle.shared.lock().unwrap(); // the loop wakes at the frame's end and waits for the lock ...
            std::thread::sleep(Duration::from_millis(6));
            socks[0].shutdown(std::net::Shutdown::Both).unwrap(); // ... and finds A gone in that same turn
            std::thread::sleep(Duration::from_millis(2));
        }
        std::thread::sleep(Duration::from_millis(5));
        socks[1].write_all(&pack_frame(0x100, &[2; 8], 0, 0.0)).unwrap(); // the same ID: its receivers are cached
        let mut rec = [0u8; RECORD_SIZE];
        for data in [1u8, 2] {
            socks[2].read_exact(&mut rec).unwrap();
            assert_eq!((rec[0], u32_at(&rec, 4), rec[16]), (KIND_FRAME, 0x100, data));
        }
        assert!(handle.running(), "the serving thread died");
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Frames a full TX queue refuses are counted; the node's first is also a warning naming it, the frame and the
    /// cause, stamped with its time, and its later ones are not (a node that floods cannot flood the log).
    #[test]
    fn a_nodes_first_frame_refused_by_its_full_tx_queue_is_one_warning_with_its_time() {
        let (mut handle, path, dir) = serve("overflow", 10_000, 10_000, Format::Classical);
        let mut flooder = connect_node(&path, "F", 0);
        let t_send = handle.now_ns();
        let batch: Vec<u8> = (0..12).flat_map(|k| pack_frame(0x300 + k, &[1; 8], 0, 0.0)).collect();
        flooder.write_all(&batch).unwrap(); // taken in one turn: eight queued, four refused
        let deadline = Instant::now() + Duration::from_secs(2);
        while handle.shared.lock().unwrap().bus.frames_dropped() < 4 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(1));
        }
        // the first is on the wire for about 11 ms now: one more fits, the other is refused and counted only
        let two: Vec<u8> = [0x3FE, 0x3FF].iter().flat_map(|&id| pack_frame(id, &[1; 8], 0, 0.0)).collect();
        flooder.write_all(&two).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        let shared = handle.shared.lock().unwrap();
        assert_eq!(shared.bus.frames_dropped(), 5);
        let said: Vec<&LogLine> = shared.messages.iter().filter(|m| m.text.contains(" dropped frame ")).collect();
        assert_eq!(said.len(), 1, "{said:?}");
        assert_eq!(said[0].level, "WARNING");
        assert!(said[0].text.starts_with("bus t/b: node F dropped frame 0x308 (its TX queue of 8 is full)"), "{}",
                said[0].text);
        let t = said[0].t_ns;
        assert!((t_send..t_send + 100_000_000).contains(&t), "sent at {t_send} ns, stamped {t}");
        drop(shared);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A node that leaves with frames in its TX queue loses them: the server says so as a warning that names the
    /// node and the count (the rig records it as an event), stamped with the model time of the leave however late
    /// it is read; a node that leaves with nothing queued, as information.
    #[test]
    fn a_node_that_leaves_with_queued_frames_is_a_warning_naming_it_and_the_count() {
        let (mut handle, path, dir) = serve("quitter", 10_000, 10_000, Format::Classical);
        let mut quitter = connect_node(&path, "Q", 0);
        let idle = connect_node(&path, "I", 0);
        let batch: Vec<u8> = (0..4).flat_map(|k| pack_frame(0x300 + k, &[1; 8], 0, 0.0)).collect();
        quitter.write_all(&batch).unwrap(); // the first on the wire for about 11 ms, three queued behind it
        std::thread::sleep(Duration::from_millis(3));
        let t_leave = handle.now_ns();
        quitter.shutdown(std::net::Shutdown::Both).unwrap();
        idle.shutdown(std::net::Shutdown::Both).unwrap();
        std::thread::sleep(Duration::from_millis(300)); // read well after the leave
        let left = |name: &str| -> Option<LogLine> {
            let deadline = Instant::now() + Duration::from_secs(2);
            while Instant::now() < deadline {
                let shared = handle.shared.lock().unwrap();
                let of_it = |m: &&LogLine| m.text.contains(&format!("node {name} (")) && m.text.contains(" left (");
                if let Some(m) = shared.messages.iter().find(of_it) {
                    return Some(m.clone());
                }
                drop(shared);
                std::thread::sleep(Duration::from_millis(1));
            }
            None
        };
        let q = left("Q").expect("no message for the quitter's leave");
        assert_eq!(q.level, "WARNING", "{}", q.text);
        assert!(q.text.ends_with("; 3 queued frames dropped"), "{}", q.text);
        assert!((t_leave..t_leave + 100_000_000).contains(&q.t_ns), "left at {t_leave} ns, stamped {}", q.t_ns);
        let i = left("I").expect("no message for the idle node's leave");
        assert_eq!(i.level, "INFO", "{}", i.text);
        assert!(i.text.ends_with("; 0 queued frames dropped"), "{}", i.text);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A server that could not run for a while (a host held its CPU) finds more of a lazy node's frames than one
    /// turn reads, stamped at their instants in that while: each still goes on the bus at its stamp, so none is
    /// queued late beside the others and none is lost at the node's TX queue (8 deep here).
    #[test]
    fn a_lazy_nodes_backlog_longer_than_a_turn_reads_goes_on_the_bus_at_its_stamps() {
        let (mut handle, path, dir) = serve_with("backlog", 500_000, 500_000, Format::Classical, Policy::Priority,
                                                 1_000_000_000, None, None);
        let mut sender = connect_node(&path, "S", OPTION_LAZY);
        let mut eager = connect_node(&path, "E", 0);
        let epoch0 = handle.epoch0_ns as f64 * 1e-9;
        let now = || epoch0 + handle.now_ns() as f64 * 1e-9;
        std::thread::sleep(Duration::from_millis(150)); // the server sleeps to its load window's end meanwhile
        let n = 3 * READ_RECORDS;
        let first = now() - 0.1;
        let stamps: Vec<f64> = (0..n).map(|k| first + k as f64 * 0.001).collect(); // all before the server reads
        let batch: Vec<u8> = stamps.iter().flat_map(|&t| pack_frame(0x100, &[1; 8], 0, t)).collect();
        sender.write_all(&batch).unwrap();
        let timing = BitTiming::new(500_000, 500_000).unwrap();
        let one_frame = timing.frame_ns(0x100, &[1; 8], false, false, false).unwrap() as f64 * 1e-9;
        let mut late = Vec::new();
        for (k, t) in stamps.iter().enumerate() {
            let mut rec = [0u8; RECORD_SIZE];
            eager.read_exact(&mut rec).unwrap_or_else(|e| panic!("frame {k} of {n} not heard: {e}"));
            let end = stamp_of(&rec);
            if (end - (t + one_frame)).abs() > 2e-6 {
                late.push((k, end - t - one_frame));
            }
        }
        assert_eq!(handle.shared.lock().unwrap().bus.frames_dropped(), 0);
        assert!(late.is_empty(), "{} of {n} frames off their instants: {:?}", late.len(), &late[..late.len().min(5)]);
        handle.shutdown();
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_node_hears_the_other_nodes_frames_at_their_end_time() {
        let (mut handle, path, dir) = serve("classic", 500_000, 500_000, Format::Classical);
        let mut a = UnixStream::connect(&path).unwrap();
        let mut b = UnixStream::connect(&path).unwrap();
        a.write_all(&hello("A")).unwrap();
        b.write_all(&hello("B")).unwrap();
        let mut rec = [0u8; RECORD_SIZE];
        a.read_exact(&mut rec).unwrap();
        assert_eq!(rec[0], KIND_WELCOME);
        b.read_exact(&mut rec).unwrap();
        a.write_all(&pack_frame(0x123, &[1, 2, 3], 0, 0.0)).unwrap();
        b.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        b.read_exact(&mut rec).unwrap();
        assert_eq!((rec[0], u32_at(&rec, 4), &rec[16..19]), (KIND_FRAME, 0x123, &[1u8, 2, 3][..]));
        a.write_all(&[99u8; RECORD_SIZE]).unwrap(); // garbage: A is dropped, the server goes on
        std::thread::sleep(Duration::from_millis(50));
        let bad = handle.shared.lock().unwrap().bad;
        assert_eq!(bad.protocol_errors, 1);
        handle.shutdown();
        assert_eq!(handle.shared.lock().unwrap().frames, 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_64_byte_fd_payload_is_a_frame_and_three_frame_data_records() {
        let data: Vec<u8> = (0..64).collect();
        let mut out = Vec::new();
        pack_frame_records(0x10, &data, FLAG_FD | FLAG_BRS, 0.0, &mut out);
        assert_eq!(out.len(), 4 * RECORD_SIZE);
        assert_eq!((out[0], out[2], &out[16..24]), (KIND_FRAME, 64, &data[..8]));
        assert_eq!((out[24], &out[25..48]), (KIND_FRAME_DATA, &data[8..31]));
        assert_eq!((&out[73..83], &out[83..96]), (&data[54..64], &[0u8; 13][..])); // 8 + 23 + 23 + 10, zero-padded
        assert_eq!((frame_data_records(8), frame_data_records(12), frame_data_records(31), frame_data_records(32)), (0, 1, 1, 2));
    }

    #[test]
    fn an_fd_bus_carries_a_long_payload_between_nodes_whole() {
        let (mut handle, path, dir) = serve("fd", 1_000_000, 5_000_000, Format::FdBrs);
        let mut streams = Vec::new();
        for name in ["A", "B"] {
            let mut s = UnixStream::connect(&path).unwrap();
            s.write_all(&hello(name)).unwrap();
            let mut r = [0u8; RECORD_SIZE];
            s.read_exact(&mut r).unwrap();
            assert_eq!((r[0], u32::from_le_bytes(r[20..24].try_into().unwrap())), (KIND_WELCOME, 5_000_000));
            streams.push(s);
        }
        let data: Vec<u8> = (100..148).collect();
        let mut out = Vec::new();
        pack_frame_records(0x20, &data, FLAG_FD | FLAG_BRS, 0.0, &mut out);
        streams[0].write_all(&out[..30]).unwrap(); // split inside a record: the server waits for the rest
        std::thread::sleep(Duration::from_millis(20));
        streams[0].write_all(&out[30..]).unwrap();
        let mut got = vec![0u8; out.len()];
        streams[1].set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        streams[1].read_exact(&mut got).unwrap();
        assert_eq!((got[1], got[2]), (FLAG_FD | FLAG_BRS, 48));
        let mut payload = got[16..24].to_vec();
        for k in 0..frame_data_records(48) {
            payload.extend_from_slice(&got[(k + 1) * RECORD_SIZE + 1..(k + 2) * RECORD_SIZE]);
        }
        assert_eq!(&payload[..48], &data[..]);
        handle.shutdown();
        assert_eq!(handle.shared.lock().unwrap().frames, 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
