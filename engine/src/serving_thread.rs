//! A serving thread: the loop that runs one or several bus servers (`server.rs`) on one poll. A rig's buses share
//! one, so an instant that several buses need at once (the units of every train read at the same offsets in their
//! cycle, the plant reads every bus at each publication) costs one wake-up of one thread, not one per bus.
//!
//! Each turn: take the servers added since the last, finish the ones asked to stop, let each put its descriptors on
//! one poll set and say how long it may sleep, sleep for the shortest (`poll_wait`: the set stays registered), then
//! let each server whose time came or whose descriptors woke the thread take its turn (a server's turn is most of
//! its cost: the others skip theirs).
//! The servers of one radio hub turn together, their events in one time order (`server::turn_together`).

use std::io::Write;
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::poll_wait::PollWait;
use crate::server::{drain_wake_ups, set_timer_slack, turn_together, Server};

/// How long an empty thread sleeps between looks (it is woken when a server comes or it is closed).
const IDLE_NS: i64 = 100_000_000;

/// The servers that turn together (by index): those of one radio hub, and each other one alone. A routed frame
/// then reaches the next bus in time order without a wake-up at its end (`server::turn_together`).
fn radio_groups(servers: &[Server]) -> Vec<Vec<usize>> {
    let mut groups: Vec<(Option<usize>, Vec<usize>)> = Vec::new();
    for (k, s) in servers.iter().enumerate() {
        match s.radio_key().and_then(|key| groups.iter_mut().find(|(g, _)| *g == Some(key))) {
            Some((_, members)) => members.push(k),
            None => groups.push((s.radio_key(), vec![k])),
        }
    }
    groups.into_iter().map(|(_, members)| members).collect()
}

/// A thread serving bus servers; it ends once closed and its servers have finished.
pub struct ServingThread {
    incoming: Mutex<Vec<Server>>,
    closed: AtomicBool,
    wake_r: UnixStream,
    wake_w: UnixStream,
    thread: Mutex<Option<JoinHandle<()>>>,
    tid: AtomicI32,
}

impl ServingThread {
    /// A thread named `name`, serving nothing yet.
    pub fn start(name: &str) -> std::io::Result<Arc<ServingThread>> {
        let (wake_r, wake_w) = UnixStream::pair()?;
        wake_r.set_nonblocking(true)?;
        wake_w.set_nonblocking(true)?;
        let me = Arc::new(ServingThread {
            incoming: Mutex::new(Vec::new()), closed: AtomicBool::new(false), wake_r, wake_w, thread: Mutex::new(None),
            tid: AtomicI32::new(-1),
        });
        let served = me.clone();
        let (tid_tx, tid_rx) = std::sync::mpsc::channel();
        let handle = std::thread::Builder::new().name(name.to_string()).spawn(move || {
            // SAFETY: gettid has no preconditions.
            let _ = tid_tx.send(unsafe { libc::gettid() });
            served.serve()
        })?;
        me.tid.store(tid_rx.recv().unwrap_or(-1), Ordering::SeqCst);
        *me.thread.lock().unwrap() = Some(handle);
        Ok(me)
    }

    /// The thread's kernel id (Linux TID): its scheduling can be set from outside (SCHED_FIFO for the rig's servers).
    pub fn thread_id(&self) -> i32 {
        self.tid.load(Ordering::SeqCst)
    }

    /// Serve `server` from the next turn on.
    pub(crate) fn add(&self, server: Server) {
        self.incoming.lock().unwrap().push(server);
        self.wake();
    }

    /// No more servers come: the thread ends once those it has are finished.
    pub fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.wake();
    }

    /// Whether the thread still runs.
    pub fn alive(&self) -> bool {
        self.thread.lock().unwrap().as_ref().is_some_and(|t| !t.is_finished())
    }

    fn wake(&self) {
        let _ = (&self.wake_w).write(b"x");
    }

    fn serve(&self) {
        set_timer_slack();
        let mut servers: Vec<Server> = Vec::new();
        let mut fds: Vec<libc::pollfd> = Vec::new();
        let mut parts: Vec<(std::ops::Range<usize>, Instant)> = Vec::new();
        let mut waiter = PollWait::new(); // the poll set stays registered between turns
        loop {
            servers.append(&mut self.incoming.lock().unwrap());
            servers.retain_mut(|s| {
                if s.stopping() {
                    s.finish();
                }
                !s.stopping()
            });
            if servers.is_empty() && self.closed.load(Ordering::SeqCst) && self.incoming.lock().unwrap().is_empty() {
                return;
            }
            fds.clear();
            parts.clear();
            fds.push(libc::pollfd { fd: self.wake_r.as_raw_fd(), events: libc::POLLIN, revents: 0 });
            let mut timeout = IDLE_NS;
            for s in servers.iter_mut() {
                let (first, asked) = (fds.len(), Instant::now());
                let own = s.poll_set(&mut fds).max(0);
                timeout = timeout.min(own);
                parts.push((first..fds.len(), asked + Duration::from_nanos(own as u64)));
            }
            waiter.wait(&mut fds, timeout.max(0));
            if fds[0].revents != 0 {
                drain_wake_ups(&mut &self.wake_r);
            }
            let now = Instant::now();
            let due: Vec<bool> = parts.iter().map(|(part, due)| now >= *due || fds[part.clone()].iter().any(|p| p.revents != 0)).collect();
            for group in radio_groups(&servers) {
                if group.iter().any(|&k| due[k]) {
                    let mut turns: Vec<(&mut Server, &[libc::pollfd])> = servers.iter_mut().zip(parts.iter()).enumerate()
                        .filter(|(k, _)| group.contains(k)).map(|(_, (s, (part, _)))| (s, &fds[part.clone()])).collect();
                    turn_together(&mut turns);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_thread_id_names_the_serving_thread_of_this_process_not_the_caller() {
        let thread = ServingThread::start("tid test").unwrap();
        let tid = thread.thread_id();
        // SAFETY: gettid has no preconditions.
        assert_ne!(tid, unsafe { libc::gettid() });
        let comm = std::fs::read_to_string(format!("/proc/self/task/{tid}/comm")).unwrap();
        assert_eq!(comm.trim(), "tid test");
        thread.close();
    }
}
