//! The Python surface of the engine (`trainhil_engine._native`); its typed stub is `trainhil_engine/_native.pyi`.

use std::sync::{Arc, Mutex};

use pyo3::exceptions::{PyIndexError, PyKeyError, PyValueError};
use pyo3::prelude::*;
use pyo3::pybacked::PyBackedBytes;
use pyo3::types::{PyBytes, PyDict, PyList, PyTuple};

use crate::bus::{Bus, Format, Policy, Sink};
use crate::codec::{CodecError, MessageLayout, SignalSpec};
use crate::e2e::{self, STATUS_NAMES};
use crate::errors::{BusEvent, Effect, EventKind, Selection};
use crate::guardian::Guardian;
use crate::rng::Pcg64;
use crate::frame::{self, BitTiming, FrameError, MAX_DATA};
use crate::mailbox;
use crate::network::{Network as CoreNetwork, FAULT_DRAWS};
use crate::packing::{Container, Packing as CorePacking, Part};
use crate::radio::{Draws, Hop, Impairment, Link, Loss};

fn frame_err(e: FrameError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn codec_err(e: CodecError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Wrapper so the network's error type can carry a Python exception raised by a radio refill.
struct EngineError(PyErr);

impl From<FrameError> for EngineError {
    fn from(e: FrameError) -> Self {
        EngineError(frame_err(e))
    }
}

// ------------------------------------------------------------------------------------------------ functions

/// Exact bits on the wire of a classical data frame, SOF through the 3-bit intermission.
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false))]
fn frame_bits(can_id: i64, data: PyBackedBytes, extended: bool) -> PyResult<u32> {
    let id = u32::try_from(can_id).map_err(|_| PyValueError::new_err(format!("can_id={can_id:#x} must be a non-negative identifier")))?;
    frame::frame_bits(id, &data, extended).map_err(frame_err)
}

/// Duration in ns of a data frame at a nominal (arbitration) and a data bit rate; a CAN FD frame (`fd`) runs its
/// data phase at the data rate when `brs` (bit rate switch) is set.
#[pyfunction]
#[pyo3(signature = (can_id, data, nominal_bitrate, data_bitrate = None, extended = false, fd = false, brs = true))]
fn frame_duration_ns(can_id: u32, data: PyBackedBytes, nominal_bitrate: u64, data_bitrate: Option<u64>, extended: bool,
                     fd: bool, brs: bool) -> PyResult<u64> {
    let timing = timing(nominal_bitrate, data_bitrate.unwrap_or(nominal_bitrate))?;
    timing.frame_ns(can_id, &data, extended, fd, brs).map_err(frame_err)
}

/// Exact bits of a CAN FD data frame, SOF through the intermission: (at the nominal rate, at the data rate).
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false, brs = true, esi = false))]
fn fd_frame_bits(can_id: i64, data: PyBackedBytes, extended: bool, brs: bool, esi: bool) -> PyResult<(u32, u32)> {
    let id = u32::try_from(can_id).map_err(|_| PyValueError::new_err(format!("can_id={can_id:#x} must be a non-negative identifier")))?;
    let b = frame::fd_frame_bits(id, &data, extended, brs, esi).map_err(frame_err)?;
    Ok((b.nominal, b.data))
}

/// CRC-8 SAE J1850 over [data_id] + payload[1:].
#[pyfunction]
fn e2e_crc(data_id: u8, payload: PyBackedBytes) -> u8 {
    e2e::e2e_crc(data_id, &payload)
}

/// A classical data frame on the wire, SOF through EOF, as the error model sees it (0 = dominant).
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false))]
fn wire_bits(can_id: u32, data: PyBackedBytes, extended: bool) -> PyResult<Vec<u8>> {
    frame::validate(can_id, data.len(), extended).map_err(frame_err)?;
    Ok(crate::errors::wire_bits(can_id, &data, extended))
}

