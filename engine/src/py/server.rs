//! `BusServerCore`: one emulated CAN bus served in wall-clock time by a native thread.

use super::*;

/// One emulated CAN bus served in wall-clock time by a native thread (see engine/src/server.rs).
#[pyclass(module = "trainhil_engine._native")]
pub struct BusServerCore {
    handle: Option<crate::server::ServerHandle>,
    bitrate: u64,
}

/// A native thread that serves several buses on one poll (engine/src/serving_thread.rs): give it to each
/// `BusServerCore` of a rig. It ends once it is dropped and its servers have shut down.
#[pyclass(module = "trainhil_engine._native")]
pub struct ServingThread {
    inner: std::sync::Arc<crate::serving_thread::ServingThread>,
}

#[pymethods]
impl ServingThread {
    #[new]
    fn new() -> PyResult<Self> {
        let inner = crate::serving_thread::ServingThread::start("bus-servers")
            .map_err(|e| PyValueError::new_err(format!("serving thread cannot start: {e}")))?;
        Ok(ServingThread { inner })
    }

    /// Whether the thread runs.
    #[getter]
    fn alive(&self) -> bool {
        self.inner.alive()
    }

    /// The thread's kernel id (a Linux TID, as ``threading.Thread.native_id``): for setting its scheduling.
    #[getter]
    fn native_id(&self) -> i32 {
        self.inner.thread_id()
    }
}

impl Drop for ServingThread {
    fn drop(&mut self) {
        self.inner.close();
    }
}

pub(super) fn stats_dict<'py>(py: Python<'py>, s: &crate::server::Shared, now_ns: u64) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("now_ns", now_ns)?;
    d.set_item("clients", s.clients)?;
    d.set_item("eager_clients", s.eager_clients)?;
    d.set_item("turns", s.turns)?;
    d.set_item("turns_held", s.turns_held)?;
    d.set_item("turn_overruns", s.turn_overruns)?;
    d.set_item("turns_let_go", s.turns_let_go.clone())?;
    d.set_item("turns_behind", s.turns_behind)?;
    d.set_item("turns_given_up_s", s.turns_given_up_s)?;
    d.set_item("frames", s.frames)?;
    d.set_item("busy_ns", s.busy_ns)?;
    d.set_item("frames_dropped", s.bus.frames_dropped())?;
    d.set_item("dropped_by_node", s.bus.dropped_by_node().into_iter().collect::<std::collections::BTreeMap<_, _>>())?;
    d.set_item("frames_rejected", s.rejected)?;
    d.set_item("rx_overruns", s.overruns)?;
    for (name, h) in [("latency", &s.latency), ("lateness", &s.lateness)] {
        d.set_item(format!("{name}_p50_s"), h.quantile_s(0.5))?;
        d.set_item(format!("{name}_p99_s"), h.quantile_s(0.99))?;
        d.set_item(format!("{name}_max_s"), if h.n > 0 { Some(h.max_ns as f64 * 1e-9) } else { None })?;
    }
    d.set_item("protocol_errors", s.bad.protocol_errors)?;
    d.set_item("truncated_records", s.bad.truncated_records)?;
    d.set_item("auth_failures", s.bad.auth_failures)?;
    d.set_item("clients_refused", s.bad.clients_refused)?;
    let load = &s.bus.stats.load;
    d.set_item("load_last_window", if load.len() >= 2 { Some(load[load.len() - 1]) } else { None })?;
    Ok(d)
}

