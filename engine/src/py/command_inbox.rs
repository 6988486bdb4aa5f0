//! `CommandInbox`: a real-time plant's TractionCmd frames decoded on receipt, and its sensor-to-actuator latency.

use std::collections::HashMap;

use super::*;
use crate::command_inbox::{CommandInbox as CoreInbox, NoSuchUnit};

fn unit_err(NoSuchUnit(u): NoSuchUnit) -> PyErr {
    PyIndexError::new_err(format!("unit {u} is out of the inbox's range"))
}

/// One train bus's command inbox (engine/src/command_inbox.rs): a `FrameLink` routes the frames into it
/// (`route_commands`), or a python-can receiver `put`s them.
#[pyclass(module = "trainhil_engine._native")]
pub struct CommandInbox {
    pub(crate) inner: Arc<Mutex<CoreInbox>>,
}

#[pymethods]
impl CommandInbox {
    /// `commands`: (frame_id, codec with signals (Mode, Force), unit) checked against `valid_modes`, as
    /// `Network.attach_commands`; `states`: (AgentState frame_id, unit); `units`: units are 0..units-1.
    #[new]
    fn new(commands: Vec<(u32, PyRef<'_, MessageCodec>, usize)>, valid_modes: Vec<i64>, states: Vec<(u32, usize)>,
           units: usize) -> PyResult<Self> {
        let table = command_table(commands, valid_modes)?;
        let inbox = CoreInbox::new(table, states.into_iter().collect::<HashMap<_, _>>(), units).map_err(unit_err)?;
        Ok(CommandInbox { inner: Arc::new(Mutex::new(inbox)) })
    }

    /// The frame IDs it takes (its commands' and its AgentStates').
    #[getter]
    fn ids(&self) -> Vec<u32> {
        self.inner.lock().unwrap().ids()
    }

    /// A frame received at `t` (simulated s); whether it was one of its IDs.
    fn put(&self, frame_id: u32, data: PyBackedBytes, t: f64) -> bool {
        self.inner.lock().unwrap().put(frame_id, &data, t)
    }

    /// The Sensor samples published at `t`: (unit, alive counter) each.
    fn published(&self, t: f64, samples: Vec<(usize, u8)>) -> PyResult<()> {
        let mut inbox = self.inner.lock().unwrap();
        samples.into_iter().try_for_each(|(u, counter)| inbox.published(u, counter, t)).map_err(unit_err)
    }

    /// What came since the last call, in arrival order: ([(unit, force, mode, t, alive counter)] of the valid
    /// commands, [(frame_id, data, t)] of the refused ones, [(command arrival t, latency s)]).
    fn take<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let mut inbox = self.inner.lock().unwrap();
        let commands = std::mem::take(&mut inbox.commands);
        let rejected = std::mem::take(&mut inbox.rejected);
        let latencies = std::mem::take(&mut inbox.latencies);
        let refused: Vec<Bound<'py, PyTuple>> = rejected.iter()
            .map(|(id, data, t)| (id, PyBytes::new(py, data.as_slice()), t).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        (commands, PyList::new(py, refused)?, latencies).into_pyobject(py)
    }
}
