//! trainhil's frame engine: everything that runs once per CAN frame, for both runtimes.
//!
//! * `frame`: exact frame length from the actual bits (stuffing, CRC-15), durations from two bit rates;
//! * `e2e`: CRC-8 SAE J1850 and the alive-counter check;
//! * `codec`: the DBC message layouts compiled from cantools (saturate and count, never wrap);
//! * `mailbox`: an ECU's input mailboxes, read once per cycle; `command_inbox`: a real-time plant's commands and
//!   sensor-to-actuator latency, taken on receipt;
//! * `bus`: the CAN bus model (TX queues, arbitration, filters, statistics);
//! * `errors`: CAN error confinement and the error model's state, the bus fault injectors' selections;
//!   `wire`: a frame's bits and the bit-level receiver; `bus/error_path`: error frames and retransmission;
//!   `guardian`: the babbling-idiot monitor; `rng`: numpy's PCG64, to continue its streams;
//! * `packing`: CAN FD frame packing (several messages in one container frame, unpacked at the receivers);
//! * `radio`: the train-to-train links and the routing gateway;
//! * `kernel` and `network`: the virtual-time event queue and the network it drives;
//! * `protocol`: the wire protocol between a bus server and its nodes (constants, record codec);
//! * `server`: the real-time bus server, its buses served by `serving_thread`, which waits through `poll_wait`
//!   (`histogram`: its delay figures); `link`: a node's end of its connection; `read_schedule`: a lazy reader's
//!   read times, which buses a wait was foreseen on;
//!   `series`: a node's per-cycle series (lateness, latency), streamed to a file, percentiles from 1 µs bins.
//!
//! `py` (feature `python`) is the Python surface, `trainhil_engine._native`.

pub mod bus;
pub mod codec;
pub mod command_inbox;
pub mod e2e;
pub mod errors;
pub mod frame;
pub mod guardian;
pub mod histogram;
pub mod kernel;
pub mod link;
pub mod mailbox;
pub mod network;
pub mod packing;
pub mod poll_wait;
pub mod protocol;
pub mod radio;
pub mod radio_hub;
pub mod read_schedule;
pub mod rng;
pub mod server;
pub mod series;
pub mod serving_thread;
pub mod wire;

#[cfg(feature = "python")]
mod py;