/// What CAN receivers make of `wire` (bits, e.g. `wire_bits` with some flipped): (error or None, the bit it was
/// found at, and for an accepted frame its ID, extended flag and data).
#[pyfunction]
fn receive_wire<'py>(py: Python<'py>, wire: Vec<u8>) -> PyResult<(Option<&'static str>, u32, u32, bool, Bound<'py, PyBytes>)> {
    if wire.iter().any(|&b| b > 1) {
        return Err(PyValueError::new_err("wire bits must be 0 or 1"));
    }
    let r = crate::errors::receive(&wire);
    Ok((r.error.map(|e| e.name()), r.at, r.can_id, r.extended, PyBytes::new(py, &r.data)))
}

fn timing(nominal: u64, data: u64) -> PyResult<BitTiming> {
    BitTiming::new(nominal, data).ok_or_else(|| {
        PyValueError::new_err(format!("bitrate {nominal} (data {data}) bit/s has no whole-nanosecond bit time"))
    })
}

// ------------------------------------------------------------------------------------------------ codec

/// One DBC message compiled for the hot path: physical values <-> frame bytes with the E2E header.
#[pyclass(module = "trainhil_engine._native", frozen)]
pub struct MessageCodec {
    layout: Arc<MessageLayout>,
    saturations: std::sync::Mutex<Vec<u64>>,
    #[pyo3(get)]
    name: String,
    #[pyo3(get)]
    frame_id: u32,
    #[pyo3(get)]
    dlc: usize,
    #[pyo3(get)]
    data_id: u8,
    #[pyo3(get)]
    cycle_time_s: f64,
    #[pyo3(get)]
    signals: Py<PyTuple>,
    #[pyo3(get)]
    units: Py<PyTuple>,
    #[pyo3(get)]
    limits: Py<PyTuple>,
}

type SpecTuple = (String, u32, u32, bool, f64, f64, i64, i64);

#[pymethods]
impl MessageCodec {
    /// `specs`: (name, start bit, length, signed, scale, offset, raw_min, raw_max) per payload signal, Intel order.
    #[new]
    #[pyo3(signature = (name, frame_id, dlc, cycle_time_s, data_id, specs, units))]
    fn new(py: Python<'_>, name: String, frame_id: u32, dlc: usize, cycle_time_s: f64, data_id: u8, specs: Vec<SpecTuple>,
           units: Vec<String>) -> PyResult<Self> {
        if !(e2e::HEADER_BYTES..=MAX_DATA).contains(&dlc) {
            return Err(PyValueError::new_err(format!("{name}: DLC {dlc} must be in {}..{MAX_DATA}", e2e::HEADER_BYTES)));
        }
        let mut signals = Vec::new();
        for (sname, start, length, signed, scale, offset, raw_min, raw_max) in specs {
            if length == 0 || length > 63 || start + length > 8 * dlc as u32 {
                return Err(PyValueError::new_err(format!("{name}.{sname}: bits {start}..{} do not fit {dlc} bytes", start + length)));
            }
            signals.push(SignalSpec { name: sname, start, length, signed, scale, offset, raw_min, raw_max });
        }
        let names = PyTuple::new(py, signals.iter().map(|s| s.name.clone()))?.unbind();
        let limits = PyTuple::new(py, signals.iter().map(|s| (s.raw_min as f64 * s.scale + s.offset, s.raw_max as f64 * s.scale + s.offset)))?.unbind();
        let n = signals.len();
        Ok(MessageCodec {
            layout: Arc::new(MessageLayout { name: name.clone(), frame_id, dlc, data_id, signals }),
            saturations: std::sync::Mutex::new(vec![0; n]),
            name, frame_id, dlc, data_id, cycle_time_s, signals: names, units: PyTuple::new(py, units)?.unbind(),
            limits,
        })
    }

    fn __repr__(&self) -> String {
        let sig: Vec<String> = self.layout.signals.iter().map(|s| format!("'{}'", s.name)).collect();
        format!("MessageCodec({}, id=0x{:03X}, dlc={}, signals=({}{}))", self.name, self.frame_id, self.dlc, sig.join(", "),
                if sig.len() == 1 { "," } else { "" })
    }