#[pymethods]
impl BusServerCore {
    /// Serve on listening sockets the caller made (their fds are taken over: pass duplicates); `radio`: the rig's
    /// radio hub and this bus's index in it; `bell_fd`: the bus's bell FIFO opened read-write and non-blocking
    /// (taken over too), which quiet readers ring; `thread`: the serving thread it shares with the rig's other buses
    /// (None: a thread of its own).
    #[new]
    #[pyo3(signature = (channel, listener_fd, tcp_fd, token, bitrate, policy_name, depth, extended, load_window_ns, pace,
                        spin_ns, max_clients, hello_timeout_s, keep_log, fd = false, data_bitrate = None, radio = None,
                        bell_fd = None, thread = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(channel: String, listener_fd: i32, tcp_fd: Option<i32>, token: Option<Vec<u8>>, bitrate: u64, policy_name: &str,
           depth: usize, extended: bool, load_window_ns: u64, pace: f64, spin_ns: u64, max_clients: usize,
           hello_timeout_s: f64, keep_log: bool, fd: bool, data_bitrate: Option<u64>,
           radio: Option<(PyRef<'_, RadioHub>, usize)>, bell_fd: Option<i32>, thread: Option<PyRef<'_, ServingThread>>)
           -> PyResult<Self> {
        // SAFETY: the caller hands the bell's descriptor over; owned (and closed on any error) from here on.
        let bell = bell_fd.map(|fd| std::fs::File::from(unsafe { <std::os::fd::OwnedFd as std::os::fd::FromRawFd>::from_raw_fd(fd) }));
        let data_bitrate = data_bitrate.unwrap_or(bitrate);
        if data_bitrate < bitrate || (!fd && data_bitrate != bitrate) {
            return Err(PyValueError::new_err(format!("data bitrate {data_bitrate}: a CAN FD bus's, at least the nominal {bitrate}")));
        }
        let token = match token {
            None => None,
            Some(t) => Some(<[u8; 16]>::try_from(t.as_slice()).map_err(|_| PyValueError::new_err("a bus token is 16 bytes"))?),
        };
        if !(pace.is_finite() && pace > 0.0) || load_window_ns == 0 {
            return Err(PyValueError::new_err("pace and load_window_ns must be positive"));
        }
        let cfg = crate::server::ServerConfig {
            channel, bitrate, data_bitrate, format: if fd { Format::FdBrs } else { Format::Classical }, policy: policy(policy_name)?,
            depth, extended, load_window_ns, pace, spin_ns, max_clients,
            hello_timeout: std::time::Duration::from_secs_f64(hello_timeout_s.max(0.0)), keep_log, token,
        };
        let radio = radio.map(|(hub, bus)| (hub.hub.clone(), bus));
        let thread = thread.map(|t| t.inner.clone());
        let handle = crate::server::start(cfg, listener_fd, tcp_fd, bell, radio, thread)
            .map_err(|e| PyValueError::new_err(format!("bus server cannot start: {e}")))?;
        Ok(BusServerCore { handle: Some(handle), bitrate })
    }

    /// Epoch nanoseconds of the bus's time zero.
    #[getter]
    fn epoch0_ns(&self) -> u64 {
        self.handle.as_ref().map_or(0, |h| h.epoch0_ns)
    }

    #[getter]
    fn bitrate(&self) -> u64 {
        self.bitrate
    }

    /// Model time now (ns since the bus's zero).
    fn now_ns(&self) -> u64 {
        self.handle.as_ref().map_or(0, |h| h.now_ns())
    }

    /// A consistent snapshot of the counters and histograms (the load windows are closed up to now first).
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        let now = h.now_ns();
        let mut s = h.shared.lock().unwrap();
        let t = match s.bus.current {
            None => now,
            Some(tx) => now.min(tx.t_end.saturating_sub(1)),
        };
        s.bus.finish(t);
        stats_dict(py, &s, now)
    }

