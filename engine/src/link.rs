//! A node's end of a connection to a bus server (the client side of `protocol`): whole frames read from the
//! non-blocking socket, frames written as records. No Python here; `FrameLink` (`py/link.rs`) routes the frames it
//! reads into ECU mailboxes.

use std::os::fd::RawFd;

use crate::protocol::{pack_frame_records, read_frames, RECORD_SIZE};

/// Why the link cannot go on.
#[derive(Debug)]
pub enum LinkError {
    /// The bus server closed the connection.
    Closed,
    /// A frame's payload is longer than its format carries: (frame ID, length, limit).
    TooLong(u32, usize, usize),
    Io(std::io::Error),
}

impl std::fmt::Display for LinkError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinkError::Closed => write!(f, "bus link: the bus server closed the connection"),
            LinkError::TooLong(id, len, limit) => write!(f, "frame {id:#x}: {len} data bytes > {limit}"),
            LinkError::Io(e) => write!(f, "bus link: {e}"),
        }
    }
}

/// The socket (owned by the caller) and the bytes of a record not yet whole.
pub struct Link {
    fd: RawFd,
    partial: Vec<u8>,
}

fn would_block(err: &std::io::Error) -> bool {
    matches!(err.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted)
}

impl Link {
    /// `fd`: a connected, handshaken, non-blocking socket.
    pub fn new(fd: RawFd) -> Link {
        Link { fd, partial: Vec::new() }
    }

    pub fn fd(&self) -> RawFd {
        self.fd
    }

    /// Read every record waiting and call `each(can_id, flags, stamp, data)` for each whole frame.
    pub fn pump(&mut self, mut each: impl FnMut(u32, u8, f64, &[u8])) -> Result<(), LinkError> {
        let mut buf = [0u8; 64 * RECORD_SIZE];
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
            let used = read_frames(&self.partial, &mut each);
            self.partial.drain(..used);
        }
    }

    /// Write `frames` as FRAME records with `flags`; an FD frame's payload is padded to a CAN FD length. Waits
    /// while the socket is full.
    pub fn send(&self, frames: &[(u32, &[u8])], flags: u8) -> Result<(), LinkError> {
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
            pack_frame_records(id, &payload, flags, 0.0, &mut out);
        }
        self.write_all(&out)
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
        tx.send(&[(0x10, &[1, 2]), (0x11, &[3; 8])], 0).unwrap();
        tx.send(&[(0x12, &[7; 13])], FLAG_FD | FLAG_BRS).unwrap(); // padded to 16
        let mut got = Vec::new();
        rx.pump(|id, flags, _, d| got.push((id, flags, d.to_vec()))).unwrap();
        let mut long = vec![7; 13];
        long.resize(16, 0);
        assert_eq!(got, vec![(0x10, 0, vec![1, 2]), (0x11, 0, vec![3; 8]), (0x12, FLAG_FD | FLAG_BRS, long)]);
        assert!(matches!(tx.send(&[(0x13, &[0; 9])], 0), Err(LinkError::TooLong(0x13, 9, 8))));
        drop(a);
        assert!(matches!(rx.pump(|_, _, _, _| {}), Err(LinkError::Closed)));
    }
}
