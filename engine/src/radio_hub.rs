//! The radio between the real-time bus servers (engine/src/server.rs): the same `Gateway` as the virtual-time
//! network, shared by the servers of one rig, so a frame crosses from one train's bus to the next without a
//! process, a socket or Python on its way.
//!
//! A server whose frame ends with a routed ID offers it here (`offer`); each delivery goes into the destination
//! bus's inbox and that server is woken; it queues the frame as its "RadioGW" node at the delivery time. The links'
//! random numbers come in blocks from the owner (the Python links' numpy streams, as in virtual time), queued
//! ahead (`push_draws`), since a serving thread cannot call Python; a link that runs dry drops the frame and counts
//! it (`starved`). Each server's bus time has its own zero: the hub keeps the links in one time, the first
//! server's, and converts (`origin_ns`).

use std::collections::{HashMap, HashSet, VecDeque};
use std::io::Write;
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::bus::Payload;
use crate::codec::MessageLayout;
use crate::packing::Packing;
use crate::radio::{Draws, Gateway, FAULT_DRAWS};

/// A frame for a bus, from the radio: queue it on that bus at `t_ns` (its bus time).
#[derive(Debug, Clone, Copy)]
pub struct Delivery {
    pub t_ns: u64,
    pub frame_id: u32,
    pub data: Payload,
}

/// One bus server as the hub sees it: how far its zero lies after the hub's, its wake-up socket, whether it must
/// be woken for a delivery (it has an eager node or a per-frame error model; else it takes the delivery at its next
/// wake-up, which comes before any reader can see past the delivery time), and the serving thread it is on.
struct Port {
    origin_ns: i64,
    wake: UnixStream,
    eager: Arc<AtomicBool>,
    thread: usize,
}

/// Everything under the hub's lock.
pub struct HubCore {
    pub gateway: Gateway,
    layouts: HashMap<u32, Arc<MessageLayout>>,
    packing: Option<Arc<Packing>>,
    /// Per link, the blocks of draws queued ahead.
    reserve: Vec<VecDeque<Draws>>,
    /// Blocks of the injected faults' draws queued ahead.
    fault_reserve: VecDeque<Vec<f64>>,
    inboxes: HashMap<usize, Vec<Delivery>>,
    ports: HashMap<usize, Port>,
    /// The hub's time zero (made before any server, whose zeros come after it) and the rig's pace.
    zero: Instant,
    pace: f64,
    /// Frames a link dropped because its draws ran out (the owner did not top them up in time).
    pub starved: u64,
    /// Per bus, the fewest data bytes its connections said their frames carry (None: it has none).
    least_data: HashMap<usize, Option<u8>>,
}

struct Starved;

impl HubCore {
    /// A bus's time (ns) in the hub's time.
    fn to_hub(&self, bus: usize, t: u64) -> i64 {
        t as i64 + self.origin_ns(bus)
    }

    /// How far bus `bus`'s zero lies after the hub's (model ns), 0 for an unknown bus.
    fn origin_ns(&self, bus: usize) -> i64 {
        self.ports.get(&bus).map_or(0, |p| p.origin_ns)
    }

    /// The IDs on `bus` that its server must hand to the hub at their ends (containers that carry a routed part).
    pub fn routed_ids(&self, bus: usize) -> HashSet<u32> {
        let ids = self.gateway.ids_for_bus(bus);
        let mut out: HashSet<u32> = ids.iter().copied().collect();
        if let Some(p) = &self.packing {
            out.extend(p.containers_of(&ids));
        }
        out
    }

    /// A frame that ended on `bus` at `t_end` (its bus ns): every delivery into its destination's inbox, whose
    /// server is woken. Returns how many deliveries were made.
    pub fn offer(&mut self, bus: usize, frame_id: u32, data: &[u8], t_end: u64) -> usize {
        let t = self.to_hub(bus, t_end);
        let parts: Vec<(u32, Payload)> = match self.packing.as_deref().and_then(|p| p.unpack(frame_id, data)) {
            Some(parts) => parts.map(|(id, d)| (id, Payload::new(d))).collect(),
            None => vec![(frame_id, Payload::new(data))],
        };
        let mut made = 0;
        for (id, payload) in parts {
            let pos = self.layouts.get(&id).and_then(|l| l.first_value(payload.as_slice()));
            let (reserve, faults) = (&mut self.reserve, &mut self.fault_reserve);
            let mut refill = |link: usize| -> Result<Draws, Starved> {
                if link == FAULT_DRAWS {
                    return faults.pop_front().map(|u_loss| Draws { u_loss, ..Draws::default() }).ok_or(Starved);
                }
                reserve[link].pop_front().ok_or(Starved)
            };
            match self.gateway.forward(bus, id, pos, t, &mut refill) {
                Ok(deliveries) => {
                    for (dst, dst_id, at) in deliveries {
                        let local = (at - self.origin_ns(dst)).max(0) as u64;
                        self.inboxes.entry(dst).or_default().push(Delivery { t_ns: local, frame_id: dst_id, data: payload });
                        if let Some(port) = self.ports.get(&dst).filter(|p| p.eager.load(Ordering::Relaxed)) {
                            let _ = (&port.wake).write(b"r");
                        }
                        made += 1;
                    }
                }
                Err(Starved) => self.starved += 1,
            }
        }
        made
    }

