//! `RadioHub`: the radio between a real-time rig's bus servers (engine/src/radio_hub.rs), as Python builds it.

use super::network::{draws_from, gateway_err, link_stats_dict, make_link};
use super::*;
use crate::radio_hub::RadioHub as CoreHub;

/// Blocks of draws kept queued per link (and for the injected faults) by `top_up`.
const RESERVE_BLOCKS: usize = 8;

/// The radio gateway of the real-time bus servers: links and routes as `Network`'s, its random numbers queued
/// ahead in blocks by `top_up` (the owner calls it a few times a second), since the servers cannot call Python.
#[pyclass(module = "trainhil_engine._native")]
pub struct RadioHub {
    pub(super) hub: Arc<CoreHub>,
    refills: Vec<Py<PyAny>>,
    fault_refill: Option<Py<PyAny>>,
}

#[pymethods]
impl RadioHub {
    /// `packing`: the CAN FD containers of the buses (routed frames are found inside them).
    #[new]
    #[pyo3(signature = (pace, packing = None))]
    fn new(pace: f64, packing: Option<&Packing>) -> PyResult<Self> {
        if !(pace.is_finite() && pace > 0.0) {
            return Err(PyValueError::new_err(format!("pace {pace} must be positive")));
        }
        Ok(RadioHub { hub: Arc::new(CoreHub::new(packing.map(|p| p.inner.clone()), pace)), refills: Vec::new(), fault_refill: None })
    }

    /// One direction of a radio link (as `Network.add_link`); its first blocks of draws are queued now.
    #[pyo3(signature = (name, range_m, blackouts, latency_ns, period_ns, loss_model, p, p_good_to_bad, p_bad_to_good,
                        loss_good, loss_bad, initially_bad, refill))]
    #[allow(clippy::too_many_arguments)]
    fn add_link(&mut self, py: Python<'_>, name: &str, range_m: f64, blackouts: Vec<(f64, f64)>, latency_ns: i64,
                period_ns: Option<i64>, loss_model: &str, p: f64, p_good_to_bad: f64, p_bad_to_good: f64, loss_good: f64,
                loss_bad: f64, initially_bad: bool, refill: Py<PyAny>) -> PyResult<usize> {
        let link = make_link(name, range_m, blackouts, latency_ns, period_ns, loss_model, p, p_good_to_bad, p_bad_to_good,
                             loss_good, loss_bad, initially_bad)?;
        self.refills.push(refill);
        let index = self.hub.add_link(link);
        self.top_up(py)?;
        Ok(index)
    }

    /// Forward `src_id` heard on `src_bus` to `dst_bus` as `dst_id` over `link` (`reverse`: the other direction).
    fn add_route(&self, src_bus: usize, src_id: u32, dst_bus: usize, dst_id: u32, link: usize, reverse: Option<usize>) -> PyResult<()> {
        let mut core = self.hub.core.lock().unwrap();
        core.gateway.add_checked_route(src_bus, src_id, Hop { dst_bus, dst_id, link, reverse }).map_err(gateway_err)
    }

    /// Frames of this message carry their sender's position in their first signal (radio range, tunnels).
    fn set_position_codec(&self, codec: &MessageCodec) {
        self.hub.set_position_layout(codec.layout.clone());
    }

    /// Injected faults on radio link `link` (as `Network.set_impairment`); the faults' draws are queued from now on.
    fn set_impairment(&mut self, py: Python<'_>, link: usize, blackout: bool, losses: Vec<f64>, extra_ns: i64,
                      refill: Py<PyAny>) -> PyResult<()> {
        self.hub.core.lock().unwrap().gateway.set_impairment(link, blackout, losses, extra_ns).map_err(gateway_err)?;
        self.fault_refill = Some(refill);
        self.top_up(py).map(|_| ())
    }

    /// Queue blocks of draws until every link (and the injected faults, once set) has `RESERVE_BLOCKS` waiting;
    /// returns the most blocks any one of them had used since the last top-up (how fast the busiest one draws).
    fn top_up(&self, py: Python<'_>) -> PyResult<usize> {
        let (links, faults) = self.hub.reserves();
        for (link, &queued) in links.iter().enumerate() {
            for _ in queued..RESERVE_BLOCKS {
                let block = self.refills[link].call0(py)?;
                self.hub.push_draws(link, draws_from(py, block)?);
            }
        }
        if let Some(refill) = &self.fault_refill {
            for _ in faults..RESERVE_BLOCKS {
                let u: Vec<f64> = refill.call0(py)?.extract(py)?;
                if u.is_empty() {
                    return Err(PyValueError::new_err("the fault refill must return a non-empty list"));
                }
                self.hub.push_fault_draws(u);
            }
        }
        let least = links.iter().copied().chain(self.fault_refill.as_ref().map(|_| faults)).min();
        Ok(RESERVE_BLOCKS.saturating_sub(least.unwrap_or(RESERVE_BLOCKS)))
    }

    /// Blocks of draws `top_up` keeps queued for each link (and for the injected faults).
    #[classattr]
    const RESERVE_BLOCKS: usize = RESERVE_BLOCKS;

    fn link_stats<'py>(&self, py: Python<'py>, link: usize) -> PyResult<Bound<'py, PyDict>> {
        let core = self.hub.core.lock().unwrap();
        let l = core.gateway.links.get(link).ok_or_else(|| PyIndexError::new_err(format!("no radio link {link}")))?;
        link_stats_dict(py, &l.stats)
    }

    /// Frames dropped because a link's draws ran out (`top_up` not called often enough).
    #[getter]
    fn starved(&self) -> u64 {
        self.hub.core.lock().unwrap().starved
    }
}
