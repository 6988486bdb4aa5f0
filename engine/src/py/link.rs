//! `FrameLink`: a node's connection to its bus server, its frames routed straight into ECU mailboxes.

use super::*;
use super::command_inbox::CommandInbox;
use crate::bus::Payload;
use crate::command_inbox::CommandInbox as CoreInbox;
use crate::link::{Link, LinkError};
use crate::protocol::{format_flags, FLAG_EXTENDED};

/// Sleep until one of `fds` is readable or `timeout_s` (wall) passed, the GIL released; whether one is.
#[pyfunction]
pub(super) fn wait_readable(py: Python<'_>, fds: Vec<i32>, timeout_s: f64) -> bool {
    let timeout = timeout_s.max(0.0);
    py.allow_threads(move || {
        let mut pfds: Vec<libc::pollfd> = fds.iter().map(|&fd| libc::pollfd { fd, events: libc::POLLIN, revents: 0 }).collect();
        let ts = libc::timespec { tv_sec: timeout as libc::time_t, tv_nsec: (timeout.fract() * 1e9) as libc::c_long };
        // SAFETY: an array of pollfd we own, for the duration of the call.
        unsafe { libc::ppoll(pfds.as_mut_ptr(), pfds.len() as libc::nfds_t, &ts, std::ptr::null()) > 0 }
    })
}


/// A node's receive path without python-can: frames read from a bus server's socket go straight into ECU
/// mailboxes (stamped in simulated time); the node sends its frames through it too.
#[pyclass(module = "trainhil_engine._native")]
pub struct FrameLink {
    link: Link,
    t0: f64,
    pub(super) pace: f64,
    routes: std::collections::HashMap<u32, Vec<Arc<Mutex<core_mailbox::Mailbox>>>>,
    /// A plant's command inbox by frame ID (`route_commands`).
    inboxes: std::collections::HashMap<u32, Arc<Mutex<CoreInbox>>>,
    received: u64,
    /// Keep the frames that have no route for `take` (a node that handles its frames itself).
    keep: bool,
    kept: Vec<(u32, Payload, f64)>,
    /// Container frames: packed on send, unpacked on receipt.
    packing: Option<Arc<CorePacking>>,
    /// A lazy reader's link: frames come in at `sync_to`, sent frames carry the epoch second they were sent.
    lazy: bool,
    /// The read time the node acts at (epoch s, `act_at`): its frames carry no earlier instant.
    acts_at: f64,
    /// Its read times are turns (protocol READ_TURNS): in a turn its frames carry the read time however late they
    /// are sent, and `end_turn` ends it.
    turns: bool,
    /// A turn is open (synced, acting at `acts_at`, not ended yet).
    in_turn: bool,
}

/// Seconds since the Unix epoch now (the stamp of a lazy link's frames; the server's time base is the epoch).
fn epoch_now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

fn link_err(e: LinkError) -> PyErr {
    match e {
        LinkError::Closed => pyo3::exceptions::PyConnectionError::new_err(e.to_string()),
        LinkError::TooLong(..) | LinkError::Sender(_) => PyValueError::new_err(e.to_string()),
        LinkError::Io(_) => pyo3::exceptions::PyOSError::new_err(e.to_string()),
    }
}

impl FrameLink {
    /// One received frame (a container's parts each) into its mailboxes, else kept (or dropped when nothing
    /// takes it).
    fn hand_over(&mut self, id: u32, data: &[u8], stamp: f64) {
        let t = (stamp - self.t0) * self.pace;
        match self.packing.clone().as_deref().and_then(|p| p.unpack(id, data)) {
            Some(parts) => parts.for_each(|(part, bytes)| self.hand_over_one(part, bytes, t)),
            None => self.hand_over_one(id, data, t),
        }
    }

    /// Frames read off the socket (id, epoch stamp, data), handed over in order.
    fn hand_over_all(&mut self, frames: Vec<(u32, f64, Payload)>) {
        for (id, stamp, data) in frames {
            self.hand_over(id, data.as_slice(), stamp);
        }
    }

