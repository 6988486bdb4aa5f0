//! `Mailbox`: an ECU's input mailboxes, read once per cycle.

use super::*;

/// An ECU's input mailboxes, one per stream; delivery stores the latest frame, `refresh` checks and decodes
/// what arrived since the last cycle.
#[pyclass(module = "trainhil_engine._native")]
pub struct Mailbox {
    pub(crate) inner: Arc<Mutex<core_mailbox::Mailbox>>,
}

#[pymethods]
impl Mailbox {
    #[new]
    fn new() -> Self {
        Mailbox { inner: Arc::new(Mutex::new(core_mailbox::Mailbox::default())) }
    }

    /// Add the mailbox of one message stream; returns its slot index.
    fn add_slot(&self, codec: &MessageCodec, max_delta: u8) -> PyResult<usize> {
        if max_delta > e2e::COUNTER_MODULO - 2 {
            return Err(PyValueError::new_err(format!("{}: max_delta {max_delta} is not in 0..14", codec.name)));
        }
        Ok(self.inner.lock().unwrap().add_slot(codec.layout.clone(), max_delta))
    }

    /// Store a frame received at `t` (s): 0 stored, 1 unknown ID, 2 known ID with the wrong length (dropped).
    fn put(&self, frame_id: u32, data: PyBackedBytes, t: f64) -> u8 {
        match self.inner.lock().unwrap().put(frame_id, &data, t) {
            core_mailbox::Delivery::Stored => 0,
            core_mailbox::Delivery::UnknownId => 1,
            core_mailbox::Delivery::WrongLength(..) => 2,
        }
    }

    /// Check and decode the frame of every slot that arrived since the last call; returns the count of
    /// wrong-length frames so far (the firmware reports the first).
    fn refresh(&self) -> u64 {
        let mut mb = self.inner.lock().unwrap();
        mb.refresh();
        mb.malformed_frames
    }

    /// One slot at time t: (fresh within `timeout`, age s, values, alive counter, reception time of the last good
    /// frame). A stream that had been fresh and is not any more counts a TIMEOUT.
    fn read<'py>(&self, py: Python<'py>, slot: usize, t: f64, timeout: f64) -> PyResult<Bound<'py, PyTuple>> {
        let mut mb = self.inner.lock().unwrap();
        let s = mb.slots.get_mut(slot).ok_or_else(|| PyIndexError::new_err(format!("no mailbox slot {slot}")))?;
        let fresh = s.fresh(t, timeout);
        let values = PyTuple::new(py, s.values.iter())?;
        (fresh, t - s.t_good, values, s.counter, s.t_good).into_pyobject(py)
    }

    /// Values of a slot's last good frame (empty before any).
    fn values<'py>(&self, py: Python<'py>, slot: usize) -> PyResult<Bound<'py, PyTuple>> {
        let mb = self.inner.lock().unwrap();
        PyTuple::new(py, mb.slots[slot].values.iter())
    }

    fn counter(&self, slot: usize) -> i32 {
        self.inner.lock().unwrap().slots[slot].counter
    }

    fn t_good(&self, slot: usize) -> f64 {
        self.inner.lock().unwrap().slots[slot].t_good
    }

    /// Forget what every slot received (a power cycle); keeps the statistics.
    fn reset(&self) {
        for s in &mut self.inner.lock().unwrap().slots {
            s.reset();
        }
    }

    /// E2E verdicts of one slot: non-zero counts by status name, plus LOST and TIMEOUT.
    fn summary<'py>(&self, py: Python<'py>, slot: usize) -> PyResult<Bound<'py, PyDict>> {
        let mb = self.inner.lock().unwrap();
        let c = &mb.slots[slot].checker;
        let d = PyDict::new(py);
        for (name, &n) in STATUS_NAMES.iter().zip(c.counts.iter()) {
            if n > 0 {
                d.set_item(*name, n)?;
            }
        }
        if c.lost > 0 {
            d.set_item("LOST", c.lost)?;
        }
        if c.timeouts > 0 {
            d.set_item("TIMEOUT", c.timeouts)?;
        }
        Ok(d)
    }

    /// Count of one E2E status (index as in ecu_sim.e2e.E2EStatus) of one slot.
    fn count(&self, slot: usize, status: usize) -> u64 {
        self.inner.lock().unwrap().slots[slot].checker.counts[status]
    }

    /// The frame IDs with a slot (the acceptance filter).
    fn ids(&self) -> Vec<u32> {
        self.inner.lock().unwrap().ids()
    }

    #[getter]
    fn unknown_frames(&self) -> u64 {
        self.inner.lock().unwrap().unknown_frames
    }

    #[getter]
    fn malformed_frames(&self) -> u64 {
        self.inner.lock().unwrap().malformed_frames
    }

    /// The first wrong-length frame not reported yet: (t, slot, length), or None.
    fn take_first_malformed(&self) -> Option<(f64, usize, usize)> {
        let mut mb = self.inner.lock().unwrap();
        let first = mb.first_malformed;
        if first.is_some() {
            mb.first_malformed = Some((f64::NAN, usize::MAX, 0)); // reported: later ones are only counted
        }
        first.filter(|f| f.1 != usize::MAX)
    }
}
