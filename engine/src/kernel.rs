//! The virtual-time event queue: integer-nanosecond times, and equal times in scheduling order, so a run is
//! reproducible bit for bit.

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;

struct Entry<E> {
    t: u64,
    seq: u64,
    event: E,
}

impl<E> PartialEq for Entry<E> {
    fn eq(&self, other: &Self) -> bool {
        (self.t, self.seq) == (other.t, other.seq)
    }
}
impl<E> Eq for Entry<E> {}
impl<E> PartialOrd for Entry<E> {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl<E> Ord for Entry<E> {
    fn cmp(&self, other: &Self) -> Ordering {
        (self.t, self.seq).cmp(&(other.t, other.seq))
    }
}

/// A time-ordered queue of events with a clock.
pub struct EventQueue<E> {
    pub now: u64,
    heap: BinaryHeap<Reverse<Entry<E>>>,
    seq: u64,
}

impl<E> Default for EventQueue<E> {
    fn default() -> Self {
        EventQueue { now: 0, heap: BinaryHeap::new(), seq: 0 }
    }
}

impl<E> EventQueue<E> {
    /// Schedule `event` at `t` (not before now: that would be a bug of the caller).
    pub fn at(&mut self, t: u64, event: E) {
        debug_assert!(t >= self.now, "event scheduled in the past: {t} < {}", self.now);
        self.seq += 1;
        self.heap.push(Reverse(Entry { t, seq: self.seq, event }));
    }

    /// Time of the next pending event.
    pub fn next_time(&self) -> Option<u64> {
        self.heap.peek().map(|Reverse(e)| e.t)
    }

    /// Pop the next event if it is due before `until`, advancing the clock to its time.
    pub fn pop_before(&mut self, until: u64) -> Option<E> {
        if self.next_time()? >= until {
            return None;
        }
        let Reverse(e) = self.heap.pop()?;
        self.now = e.t;
        Some(e.event)
    }

    pub fn len(&self) -> usize {
        self.heap.len()
    }

    pub fn is_empty(&self) -> bool {
        self.heap.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equal_times_run_in_scheduling_order() {
        let mut q = EventQueue::default();
        q.at(5, "b");
        q.at(3, "a");
        q.at(5, "c");
        q.at(9, "d");
        let mut seen = Vec::new();
        while let Some(e) = q.pop_before(9) {
            seen.push((q.now, e));
        }
        assert_eq!(seen, vec![(3, "a"), (5, "b"), (5, "c")]);
        assert_eq!(q.next_time(), Some(9));
    }
}