    /// `sync_to` without waiting: the SYNC of read time `t` (epoch s) is already here or not. Nothing blocks, so the
    /// interpreter lock is kept.
    pub(super) fn sync_now(&mut self, t: f64) -> PyResult<bool> {
        let mut frames = Vec::new();
        let result = self.link.wait_synced(t, 0.0, |id, _, stamp, data| frames.push((id, stamp, Payload::new(data))));
        self.hand_over_all(frames);
        result.map_err(link_err)
    }

    /// End the server's turns of this link's read times before `t` (epoch s) that the node skipped (it was late and
    /// never acted at them): a DONE just before `t`. Nothing on a link without turns.
    pub(super) fn end_turns_skipped(&mut self, t: f64) -> PyResult<()> {
        if self.turns {
            self.in_turn = false;
            self.link.end_turn(t - 2.0 * crate::protocol::SYNC_TOLERANCE_S).map_err(link_err)?;
        }
        Ok(())
    }

    /// The node's turns on this link are over (its run ended): a DONE stamped +inf, after which the server holds
    /// its bus for none of the link's read times. Nothing on a link without turns.
    pub(super) fn end_turns_for_good(&mut self) -> PyResult<()> {
        if std::mem::take(&mut self.turns) {
            self.in_turn = false;
            self.link.end_turn(f64::INFINITY).map_err(link_err)?;
        }
        Ok(())
    }

    /// The read time the node acts at (epoch s; -inf before the first).
    pub(super) fn acts_at(&self) -> f64 {
        self.acts_at
    }

    /// The epoch second of simulated time `sim_t` (this link's clock).
    pub(super) fn epoch(&self, sim_t: f64) -> f64 {
        self.t0 + sim_t / self.pace
    }

    fn hand_over_one(&mut self, id: u32, data: &[u8], t: f64) {
        if let Some(boxes) = self.routes.get(&id) {
            for mb in boxes {
                mb.lock().unwrap().put(id, data, t);
            }
            self.received += 1;
        } else if let Some(inbox) = self.inboxes.get(&id) {
            inbox.lock().unwrap().put(id, data, t);
            self.received += 1;
        } else if self.keep {
            self.kept.push((id, Payload::new(data), t));
            self.received += 1;
        }
    }
}

#[pymethods]
impl FrameLink {
    /// `fd`: the connected, handshaken, non-blocking socket of a node (still owned by the caller). A frame's
    /// simulated time is (its epoch stamp - t0) * pace. `keep`: frames without a route are kept for `take`.
    /// `lazy`: the connection said OPTION_LAZY; frames come in at `sync_to`, and sent frames carry their time.
    /// `bell`: the connection also said OPTION_QUIET; the write end of the server's bell FIFO (owned by the caller),
    /// rung when the server must see a record now.
    #[new]
    #[pyo3(signature = (fd, t0, pace, keep = false, lazy = false, bell = None))]
    fn new(fd: i32, t0: f64, pace: f64, keep: bool, lazy: bool, bell: Option<i32>) -> PyResult<Self> {
        if !(pace.is_finite() && pace > 0.0) {
            return Err(PyValueError::new_err(format!("pace={pace} must be positive")));
        }
        let link = match (lazy, bell) {
            (true, Some(bell)) => Link::quiet(fd, bell),
            (true, None) => Link::lazy(fd),
            (false, None) => Link::new(fd),
            (false, Some(_)) => return Err(PyValueError::new_err("a bell is for a lazy link")),
        };
        Ok(FrameLink { link, t0, pace, routes: Default::default(), inboxes: Default::default(), received: 0, keep, kept: Vec::new(), packing: None,
                       lazy, acts_at: f64::NEG_INFINITY, turns: false, in_turn: false })
    }