    /// Physical values (in `signals` order) -> frame bytes with alive counter and E2E CRC; out-of-range values
    /// saturate and are counted, NaN raises ValueError naming the signal.
    fn encode<'py>(&self, py: Python<'py>, values: Vec<f64>, counter: i64) -> PyResult<Bound<'py, PyBytes>> {
        let mut out = [0u8; MAX_DATA];
        let mut sat = self.saturations.lock().unwrap();
        let n = self.layout.encode(&values, counter, &mut sat, &mut out).map_err(codec_err)?;
        Ok(PyBytes::new(py, &out[..n]))
    }

    /// Frame bytes -> physical values in `signals` order (E2E header not checked here).
    fn decode<'py>(&self, py: Python<'py>, data: PyBackedBytes) -> PyResult<Bound<'py, PyTuple>> {
        let mut v = Vec::with_capacity(self.layout.signals.len());
        self.layout.decode_into(&data, &mut v).map_err(codec_err)?;
        PyTuple::new(py, v)
    }

    /// Alive counter carried in the frame.
    fn counter_of(&self, data: PyBackedBytes) -> PyResult<u8> {
        self.check_length(&data)?;
        Ok(data[1] & 0xF)
    }

    /// Whether the frame's CRC byte matches this message's data ID and payload.
    fn crc_ok(&self, data: PyBackedBytes) -> PyResult<bool> {
        self.check_length(&data)?;
        Ok(e2e::crc_ok(self.data_id, &data))
    }

    /// Position of a payload signal in `signals`.
    fn index(&self, signal: &str) -> PyResult<usize> {
        self.layout.signals.iter().position(|s| s.name == signal).ok_or_else(|| {
            let names: Vec<&str> = self.layout.signals.iter().map(|s| s.name.as_str()).collect();
            PyKeyError::new_err(format!("message {} has no payload signal '{signal}' (has {names:?})", self.name))
        })
    }

    /// The compiled layout: (name, start bit, length, signed, scale, offset, raw_min, raw_max) per signal.
    #[getter]
    fn specs(&self) -> Vec<SpecTuple> {
        self.layout.signals.iter()
            .map(|s| (s.name.clone(), s.start, s.length, s.signed, s.scale, s.offset, s.raw_min, s.raw_max))
            .collect()
    }

    /// The LSB (DBC scale) of each payload signal, in `signals` order.
    #[getter]
    fn scales(&self) -> Vec<f64> {
        self.layout.signals.iter().map(|s| s.scale).collect()
    }

    /// Saturated encodes per signal name.
    #[getter]
    fn saturations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let sat = self.saturations.lock().unwrap();
        for (s, n) in self.layout.signals.iter().zip(sat.iter()) {
            d.set_item(&s.name, *n)?;
        }
        Ok(d)
    }

    /// Zero the saturation counts.
    fn reset_saturations(&self) {
        self.saturations.lock().unwrap().fill(0);
    }
}

