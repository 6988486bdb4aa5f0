//! trainhil's frame engine: everything that runs once per CAN frame, for both runtimes.
//!
//! * `frame`: exact frame length from the actual bits (stuffing, CRC-15), durations from two bit rates;
//! * `e2e`: CRC-8 SAE J1850 and the alive-counter check;
//! * `codec`: the DBC message layouts compiled from cantools (saturate and count, never wrap);
//! * `mailbox`: an ECU's input mailboxes, read once per cycle;
//! * `bus`: the CAN bus model (TX queues, arbitration, filters, statistics);
//! * `errors`: CAN error confinement, corruption with a bit-level receiver, error frames and retransmission, and
//!   the bus fault injectors; `guardian`: the babbling-idiot monitor; `rng`: numpy's PCG64, to continue its streams;
//! * `packing`: CAN FD frame packing (several messages in one container frame, unpacked at the receivers);
//! * `radio`: the train-to-train links and the routing gateway;
//! * `kernel` and `network`: the virtual-time event queue and the network it drives;
//! * `server`: the real-time bus server, one OS thread per bus.
//!
//! `py` (feature `python`) is the Python surface, `trainhil_engine._native`.

pub mod bus;
pub mod codec;
pub mod e2e;
pub mod errors;
pub mod frame;
pub mod guardian;
pub mod kernel;
pub mod mailbox;
pub mod network;
pub mod packing;
pub mod protocol;
pub mod radio;
pub mod rng;
pub mod server;

#[cfg(feature = "python")]
mod py;