    /// A lazy link's read times: `first` (epoch s), then every `period` s (0: once). `turns`: from now on each of
    /// the link's read times is a turn (protocol READ_TURNS; see `act_at`, `end_turn`).
    #[pyo3(signature = (first, period, turns = false))]
    pub(super) fn read_every(&mut self, first: f64, period: f64, turns: bool) -> PyResult<()> {
        if !self.lazy {
            return Err(PyValueError::new_err("read_every is for a lazy link"));
        }
        self.turns |= turns;
        self.link.read_every(first, period, self.turns).map_err(link_err)
    }

    /// Every frame this link will send carries at least `bytes` data bytes (protocol LEAST_DATA), said before its
    /// first frame: the server then need not wait for shorter frames before it SYNCs, and refuses one.
    fn sends_at_least(&self, bytes: u8) -> PyResult<()> {
        self.link.sends_at_least(bytes).map_err(link_err)
    }

    /// Name sender `sender`'s bus node `name` (protocol SENDER_NAME), said before the link's first frame: that
    /// sender's TX queue, drops and error state go by it on the bus (an ECU process names each unit it hosts).
    fn name_sender(&self, sender: usize, name: &str) -> PyResult<()> {
        if name.is_empty() || name.len() > crate::protocol::NAME_BYTES {
            let most = crate::protocol::NAME_BYTES;
            return Err(PyValueError::new_err(format!("sender name {name:?}: 1 to {most} bytes")));
        }
        self.link.name_sender(sender, name).map_err(link_err)
    }

    /// The node acts at read time `t` (epoch s), synced to it perhaps before it comes: the frames it sends from
    /// now on carry `t` while that is still ahead (the server queues them then), else the instant they are sent;
    /// on a link of turns, `t` until `end_turn`, however late (the server holds its bus for the turn).
    pub(super) fn act_at(&mut self, t: f64) {
        self.acts_at = t;
        self.in_turn = self.turns;
    }

    /// End the open turn (a DONE record): the node sends nothing more before its next read time. Nothing without
    /// one.
    pub(super) fn end_turn(&mut self) -> PyResult<()> {
        if std::mem::take(&mut self.in_turn) {
            self.link.end_turn(self.acts_at).map_err(link_err)?;
        }
        Ok(())
    }

    /// Whether a turn is open (see `act_at`).
    #[getter]
    pub(super) fn in_turn(&self) -> bool {
        self.in_turn
    }

    /// Hand over every frame that ended by read time `t` (epoch s): wait up to `timeout_s` (wall, the interpreter
    /// lock released) for the server's SYNC of it. Whether it came; frames that came before are handed over anyway.
    fn sync_to(&mut self, py: Python<'_>, t: f64, timeout_s: f64) -> PyResult<bool> {
        if timeout_s <= 0.0 {
            return self.sync_now(t);
        }
        let mut frames = Vec::new();
        let link = &mut self.link;
        let result = py.allow_threads(|| link.wait_synced(t, timeout_s, |id, _, stamp, data| frames.push((id, stamp, Payload::new(data)))));
        self.hand_over_all(frames);
        result.map_err(link_err)
    }

    /// The latest read time the server synced this link to (epoch s; -inf before the first).
    #[getter]
    fn synced(&self) -> f64 {
        self.link.synced()
    }

    /// Pack each `send` batch into `packing`'s containers, and unpack the containers received.
    fn set_packing(&mut self, packing: &Packing) {
        self.packing = Some(packing.inner.clone());
    }

    /// The socket's file descriptor (for `wait_readable`).
    #[getter]
    pub(super) fn fd(&self) -> i32 {
        self.link.fd()
    }

