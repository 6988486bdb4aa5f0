//! `Network`: the virtual-time network (buses, radio, gateway, mailboxes) driven from Python.

use super::*;

#[pyclass(module = "trainhil_engine._native")]
pub struct Network {
    core: CoreNetwork,
    refills: Vec<Py<PyAny>>,
    /// Blocks of the injected radio faults' draws (`set_impairment`).
    fault_refill: Option<Py<PyAny>>,
    /// Wall time spent inside `advance` and `send` (the engine's own cost, for the benchmarks).
    busy: std::time::Duration,
}

pub(super) fn policy(name: &str) -> PyResult<Policy> {
    match name {
        "priority" => Ok(Policy::Priority),
        "fifo" => Ok(Policy::Fifo),
        _ => Err(PyValueError::new_err(format!("queue policy must be 'priority' or 'fifo', got '{name}'"))),
    }
}

#[pymethods]
impl Network {
    #[new]
    fn new() -> Self {
        Network { core: CoreNetwork::default(), refills: Vec::new(), fault_refill: None, busy: std::time::Duration::ZERO }
    }

    /// Add a bus; returns its index. With `fd` its nodes send CAN FD frames, switching to `data_bitrate`
    /// (default: `bitrate`) in the data phase when `brs` is set.
    #[pyo3(signature = (name, bitrate, policy_name = "priority", depth = 64, extended = false, load_window_ns = 100_000_000,
                        fd = false, data_bitrate = None, brs = true))]
    #[allow(clippy::too_many_arguments)]
    fn add_bus(&mut self, name: &str, bitrate: u64, policy_name: &str, depth: usize, extended: bool, load_window_ns: u64,
               fd: bool, data_bitrate: Option<u64>, brs: bool) -> PyResult<usize> {
        if load_window_ns == 0 {
            return Err(PyValueError::new_err("load_window_ns must be positive"));
        }
        let data_rate = data_bitrate.unwrap_or(bitrate);
        if !fd && data_rate != bitrate {
            return Err(PyValueError::new_err("data_bitrate is for CAN FD buses (fd=True)"));
        }
        if data_rate < bitrate {
            return Err(PyValueError::new_err(format!("data_bitrate {data_rate} is below the nominal bitrate {bitrate}")));
        }
        let format = Format::of(fd, brs);
        let bus = Bus::new(name, timing(bitrate, data_rate)?, policy(policy_name)?, depth, extended, load_window_ns).with_format(format);
        Ok(self.core.add_bus(bus))
    }

    /// A node that only sends; returns its node index on the bus.
    fn attach_sender(&mut self, bus: usize, name: &str) -> PyResult<usize> {
        Ok(self.bus_mut(bus)?.attach(name, Sink::None, None, false))
    }

    /// A node delivering into an ECU's mailboxes (filter: the mailbox's IDs).
    fn attach_mailbox(&mut self, bus: usize, name: &str, mailbox: &Mailbox) -> PyResult<usize> {
        let ids = mailbox.inner.lock().unwrap().ids();
        let m = self.core.add_mailbox(mailbox.inner.clone());
        Ok(self.bus_mut(bus)?.attach(name, Sink::Mailbox(m), Some(ids), false))
    }

    /// A node delivering into an inbox drained by `drain_inbox`; returns (node, inbox).
    fn attach_inbox(&mut self, bus: usize, name: &str, rx_ids: Option<Vec<u32>>) -> PyResult<(usize, usize)> {
        self.bus_mut(bus)?;
        let inbox = self.core.add_inbox();
        Ok((self.core.buses[bus].attach(name, Sink::Inbox(inbox), rx_ids, false), inbox))
    }

    /// The plant's node on a bus: TractionCmd frames are checked (length, E2E CRC, a mode in `valid_modes`) and
    /// decoded on delivery. `commands`: (frame_id, codec with signals (Mode, Force), unit index). Returns
    /// (node, table) where the table index is what `drain_commands` names a rejected frame by.
    fn attach_commands(&mut self, bus: usize, name: &str, commands: Vec<(u32, PyRef<'_, MessageCodec>, usize)>,
                       valid_modes: Vec<i64>) -> PyResult<(usize, usize)> {
        self.bus_mut(bus)?;
        let table = command_table(commands, valid_modes)?;
        Ok(self.core.attach_commands(bus, name, table))
    }

    /// Whether commands or rejected frames wait for `drain_commands` (a cheap check once per plant step).
    #[getter]
    fn has_commands(&self) -> bool {
        !self.core.commands.is_empty() || !self.core.rejected.is_empty()
    }

    /// The commands accepted since the last call, in arrival order: ([(unit, force, mode, t_s, alive counter)],
    /// [(table, frame_id, data, t_end_ns)] of the frames rejected).
    fn drain_commands<'py>(&mut self, py: Python<'py>) -> PyResult<(Vec<(usize, f64, i64, f64, u8)>, Bound<'py, PyList>)> {
        let commands = std::mem::take(&mut self.core.commands);
        let rejected = std::mem::take(&mut self.core.rejected);
        let items: Vec<Bound<'py, PyTuple>> = rejected.iter()
            .map(|(table, id, data, t)| (table, id, PyBytes::new(py, data.as_slice()), t).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        Ok((commands, PyList::new(py, items)?))
    }

    /// The radio gateway's node on a bus (add the links and routes first).
    fn attach_gateway(&mut self, bus: usize, name: &str) -> PyResult<usize> {
        self.bus_mut(bus)?;
        Ok(self.core.attach_gateway(bus, name))
    }

    /// One direction of a radio link; `refill()` returns the next block (u_step, u_loss, jitter_ns) of draws.
    #[pyo3(signature = (name, range_m, blackouts, latency_ns, period_ns, loss_model, p, p_good_to_bad, p_bad_to_good,
                        loss_good, loss_bad, initially_bad, refill))]
    #[allow(clippy::too_many_arguments)]
    fn add_link(&mut self, name: &str, range_m: f64, blackouts: Vec<(f64, f64)>, latency_ns: i64, period_ns: Option<i64>,
                loss_model: &str, p: f64, p_good_to_bad: f64, p_bad_to_good: f64, loss_good: f64, loss_bad: f64,
                initially_bad: bool, refill: Py<PyAny>) -> PyResult<usize> {
        let link = make_link(name, range_m, blackouts, latency_ns, period_ns, loss_model, p, p_good_to_bad, p_bad_to_good,
                             loss_good, loss_bad, initially_bad)?;
        self.refills.push(refill);
        Ok(self.core.gateway.add_link(link))
    }

    /// Forward `src_id` heard on `src_bus` to `dst_bus` as `dst_id` over `link` (`reverse`: the other direction).
    fn add_route(&mut self, src_bus: usize, src_id: u32, dst_bus: usize, dst_id: u32, link: usize, reverse: Option<usize>) -> PyResult<()> {
        self.core.gateway.add_checked_route(src_bus, src_id, Hop { dst_bus, dst_id, link, reverse }).map_err(gateway_err)
    }

    /// Frames of this message carry their sender's position in their first signal (radio range, tunnels).
    fn set_position_codec(&mut self, codec: &MessageCodec) {
        self.core.set_position_layout(codec.layout.clone());
    }

    /// A periodic task from `first_ns` every `period_ns` (0: once); `advance` returns its token when it is due.
    fn every(&mut self, first_ns: u64, period_ns: u64) -> PyResult<u64> {
        if first_ns < self.core.queue.now {
            return Err(PyValueError::new_err(format!("event scheduled in the past: {first_ns} ns < now {} ns", self.core.queue.now)));
        }
        Ok(self.core.every(first_ns, period_ns))
    }

    /// Run every frame event before `until_ns`; the token of a task that is due (the clock at its time), or None.
    fn advance(&mut self, py: Python<'_>, until_ns: u64) -> PyResult<Option<u64>> {
        let started = std::time::Instant::now();
        let (refills, fault_refill) = (&self.refills, &self.fault_refill);
        let mut refill = |link: usize| -> Result<Draws, EngineError> {
            if link == FAULT_DRAWS {
                let refill = fault_refill.as_ref()
                    .ok_or_else(|| EngineError(PyValueError::new_err("a radio link is impaired but no fault refill is set")))?;
                let u_loss: Vec<f64> = refill.call0(py).and_then(|b| b.extract(py)).map_err(EngineError)?;
                if u_loss.is_empty() {
                    return Err(EngineError(PyValueError::new_err("the fault refill must return a non-empty list")));
                }
                return Ok(Draws { u_loss, ..Draws::default() });
            }
            let block = refills[link].call0(py).map_err(EngineError)?;
            draws_from(py, block).map_err(EngineError)
        };
        let out = self.core.advance(until_ns, &mut refill).map_err(|e| e.0);
        self.busy += started.elapsed();
        out
    }

    /// Seconds of wall time spent inside `advance`, `send` and `send_frames` so far (radio refills included).
    #[getter]
    fn busy_s(&self) -> f64 {
        self.busy.as_secs_f64()
    }

    /// The clock (ns).
    #[getter]
    fn now(&self) -> u64 {
        self.core.queue.now
    }

    /// Queue a frame at the current time; False when the node's TX queue is full (counted).
    fn send(&mut self, bus: usize, node: usize, frame_id: u32, data: PyBackedBytes) -> PyResult<bool> {
        self.check_node(bus, node)?;
        let started = std::time::Instant::now();
        let out = self.core.send(bus, node, frame_id, &data).map_err(frame_err);
        self.busy += started.elapsed();
        out
    }

    /// Queue several (frame_id, data) frames from one node at once (packed into containers on a bus with packing).
    fn send_frames(&mut self, bus: usize, node: usize, frames: Vec<(u32, PyBackedBytes)>) -> PyResult<()> {
        self.check_node(bus, node)?;
        let started = std::time::Instant::now();
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_ref())).collect();
        self.core.send_batch(bus, node, &batch).map_err(frame_err)?;
        self.busy += started.elapsed();
        Ok(())
    }

    /// Encode one ECU cycle's outputs [(codec, values, counter)] and queue them as `send_frames` does: one call
    /// per cycle instead of one per frame and one to send.
    fn send_encoded(&mut self, bus: usize, node: usize, outputs: Vec<Output<'_>>) -> PyResult<()> {
        self.check_node(bus, node)?;
        let started = std::time::Instant::now();
        let frames = encode_outputs(&outputs)?;
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_slice())).collect();
        self.core.send_batch(bus, node, &batch).map_err(frame_err)?;
        self.busy += started.elapsed();
        Ok(())
    }

    /// Pack the batches sent on a CAN FD bus into `packing`'s containers, and unpack them at its receivers.
    fn set_packing(&mut self, bus: usize, packing: &Packing) -> PyResult<()> {
        let b = self.bus_mut(bus)?;
        if !b.format.is_fd() {
            return Err(PyValueError::new_err(format!("{}: frame packing needs a CAN FD bus (fd=True)", b.name)));
        }
        b.set_packing(Some(packing.inner.clone()));
        Ok(())
    }

    /// Take the frames delivered into every inbox since the last call, in arrival order:
    /// [(inbox, frame_id, data, t_end_ns)] (an empty list costs next to nothing).
    fn drain_inboxes<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let frames = std::mem::take(&mut self.core.inbox);
        let items: Vec<Bound<'py, PyTuple>> = frames.iter()
            .map(|(inbox, id, data, t)| (inbox, id, PyBytes::new(py, data.as_slice()), t).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        PyList::new(py, items)
    }

    /// Take a bus's statistics gathered since the last call: (frames rows, load rows) as bytes of float64
    /// ((t_end, id, latency, queueing) and (window end, load)), and the totals (sent, dropped).
    fn take_stats<'py>(&mut self, py: Python<'py>, bus: usize) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>, u64, u64)> {
        let b = self.bus_mut(bus)?;
        let frames = std::mem::take(&mut b.stats.frames);
        let load = std::mem::take(&mut b.stats.load);
        let as_bytes = |v: &[f64]| -> Vec<u8> { v.iter().flat_map(|x| x.to_ne_bytes()).collect() };
        Ok((PyBytes::new(py, &as_bytes(&frames)), PyBytes::new(py, &as_bytes(&load)), b.stats.frames_sent, b.frames_dropped()))
    }

    /// Keep every completed transmission of a bus for `take_trace` (CAN logs, frame rows).
    fn set_trace(&mut self, bus: usize, on: bool) -> PyResult<()> {
        let b = self.bus_mut(bus)?;
        b.trace = if on { Some(b.trace.take().unwrap_or_default()) } else { None };
        Ok(())
    }

    /// Take the kept transmissions: [(frame_id, data, extended, t_enqueue, t_start, t_end, sender node, fd, brs)].
    fn take_trace<'py>(&mut self, py: Python<'py>, bus: usize) -> PyResult<Bound<'py, PyList>> {
        let b = self.bus_mut(bus)?;
        let trace = b.trace.as_mut().map(std::mem::take).unwrap_or_default();
        let items: Vec<Bound<'py, PyTuple>> = trace.iter()
            .map(|tx| (tx.frame_id, PyBytes::new(py, tx.data.as_slice()), tx.extended, tx.t_enqueue, tx.t_start, tx.t_end, tx.node,
                       tx.format.is_fd(), tx.format.brs()).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        PyList::new(py, items)
    }

    /// Close the load windows (and the error models) of every bus up to `t_ns` (the end of a run).
    fn finish(&mut self, t_ns: u64) {
        self.core.finish(t_ns);
    }

    /// Model CAN errors and fault confinement on a bus; `rng_state`: (state, inc) of a numpy PCG64 stream, which
    /// the error model continues (error flag and corruption positions).
    fn enable_bus_errors(&mut self, bus: usize, rng_state: (u128, u128)) -> PyResult<()> {
        self.bus_mut(bus)?.enable_errors(Pcg64::from_state(rng_state.0, rng_state.1));
        Ok(())
    }

    /// Watch a bus for a babbling idiot: `allowances` frames per window by ID (others: 2), flagged above them
    /// when they also hold more than `share_ns` of a `window_ns` window.
    fn set_guardian(&mut self, bus: usize, allowances: std::collections::HashMap<u32, u32>, window_ns: u64, share_ns: f64) -> PyResult<()> {
        check_window(window_ns)?;
        self.bus_mut(bus)?.guardian = Some(Guardian::new(allowances, window_ns, share_ns));
        Ok(())
    }

    /// Start fault `fault`'s effect on a bus: `kind` "corruption", "error_flags" or "drops" of the frames it
    /// selects (`probability` each, only `frame_ids` if given, at most `count`), drawing from its own stream.
    #[pyo3(signature = (bus, fault, kind, rng_state, probability, frame_ids, count, bits = 1))]
    #[allow(clippy::too_many_arguments)]
    fn add_bus_fault(&mut self, bus: usize, fault: u64, kind: &str, rng_state: (u128, u128), probability: f64,
                     frame_ids: Option<Vec<u32>>, count: Option<u64>, bits: u32) -> PyResult<()> {
        add_bus_fault(self.bus_mut(bus)?, fault, kind, rng_state, probability, frame_ids, count, bits)
    }

    /// A babbling node for fault `fault` joins a bus and queues its first frame now; returns its node.
    fn start_babbler(&mut self, bus: usize, fault: u64, name: &str, frame_id: u32, data: PyBackedBytes, extended: bool) -> PyResult<usize> {
        let b = self.bus_mut(bus)?;
        frame::validate_as(frame_id, data.len(), extended, b.format.is_fd()).map_err(frame_err)?;
        let node = b.start_babbler(fault, name, frame_id, &data, extended)
            .ok_or_else(|| PyValueError::new_err("a babbling node needs the bus's error model (enable_bus_errors)"))?;
        self.core.send(bus, node, frame_id, &data).map_err(frame_err)?;
        Ok(node)
    }

    /// End fault `fault`'s effect on a bus (a babbler leaves it).
    fn end_bus_fault(&mut self, bus: usize, fault: u64) -> PyResult<()> {
        self.bus_mut(bus)?.end_fault(fault);
        Ok(())
    }

    /// Whether error or guardian events wait for `take_bus_events`.
    #[getter]
    fn has_bus_events(&self) -> bool {
        !self.core.events.is_empty()
    }

    /// Take the buses' error-model and guardian events since the last call, in the order they happened:
    /// [(bus, t_ns, kind, fields)] (see `trainhil_engine._native.pyi` for the kinds and their fields).
    fn take_bus_events<'py>(&mut self, py: Python<'py>) -> PyResult<Vec<(usize, i64, &'static str, Bound<'py, PyDict>)>> {
        let events = std::mem::take(&mut self.core.events);
        events.iter().map(|(bus, e)| {
            let (kind, fields) = event_fields(py, &self.core.buses[*bus], e)?;
            Ok((*bus, e.t_ns, kind, fields))
        }).collect()
    }

    /// A bus's error model summary (None without one): counts, error frames by kind, nodes whose counters moved,
    /// the corruptions CAN did not detect, and the guardian's detections.
    fn bus_errors<'py>(&self, py: Python<'py>, bus: usize) -> PyResult<Option<Bound<'py, PyDict>>> {
        let b = self.core.buses.get(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))?;
        errors_summary(py, b)
    }

    /// Counters of a radio link: offered, delivered, out_of_range, blackout, lost, rate_capped.
    fn link_stats<'py>(&self, py: Python<'py>, link: usize) -> PyResult<Bound<'py, PyDict>> {
        let l = self.core.gateway.links.get(link).ok_or_else(|| PyIndexError::new_err(format!("no radio link {link}")))?;
        link_stats_dict(py, &l.stats)
    }

    /// Injected faults on radio link `link`: a blackout, burst losses (probabilities, one draw each in order), an
    /// extra latency; all off: no impairment. `refill()` returns a block of uniform draws (the faults' one stream).
    fn set_impairment(&mut self, link: usize, blackout: bool, losses: Vec<f64>, extra_ns: i64, refill: Py<PyAny>) -> PyResult<()> {
        self.core.gateway.set_impairment(link, blackout, losses, extra_ns).map_err(gateway_err)?;
        self.fault_refill = Some(refill);
        Ok(())
    }

    /// The frames each node of a bus dropped, by node name (`Bus::dropped_by_node`): nodes that dropped none left out.
    fn dropped_by_node(&self, bus: usize) -> PyResult<std::collections::BTreeMap<String, u64>> {
        let b = self.core.buses.get(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))?;
        Ok(b.dropped_by_node().into_iter().collect())
    }

    /// Each node's first frame refused on a bus (a full TX queue, bus-off) since the last call, as (t_ns, what
    /// happened): where and when a loss began; its later drops are counted only.
    fn take_refusals(&mut self, bus: usize) -> PyResult<Vec<(u64, String)>> {
        let b = self.core.buses.get_mut(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))?;
        Ok(b.take_refusals())
    }

    /// (name, sent, dropped, queued) of every node of a bus, in attach order.
    fn nodes(&self, bus: usize) -> PyResult<Vec<(String, u64, u64, usize)>> {
        let b = self.core.buses.get(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))?;
        Ok(b.nodes.iter().map(|n| (n.name.clone(), n.sent, n.dropped, n.queued)).collect())
    }

    /// Take a node off its bus (a crashed ECU): its queued frames are dropped and counted, how many is returned; a
    /// frame of it already on the wire completes. Its index stays taken.
    fn detach(&mut self, bus: usize, node: usize) -> PyResult<usize> {
        self.check_node(bus, node)?;
        let b = self.bus_mut(bus)?;
        if !b.nodes[node].attached {
            return Err(PyValueError::new_err(format!("bus {}: node {node} ({}) is not attached", b.name, b.nodes[node].name)));
        }
        Ok(b.detach(node))
    }

    /// Whether a node is on its bus (not detached).
    fn attached(&self, bus: usize, node: usize) -> PyResult<bool> {
        self.check_node(bus, node)?;
        Ok(self.core.buses[bus].nodes[node].attached)
    }

    /// The gateway's IDs on a bus.
    fn gateway_ids(&self, bus: usize) -> Vec<u32> {
        self.core.gateway.ids_for_bus(bus)
    }
}