    /// Take the bus log rows since the last call: (frames rows, load rows) as float64 bytes, and (sent, dropped).
    fn take_log<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>, u64, u64)> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        let mut s = h.shared.lock().unwrap();
        let frames = std::mem::take(&mut s.bus.stats.frames);
        let load = std::mem::take(&mut s.bus.stats.load);
        let as_bytes = |v: &[f64]| -> Vec<u8> { v.iter().flat_map(|x| x.to_ne_bytes()).collect() };
        Ok((PyBytes::new(py, &as_bytes(&frames)), PyBytes::new(py, &as_bytes(&load)), s.bus.stats.frames_sent, s.bus.frames_dropped()))
    }

    /// The frames each node dropped, by node name (`Bus::dropped_by_node`): nodes that dropped none left out.
    fn dropped_by_node(&self) -> PyResult<std::collections::BTreeMap<String, u64>> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        Ok(h.shared.lock().unwrap().bus.dropped_by_node().into_iter().collect())
    }

    /// Keep completed transmissions for `take_trace` (CAN logs).
    fn set_trace(&self, on: bool) {
        if let Some(h) = self.handle.as_ref() {
            let mut s = h.shared.lock().unwrap();
            s.bus.trace = if on { Some(s.bus.trace.take().unwrap_or_default()) } else { None };
        }
    }

    /// [(frame_id, data, extended, t_enqueue, t_start, t_end, fd, brs)] completed since the last call (model ns).
    fn take_trace<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let Some(h) = self.handle.as_ref() else { return Ok(PyList::empty(py)) };
        let trace = {
            let mut s = h.shared.lock().unwrap();
            s.bus.trace.as_mut().map(std::mem::take).unwrap_or_default()
        };
        let items: Vec<Bound<'py, PyTuple>> = trace.iter()
            .map(|tx| (tx.frame_id, PyBytes::new(py, tx.data.as_slice()), tx.extended, tx.t_enqueue, tx.t_start, tx.t_end,
                       tx.format.is_fd(), tx.format.brs()).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        PyList::new(py, items)
    }

    /// Whether the serving thread runs.
    #[getter]
    fn serving(&self) -> bool {
        self.handle.as_ref().is_some_and(|h| h.running())
    }

    /// The frame on the wire: (frame_id, t_end ns), or None while the bus is idle.
    fn current(&self) -> Option<(u32, u64)> {
        let h = self.handle.as_ref()?;
        let s = h.shared.lock().unwrap();
        s.bus.current.map(|tx| (tx.frame_id, tx.t_end))
    }

    /// Model CAN errors and fault confinement on this bus (see `Network.enable_bus_errors`).
    fn enable_bus_errors(&self, rng_state: (u128, u128)) -> PyResult<()> {
        self.with_bus(|bus, _| {
            bus.enable_errors(Pcg64::from_state(rng_state.0, rng_state.1));
            Ok(())
        })
    }

    /// From now on the load windows end at model time `origin_ns` + k x the window (the run's zero: virtual
    /// time's phase); call it before that time.
    fn align_load_windows(&self, origin_ns: u64) -> PyResult<()> {
        self.with_bus(|bus, now| {
            bus.align_load_windows(origin_ns, now);
            Ok(())
        })
    }

    /// Watch this bus for a babbling idiot (see `Network.set_guardian`).
    fn set_guardian(&self, allowances: std::collections::HashMap<u32, u32>, window_ns: u64, share_ns: f64) -> PyResult<()> {
        check_window(window_ns)?;
        self.with_bus(|bus, _| {
            bus.guardian = Some(Guardian::new(allowances, window_ns, share_ns));
            Ok(())
        })
    }

    /// Start fault `fault`'s effect on this bus (see `Network.add_bus_fault`).
    #[pyo3(signature = (fault, kind, rng_state, probability, frame_ids, count, bits = 1))]
    #[allow(clippy::too_many_arguments)]
    fn add_bus_fault(&self, fault: u64, kind: &str, rng_state: (u128, u128), probability: f64, frame_ids: Option<Vec<u32>>,
                     count: Option<u64>, bits: u32) -> PyResult<()> {
        self.with_bus(|bus, _| add_bus_fault(bus, fault, kind, rng_state, probability, frame_ids, count, bits))
    }

    /// A babbling node for fault `fault` joins this bus and queues its first frame now; returns its node.
    fn start_babbler(&self, fault: u64, name: &str, frame_id: u32, data: PyBackedBytes, extended: bool) -> PyResult<usize> {
        self.with_bus(|bus, now| {
            frame::validate_as(frame_id, data.len(), extended, bus.format.is_fd()).map_err(frame_err)?;
            let node = bus.start_babbler(fault, name, frame_id, &data, extended)
                .ok_or_else(|| PyValueError::new_err("a babbling node needs the bus's error model (enable_bus_errors)"))?;
            let format = bus.format;
            bus.enqueue_as(node, frame_id, &data, now, Some(extended), format);
            Ok(node)
        })
    }

    /// End fault `fault`'s effect on this bus (a babbler leaves it).
    fn end_bus_fault(&self, fault: u64) -> PyResult<()> {
        self.with_bus(|bus, _| {
            bus.end_fault(fault);
            Ok(())
        })
    }

    /// Take this bus's error-model and guardian events since the last call: [(t_ns, kind, fields)] in model time.
    fn take_bus_events<'py>(&self, py: Python<'py>) -> PyResult<Vec<(i64, &'static str, Bound<'py, PyDict>)>> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        let s = &mut *h.shared.lock().unwrap();
        let events = std::mem::take(&mut s.bus.events);
        events.iter().map(|e| {
            let (kind, fields) = event_fields(py, &s.bus, e)?;
            Ok((e.t_ns, kind, fields))
        }).collect()
    }

    /// This bus's error model summary (see `Network.bus_errors`).
    fn bus_errors<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        let s = h.shared.lock().unwrap();
        errors_summary(py, &s.bus)
    }

    /// Log lines since the last call: [(level, text, t_ns)], t_ns the model time each happened (ns since the
    /// server's zero).
    fn take_messages(&self) -> Vec<(&'static str, String, u64)> {
        let Some(h) = self.handle.as_ref() else { return Vec::new() };
        let lines = std::mem::take(&mut h.shared.lock().unwrap().messages);
        lines.into_iter().map(|m| (m.level, m.text, m.t_ns)).collect()
    }

    /// Stop serving (disconnects every node) and join the thread; idempotent.
    fn shutdown(&mut self, py: Python<'_>) {
        if let Some(h) = self.handle.as_mut() {
            py.allow_threads(|| h.shutdown());
        }
    }
}

impl BusServerCore {
    /// Run `f(bus, now_ns)` under the server's lock, then wake its loop.
    fn with_bus<R>(&self, f: impl FnOnce(&mut Bus, u64) -> PyResult<R>) -> PyResult<R> {
        let h = self.handle.as_ref().ok_or_else(|| PyValueError::new_err("bus server is closed"))?;
        let out = {
            let now = h.now_ns();
            let mut s = h.shared.lock().unwrap();
            f(&mut s.bus, now)
        };
        h.wake();
        out
    }
}