    /// Whether a frame the radio takes must be handed over at its end: some bus must be woken for its deliveries
    /// (see `Port`), or the buses are not all served by one thread. Otherwise that thread runs them together, in
    /// time order, at each of its wake-ups (`server::settle`), and a delivery is made before anyone can see it.
    pub fn needs_ends(&self) -> bool {
        let mut threads = self.ports.values().map(|p| p.thread);
        let first = threads.next();
        threads.any(|t| Some(t) != first) || self.ports.values().any(|p| p.eager.load(Ordering::Relaxed))
    }

    /// Bus `bus`'s connections send frames of at least `bytes` data bytes (None: it has no connection).
    pub fn set_least_data(&mut self, bus: usize, bytes: Option<u8>) {
        self.least_data.insert(bus, bytes);
    }

    /// The fewest data bytes a frame the radio forwards can carry: what the buses' connections said (a forwarded
    /// frame is one of theirs), 0 when containers are unpacked (a part may be shorter than its container).
    pub fn least_data(&self) -> Option<u8> {
        if self.packing.is_some() {
            return Some(0);
        }
        self.least_data.values().flatten().copied().min()
    }

    /// How far bus `bus`'s zero lies after the hub's (model ns): bus times plus it are the hub's time.
    pub fn origin_of(&self, bus: usize) -> i64 {
        self.origin_ns(bus)
    }

    /// The deliveries waiting for `bus`, oldest first.
    pub fn take(&mut self, bus: usize) -> Vec<Delivery> {
        let mut out = self.inboxes.remove(&bus).unwrap_or_default();
        out.sort_by_key(|d| d.t_ns);
        out
    }
}

/// The hub the servers of one rig share.
pub struct RadioHub {
    pub core: Mutex<HubCore>,
}

impl RadioHub {
    pub fn new(packing: Option<Arc<Packing>>, pace: f64) -> RadioHub {
        RadioHub { core: Mutex::new(HubCore {
            gateway: Gateway::default(), layouts: HashMap::new(), packing, reserve: Vec::new(), fault_reserve: VecDeque::new(),
            inboxes: HashMap::new(), ports: HashMap::new(), zero: Instant::now(), pace, starved: 0,
            least_data: HashMap::new(),
        }) }
    }

    /// Frames of `layout`'s ID carry their sender's position in their first signal (range, tunnels).
    pub fn set_position_layout(&self, layout: Arc<MessageLayout>) {
        self.core.lock().unwrap().layouts.insert(layout.frame_id, layout);
    }

    /// Add a link (its draws come by `push_draws`); returns its index.
    pub fn add_link(&self, link: crate::radio::Link) -> usize {
        let mut core = self.core.lock().unwrap();
        core.reserve.push(VecDeque::new());
        core.gateway.add_link(link)
    }

    /// Queue a block of draws for link `link`.
    pub fn push_draws(&self, link: usize, draws: Draws) {
        self.core.lock().unwrap().reserve[link].push_back(draws);
    }

    /// Queue a block of the injected faults' draws.
    pub fn push_fault_draws(&self, u: Vec<f64>) {
        self.core.lock().unwrap().fault_reserve.push_back(u);
    }

    /// Blocks queued per link, and of the faults' draws.
    pub fn reserves(&self) -> (Vec<usize>, usize) {
        let core = self.core.lock().unwrap();
        (core.reserve.iter().map(VecDeque::len).collect(), core.fault_reserve.len())
    }

