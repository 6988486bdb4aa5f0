//! The bus guardian: a monitor on a train bus that notices a babbling idiot (`hil/faults/guardian.py` has the
//! rule and its reasons). It counts every delivered frame per ID in windows, with the bus time they took; an ID
//! that in one window sends more than its allowance AND holds more than a share of the bus is flagged, and
//! cleared after a window within both.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use crate::bus::Transmission;
use crate::errors::{BusEvent, EventKind};

/// Frames an ID the DBC does not know may send per window.
const UNKNOWN_ALLOWANCE: u32 = 2;

#[derive(Debug, Clone)]
pub struct Guardian {
    /// Frames per window each known ID may send (worked out from the DBC's cycle times by the Python side).
    allow: HashMap<u32, u32>,
    /// Bus time (ns) an ID must exceed in a window to be flagged.
    share_ns: f64,
    window_ns: u64,
    end: u64,
    /// Per ID in the window: (frames, bus time ns).
    counts: BTreeMap<u32, (u32, u64)>,
    flagged: BTreeSet<u32>,
    pub detections: u64,
}

impl Guardian {
    pub fn new(allow: HashMap<u32, u32>, window_ns: u64, share_ns: f64) -> Guardian {
        Guardian { allow, share_ns, window_ns, end: window_ns, counts: BTreeMap::new(), flagged: BTreeSet::new(), detections: 0 }
    }

    /// A frame the bus delivered; the window it closes (if any) is judged first.
    pub fn observe(&mut self, tx: &Transmission, events: &mut Vec<BusEvent>) {
        if tx.t_end >= self.end {
            self.judge(tx.t_end, events);
        }
        let c = self.counts.entry(tx.frame_id).or_insert((0, 0));
        c.0 += 1;
        c.1 += tx.t_end - tx.t_start;
    }

    /// Close the window ending at `end` (and any empty ones after it).
    fn judge(&mut self, t: u64, events: &mut Vec<BusEvent>) {
        let t_window = self.end as i64;
        let over: BTreeMap<u32, (u32, u64)> = self.counts.iter()
            .filter(|(fid, &(n, busy))| n > *self.allow.get(fid).unwrap_or(&UNKNOWN_ALLOWANCE) && busy as f64 > self.share_ns)
            .map(|(&fid, &c)| (fid, c))
            .collect();
        for (&frame_id, &(frames, busy_ns)) in &over {
            if self.flagged.insert(frame_id) {
                self.detections += 1;
                let allowance = self.allow.get(&frame_id).copied();
                events.push(BusEvent { t_ns: t_window, kind: EventKind::Babbling { frame_id, frames, busy_ns, allowance } });
            }
        }
        let cleared: Vec<u32> = self.flagged.iter().copied().filter(|fid| !over.contains_key(fid)).collect();
        for frame_id in cleared {
            self.flagged.remove(&frame_id);
            events.push(BusEvent { t_ns: t_window, kind: EventKind::Cleared { frame_id } });
        }
        self.counts.clear();
        self.end += self.window_ns * ((t - self.end) / self.window_ns + 1).max(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::{Format, Payload};

    fn tx(frame_id: u32, t_start: u64, t_end: u64) -> Transmission {
        Transmission { node: 0, frame_id, extended: false, format: Format::Classical, data: Payload::new(&[]), t_enqueue: t_start,
                       t_start, t_end, error: None }
    }

    #[test]
    fn an_id_over_its_allowance_and_its_share_is_flagged_once_then_cleared() {
        let mut g = Guardian::new(HashMap::from([(0x10, 22)]), 100_000_000, 30_000_000.0);
        let mut events = Vec::new();
        for k in 0..1000u64 {
            g.observe(&tx(0x001, k * 100_000, k * 100_000 + 90_000), &mut events); // babbling: 90 % of the bus
            g.observe(&tx(0x10, k * 100_000 + 90_000, k * 100_000 + 95_000), &mut events); // 1000 in a window, 5 % of the bus
        }
        g.observe(&tx(0x10, 250_000_000, 250_000_100), &mut events); // closes 0..100 ms; 100..200 ms was empty
        g.observe(&tx(0x10, 350_000_000, 350_000_100), &mut events); // closes 200..300 ms
        assert_eq!(events, vec![
            BusEvent { t_ns: 100_000_000, kind: EventKind::Babbling { frame_id: 1, frames: 1000, busy_ns: 90_000_000, allowance: None } },
            BusEvent { t_ns: 300_000_000, kind: EventKind::Cleared { frame_id: 1 } },
        ]);
        assert_eq!(g.detections, 1);
    }
}