    /// The kept frames received since the last call, in arrival order: [(frame_id, data, t_sim)]. `pump`: read
    /// the socket first (a lazy link just synced has read what its read time needs: no system call then).
    #[pyo3(signature = (pump = true))]
    pub(super) fn take<'py>(&mut self, py: Python<'py>, pump: bool) -> PyResult<Bound<'py, PyList>> {
        if pump {
            self.pump()?;
        }
        let kept = std::mem::take(&mut self.kept);
        let items: Vec<Bound<'py, PyTuple>> = kept.iter()
            .map(|(id, data, t)| (id, PyBytes::new(py, data.as_slice()), t).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        PyList::new(py, items)
    }

    /// Deliver frames of `frame_id` into `mailbox` (several mailboxes may take one ID).
    fn route(&mut self, frame_id: u32, mailbox: &Mailbox) {
        self.routes.entry(frame_id).or_default().push(mailbox.inner.clone());
    }

    /// Deliver the frames of `inbox`'s IDs into it (a plant's TractionCmd and AgentState frames).
    fn route_commands(&mut self, inbox: &CommandInbox) {
        let shared = inbox.inner.clone();
        for id in shared.lock().unwrap().ids() {
            self.inboxes.insert(id, shared.clone());
        }
    }

    /// Read every record waiting on the socket; returns how many frames went into mailboxes.
    fn pump(&mut self) -> PyResult<u64> {
        let before = self.received;
        let mut frames = Vec::new();
        let result = self.link.pump(|id, _, stamp, data| frames.push((id, stamp, Payload::new(data))));
        self.hand_over_all(frames);
        result.map_err(link_err)?;
        Ok(self.received - before)
    }

    /// Send frames [(frame_id, data)] as FRAME records: `extended` for 29-bit IDs, `fd` for CAN FD frames (with
    /// the bit-rate switch unless `brs` is false); `sender`: which of the connection's senders sends them (each
    /// its own TX queue on the bus, as separate controllers; 0..MAX_SENDERS-1). `end_turn`: they end the open turn
    /// (as `end_turn` after them, in the same write).
    #[pyo3(signature = (frames, extended = false, fd = false, brs = true, sender = 0, end_turn = false))]
    fn send(&mut self, frames: Vec<(u32, PyBackedBytes)>, extended: bool, fd: bool, brs: bool, sender: usize,
            end_turn: bool) -> PyResult<()> {
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_ref())).collect();
        self.send_batch(&batch, extended, fd, brs, sender, end_turn)
    }

    /// Encode one ECU cycle's outputs [(codec, values, counter)] and send them as `send` does, in one call.
    #[pyo3(signature = (outputs, extended = false, fd = false, brs = true, sender = 0, end_turn = false))]
    fn send_encoded(&mut self, outputs: Vec<Output<'_>>, extended: bool, fd: bool, brs: bool, sender: usize,
                    end_turn: bool) -> PyResult<()> {
        let frames = encode_outputs(&outputs)?;
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_slice())).collect();
        self.send_batch(&batch, extended, fd, brs, sender, end_turn)
    }
}

impl FrameLink {
    /// FRAME records of a batch (packed into containers with a packing); a lazy link stamps them now, or at the
    /// read time it acts at if that is later, and in a turn at that read time. `end_turn`: a DONE after them.
    fn send_batch(&mut self, batch: &[(u32, &[u8])], extended: bool, fd: bool, brs: bool, sender: usize,
                  end_turn: bool) -> PyResult<()> {
        let flags = if extended { FLAG_EXTENDED } else { 0 } | format_flags(Format::of(fd, brs));
        let limit = if fd { MAX_DATA } else { crate::protocol::MAX_DLC };
        if let Some((id, data)) = batch.iter().find(|(_, d)| d.len() > limit) {
            return Err(link_err(LinkError::TooLong(*id, data.len(), limit)));
        }
        let packed = match &self.packing {
            Some(p) => p.pack(batch),
            None => batch.iter().map(|&(id, d)| (id, Payload::new(d))).collect(),
        };
        let parts: Vec<(u32, &[u8])> = packed.iter().map(|(id, d)| (*id, d.as_slice())).collect();
        let stamp = match (self.lazy, self.in_turn) {
            (false, _) => 0.0,
            (true, true) => self.acts_at,
            (true, false) => epoch_now().max(self.acts_at),
        };
        let done = (end_turn && std::mem::take(&mut self.in_turn)).then_some(self.acts_at);
        self.link.send(&parts, flags, stamp, sender, done).map_err(link_err)
    }
}
