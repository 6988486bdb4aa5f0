//! A node's end of a connection to a bus server (the client side of `protocol`): whole frames read from the
//! non-blocking socket, frames written as records. No Python here; `FrameLink` (`py/link.rs`) routes the frames it
//! reads into ECU mailboxes.
//!
//! A lazy link (HELLO option `OPTION_LAZY`) reads only up to its horizon: `wait_synced(t)` waits for the server's
//! SYNC of read time `t` and hands over the frames that ended by then, never one that ended later.
//!
//! A quiet link (also `OPTION_QUIET`) does not wake its server by writing: the server reads its records at its
//! next wake-up. The link rings the server's bell (a FIFO) after a record the server must see now: a READ_EVERY,
//! or a frame the server's BELL records name (one it hands over at its end: to an eager node, to the radio).

use std::os::fd::RawFd;

use crate::protocol::{pack_done, pack_frame_records_from, pack_least_data, pack_read_every, pack_sender_name, read_frames, BellSet,
                      MAX_SENDERS, RECORD_SIZE};

/// Why the link cannot go on.
#[derive(Debug)]
pub enum LinkError {
    /// The bus server closed the connection.
    Closed,
    /// A frame's payload is longer than its format carries: (frame ID, length, limit).
    TooLong(u32, usize, usize),
    /// A sender index at or above MAX_SENDERS.
    Sender(usize),
    Io(std::io::Error),
}

impl std::fmt::Display for LinkError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinkError::Closed => write!(f, "bus link: the bus server closed the connection"),
            LinkError::TooLong(id, len, limit) => write!(f, "frame {id:#x}: {len} data bytes > {limit}"),
            LinkError::Sender(k) => write!(f, "sender {k}: a connection has senders 0..{}", MAX_SENDERS - 1),
            LinkError::Io(e) => write!(f, "bus link: {e}"),
        }
    }
}

/// The socket (owned by the caller) and the bytes of a record not yet whole.
pub struct Link {
    fd: RawFd,
    partial: Vec<u8>,
    /// Records are handed over until a SYNC at or after this time (epoch s) is read: +inf for an eager link.
    horizon: f64,
    /// The latest SYNC read (epoch s).
    synced: f64,
    /// A quiet link's bell: the write end of the server's FIFO (owned by the caller).
    bell: Option<RawFd>,
    /// Which frames ring it (the server's BELL records read so far).
    rings: BellSet,
}

fn would_block(err: &std::io::Error) -> bool {
    matches!(err.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted)
}

impl Link {
    /// `fd`: a connected, handshaken, non-blocking socket.
    pub fn new(fd: RawFd) -> Link {
        Link { fd, partial: Vec::new(), horizon: f64::INFINITY, synced: f64::NEG_INFINITY, bell: None,
               rings: BellSet::default() }
    }

    /// A lazy link: nothing is handed over before the first `wait_synced`.
    pub fn lazy(fd: RawFd) -> Link {
        Link { horizon: f64::NEG_INFINITY, ..Link::new(fd) }
    }

    /// A quiet lazy link (the connection said OPTION_LAZY and OPTION_QUIET): `bell`, the write end of the server's
    /// bell FIFO, non-blocking.
    pub fn quiet(fd: RawFd, bell: RawFd) -> Link {
        Link { bell: Some(bell), ..Link::lazy(fd) }
    }

    /// Wake the server now (a quiet link). A full FIFO already holds wake-ups the server has not read: nothing lost.
    fn ring(&self) {
        if let Some(bell) = self.bell {
            // SAFETY: one byte from our own buffer to a descriptor the caller keeps open.
            unsafe { libc::write(bell, b"!".as_ptr() as *const libc::c_void, 1) };
        }
    }

    /// Whether the server must see a frame of `can_id` at once (a quiet link: the BELL records say).
    pub fn rings_for(&self, can_id: u32) -> bool {
        self.bell.is_some() && self.rings.rings(can_id)
    }