impl MessageCodec {
    fn check_length(&self, data: &[u8]) -> PyResult<()> {
        if data.len() != self.dlc {
            return Err(PyValueError::new_err(format!("{}: frame has {} bytes, DLC is {}", self.name, data.len(), self.dlc)));
        }
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------------ mailbox

/// An ECU's input mailboxes, one per stream; delivery stores the latest frame, `refresh` checks and decodes
/// what arrived since the last cycle.
#[pyclass(module = "trainhil_engine._native")]
pub struct Mailbox {
    inner: Arc<Mutex<mailbox::Mailbox>>,
}

#[pymethods]
impl Mailbox {
    #[new]
    fn new() -> Self {
        Mailbox { inner: Arc::new(Mutex::new(mailbox::Mailbox::default())) }
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
            mailbox::Delivery::Stored => 0,
            mailbox::Delivery::UnknownId => 1,
            mailbox::Delivery::WrongLength(..) => 2,
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

// ------------------------------------------------------------------------------------------------ network

/// Every train bus, the radio gateway, the mailboxes and inboxes, on one virtual-time event queue.
/// CAN FD frame packing: container frames and the messages they carry (see engine/src/packing.rs).
#[pyclass(module = "trainhil_engine._native", frozen)]
pub struct Packing {
    inner: Arc<CorePacking>,
}

#[pymethods]
impl Packing {
    /// `containers`: [(container_id, data_length, [(part_id, byte_offset, byte_length)])], checked.
    #[new]
    fn new(containers: Vec<(u32, usize, Vec<(u32, usize, usize)>)>) -> PyResult<Self> {
        let containers = containers.into_iter()
            .map(|(id, len, parts)| Container { id, len, parts: parts.into_iter().map(|(id, offset, len)| Part { id, offset, len }).collect() })
            .collect();
        Ok(Packing { inner: Arc::new(CorePacking::new(containers).map_err(PyValueError::new_err)?) })
    }

    /// A sender's batch [(frame_id, data)] as it goes on the bus: complete containers replace their parts.
    fn pack<'py>(&self, py: Python<'py>, frames: Vec<(u32, PyBackedBytes)>) -> PyResult<Vec<(u32, Bound<'py, PyBytes>)>> {
        if let Some((id, data)) = frames.iter().find(|(_, d)| d.len() > MAX_DATA) {
            return Err(PyValueError::new_err(format!("frame {id:#x}: {} data bytes > {MAX_DATA}", data.len())));
        }
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_ref())).collect();
        Ok(self.inner.pack(&batch).into_iter().map(|(id, data)| (id, PyBytes::new(py, data.as_slice()))).collect())
    }

    /// The parts [(frame_id, data)] a container frame carries; None when `frame_id` is not a container.
    fn unpack<'py>(&self, py: Python<'py>, frame_id: u32, data: PyBackedBytes) -> Option<Vec<(u32, Bound<'py, PyBytes>)>> {
        let parts = self.inner.unpack(frame_id, &data)?;
        Some(parts.map(|(id, d)| (id, PyBytes::new(py, d))).collect())
    }

    /// The containers that carry any of `ids` (what a receiver of `ids` must also accept), sorted.
    fn containers_of(&self, ids: Vec<u32>) -> Vec<u32> {
        self.inner.containers_of(&ids)
    }

    /// The parts [(part_id, byte_offset, byte_length)] of container `frame_id`; None when it is not a container.
    fn parts(&self, frame_id: u32) -> Option<Vec<(u32, usize, usize)>> {
        self.inner.parts(frame_id).map(|parts| parts.iter().map(|p| (p.id, p.offset, p.len)).collect())
    }
}

#[pyclass(module = "trainhil_engine._native")]
pub struct Network {
    core: CoreNetwork,
    refills: Vec<Py<PyAny>>,
    /// Blocks of the injected radio faults' draws (`set_impairment`).
    fault_refill: Option<Py<PyAny>>,
    /// Wall time spent inside `advance` and `send` (the engine's own cost, for the benchmarks).
    busy: std::time::Duration,
}

