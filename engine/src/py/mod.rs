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
use crate::mailbox as core_mailbox;
use crate::network::{CommandTable, Network as CoreNetwork, FAULT_DRAWS};
use crate::packing::{Container, Packing as CorePacking, Part};
use crate::radio::{Draws, GatewayError, Hop, Link, Loss};

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

mod bus_events;
mod codec;
mod command_inbox;
mod frames;
mod link;
mod link_group;
mod mailbox;
mod network;
mod radio_hub;
mod series;
mod server;

use self::bus_events::{errors_summary, event_fields};
use self::command_inbox::CommandInbox;
use self::codec::{command_table, encode_outputs, MessageCodec, Output, Packing};
use self::frames::*;
use self::link::{wait_readable, FrameLink};
use self::link_group::LinkGroup;
use self::mailbox::Mailbox;
use self::network::{add_bus_fault, check_window, policy, Network};
use self::radio_hub::RadioHub;
use self::series::Series;
use self::server::{BusServerCore, ServingThread};

fn timing(nominal: u64, data: u64) -> PyResult<BitTiming> {
    BitTiming::new(nominal, data).ok_or_else(|| {
        PyValueError::new_err(format!("bitrate {nominal} (data {data}) bit/s has no whole-nanosecond bit time"))
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
    m.add_function(wrap_pyfunction!(frame_error, m)?)?;
    m.add_function(wrap_pyfunction!(filters_accept, m)?)?;
    m.add_class::<MessageCodec>()?;
    m.add_class::<CommandInbox>()?;
    m.add_class::<Mailbox>()?;
    m.add_class::<Network>()?;
    m.add_class::<Packing>()?;
    m.add_class::<BusServerCore>()?;
    m.add_class::<ServingThread>()?;
    m.add_class::<RadioHub>()?;
    m.add_class::<FrameLink>()?;
    m.add_class::<LinkGroup>()?;
    m.add_class::<Series>()?;
    m.add("SERIES_FLUSH_ROWS", crate::series::FLUSH_ROWS)?;
    m.add("__all__", vec!["VERSION", "MAX_DATA", "PROTOCOL", "frame_bits", "frame_duration_ns", "fd_frame_bits", "e2e_crc", "wire_bits", "receive_wire", "MessageCodec", "CommandInbox", "Mailbox", "Network", "Packing",
                          "BusServerCore", "ServingThread", "RadioHub", "FrameLink", "LinkGroup", "Series", "SERIES_FLUSH_ROWS", "wait_readable", "frame_error", "filters_accept"])?;
    Ok(())
}

