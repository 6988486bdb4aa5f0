//! The serving thread's wait on its poll set (`serving_thread.rs`): what `ppoll` does with the same `pollfd` array
//! (the same events asked, the same `revents` given back, a nanosecond timeout), but through an epoll instance that
//! keeps the descriptors registered from one turn to the next.
//!
//! `ppoll` registers and unregisters every descriptor of the set at each call: with some twenty sockets per rig that
//! was about a fifth of the serving thread's CPU (`perf` in docs/realtime-performance.md). Here a turn whose poll set
//! is the one of the last turn costs one `epoll_pwait2`, plus an `epoll_ctl` per descriptor whose events changed.
//! A set with other descriptors, or after a connection came or went anywhere in the process (`FD_EPOCH`: a closed
//! descriptor's number may be reused by the next one), is registered anew. Where epoll fails (a kernel before 5.11
//! has no `epoll_pwait2`), the wait is `ppoll` from then on.

use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::sync::atomic::{AtomicU64, Ordering};

/// Bumped whenever a descriptor that may be in a poll set is opened or closed (a client accepted or removed, a
/// server started or finished): the waits register their sets anew.
pub(crate) static FD_EPOCH: AtomicU64 = AtomicU64::new(0);

/// A change of descriptors somewhere in this process (see `FD_EPOCH`).
pub(crate) fn descriptors_changed() {
    FD_EPOCH.fetch_add(1, Ordering::SeqCst);
}

/// A wait on a poll set that stays registered between calls (see the module docstring).
pub struct PollWait {
    /// The epoll instance; None: `ppoll` (epoll could not be used).
    ep: Option<OwnedFd>,
    /// The set as registered: (fd, events) by index in the `pollfd` array, which is each event's data.
    registered: Vec<(RawFd, i16)>,
    /// `FD_EPOCH` when the set was registered.
    epoch: u64,
    events: Vec<libc::epoll_event>,
}

impl Default for PollWait {
    fn default() -> Self {
        Self::new()
    }
}

impl PollWait {
    pub fn new() -> Self {
        PollWait { ep: None, registered: Vec::new(), epoch: u64::MAX, events: Vec::new() }
            .with_instance()
    }

    fn with_instance(mut self) -> Self {
        // SAFETY: epoll_create1 has no memory preconditions; a descriptor it returns is ours to own.
        let fd = unsafe { libc::epoll_create1(libc::EPOLL_CLOEXEC) };
        self.ep = (fd >= 0).then(|| unsafe { OwnedFd::from_raw_fd(fd) });
        self
    }

    /// Whether the waits go through epoll (false: `ppoll`).
    pub fn uses_epoll(&self) -> bool {
        self.ep.is_some()
    }

    /// Wait until a descriptor of `fds` is ready or `timeout_ns` (wall ns, >= 0) passed; `revents` set as `ppoll`
    /// sets them (0 where nothing happened). Returns as `ppoll` does: how many are ready, -1 when the wait was
    /// interrupted (none set).
    pub fn wait(&mut self, fds: &mut [libc::pollfd], timeout_ns: i64) -> i32 {
        for p in fds.iter_mut() {
            p.revents = 0;
        }
        if self.ep.is_some() {
            match self.register(fds).and_then(|()| self.epoll_wait(fds, timeout_ns)) {
                Ok(n) => return n,
                Err(_) => self.ep = None, // ppoll from now on (the set may have been half taken: nothing was lost)
            }
        }
        ppoll(fds, timeout_ns)
    }

    /// Bring the registrations to `fds`: anew when its descriptors differ or any descriptor of the process came
    /// or went, else only the events that changed.
    fn register(&mut self, fds: &[libc::pollfd]) -> std::io::Result<()> {
        let epoch = FD_EPOCH.load(Ordering::SeqCst);
        let same = epoch == self.epoch && self.registered.len() == fds.len()
            && self.registered.iter().zip(fds).all(|(&(fd, _), p)| fd == p.fd);
        if same {
            return self.update(fds);
        }
        let events = std::mem::take(&mut self.events);
        *self = PollWait { ep: None, registered: Vec::new(), epoch, events }.with_instance();
        if self.ep.is_none() {
            return Err(std::io::Error::last_os_error());
        }
        for (k, p) in fds.iter().enumerate().filter(|(_, p)| p.fd >= 0) {
            self.ctl(libc::EPOLL_CTL_ADD, k, p)?;
        }
        self.registered = fds.iter().map(|p| (p.fd, p.events)).collect();
        Ok(())
    }