    /// The latest read time the server has synced this link to (epoch s).
    pub fn synced(&self) -> f64 {
        self.synced
    }

    /// Ask for read times: `first` (epoch s), then every `period` s (0: once); `turns`: each is a turn, which the
    /// node ends with `end_turn` (protocol READ_TURNS).
    pub fn read_every(&self, first: f64, period: f64, turns: bool) -> Result<(), LinkError> {
        self.write_all(&pack_read_every(first, period, turns))?;
        self.ring();
        Ok(())
    }

    /// Tell the server that every frame sent through this link carries at least `bytes` data bytes (LEAST_DATA;
    /// before the first frame): its reads need not wait for frames shorter than that. A shorter one is refused.
    pub fn sends_at_least(&self, bytes: u8) -> Result<(), LinkError> {
        self.write_all(&pack_least_data(bytes))
    }

    /// Name sender `sender`'s bus node (SENDER_NAME; before the first frame): its TX queue, drops and error state
    /// go by that name.
    pub fn name_sender(&self, sender: usize, name: &str) -> Result<(), LinkError> {
        if sender >= MAX_SENDERS {
            return Err(LinkError::Sender(sender));
        }
        self.write_all(&pack_sender_name(sender as u8, name))
    }

    /// End the node's turn at read time `stamp` (epoch s): a DONE record. The server listens for it while the turn
    /// holds its bus, so a quiet link need not ring.
    pub fn end_turn(&self, stamp: f64) -> Result<(), LinkError> {
        self.write_all(&pack_done(stamp))
    }

