//! Frame arithmetic for Python: exact bits and durations, E2E CRC, the bit-level receiver, the wire protocol's checks.

use super::*;
use crate::protocol;

/// Exact bits on the wire of a classical data frame, SOF through the 3-bit intermission.
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false))]
pub(super) fn frame_bits(can_id: i64, data: PyBackedBytes, extended: bool) -> PyResult<u32> {
    let id = u32::try_from(can_id).map_err(|_| PyValueError::new_err(format!("can_id={can_id:#x} must be a non-negative identifier")))?;
    frame::frame_bits(id, &data, extended).map_err(frame_err)
}

/// Duration in ns of a data frame at a nominal (arbitration) and a data bit rate; a CAN FD frame (`fd`) runs its
/// data phase at the data rate when `brs` (bit rate switch) is set.
#[pyfunction]
#[pyo3(signature = (can_id, data, nominal_bitrate, data_bitrate = None, extended = false, fd = false, brs = true))]
pub(super) fn frame_duration_ns(can_id: u32, data: PyBackedBytes, nominal_bitrate: u64, data_bitrate: Option<u64>, extended: bool,
                     fd: bool, brs: bool) -> PyResult<u64> {
    let timing = timing(nominal_bitrate, data_bitrate.unwrap_or(nominal_bitrate))?;
    timing.frame_ns(can_id, &data, extended, fd, brs).map_err(frame_err)
}

/// Exact bits of a CAN FD data frame, SOF through the intermission: (at the nominal rate, at the data rate).
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false, brs = true, esi = false))]
pub(super) fn fd_frame_bits(can_id: i64, data: PyBackedBytes, extended: bool, brs: bool, esi: bool) -> PyResult<(u32, u32)> {
    let id = u32::try_from(can_id).map_err(|_| PyValueError::new_err(format!("can_id={can_id:#x} must be a non-negative identifier")))?;
    let b = frame::fd_frame_bits(id, &data, extended, brs, esi).map_err(frame_err)?;
    Ok((b.nominal, b.data))
}

/// CRC-8 SAE J1850 over [data_id] + payload[1:].
#[pyfunction]
pub(super) fn e2e_crc(data_id: u8, payload: PyBackedBytes) -> u8 {
    e2e::e2e_crc(data_id, &payload)
}

/// A classical data frame on the wire, SOF through EOF, as the error model sees it (0 = dominant).
#[pyfunction]
#[pyo3(signature = (can_id, data, extended = false))]
pub(super) fn wire_bits(can_id: u32, data: PyBackedBytes, extended: bool) -> PyResult<Vec<u8>> {
    frame::validate(can_id, data.len(), extended).map_err(frame_err)?;
    Ok(crate::wire::wire_bits(can_id, &data, extended))
}

/// What CAN receivers make of `wire` (bits, e.g. `wire_bits` with some flipped): (error or None, the bit it was
/// found at, and for an accepted frame its ID, extended flag and data).
#[pyfunction]
pub(super) fn receive_wire<'py>(py: Python<'py>, wire: Vec<u8>) -> PyResult<(Option<&'static str>, u32, u32, bool, Bound<'py, PyBytes>)> {
    if wire.iter().any(|&b| b > 1) {
        return Err(PyValueError::new_err("wire bits must be 0 or 1"));
    }
    let r = crate::wire::receive(&wire);
    Ok((r.error.map(|e| e.name()), r.at, r.can_id, r.extended, PyBytes::new(py, &r.data)))
}

/// Why a frame from a node cannot go on the emulated bus (None if it can), the bus server's own check
/// (`protocol::frame_error`); a CAN FD bus (`fd_bus`) carries both formats.
#[pyfunction]
#[pyo3(signature = (can_id, dlc, flags, fd_bus = false))]
pub(super) fn frame_error(can_id: i64, dlc: i64, flags: i64, fd_bus: bool) -> Option<String> {
    let Ok(flags) = u8::try_from(flags) else {
        return Some(format!("flags {flags:#04x}: unknown flag bits"));
    };
    let Ok(dlc) = u8::try_from(dlc) else {
        return Some(format!("length {dlc} is not a CAN FD payload length (0..8, 12, 16, 20, 24, 32, 48, 64)"));
    };
    match u32::try_from(can_id) {
        Ok(id) => protocol::frame_error(id, dlc, flags, fd_bus),
        // Out of any identifier's range: the check names it with the id as given.
        Err(_) => protocol::frame_error(u32::MAX, dlc, flags, fd_bus)
            .map(|why| why.replace(&format!("{:#x}", u32::MAX), &format!("{can_id:#x}"))),
    }
}

/// python-can's acceptance: no filters (None or empty) accept every frame, else any filter (can_id, can_mask,
/// match) that matches the id and format does.
#[pyfunction]
pub(super) fn filters_accept(filters: Option<Vec<(u32, u32, u8)>>, can_id: u32, extended: bool) -> bool {
    let filters = filters.filter(|f| !f.is_empty())
        .map(|f| f.into_iter().map(|(can_id, can_mask, matching)| protocol::Filter { can_id, can_mask, matching }).collect());
    protocol::filters_accept(&filters, can_id, extended)
}
