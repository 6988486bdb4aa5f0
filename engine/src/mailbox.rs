//! An ECU's input mailboxes: the latest raw frame of each input stream, and the latest frame that passed
//! the E2E check. Delivery only stores the frame; the firmware reads every mailbox once per cycle
//! (`refresh`), which checks and decodes the frame that arrived since the last cycle, if any.

use std::sync::Arc;

use crate::codec::MessageLayout;
use crate::e2e::Checker;
use crate::frame::MAX_DATA;

/// One input stream's mailbox.
#[derive(Debug, Clone)]
pub struct Slot {
    pub layout: Arc<MessageLayout>,
    pub checker: Checker,
    raw: [u8; MAX_DATA],
    has_raw: bool,
    t_raw: f64,
    pub values: Vec<f64>,
    pub t_good: f64,
    pub counter: i32,
    pub was_fresh: bool,
}

impl Slot {
    fn new(layout: Arc<MessageLayout>, max_delta: u8) -> Slot {
        let checker = Checker::new(layout.data_id, max_delta);
        Slot { layout, checker, raw: [0; MAX_DATA], has_raw: false, t_raw: f64::NEG_INFINITY, values: Vec::new(),
               t_good: f64::NEG_INFINITY, counter: -1, was_fresh: false }
    }

    /// Check and decode the frame that arrived since the last read, if any.
    pub fn refresh(&mut self) {
        if !self.has_raw {
            return;
        }
        self.has_raw = false;
        let dlc = self.layout.dlc;
        if self.checker.check(&self.raw[..dlc]).usable() {
            // the length was checked on delivery, so decoding cannot fail
            let _ = self.layout.decode_into(&self.raw[..dlc], &mut self.values);
            self.t_good = self.t_raw;
            self.counter = (self.raw[1] & 0xF) as i32;
        }
    }

    /// Whether the last good frame is at most `timeout` old at `t`; a stream that had been fresh and is not
    /// any more counts a TIMEOUT.
    pub fn fresh(&mut self, t: f64, timeout: f64) -> bool {
        let ok = t - self.t_good <= timeout;
        if ok != self.was_fresh {
            if !ok {
                self.checker.timeouts += 1;
            }
            self.was_fresh = ok;
        }
        ok
    }

    /// Forget everything received (a power cycle); keeps the statistics.
    pub fn reset(&mut self) {
        self.has_raw = false;
        self.values.clear();
        self.t_good = f64::NEG_INFINITY;
        self.counter = -1;
        self.was_fresh = false;
        self.checker.reset();
    }
}

/// What a delivery into the mailboxes did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    Stored,
    UnknownId,
    /// A known ID with the wrong length: (slot index, length), dropped without decoding.
    WrongLength(usize, usize),
}

/// All input mailboxes of one ECU, by frame ID.
#[derive(Debug, Clone, Default)]
pub struct Mailbox {
    pub slots: Vec<Slot>,
    /// Frame ID of each slot, in slot order (an ECU has a handful: a linear scan beats hashing).
    ids: Vec<u32>,
    pub unknown_frames: u64,
    pub malformed_frames: u64,
    /// The first wrong-length frame (time, slot, length): the firmware reports it once.
    pub first_malformed: Option<(f64, usize, usize)>,
}

impl Mailbox {
    /// Add the mailbox of one stream; returns its index.
    pub fn add_slot(&mut self, layout: Arc<MessageLayout>, max_delta: u8) -> usize {
        let index = self.slots.len();
        self.ids.push(layout.frame_id);
        self.slots.push(Slot::new(layout, max_delta));
        index
    }

    /// The frame IDs with a mailbox (the ECU's acceptance filter).
    pub fn ids(&self) -> Vec<u32> {
        self.ids.clone()
    }

    /// Store a frame received at `t` (s): the latest frame of its stream replaces an unread one.
    pub fn put(&mut self, frame_id: u32, data: &[u8], t: f64) -> Delivery {
        let Some(i) = self.ids.iter().position(|&id| id == frame_id) else {
            self.unknown_frames += 1;
            return Delivery::UnknownId;
        };
        let slot = &mut self.slots[i];
        if data.len() != slot.layout.dlc {
            self.malformed_frames += 1;
            if self.first_malformed.is_none() {
                self.first_malformed = Some((t, i, data.len()));
            }
            return Delivery::WrongLength(i, data.len());
        }
        slot.raw[..data.len()].copy_from_slice(data);
        slot.has_raw = true;
        slot.t_raw = t;
        Delivery::Stored
    }

    /// Read every mailbox once (the start of an ECU cycle).
    pub fn refresh(&mut self) {
        for slot in &mut self.slots {
            slot.refresh();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::SignalSpec;

    fn layout() -> Arc<MessageLayout> {
        Arc::new(MessageLayout {
            name: "AgentState_U02".into(), frame_id: 0x101, dlc: 8, data_id: 0x21,
            signals: vec![SignalSpec { name: "Position".into(), start: 12, length: 32, signed: false, scale: 0.001,
                                       offset: 0.0, raw_min: 0, raw_max: (1 << 32) - 1 }],
        })
    }

    #[test]
    fn latest_frame_wins_and_is_checked_once_per_read() {
        let l = layout();
        let mut mb = Mailbox::default();
        let i = mb.add_slot(l.clone(), 2);
        let mut buf = [0u8; MAX_DATA];
        let mut sat = [0u64];
        l.encode(&[1.0], 1, &mut sat, &mut buf).unwrap();
        assert_eq!(mb.put(0x101, &buf[..8], 0.1), Delivery::Stored);
        l.encode(&[2.0], 2, &mut sat, &mut buf).unwrap();
        mb.put(0x101, &buf[..8], 0.2);
        mb.refresh();
        let s = &mut mb.slots[i];
        assert_eq!(s.values, vec![2.0]);
        assert_eq!(s.t_good, 0.2);
        assert_eq!(s.counter, 2);
        assert_eq!(s.checker.counts[1], 1); // one INITIAL: the overwritten frame was never read
        assert!(s.fresh(0.25, 0.1));
        assert!(!s.fresh(0.5, 0.1));
        assert_eq!(s.checker.timeouts, 1);
        assert_eq!(mb.put(0x102, &buf[..8], 0.3), Delivery::UnknownId);
        assert_eq!(mb.put(0x101, &buf[..7], 0.3), Delivery::WrongLength(0, 7));
        assert_eq!(mb.first_malformed, Some((0.3, 0, 7)));
    }
}