    /// Bus `bus`'s server: its zero, a socket that wakes it, the flag it keeps saying whether it must be woken, and
    /// the serving thread it is on (any number that tells the threads apart).
    pub fn register(&self, bus: usize, mono0: Instant, wake: UnixStream, eager: Arc<AtomicBool>, thread: usize) {
        let mut core = self.core.lock().unwrap();
        let origin_ns = (mono0.saturating_duration_since(core.zero).as_nanos() as f64 * core.pace) as i64;
        core.ports.insert(bus, Port { origin_ns, wake, eager, thread });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::radio::{Hop, Link, Loss};

    fn block(n: usize, jitter: i64) -> Draws {
        Draws { u_step: vec![0.5; n], u_loss: vec![0.5; n], jitter_ns: vec![jitter; n], next: 0 }
    }

    fn hub_1_to_2(latency_ns: i64) -> RadioHub {
        let hub = RadioHub::new(None, 1.0);
        let link = hub.add_link(Link::new("1>2", 1e9, vec![], latency_ns, None, Loss::None, false));
        hub.core.lock().unwrap().gateway.add_route(0, 0x100, Hop { dst_bus: 1, dst_id: 0x300, link, reverse: None });
        hub
    }

    #[test]
    fn a_routed_frame_reaches_the_other_bus_inbox_at_its_delivery_time_and_wakes_its_server() {
        let hub = hub_1_to_2(2_000);
        hub.push_draws(0, block(4, 500));
        let (r, w) = UnixStream::pair().unwrap();
        r.set_nonblocking(true).unwrap();
        let t0 = Instant::now();
        hub.register(0, t0, UnixStream::pair().unwrap().1, Arc::new(AtomicBool::new(true)), 1);
        let eager = Arc::new(AtomicBool::new(true));
        hub.register(1, t0, w, eager.clone(), 1);
        let mut core = hub.core.lock().unwrap();
        assert_eq!(core.offer(0, 0x100, &[1, 2, 3], 10_000), 1);
        assert_eq!(core.offer(0, 0x101, &[9], 10_000), 0); // not routed
        let got = core.take(1);
        assert_eq!((got.len(), got[0].t_ns, got[0].frame_id, got[0].data.as_slice()), (1, 12_500, 0x300, &[1u8, 2, 3][..]));
        assert!(core.take(1).is_empty());
        let mut buf = [0u8; 8];
        assert_eq!(std::io::Read::read(&mut &r, &mut buf).unwrap(), 1);
        assert_eq!(core.routed_ids(0), HashSet::from([0x100]));
        eager.store(false, Ordering::Relaxed); // only lazy readers there: delivered without a wake-up
        assert_eq!(core.offer(0, 0x100, &[4], 20_000), 1);
        assert!(std::io::Read::read(&mut &r, &mut buf).is_err()); // WouldBlock
        assert_eq!(core.take(1).len(), 1);
    }

    #[test]
    fn bus_times_with_different_zeros_meet_in_the_hubs_time() {
        let hub = hub_1_to_2(0);
        hub.push_draws(0, block(4, 0));
        let t0 = Instant::now();
        let flag = || Arc::new(AtomicBool::new(true));
        hub.register(0, t0, UnixStream::pair().unwrap().1, flag(), 1);
        hub.register(1, t0 + std::time::Duration::from_micros(300), UnixStream::pair().unwrap().1, flag(), 1);
        let mut core = hub.core.lock().unwrap();
        core.offer(0, 0x100, &[1], 1_000_000);
        assert_eq!(core.take(1)[0].t_ns, 700_000); // bus 2 started 300 µs later: its clock reads 300 µs less
    }

    #[test]
    fn routed_frames_need_their_ends_unless_every_bus_is_lazy_and_on_one_thread() {
        let hub = hub_1_to_2(0);
        let t0 = Instant::now();
        let (e1, e2) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)));
        hub.register(0, t0, UnixStream::pair().unwrap().1, e1.clone(), 7);
        hub.register(1, t0, UnixStream::pair().unwrap().1, e2.clone(), 7);
        assert!(!hub.core.lock().unwrap().needs_ends());
        e2.store(true, Ordering::Relaxed); // an eager node on bus 2: woken for each delivery, which must come at once
        assert!(hub.core.lock().unwrap().needs_ends());
        e2.store(false, Ordering::Relaxed);
        hub.register(1, t0, UnixStream::pair().unwrap().1, e2, 8); // another thread: no common time order
        assert!(hub.core.lock().unwrap().needs_ends());
    }

    #[test]
    fn a_link_without_draws_drops_the_frame_and_counts_it() {
        let hub = hub_1_to_2(0);
        let mut core = hub.core.lock().unwrap();
        assert_eq!(core.offer(0, 0x100, &[1], 5), 0);
        assert_eq!((core.starved, core.gateway.links[0].stats.offered), (1, 0));
        drop(core);
        hub.push_draws(0, block(1, 0));
        let mut core = hub.core.lock().unwrap();
        assert_eq!(core.offer(0, 0x100, &[1], 6), 1);
        assert_eq!(core.offer(0, 0x100, &[1], 7), 0); // the block had one frame's draws
        assert_eq!(core.starved, 2);
    }
}