    /// The same descriptors as registered: a changed interest is told to epoll.
    fn update(&mut self, fds: &[libc::pollfd]) -> std::io::Result<()> {
        for (k, p) in fds.iter().enumerate() {
            if p.fd >= 0 && self.registered[k].1 != p.events {
                self.ctl(libc::EPOLL_CTL_MOD, k, p)?;
                self.registered[k].1 = p.events;
            }
        }
        Ok(())
    }

    /// `p` (entry `k` of the set, its event's data) added or changed in the epoll instance.
    fn ctl(&self, op: libc::c_int, k: usize, p: &libc::pollfd) -> std::io::Result<()> {
        // (the kernel adds EPOLLHUP and EPOLLERR: reported with no events asked, as by poll)
        let mut ev = libc::epoll_event { events: p.events as u16 as u32, u64: k as u64 };
        // SAFETY: ev is a valid epoll_event for the duration of the call.
        if unsafe { libc::epoll_ctl(self.ep_fd(), op, p.fd, &mut ev) } < 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(())
    }

    fn epoll_wait(&mut self, fds: &mut [libc::pollfd], timeout_ns: i64) -> std::io::Result<i32> {
        let max = fds.len().max(1);
        self.events.resize(max, libc::epoll_event { events: 0, u64: 0 });
        let ts = timespec(timeout_ns);
        // SAFETY: events holds `max` entries, ts is a valid timespec; no signal mask is given.
        let n = unsafe {
            libc::syscall(libc::SYS_epoll_pwait2, self.ep_fd(), self.events.as_mut_ptr(), max as libc::c_int,
                          &ts as *const libc::timespec, std::ptr::null::<libc::sigset_t>(), 0usize)
        };
        if n < 0 {
            let err = std::io::Error::last_os_error();
            return if err.raw_os_error() == Some(libc::EINTR) { Ok(-1) } else { Err(err) };
        }
        for ev in &self.events[..n as usize] {
            let (k, bits) = (ev.u64 as usize, ev.events);
            if let Some(p) = fds.get_mut(k) {
                p.revents = (bits & 0xffff) as u16 as i16;
            }
        }
        Ok(n as i32)
    }

    fn ep_fd(&self) -> RawFd {
        self.ep.as_ref().map_or(-1, |fd| fd.as_raw_fd())
    }
}

fn timespec(ns: i64) -> libc::timespec {
    let ns = ns.max(0);
    libc::timespec { tv_sec: (ns / 1_000_000_000) as libc::time_t, tv_nsec: (ns % 1_000_000_000) as libc::c_long }
}