fn policy(name: &str) -> PyResult<Policy> {
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
        let mut table = crate::network::CommandTable { valid_modes, ..Default::default() };
        for (frame_id, codec, unit) in commands {
            if codec.layout.signals.len() != 2 {
                return Err(PyValueError::new_err(format!("{}: a command needs the signals (Mode, Force)", codec.name)));
            }
            table.by_id.insert(frame_id, (unit, codec.layout.clone()));
        }
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
        let loss = match loss_model {
            "none" => Loss::None,
            "bernoulli" => Loss::Bernoulli { p },
            "gilbert_elliott" => Loss::GilbertElliott { p_gb: p_good_to_bad, p_bg: p_bad_to_good, loss_good, loss_bad },
            other => return Err(PyValueError::new_err(format!("radio link {name}: unknown loss model '{other}'"))),
        };
        self.refills.push(refill);
        Ok(self.core.gateway.add_link(Link::new(name, range_m, blackouts, latency_ns, period_ns, loss, initially_bad)))
    }

    /// Forward `src_id` heard on `src_bus` to `dst_bus` as `dst_id` over `link` (`reverse`: the other direction).
    fn add_route(&mut self, src_bus: usize, src_id: u32, dst_bus: usize, dst_id: u32, link: usize, reverse: Option<usize>) -> PyResult<()> {
        if link >= self.core.gateway.links.len() || reverse.is_some_and(|r| r >= self.core.gateway.links.len()) {
            return Err(PyIndexError::new_err(format!("route {src_bus}:{src_id:#x}: no radio link {link}")));
        }
        self.core.gateway.add_route(src_bus, src_id, Hop { dst_bus, dst_id, link, reverse });
        Ok(())
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
            let (u_step, u_loss, jitter_ns): (Vec<f64>, Vec<f64>, Vec<i64>) = block.extract(py).map_err(EngineError)?;
            if u_step.is_empty() || u_loss.len() != u_step.len() || jitter_ns.len() != u_step.len() {
                return Err(EngineError(PyValueError::new_err("radio refill must return three equal, non-empty lists")));
            }
            Ok(Draws { u_step, u_loss, jitter_ns, next: 0 })
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
        let s = l.stats;
        let d = PyDict::new(py);
        for (k, v) in [("offered", s.offered), ("delivered", s.delivered), ("out_of_range", s.out_of_range),
                       ("blackout", s.blackout), ("lost", s.lost), ("rate_capped", s.rate_capped)] {
            d.set_item(k, v)?;
        }
        if s.fault > 0 {
            d.set_item("fault", s.fault)?; // as the Python links count it: only once a fault dropped a frame
        }
        Ok(d)
    }

    /// Injected faults on radio link `link`: a blackout, burst losses (probabilities, one draw each in order), an
    /// extra latency; all off: no impairment. `refill()` returns a block of uniform draws (the faults' one stream).
    fn set_impairment(&mut self, link: usize, blackout: bool, losses: Vec<f64>, extra_ns: i64, refill: Py<PyAny>) -> PyResult<()> {
        let l = self.core.gateway.links.get_mut(link).ok_or_else(|| PyIndexError::new_err(format!("no radio link {link}")))?;
        if let Some(p) = losses.iter().find(|p| !(0.0..=1.0).contains(*p)) {
            return Err(PyValueError::new_err(format!("radio link {}: loss probability {p} is not in [0, 1]", l.name)));
        }
        let on = blackout || !losses.is_empty() || extra_ns != 0;
        l.impairment = on.then_some(Impairment { blackout, losses, extra_ns });
        self.fault_refill = Some(refill);
        Ok(())
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

fn check_window(window_ns: u64) -> PyResult<()> {
    if window_ns == 0 {
        return Err(PyValueError::new_err("the guardian's window_ns must be positive"));
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn add_bus_fault(bus: &mut Bus, fault: u64, kind: &str, rng_state: (u128, u128), probability: f64, frame_ids: Option<Vec<u32>>,
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

/// An event as (kind, fields) for Python (`hil.can.error_events.event_text` and the guardian word them).
fn event_fields<'py>(py: Python<'py>, bus: &Bus, e: &BusEvent) -> PyResult<(&'static str, Bound<'py, PyDict>)> {
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
fn errors_summary<'py>(py: Python<'py>, bus: &Bus) -> PyResult<Option<Bound<'py, PyDict>>> {
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

/// Sleep until one of `fds` is readable or `timeout_s` (wall) passed, the GIL released; whether one is.
#[pyfunction]
fn wait_readable(py: Python<'_>, fds: Vec<i32>, timeout_s: f64) -> bool {
    let timeout = timeout_s.max(0.0);
    py.allow_threads(move || {
        let mut pfds: Vec<libc::pollfd> = fds.iter().map(|&fd| libc::pollfd { fd, events: libc::POLLIN, revents: 0 }).collect();
        let ts = libc::timespec { tv_sec: timeout as libc::time_t, tv_nsec: (timeout.fract() * 1e9) as libc::c_long };
        // SAFETY: an array of pollfd we own, for the duration of the call.
        unsafe { libc::ppoll(pfds.as_mut_ptr(), pfds.len() as libc::nfds_t, &ts, std::ptr::null()) > 0 }
    })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("VERSION", env!("CARGO_PKG_VERSION"))?;
    m.add("MAX_DATA", MAX_DATA)?;
    let protocol = PyDict::new(m.py());
    for (name, value) in crate::protocol::constants() {
        if name.ends_with("_S") {
            protocol.set_item(name, value)?;  // seconds
        } else {
            protocol.set_item(name, value as i64)?;
        }
    }
    m.add("PROTOCOL", protocol)?;
    m.add_function(wrap_pyfunction!(frame_bits, m)?)?;
    m.add_function(wrap_pyfunction!(frame_duration_ns, m)?)?;
    m.add_function(wrap_pyfunction!(fd_frame_bits, m)?)?;
    m.add_function(wrap_pyfunction!(e2e_crc, m)?)?;
    m.add_function(wrap_pyfunction!(wire_bits, m)?)?;
    m.add_function(wrap_pyfunction!(receive_wire, m)?)?;
    m.add_function(wrap_pyfunction!(wait_readable, m)?)?;
    m.add_class::<MessageCodec>()?;
    m.add_class::<Mailbox>()?;
    m.add_class::<Network>()?;
    m.add_class::<Packing>()?;
    m.add_class::<BusServerCore>()?;
    m.add_class::<FrameLink>()?;
    m.add("__all__", vec!["VERSION", "MAX_DATA", "PROTOCOL", "frame_bits", "frame_duration_ns", "fd_frame_bits", "e2e_crc", "wire_bits", "receive_wire", "MessageCodec", "Mailbox", "Network", "Packing",
                          "BusServerCore", "FrameLink", "wait_readable"])?;
    Ok(())
}

// ------------------------------------------------------------------------------------------------ real time

/// One emulated CAN bus served in wall-clock time by a native thread (see engine/src/server.rs).
#[pyclass(module = "trainhil_engine._native")]
pub struct BusServerCore {
    handle: Option<crate::server::ServerHandle>,
    bitrate: u64,
}

fn stats_dict<'py>(py: Python<'py>, s: &crate::server::Shared, now_ns: u64) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("now_ns", now_ns)?;
    d.set_item("clients", s.clients)?;
    d.set_item("frames", s.frames)?;
    d.set_item("busy_ns", s.busy_ns)?;
    d.set_item("frames_dropped", s.bus.frames_dropped())?;
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
    /// Serve on listening sockets the caller made (their fds are taken over: pass duplicates).
    #[new]
    #[pyo3(signature = (channel, listener_fd, tcp_fd, token, bitrate, policy_name, depth, extended, load_window_ns, pace,
                        spin_ns, max_clients, hello_timeout_s, keep_log, fd = false, data_bitrate = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(channel: String, listener_fd: i32, tcp_fd: Option<i32>, token: Option<Vec<u8>>, bitrate: u64, policy_name: &str,
           depth: usize, extended: bool, load_window_ns: u64, pace: f64, spin_ns: u64, max_clients: usize,
           hello_timeout_s: f64, keep_log: bool, fd: bool, data_bitrate: Option<u64>) -> PyResult<Self> {
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
        let handle = crate::server::start(cfg, listener_fd, tcp_fd)
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

    /// Log lines since the last call: [(level, text)].
    fn take_messages(&self) -> Vec<(String, String)> {
        self.handle.as_ref().map_or_else(Vec::new, |h| std::mem::take(&mut h.shared.lock().unwrap().messages))
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

/// A node's receive path without python-can: frames read from a bus server's socket go straight into ECU
/// mailboxes (stamped in simulated time); the node sends its frames through it too.
#[pyclass(module = "trainhil_engine._native")]
pub struct FrameLink {
    fd: i32,
    t0: f64,
    pace: f64,
    routes: std::collections::HashMap<u32, Vec<Arc<Mutex<mailbox::Mailbox>>>>,
    partial: Vec<u8>,
    received: u64,
    /// Keep the frames that have no route for `take` (a node that handles its frames itself).
    keep: bool,
    kept: Vec<(u32, crate::bus::Payload, f64)>,
    /// Container frames: packed on send, unpacked on receipt.
    packing: Option<Arc<CorePacking>>,
}

impl FrameLink {
    /// Hand the whole frames in `partial` to their mailboxes (or keep them); returns the bytes used. A CAN FD frame
    /// above 8 bytes waits until its FRAME_DATA records are in.
    fn take_records(&mut self) -> usize {
        const RS: usize = crate::protocol::RECORD_SIZE;
        let mut off = 0;
        let mut data = [0u8; crate::frame::MAX_DATA];
        while off + RS <= self.partial.len() {
            let r = &self.partial[off..off + RS];
            if r[0] != 1 {
                off += RS; // FILTERS_ACK and the like: nothing for the mailboxes
                continue;
            }
            let dlc = (r[2] as usize).min(crate::frame::MAX_DATA);
            let extra = crate::server::frame_data_records(dlc);
            if off + (1 + extra) * RS > self.partial.len() {
                break; // the rest of a long frame is still on its way
            }
            let id = u32::from_le_bytes(r[4..8].try_into().unwrap());
            let stamp = f64::from_le_bytes(r[8..16].try_into().unwrap());
            data[..dlc.min(8)].copy_from_slice(&r[16..16 + dlc.min(8)]);
            for k in 0..extra {
                let at = 8 + k * (RS - 1);
                let take = (dlc - at).min(RS - 1);
                let rec = off + (1 + k) * RS;
                data[at..at + take].copy_from_slice(&self.partial[rec + 1..rec + 1 + take]);
            }
            off += (1 + extra) * RS;
            let t = (stamp - self.t0) * self.pace;
            match self.packing.clone().as_deref().and_then(|p| p.unpack(id, &data[..dlc])) {
                Some(parts) => parts.for_each(|(part, bytes)| self.hand_over(part, bytes, t)),
                None => self.hand_over(id, &data[..dlc], t),
            }
        }
        off
    }

    /// One received frame into its mailboxes, else kept (or dropped when nothing takes it).
    fn hand_over(&mut self, id: u32, data: &[u8], t: f64) {
        if let Some(boxes) = self.routes.get(&id) {
            for mb in boxes {
                mb.lock().unwrap().put(id, data, t);
            }
            self.received += 1;
        } else if self.keep {
            self.kept.push((id, crate::bus::Payload::new(data), t));
            self.received += 1;
        }
    }
}

#[pymethods]
impl FrameLink {
    /// `fd`: the connected, handshaken, non-blocking socket of a node (still owned by the caller). A frame's
    /// simulated time is (its epoch stamp - t0) * pace. `keep`: frames without a route are kept for `take`.
    #[new]
    #[pyo3(signature = (fd, t0, pace, keep = false))]
    fn new(fd: i32, t0: f64, pace: f64, keep: bool) -> PyResult<Self> {
        if !(pace.is_finite() && pace > 0.0) {
            return Err(PyValueError::new_err(format!("pace={pace} must be positive")));
        }
        Ok(FrameLink { fd, t0, pace, routes: Default::default(), partial: Vec::new(), received: 0, keep,
                       kept: Vec::new(), packing: None })
    }

    /// Pack each `send` batch into `packing`'s containers, and unpack the containers received.
    fn set_packing(&mut self, packing: &Packing) {
        self.packing = Some(packing.inner.clone());
    }

    /// The socket's file descriptor (for `wait_readable`).
    #[getter]
    fn fd(&self) -> i32 {
        self.fd
    }

    /// The kept frames received since the last call, in arrival order: [(frame_id, data, t_sim)].
    fn take<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        self.pump()?;
        let kept = std::mem::take(&mut self.kept);
        let items: Vec<Bound<'py, PyTuple>> = kept.iter()
            .map(|(id, data, t)| (id, PyBytes::new(py, data.as_slice()), t).into_pyobject(py))
            .collect::<PyResult<_>>()?;
        PyList::new(py, items)
    }

    /// Deliver frames of `frame_id` into `mailbox` (several mailboxes may take one ID).
    fn route(&mut self, frame_id: u32, mailbox: &Mailbox) {
        self.routes.entry(frame_id).or_default().push(mailbox.inner.clone());
    }

    /// Read every record waiting on the socket; returns how many frames went into mailboxes.
    fn pump(&mut self) -> PyResult<u64> {
        let mut buf = [0u8; 64 * crate::protocol::RECORD_SIZE];
        let before = self.received;
        loop {
            // SAFETY: reading into our own buffer from the node's socket.
            let n = unsafe { libc::recv(self.fd, buf.as_mut_ptr() as *mut libc::c_void, buf.len(), libc::MSG_DONTWAIT) };
            if n < 0 {
                let err = std::io::Error::last_os_error();
                if err.kind() == std::io::ErrorKind::WouldBlock || err.kind() == std::io::ErrorKind::Interrupted {
                    return Ok(self.received - before);
                }
                return Err(pyo3::exceptions::PyOSError::new_err(format!("bus link: receive failed: {err}")));
            }
            if n == 0 {
                return Err(pyo3::exceptions::PyConnectionError::new_err("bus link: the bus server closed the connection"));
            }
            self.partial.extend_from_slice(&buf[..n as usize]);
            let consumed = self.take_records();
            self.partial.drain(..consumed);
        }
    }

    /// Send frames [(frame_id, data)] as FRAME records: `extended` for 29-bit IDs, `fd` for CAN FD frames (with
    /// the bit-rate switch unless `brs` is false).
    #[pyo3(signature = (frames, extended = false, fd = false, brs = true))]
    fn send(&self, frames: Vec<(u32, PyBackedBytes)>, extended: bool, fd: bool, brs: bool) -> PyResult<()> {
        let mut out = Vec::with_capacity(frames.len() * crate::protocol::RECORD_SIZE);
        let format = Format::of(fd, brs);
        let flags = if extended { 1 } else { 0 } | crate::server::format_flags(format);
        let limit = if fd { crate::frame::MAX_DATA } else { 8 };
        if let Some((id, data)) = frames.iter().find(|(_, d)| d.len() > limit) {
            return Err(PyValueError::new_err(format!("frame {id:#x}: {} data bytes > {limit}", data.len())));
        }
        let batch: Vec<(u32, &[u8])> = frames.iter().map(|(id, d)| (*id, d.as_ref())).collect();
        let packed = match &self.packing {
            Some(p) => p.pack(&batch),
            None => batch.iter().map(|&(id, d)| (id, crate::bus::Payload::new(d))).collect(),
        };
        for (id, data) in packed.iter().map(|(id, d)| (id, d.as_slice())) {
            let padded = if fd { crate::frame::fd_padded_len(data.len()).unwrap_or(data.len()) } else { data.len() };
            let mut payload = data.to_vec();
            payload.resize(padded, 0);
            crate::server::pack_frame_records(*id, &payload, flags, 0.0, &mut out);
        }
        let mut sent = 0;
        while sent < out.len() {
            // SAFETY: writing our own buffer to the node's socket.
            let n = unsafe { libc::send(self.fd, out[sent..].as_ptr() as *const libc::c_void, out.len() - sent, libc::MSG_NOSIGNAL) };
            if n < 0 {
                let err = std::io::Error::last_os_error();
                if err.kind() == std::io::ErrorKind::WouldBlock || err.kind() == std::io::ErrorKind::Interrupted {
                    let mut pfd = libc::pollfd { fd: self.fd, events: libc::POLLOUT, revents: 0 };
                    // SAFETY: one pollfd we own.
                    unsafe { libc::poll(&mut pfd, 1, 100) };
                    continue;
                }
                return Err(pyo3::exceptions::PyOSError::new_err(format!("bus link: send failed: {err}")));
            }
            sent += n as usize;
        }
        Ok(())
    }
}
