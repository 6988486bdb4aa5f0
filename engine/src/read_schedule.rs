//! A lazy reader's read times, per bus: which of its buses a wait at a given instant was foreseen on.
//!
//! A real-time node that reads lazily tells each bus server its periodic read times once (`READ_EVERY`); a wait at
//! one of them then waits only for the SYNCs of the buses that have it, and a wait at any other instant asks its
//! buses once. Times are integer microseconds of simulated time, matched to within 1 µs (the float seconds they
//! come from round differently on each side).

/// One periodic read time: the next instant, its period (µs, > 0) and its bus.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Entry {
    next_us: i64,
    period_us: i64,
    bus: usize,
}

/// The periodic read times a lazy reader gave its bus servers.
#[derive(Clone, Debug, Default)]
pub struct ReadSchedule {
    entries: Vec<Entry>,
}

impl ReadSchedule {
    pub fn new() -> ReadSchedule {
        ReadSchedule::default()
    }

    /// Read times `first_us + k * period_us` on `bus`; a period of 0 or less is a single read, asked for at its
    /// wait, so it is not kept.
    pub fn add(&mut self, first_us: i64, period_us: i64, bus: usize) {
        if period_us > 0 {
            self.entries.push(Entry { next_us: first_us, period_us, bus });
        }
    }

    /// The buses (ascending, each once) that have `now_us` among their read times, to within 1 µs; every schedule
    /// moves on past it. Read times passed without a wait (skipped cycles) are caught up first.
    pub fn due(&mut self, now_us: i64) -> Vec<usize> {
        let mut buses = Vec::new();
        for e in self.entries.iter_mut() {
            while e.next_us <= now_us + 1 {
                if e.next_us < now_us - 1 {
                    let behind = now_us - 1 - e.next_us;
                    e.next_us += (behind + e.period_us - 1) / e.period_us * e.period_us;
                }
                if e.next_us <= now_us + 1 {
                    buses.push(e.bus);
                    e.next_us += e.period_us;
                }
            }
        }
        buses.sort_unstable();
        buses.dedup();
        buses
    }

    /// The buses (ascending, each once) with a read time before `now_us` that no wait took (skipped cycles). A
    /// node whose read times are turns ends those on its way to `now_us` (`LinkGroup.begin_wait`); call it before
    /// `due`, which catches them up.
    pub fn skipped(&self, now_us: i64) -> Vec<usize> {
        let mut buses: Vec<usize> = self.entries.iter().filter(|e| e.next_us < now_us - 1).map(|e| e.bus).collect();
        buses.sort_unstable();
        buses.dedup();
        buses
    }

    /// Whether no periodic read time was given.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// Seconds -> integer microseconds, rounded half to even (as Python's `round`).
pub fn to_us(seconds: f64) -> i64 {
    (seconds * 1e6).round_ties_even() as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wait_at_a_read_time_names_its_buses_once_and_moves_them_on() {
        let mut s = ReadSchedule::new();
        s.add(2_000, 10_000, 0);
        s.add(2_000, 10_000, 2);
        s.add(2_100, 10_000, 1);
        assert_eq!(s.due(2_000), vec![0, 2]);
        assert_eq!(s.due(2_000), Vec::<usize>::new()); // a second event at the same instant: asked already
        assert_eq!(s.due(2_101), vec![1]); // within 1 µs
        assert_eq!(s.due(12_000), vec![0, 2]);
    }

    #[test]
    fn an_instant_between_read_times_is_not_foreseen() {
        let mut s = ReadSchedule::new();
        s.add(2_000, 10_000, 0);
        assert!(s.due(1_000).is_empty());
        assert!(s.due(1_998).is_empty()); // 2 µs early: not the read time
        assert_eq!(s.due(1_999), vec![0]);
    }

    #[test]
    fn read_times_passed_without_a_wait_are_caught_up() {
        let mut s = ReadSchedule::new();
        s.add(0, 10_000, 0);
        assert_eq!(s.due(0), vec![0]);
        assert!(s.skipped(10_000).is_empty(), "10 ms is the next read, not a skipped one");
        assert_eq!(s.skipped(40_000), vec![0]);
        assert_eq!(s.due(40_000), vec![0]); // 10, 20 and 30 ms were skipped
        assert!(s.skipped(45_000).is_empty(), "caught up");
        assert!(s.due(45_000).is_empty());
        assert_eq!(s.due(50_000), vec![0]);
        assert!(s.due(55_000).is_empty()); // skipped past a read time that is not one: nothing due, moved on
        assert_eq!(s.due(60_000), vec![0]);
    }

    #[test]
    fn a_single_read_is_not_kept() {
        let mut s = ReadSchedule::new();
        s.add(5_000, 0, 0);
        assert!(s.is_empty());
        assert!(s.due(5_000).is_empty());
    }

    #[test]
    fn seconds_round_to_the_nearest_microsecond() {
        assert_eq!(to_us(0.002), 2_000);
        assert_eq!(to_us(0.0021), 2_100); // 2100.0000000000005 µs as a float product
        assert_eq!(to_us(0.0020994), 2_099);
        assert_eq!(to_us(-0.0000014), -1);
    }
}