/// `ppoll` on `fds` with a nanosecond timeout (where epoll cannot be used).
fn ppoll(fds: &mut [libc::pollfd], timeout_ns: i64) -> i32 {
    let ts = timespec(timeout_ns);
    // SAFETY: fds is a valid array of pollfd for the duration of the call.
    unsafe { libc::ppoll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, &ts, std::ptr::null()) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};
    use std::os::unix::net::UnixStream;
    use std::time::{Duration, Instant};

    fn set(streams: &[&UnixStream], events: i16) -> Vec<libc::pollfd> {
        streams.iter().map(|s| libc::pollfd { fd: s.as_raw_fd(), events, revents: 0 }).collect()
    }

    /// Both waits on the same set and state: the revents they give.
    fn both(wait: &mut PollWait, fds: &[libc::pollfd]) -> (Vec<i16>, Vec<i16>) {
        let mut a = fds.to_vec();
        wait.wait(&mut a, 0);
        let mut b = fds.to_vec();
        ppoll(&mut b, 0);
        (a.iter().map(|p| p.revents).collect(), b.iter().map(|p| p.revents).collect())
    }

    #[test]
    fn it_reports_what_ppoll_reports_as_the_set_and_its_events_change() {
        let mut wait = PollWait::new();
        assert!(wait.uses_epoll(), "this kernel has epoll_pwait2");
        let (a, mut a_peer) = UnixStream::pair().unwrap();
        let (b, b_peer) = UnixStream::pair().unwrap();
        let mut fds = set(&[&a, &b], libc::POLLIN);
        assert_eq!(both(&mut wait, &fds), (vec![0, 0], vec![0, 0]));
        a_peer.write_all(b"x").unwrap();
        let (got, want) = both(&mut wait, &fds);
        assert_eq!(got, want);
        assert_eq!(got, vec![libc::POLLIN, 0]);
        fds[1].events = libc::POLLIN | libc::POLLOUT; // a changed interest: the registration follows
        let (got, want) = both(&mut wait, &fds);
        assert_eq!(got, want);
        assert_eq!(got, vec![libc::POLLIN, libc::POLLOUT]);
        fds[0].events = 0; // no interest: only a hang-up is reported, as by poll
        assert_eq!(both(&mut wait, &fds), (vec![0, libc::POLLOUT], vec![0, libc::POLLOUT]));
        let (quiet, quiet_peer) = UnixStream::pair().unwrap();
        fds.push(libc::pollfd { fd: quiet.as_raw_fd(), events: 0, revents: 0 });
        assert_eq!(both(&mut wait, &fds), (vec![0, libc::POLLOUT, 0], vec![0, libc::POLLOUT, 0]));
        drop(quiet_peer);
        let (got, want) = both(&mut wait, &fds);
        assert_eq!(got, want);
        assert_eq!(got[2], libc::POLLHUP);
        fds.pop();
        drop(b_peer);
        let (got, want) = both(&mut wait, &fds);
        assert_eq!(got, want);
        assert_ne!(got[1] & libc::POLLHUP, 0);
        let mut one = [0u8; 1];
        (&a).read_exact(&mut one).unwrap();
        fds.truncate(1); // another set: registered anew
        fds[0].events = libc::POLLIN;
        assert_eq!(both(&mut wait, &fds), (vec![0], vec![0]));
        a_peer.write_all(b"y").unwrap();
        assert_eq!(both(&mut wait, &fds), (vec![libc::POLLIN], vec![libc::POLLIN]));
        assert!(wait.uses_epoll());
    }

    #[test]
    fn a_descriptor_number_reused_after_a_close_is_registered_anew() {
        let mut wait = PollWait::new();
        let (a, _a_peer) = UnixStream::pair().unwrap();
        let fds = set(&[&a], libc::POLLIN);
        assert_eq!(both(&mut wait, &fds).0, vec![0]);
        let (c, mut c_peer) = UnixStream::pair().unwrap();
        // a's number now names c's socket (a's is closed, so epoll forgets it), as when a client leaves and the next
        // one accepted gets its number
        // SAFETY: both descriptors are open and ours; `a` keeps owning its number.
        assert!(unsafe { libc::dup2(c.as_raw_fd(), a.as_raw_fd()) } >= 0);
        c_peer.write_all(b"z").unwrap();
        let (got, want) = both(&mut wait, &fds);
        assert_eq!((got, want), (vec![0], vec![libc::POLLIN]), "unseen until the change is told");
        descriptors_changed();
        assert_eq!(both(&mut wait, &fds), (vec![libc::POLLIN], vec![libc::POLLIN]));
    }

    #[test]
    fn it_sleeps_for_the_timeout_when_nothing_comes_and_wakes_at_once_when_something_does() {
        let mut wait = PollWait::new();
        let (a, mut a_peer) = UnixStream::pair().unwrap();
        let mut fds = set(&[&a], libc::POLLIN);
        let t0 = Instant::now();
        wait.wait(&mut fds, 20_000_000);
        let slept = t0.elapsed();
        assert!(slept >= Duration::from_millis(20), "{slept:?}");
        assert_eq!(fds[0].revents, 0);
        let writer = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(10));
            a_peer.write_all(b"w").unwrap();
            a_peer
        });
        let t0 = Instant::now();
        wait.wait(&mut fds, 5_000_000_000);
        assert!(t0.elapsed() < Duration::from_secs(2));
        assert_eq!(fds[0].revents, libc::POLLIN);
        drop(writer.join());
    }
}