pub(super) fn check_window(window_ns: u64) -> PyResult<()> {
    if window_ns == 0 {
        return Err(PyValueError::new_err("the guardian's window_ns must be positive"));
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
pub(super) fn add_bus_fault(bus: &mut Bus, fault: u64, kind: &str, rng_state: (u128, u128), probability: f64, frame_ids: Option<Vec<u32>>,
                 count: Option<u64>, bits: u32) -> PyResult<()> {
    let effect = match kind {
        "corruption" => Effect::Corruption,
        "error_flags" => Effect::ErrorFlags,
        "drops" => Effect::Drops,
        _ => return Err(PyValueError::new_err(format!("bus fault kind must be corruption, error_flags or drops, got '{kind}'"))),
    };
    if bits == 0 {
        return Err(PyValueError::new_err(format!("bus fault {fault}: a corruption flips at least 1 bit")));
    }
    if !(0.0..=1.0).contains(&probability) {
        return Err(PyValueError::new_err(format!("bus fault {fault}: probability {probability} is not in [0, 1]")));
    }
    if bus.errors.is_none() {
        return Err(PyValueError::new_err(format!("{}: bus faults need the bus's error model (enable_bus_errors)", bus.name)));
    }
    let rng = Pcg64::from_state(rng_state.0, rng_state.1);
    bus.add_effect(effect, Selection { fault, rng, probability, frame_ids, count, hits: 0, bits });
    Ok(())
}

impl Network {
    fn bus_mut(&mut self, bus: usize) -> PyResult<&mut Bus> {
        self.core.buses.get_mut(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))
    }

    fn check_node(&self, bus: usize, node: usize) -> PyResult<()> {
        let b = self.core.buses.get(bus).ok_or_else(|| PyIndexError::new_err(format!("no bus {bus}")))?;
        if node >= b.nodes.len() {
            return Err(PyIndexError::new_err(format!("bus {}: no node {node}", b.name)));
        }
        Ok(())
    }
}

/// One direction of a radio link from `add_link`'s arguments (the loss model by name).
#[allow(clippy::too_many_arguments)]
pub(super) fn make_link(name: &str, range_m: f64, blackouts: Vec<(f64, f64)>, latency_ns: i64, period_ns: Option<i64>,
                        loss_model: &str, p: f64, p_good_to_bad: f64, p_bad_to_good: f64, loss_good: f64, loss_bad: f64,
                        initially_bad: bool) -> PyResult<Link> {
    let loss = match loss_model {
        "none" => Loss::None,
        "bernoulli" => Loss::Bernoulli { p },
        "gilbert_elliott" => Loss::GilbertElliott { p_gb: p_good_to_bad, p_bg: p_bad_to_good, loss_good, loss_bad },
        other => return Err(PyValueError::new_err(format!("radio link {name}: unknown loss model '{other}'"))),
    };
    Ok(Link::new(name, range_m, blackouts, latency_ns, period_ns, loss, initially_bad))
}

/// A gateway's refusal as a Python error: an unknown link an IndexError, a bad value a ValueError.
pub(super) fn gateway_err(e: GatewayError) -> PyErr {
    match e {
        GatewayError::NoLink(why) => PyIndexError::new_err(why),
        GatewayError::Invalid(why) => PyValueError::new_err(why),
    }
}

/// A link's counters as the Python links keep them (`fault` only once a fault dropped a frame).
pub(super) fn link_stats_dict<'py>(py: Python<'py>, s: &crate::radio::LinkStats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (k, v) in [("offered", s.offered), ("delivered", s.delivered), ("out_of_range", s.out_of_range),
                   ("blackout", s.blackout), ("lost", s.lost), ("rate_capped", s.rate_capped)] {
        d.set_item(k, v)?;
    }
    if s.fault > 0 {
        d.set_item("fault", s.fault)?;
    }
    Ok(d)
}

/// A block (u_step, u_loss, jitter_ns) from a link's `refill()`, checked.
pub(super) fn draws_from(py: Python<'_>, block: Py<PyAny>) -> PyResult<Draws> {
    let (u_step, u_loss, jitter_ns): (Vec<f64>, Vec<f64>, Vec<i64>) = block.extract(py)?;
    if u_step.is_empty() || u_loss.len() != u_step.len() || jitter_ns.len() != u_step.len() {
        return Err(PyValueError::new_err("radio refill must return three equal, non-empty lists"));
    }
    Ok(Draws { u_step, u_loss, jitter_ns, next: 0 })
}
