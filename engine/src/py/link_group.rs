//! `LinkGroup`: a lazy reader's wait for its read time on all its buses at once, in a few engine calls.
//!
//! A real-time node waits at each event for its bus servers' SYNCs of the event's time, then acts as at that
//! time and takes what its buses kept. Done per bus from Python, that was a dozen interpreter calls per wait (a
//! node wakes cold, so each is dear); here it is three: `begin_wait`, `wait_more` while a SYNC is missing, and
//! `finish`.

use super::*;
use super::link::FrameLink;
use crate::read_schedule::{to_us, ReadSchedule};

/// The lazy links of one node, with the read times it gave them.
#[pyclass(module = "trainhil_engine._native")]
pub struct LinkGroup {
    links: Vec<Py<FrameLink>>,
    schedule: ReadSchedule,
    /// The buses the current wait waits for, and those of them not synced yet.
    asked: Vec<usize>,
    waiting: Vec<usize>,
    /// Some of its read times are turns (`read_every(..., turns=True)`): only then has a wait turns to end.
    turns: bool,
}

impl LinkGroup {
    fn link<'py>(&self, py: Python<'py>, bus: usize) -> PyResult<PyRefMut<'py, FrameLink>> {
        let link = self.links.get(bus).ok_or_else(|| PyIndexError::new_err(format!("bus {bus} is not in the group")))?;
        Ok(link.bind(py).borrow_mut())
    }

    /// The epoch second of simulated time `sim_t` (the links share one clock).
    fn epoch(&self, py: Python<'_>, sim_t: f64) -> PyResult<f64> {
        Ok(match self.links.first() {
            Some(link) => link.bind(py).borrow().epoch(sim_t),
            None => sim_t,
        })
    }

    /// End the turns still open at an instant before `t` (epoch s): the node has moved on to wait for `t`.
    fn end_turns_before(&self, py: Python<'_>, t: f64) -> PyResult<()> {
        for bus in 0..self.links.len() {
            let mut link = self.link(py, bus)?;
            if link.in_turn() && link.acts_at() < t - crate::protocol::SYNC_TOLERANCE_S {
                link.end_turn()?;
            }
        }
        Ok(())
    }

    /// Of `buses`, those whose SYNC of `t` (epoch s) has not come yet (what came is handed over).
    fn not_synced(&self, py: Python<'_>, buses: &[usize], t: f64) -> PyResult<Vec<usize>> {
        let mut left = Vec::new();
        for &bus in buses {
            if !self.link(py, bus)?.sync_now(t)? {
                left.push(bus);
            }
        }
        Ok(left)
    }
}

#[pymethods]
impl LinkGroup {
    /// `links`: the node's lazy links, one per bus, indexed as its buses.
    #[new]
    fn new(links: Vec<Py<FrameLink>>) -> Self {
        LinkGroup { links, schedule: ReadSchedule::new(), asked: Vec::new(), waiting: Vec::new(), turns: false }
    }

    /// Read times `first + k * period` (simulated s) on `bus`, told to its server (0: a single read). `turns`:
    /// the bus's read times are the node's turns (`FrameLink.read_every`), which `end_turn` ends.
    #[pyo3(signature = (bus, first, period, turns = false))]
    fn read_every(&mut self, py: Python<'_>, bus: usize, first: f64, period: f64, turns: bool) -> PyResult<()> {
        let mut link = self.link(py, bus)?;
        let (epoch, wall_period) = (link.epoch(first), period / link.pace);
        link.read_every(epoch, wall_period, turns)?;
        drop(link);
        self.turns |= turns;
        self.schedule.add(to_us(first), to_us(period), bus);
        Ok(())
    }

    /// Start the wait for read time `sim_t` (simulated s): the buses that have it among their read times, or, at an
    /// instant none foresaw, every bus not yet synced to it, asked once. Returns those whose SYNC has not come.
    fn begin_wait(&mut self, py: Python<'_>, sim_t: f64) -> PyResult<Vec<usize>> {
        let t = self.epoch(py, sim_t)?;
        if self.turns {
            self.end_turns_before(py, t)?;
            for bus in self.schedule.skipped(to_us(sim_t)) {
                self.link(py, bus)?.end_turns_skipped(t)?; // a late node's skipped cycles must not hold its bus
            }
        }
        let mut asked = self.schedule.due(to_us(sim_t));
        if asked.is_empty() {
            let all: Vec<usize> = (0..self.links.len()).collect();
            asked = self.not_synced(py, &all, t)?;
            for &bus in &asked {
                self.link(py, bus)?.read_every(t, 0.0, false)?;
            }
        }
        self.waiting = self.not_synced(py, &asked, t)?;
        self.asked = asked;
        Ok(self.waiting.clone())
    }

    /// Sleep up to `timeout_s` (wall, the interpreter lock released) until a bus still waited for has something,
    /// then take what came. Returns the buses whose SYNC of `sim_t` has still not come.
    fn wait_more(&mut self, py: Python<'_>, sim_t: f64, timeout_s: f64) -> PyResult<Vec<usize>> {
        let fds = self.waiting.iter().map(|&bus| Ok(self.link(py, bus)?.fd())).collect::<PyResult<Vec<i32>>>()?;
        super::link::wait_readable(py, fds, timeout_s);
        let t = self.epoch(py, sim_t)?;
        let waiting = std::mem::take(&mut self.waiting);
        self.waiting = self.not_synced(py, &waiting, t)?;
        Ok(self.waiting.clone())
    }

    /// End the node's open turns on `buses` (default: every bus): those its last `finish` opened and no
    /// `send(end_turn=True)` ended yet. A turn still open when the node next waits for a later instant ends then.
    #[pyo3(signature = (buses = None))]
    fn end_turn(&mut self, py: Python<'_>, buses: Option<Vec<usize>>) -> PyResult<()> {
        if !self.turns {
            return Ok(());
        }
        for bus in buses.unwrap_or_else(|| (0..self.links.len()).collect()) {
            self.link(py, bus)?.end_turn()?;
        }
        Ok(())
    }

    /// The node's turns are over (its run ended): none of its read times holds a bus any more, though it may still
    /// wait for them (``FrameLink.end_turns_for_good`` on every link). A node that lingers after its last turn
    /// calls it, so its servers do not hold their buses for turns it will never take.
    fn end_turns_for_good(&mut self, py: Python<'_>) -> PyResult<()> {
        for bus in 0..self.links.len() {
            self.link(py, bus)?.end_turns_for_good()?;
        }
        self.turns = false;
        Ok(())
    }

    /// End the wait: every link acts at `sim_t` (its frames sent from now on carry that instant while it is ahead),
    /// and gives the frames it kept, read off its socket first unless it was just synced. Returns the buses' kept
    /// frames, [(bus, [(frame_id, data, t_sim)])], only those with some.
    fn finish<'py>(&mut self, py: Python<'py>, sim_t: f64) -> PyResult<Vec<(usize, Bound<'py, PyList>)>> {
        let t = self.epoch(py, sim_t)?;
        let mut out = Vec::new();
        for bus in 0..self.links.len() {
            let synced = self.asked.contains(&bus) && !self.waiting.contains(&bus);
            let mut link = self.link(py, bus)?;
            link.act_at(t);
            let kept = link.take(py, !synced)?;
            if !kept.is_empty() {
                out.push((bus, kept));
            }
        }
        self.asked.clear();
        self.waiting.clear();
        Ok(out)
    }
}
