//! A bus's error-model events and summary as Python dicts, for the virtual network and the bus server alike.

use super::*;

/// An event as (kind, fields) for Python (`hil.can.error_events.event_text` and the guardian word them).
pub(super) fn event_fields<'py>(py: Python<'py>, bus: &Bus, e: &BusEvent) -> PyResult<(&'static str, Bound<'py, PyDict>)> {
    let d = PyDict::new(py);
    let name = |node: usize| bus.nodes[node].name.clone();
    let kind = match &e.kind {
        EventKind::State { node, state, tec, rec } => {
            d.set_item("node", name(*node))?;
            d.set_item("tec", tec)?;
            d.set_item("rec", rec)?;
            state.name()
        }
        EventKind::BusOff { node, tec, lost } => {
            d.set_item("node", name(*node))?;
            d.set_item("tec", tec)?;
            d.set_item("lost", lost)?;
            "bus_off"
        }
        EventKind::Recovered { node, after_ns } => {
            d.set_item("node", name(*node))?;
            d.set_item("after_ns", after_ns)?;
            "recovered"
        }
        EventKind::ErrorFrame { error, frame_id, node } => {
            d.set_item("error", error.name())?;
            d.set_item("frame_id", frame_id)?;
            d.set_item("node", name(*node))?;
            "error_frame"
        }
        EventKind::Episode { start_ns, last_ns, by_error } => {
            d.set_item("start_ns", start_ns)?;
            d.set_item("last_ns", last_ns)?;
            let kinds = PyDict::new(py);
            for (k, n) in by_error {
                kinds.set_item(k.name(), n)?;
            }
            d.set_item("by_error", kinds)?;
            "episode"
        }
        EventKind::Babbling { frame_id, frames, busy_ns, allowance } => {
            d.set_item("frame_id", frame_id)?;
            d.set_item("frames", frames)?;
            d.set_item("busy_ns", busy_ns)?;
            d.set_item("allowance", allowance)?;
            "babbling"
        }
        EventKind::Cleared { frame_id } => {
            d.set_item("frame_id", frame_id)?;
            "cleared"
        }
    };
    Ok((kind, d))
}

/// The error model's summary of a bus for Python (see `Network.bus_errors`).
pub(super) fn errors_summary<'py>(py: Python<'py>, bus: &Bus) -> PyResult<Option<Bound<'py, PyDict>>> {
    let Some(e) = bus.errors.as_deref() else { return Ok(None) };
    let d = PyDict::new(py);
    for (k, v) in e.stats.items() {
        d.set_item(k, v)?;
    }
    let by_error = PyDict::new(py);
    for (k, n) in &e.by_error {
        by_error.set_item(k.name(), n)?;
    }
    d.set_item("by_error", by_error)?;
    let nodes = PyDict::new(py);
    for (node, c, bus_off_ns) in e.nodes() {
        let n = PyDict::new(py);
        n.set_item("tec_max", c.tec_max)?;
        n.set_item("rec_max", c.rec_max)?;
        n.set_item("error_passive", c.passive_count)?;
        n.set_item("bus_off", c.bus_off_count)?;
        n.set_item("bus_off_s", bus_off_ns as f64 * 1e-9)?;
        n.set_item("state", c.state.name())?;
        nodes.set_item(&bus.nodes[node].name, n)?;
    }
    d.set_item("nodes", nodes)?;
    let undetected: Vec<Bound<'py, PyTuple>> = e.undetected.iter()
        .map(|u| (u.t_ns, u.sent_id, u.delivered_id, PyBytes::new(py, u.delivered.as_slice()), PyBytes::new(py, u.sent.as_slice()),
                  u.flipped.clone()).into_pyobject(py))
        .collect::<PyResult<_>>()?;
    d.set_item("undetected_frames", undetected)?;
    d.set_item("babbling_detections", bus.guardian.as_ref().map_or(0, |g| g.detections))?;
    Ok(Some(d))
}