    /// Hand over every frame that ended by read time `t` (epoch s), waiting up to `timeout_s` (wall) for the
    /// server's SYNC of it; whether it came.
    /// Already synced to `t` (its SYNC was read with an earlier one's), it hands over what it held back and reads
    /// nothing: every frame that ended by `t` came before that SYNC.
    pub fn wait_synced(&mut self, t: f64, timeout_s: f64, mut each: impl FnMut(u32, u8, f64, &[u8])) -> Result<bool, LinkError> {
        self.horizon = self.horizon.max(t);
        self.hand_over(&mut each);
        if self.synced >= t - crate::protocol::SYNC_TOLERANCE_S {
            return Ok(true);
        }
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(timeout_s.max(0.0));
        loop {
            self.pump(&mut each)?;
            if self.synced >= t - crate::protocol::SYNC_TOLERANCE_S {
                return Ok(true);
            }
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return Ok(false);
            }
            let mut pfd = libc::pollfd { fd: self.fd, events: libc::POLLIN, revents: 0 };
            let ts = libc::timespec { tv_sec: left.as_secs() as libc::time_t, tv_nsec: left.subsec_nanos() as libc::c_long };
            // SAFETY: one pollfd we own, for the duration of the call.
            unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) };
        }
    }

    pub fn fd(&self) -> RawFd {
        self.fd
    }

    /// Read every record waiting and call `each(can_id, flags, stamp, data)` for each whole frame (up to the
    /// horizon, on a lazy link). A read that does not fill the buffer took all there was: no second read to learn it.
    pub fn pump(&mut self, mut each: impl FnMut(u32, u8, f64, &[u8])) -> Result<(), LinkError> {
        let mut buf = [0u8; 64 * RECORD_SIZE];
        self.hand_over(&mut each); // what an earlier horizon held back
        loop {
            // SAFETY: reading into our own buffer from the node's socket.
            let n = unsafe { libc::recv(self.fd, buf.as_mut_ptr() as *mut libc::c_void, buf.len(), libc::MSG_DONTWAIT) };
            if n < 0 {
                let err = std::io::Error::last_os_error();
                return if would_block(&err) { Ok(()) } else { Err(LinkError::Io(err)) };
            }
            if n == 0 {
                return Err(LinkError::Closed);
            }
            self.partial.extend_from_slice(&buf[..n as usize]);
            self.hand_over(&mut each);
            if (n as usize) < buf.len() {
                return Ok(());
            }
        }
    }

    /// The records read so far, up to the horizon.
    fn hand_over(&mut self, each: &mut impl FnMut(u32, u8, f64, &[u8])) {
        let used = read_frames(&self.partial, self.horizon, &mut self.synced, &mut self.rings, each);
        self.partial.drain(..used);
    }

    /// Write `frames` as FRAME records with `flags`, stamped `stamp` (the epoch second they were sent, which a lazy
    /// link's server queues them at; 0: when the server reads them); an FD frame's payload is padded to a CAN FD
    /// length. Waits while the socket is full. A quiet link rings the bell if one of them must be seen now.
    /// `sender`: which of the connection's senders they are from (its own TX queue on the bus; see MAX_SENDERS).
    /// `end_turn`: the read time of the node's turn these frames end (a DONE record after them, in the same write).
    pub fn send(&self, frames: &[(u32, &[u8])], flags: u8, stamp: f64, sender: usize, end_turn: Option<f64>) -> Result<(), LinkError> {
        if sender >= MAX_SENDERS {
            return Err(LinkError::Sender(sender));
        }
        let fd = flags & crate::protocol::FLAG_FD != 0;
        let limit = if fd { crate::frame::MAX_DATA } else { crate::protocol::MAX_DLC };
        if let Some((id, data)) = frames.iter().find(|(_, d)| d.len() > limit) {
            return Err(LinkError::TooLong(*id, data.len(), limit));
        }
        let mut out = Vec::with_capacity(frames.len() * RECORD_SIZE);
        for &(id, data) in frames {
            let padded = if fd { crate::frame::fd_padded_len(data.len()).unwrap_or(data.len()) } else { data.len() };
            let mut payload = data.to_vec();
            payload.resize(padded, 0);
            pack_frame_records_from(id, &payload, flags, stamp, sender as u8, &mut out);
        }
        if let Some(t) = end_turn {
            out.extend_from_slice(&pack_done(t));
        }
        self.write_all(&out)?;
        if frames.iter().any(|&(id, _)| self.rings_for(id)) {
            self.ring();
        }
        Ok(())
    }

    fn write_all(&self, out: &[u8]) -> Result<(), LinkError> {
        let mut sent = 0;
        while sent < out.len() {
            // SAFETY: writing our own buffer to the node's socket.
            let n = unsafe { libc::send(self.fd, out[sent..].as_ptr() as *const libc::c_void, out.len() - sent, libc::MSG_NOSIGNAL) };
            if n < 0 {
                let err = std::io::Error::last_os_error();
                if !would_block(&err) {
                    return Err(LinkError::Io(err));
                }
                let mut pfd = libc::pollfd { fd: self.fd, events: libc::POLLOUT, revents: 0 };
                // SAFETY: one pollfd we own.
                unsafe { libc::poll(&mut pfd, 1, 100) };
                continue;
            }
            sent += n as usize;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{FLAG_BRS, FLAG_FD};
    use std::os::fd::AsRawFd;
    use std::os::unix::net::UnixStream;

    #[test]
    fn frames_sent_on_one_end_are_read_whole_on_the_other() {
        let (a, b) = UnixStream::pair().unwrap();
        a.set_nonblocking(true).unwrap();
        b.set_nonblocking(true).unwrap();
        let (tx, mut rx) = (Link::new(a.as_raw_fd()), Link::new(b.as_raw_fd()));
        tx.send(&[(0x10, &[1, 2]), (0x11, &[3; 8])], 0, 0.0, 0, None).unwrap();
        tx.send(&[(0x12, &[7; 13])], FLAG_FD | FLAG_BRS, 0.0, 0, None).unwrap(); // padded to 16
        let mut got = Vec::new();
        rx.pump(|id, flags, _, d| got.push((id, flags, d.to_vec()))).unwrap();
        let mut long = vec![7; 13];
        long.resize(16, 0);
        assert_eq!(got, vec![(0x10, 0, vec![1, 2]), (0x11, 0, vec![3; 8]), (0x12, FLAG_FD | FLAG_BRS, long)]);
        assert!(matches!(tx.send(&[(0x13, &[0; 9])], 0, 0.0, 0, None), Err(LinkError::TooLong(0x13, 9, 8))));
        drop(a);
        assert!(matches!(rx.pump(|_, _, _, _| {}), Err(LinkError::Closed)));
    }

    #[test]
    fn a_lazy_link_hands_over_only_what_ended_by_its_read_time() {
        let (_a, b) = written(&records(&[(Some(0x10), 1.0), (None, 1.5), (Some(0x11), 1.7)]));
        let mut rx = Link::lazy(b.as_raw_fd());
        let mut got = Vec::new();
        rx.pump(|id, _, _, _| got.push(id)).unwrap();
        assert!(got.is_empty()); // no read time yet
        assert!(rx.wait_synced(1.5, 1.0, |id, _, _, _| got.push(id)).unwrap());
        assert_eq!(got, vec![0x10]);
        rx.pump(|id, _, _, _| got.push(id)).unwrap();
        assert_eq!(got, vec![0x10]); // 0x11 ended after the read time
        assert!(!rx.wait_synced(2.0, 0.01, |id, _, _, _| got.push(id)).unwrap()); // no SYNC of 2.0: timed out
        assert_eq!(got, vec![0x10, 0x11]); // what came before the missing SYNC is handed over
    }

    /// A second read time already synced by the SYNCs read with the first: its frames come without a read of the
    /// socket (what is there is for later), and a pump takes everything waiting, more than one buffer too.
    #[test]
    fn a_lazy_link_synced_ahead_hands_over_without_reading_and_a_pump_reads_past_a_full_buffer() {
        let (a, b) = written(&records(&[(Some(0x10), 1.0), (None, 1.5), (Some(0x11), 1.6), (None, 1.7)]));
        let mut rx = Link::lazy(b.as_raw_fd());
        let mut got = Vec::new();
        assert!(rx.wait_synced(1.5, 1.0, |id, _, _, _| got.push(id)).unwrap());
        use std::io::Write;
        (&a).write_all(&records(&[(Some(0x12), 1.8)])).unwrap();
        assert!(rx.wait_synced(1.7, 1.0, |id, _, _, _| got.push(id)).unwrap());
        assert_eq!(got, vec![0x10, 0x11]);
        assert_eq!(waiting(b.as_raw_fd()), RECORD_SIZE); // 0x12 was not read
        let mut many = Vec::new();
        for k in 0..200u32 {
            crate::protocol::pack_frame_records(0x100 + k, &[0; 8], 0, 2.0, &mut many);
        }
        (&a).write_all(&many).unwrap();
        let mut eager = Link::new(b.as_raw_fd());
        let mut n = 0;
        eager.pump(|_, _, _, _| n += 1).unwrap();
        assert_eq!(n, 200);
    }

    /// The records of one-byte frames `(Some(id), stamp)` and SYNCs `(None, stamp)`, in order.
    fn records(items: &[(Option<u32>, f64)]) -> Vec<u8> {
        let mut out = Vec::new();
        for &(id, stamp) in items {
            match id {
                Some(id) => crate::protocol::pack_frame_records(id, &[1], 0, stamp, &mut out),
                None => out.extend_from_slice(&crate::protocol::pack_sync(stamp)),
            }
        }
        out
    }

    /// A socket pair whose first end wrote `stream`; the second end, non-blocking, is the node's.
    fn written(stream: &[u8]) -> (UnixStream, UnixStream) {
        let (a, b) = UnixStream::pair().unwrap();
        b.set_nonblocking(true).unwrap();
        use std::io::Write;
        (&a).write_all(stream).unwrap();
        (a, b)
    }

    /// Bytes waiting on a non-blocking socket or FIFO.
    fn waiting(fd: RawFd) -> usize {
        let mut buf = [0u8; 256];
        // SAFETY: reading into our own buffer.
        let n = unsafe { libc::read(fd, buf.as_mut_ptr() as *mut libc::c_void, buf.len()) };
        n.max(0) as usize
    }

    #[test]
    fn a_quiet_link_rings_for_read_requests_and_for_the_frames_its_server_names_only() {
        let (node, server) = UnixStream::pair().unwrap();
        let (bell_w, bell_r) = UnixStream::pair().unwrap(); // stands for the server's FIFO
        for s in [&node, &server, &bell_w, &bell_r] {
            s.set_nonblocking(true).unwrap();
        }
        let mut link = Link::quiet(node.as_raw_fd(), bell_w.as_raw_fd());
        link.send(&[(0x10, &[1])], 0, 1.0, 0, None).unwrap();
        assert_eq!(waiting(bell_r.as_raw_fd()), 1); // no BELL record yet: every frame rings
        use std::io::Write;
        (&server).write_all(&crate::protocol::pack_bell(false, &[0x20])).unwrap();
        (&server).write_all(&crate::protocol::pack_sync(1.5)).unwrap(); // read in stream order, at a read time
        assert!(link.wait_synced(1.5, 1.0, |_, _, _, _| {}).unwrap());
        link.send(&[(0x10, &[1]), (0x11, &[2])], 0, 1.0, 0, None).unwrap();
        assert_eq!(waiting(bell_r.as_raw_fd()), 0); // the server does not need these now
        link.send(&[(0x10, &[1]), (0x20, &[2])], 0, 1.0, 0, None).unwrap();
        assert_eq!(waiting(bell_r.as_raw_fd()), 1);
        link.read_every(2.0, 0.01, false).unwrap();
        assert_eq!(waiting(bell_r.as_raw_fd()), 1);
        assert_eq!(waiting(server.as_raw_fd()), 6 * RECORD_SIZE); // every record was written all the same
        assert!(!Link::lazy(node.as_raw_fd()).rings_for(0x20)); // no bell: nothing to ring
    }

    #[test]
    fn a_quiet_link_that_never_reads_takes_in_its_bell_records_but_holds_back_frames_and_syncs() {
        let (node, server) = UnixStream::pair().unwrap();
        let (bell_w, bell_r) = UnixStream::pair().unwrap();
        for s in [&node, &server, &bell_w, &bell_r] {
            s.set_nonblocking(true).unwrap();
        }
        let mut link = Link::quiet(node.as_raw_fd(), bell_w.as_raw_fd()); // e.g. the plant's Wayside connection
        use std::io::Write;
        (&server).write_all(&crate::protocol::pack_bell(false, &[0x20])).unwrap();
        let mut frame = Vec::new();
        crate::protocol::pack_frame_records(0x30, &[7], 0, 0.5, &mut frame);
        (&server).write_all(&frame).unwrap();
        (&server).write_all(&crate::protocol::pack_sync(1.5)).unwrap();
        let mut seen = 0;
        link.pump(|_, _, _, _| seen += 1).unwrap(); // never synced: its horizon is before everything
        assert_eq!((seen, link.synced()), (0, f64::NEG_INFINITY)); // the frame and the SYNC wait for a read time
        link.send(&[(0x10, &[1])], 0, 1.0, 0, None).unwrap();
        assert_eq!(waiting(bell_r.as_raw_fd()), 0); // the BELL record was taken in: 0x10 need not ring
        assert!(link.wait_synced(1.5, 1.0, |id, _, _, _| assert_eq!(id, 0x30)).unwrap()); // handed over in order
    }
}
