//! `MessageCodec` (one DBC message for the hot path) and `Packing` (CAN FD containers).

use super::*;

/// One DBC message compiled for the hot path: physical values <-> frame bytes with the E2E header.
#[pyclass(module = "trainhil_engine._native", frozen)]
pub struct MessageCodec {
    pub(crate) layout: Arc<MessageLayout>,
    pub(crate) saturations: std::sync::Mutex<Vec<u64>>,
    #[pyo3(get)]
    pub(crate) name: String,
    #[pyo3(get)]
    pub(crate) frame_id: u32,
    #[pyo3(get)]
    pub(crate) dlc: usize,
    #[pyo3(get)]
    pub(crate) data_id: u8,
    #[pyo3(get)]
    pub(crate) cycle_time_s: f64,
    #[pyo3(get)]
    pub(crate) signals: Py<PyTuple>,
    #[pyo3(get)]
    pub(crate) units: Py<PyTuple>,
    #[pyo3(get)]
    pub(crate) limits: Py<PyTuple>,
}

type SpecTuple = (String, u32, u32, bool, f64, f64, i64, i64);

/// One output of an ECU cycle, not yet encoded: (message, physical values, alive counter).
pub(super) type Output<'py> = (PyRef<'py, MessageCodec>, Vec<f64>, i64);

impl MessageCodec {
    /// Physical values -> frame payload (saturations counted, NaN an error naming the signal): `encode`'s work.
    pub(super) fn encode_payload(&self, values: &[f64], counter: i64) -> PyResult<crate::bus::Payload> {
        let mut out = [0u8; MAX_DATA];
        let mut sat = self.saturations.lock().unwrap();
        let n = self.layout.encode(values, counter, &mut sat, &mut out).map_err(codec_err)?;
        Ok(crate::bus::Payload::new(&out[..n]))
    }
}

/// A cycle's outputs encoded: [(frame_id, payload)].
pub(super) fn encode_outputs(outputs: &[Output<'_>]) -> PyResult<Vec<(u32, crate::bus::Payload)>> {
    outputs.iter().map(|(codec, values, counter)| Ok((codec.frame_id, codec.encode_payload(values, *counter)?))).collect()
}

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
        Ok(PyBytes::new(py, self.encode_payload(&values, counter)?.as_slice()))
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


/// CAN FD frame packing: container frames and the messages they carry (see engine/src/packing.rs).
#[pyclass(module = "trainhil_engine._native", frozen)]
pub struct Packing {
    pub(crate) inner: Arc<CorePacking>,
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

/// A command table from (frame_id, codec with signals (Mode, Force), unit index) and the valid modes.
pub(super) fn command_table(commands: Vec<(u32, PyRef<'_, MessageCodec>, usize)>, valid_modes: Vec<i64>) -> PyResult<CommandTable> {
    let mut table = CommandTable { valid_modes, ..Default::default() };
    for (frame_id, codec, unit) in commands {
        if codec.layout.signals.len() != 2 {
            return Err(PyValueError::new_err(format!("{}: a command needs the signals (Mode, Force)", codec.name)));
        }
        table.by_id.insert(frame_id, (unit, codec.layout.clone()));
    }
    Ok(table)
}
