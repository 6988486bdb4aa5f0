//! The virtual-time network: every train bus, the radio gateway, the mailboxes and inboxes they deliver into,
//! and one event queue for all of them. Python's periodic tasks (plant steps, ECU cycles, wayside ticks) are
//! external events on the same queue: `advance` runs every frame event in Rust and returns to Python only when
//! an external event is due. Scheduling follows the Python kernel exactly (a periodic task is rescheduled
//! after its handler ran), so both give the same frame schedule.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crate::bus::{Bus, Payload, Sink, Transmission};
use crate::errors::BusEvent;
use crate::codec::MessageLayout;
use crate::frame::{self, FrameError};
use crate::kernel::EventQueue;
use crate::mailbox::Mailbox;
use crate::radio::{Draws, Gateway};

/// What happens at a time.
pub enum Event {
    Arbitrate(usize),
    End(usize),
    RadioSend { bus: usize, frame_id: u32, data: Payload },
    External { token: u64, period: u64 },
}

pub use crate::radio::FAULT_DRAWS;

/// A frame delivered into an inbox: (inbox, frame id, payload, end of transmission in ns).
pub type InboxFrame = (usize, u32, Payload, u64);

/// An actuator command decoded on delivery: (unit, force N, mode, arrival time s, E2E alive counter). The
/// counter goes with it so that the plant can check each command stream's sequence (a second sender).
pub type Command = (usize, f64, i64, f64, u8);

/// What a command inbox accepts: per frame ID the unit it drives and the message layout (signals Mode, Force).
#[derive(Default)]
pub struct CommandTable {
    pub by_id: HashMap<u32, (usize, Arc<MessageLayout>)>,
    pub valid_modes: Vec<i64>,
}

impl CommandTable {
    /// The command a frame carries, or None when it must be rejected (wrong length, CRC, unknown mode).
    fn decode(&self, frame_id: u32, data: &[u8], t_ns: u64, scratch: &mut Vec<f64>) -> Option<Command> {
        let (unit, force, mode, counter) = self.check(frame_id, data, scratch)?;
        Some((unit, force, mode, t_ns as f64 * 1e-9, counter))
    }

    /// (unit, force, mode, alive counter) of a frame of this table, or None when it is not one of its IDs or
    /// must be rejected (wrong length, E2E CRC, a mode not in `valid_modes`); `scratch` holds the decoded values.
    pub fn check(&self, frame_id: u32, data: &[u8], scratch: &mut Vec<f64>) -> Option<(usize, f64, i64, u8)> {
        let (unit, layout) = self.by_id.get(&frame_id)?;
        if data.len() != layout.dlc || !crate::e2e::crc_ok(layout.data_id, data) {
            return None;
        }
        layout.decode_into(data, scratch).ok()?;
        let (mode, force) = (scratch[0], scratch[1]);
        let m = mode as i64;
        if m as f64 != mode || !self.valid_modes.contains(&m) {
            return None;
        }
        Some((*unit, force, m, crate::e2e::counter_of(data)))
    }
}

#[derive(Default)]
pub struct Network {
    pub queue: EventQueue<Event>,
    pub buses: Vec<Bus>,
    arbitration_pending: Vec<bool>,
    pub mailboxes: Vec<Arc<Mutex<Mailbox>>>,
    /// Frames delivered into any inbox, in arrival order (the rig drains them once per plant step).
    pub inbox: Vec<InboxFrame>,
    inboxes: usize,
    /// Commands accepted by the command inboxes, in arrival order.
    pub commands: Vec<Command>,
    /// Frames a command inbox rejected, as (table, frame id, payload, t_end ns): the rig reports them.
    pub rejected: Vec<InboxFrame>,
    pub command_tables: Vec<CommandTable>,
    scratch: Vec<f64>,
    pub gateway: Gateway,
    gateway_nodes: Vec<Option<usize>>,
    position_layouts: HashMap<u32, Arc<MessageLayout>>,
    reschedule: Option<(u64, u64, u64)>,
    next_token: u64,
    /// What the buses' error models and guardians reported, as (bus, event), in the order it happened.
    pub events: Vec<(usize, BusEvent)>,
}

impl Network {
    pub fn add_bus(&mut self, bus: Bus) -> usize {
        self.buses.push(bus);
        self.arbitration_pending.push(false);
        self.gateway_nodes.push(None);
        self.buses.len() - 1
    }

    pub fn add_mailbox(&mut self, mailbox: Arc<Mutex<Mailbox>>) -> usize {
        self.mailboxes.push(mailbox);
        self.mailboxes.len() - 1
    }

    pub fn add_inbox(&mut self) -> usize {
        self.inboxes += 1;
        self.inboxes - 1
    }

    /// A node that checks and decodes actuator commands on delivery (filter: the table's IDs); returns the node
    /// and the table's index (which `rejected` names).
    pub fn attach_commands(&mut self, bus: usize, name: &str, table: CommandTable) -> (usize, usize) {
        let mut ids: Vec<u32> = table.by_id.keys().copied().collect();
        ids.sort_unstable();
        self.command_tables.push(table);
        let index = self.command_tables.len() - 1;
        (self.buses[bus].attach(name, Sink::Commands(index), Some(ids), false), index)
    }

    /// Attach the radio gateway's node on `bus` (its filter: the routed IDs of that bus).
    pub fn attach_gateway(&mut self, bus: usize, name: &str) -> usize {
        let ids = self.gateway.ids_for_bus(bus);
        let node = self.buses[bus].attach(name, Sink::Gateway(bus), Some(ids), false);
        self.gateway_nodes[bus] = Some(node);
        node
    }

    /// Frames of `frame_id` carry their sender's position in their first signal (the radio's range check).
    pub fn set_position_layout(&mut self, layout: Arc<MessageLayout>) {
        self.position_layouts.insert(layout.frame_id, layout);
    }

    /// A periodic external event from `first` every `period` ns (period 0: once); returns its token.
    pub fn every(&mut self, first: u64, period: u64) -> u64 {
        self.next_token += 1;
        let token = self.next_token;
        self.queue.at(first, Event::External { token, period });
        token
    }

    /// Queue a frame on a bus at the current time; false (counted) when the node's queue is full.
    /// Frames queued at the same instant all join one arbitration.
    pub fn send(&mut self, bus: usize, node: usize, frame_id: u32, data: &[u8]) -> Result<bool, FrameError> {
        let b = &mut self.buses[bus];
        frame::validate_as(frame_id, data.len(), b.extended, b.format.is_fd())?;
        let now = self.queue.now;
        let ok = b.enqueue(node, frame_id, data, now, None);
        if ok && b.current.is_none() && !self.arbitration_pending[bus] {
            self.arbitration_pending[bus] = true;
            let t = now.max(b.busy_until);
            self.queue.at(t, Event::Arbitrate(bus));
        }
        self.collect_events(bus);
        Ok(ok)
    }

    /// Move a bus's error and guardian events to the network's list, keeping the order they happened in.
    fn collect_events(&mut self, bus: usize) {
        if !self.buses[bus].events.is_empty() {
            self.events.extend(self.buses[bus].events.drain(..).map(|e| (bus, e)));
        }
    }

    /// Close every bus's load windows (and error model) at `t` ns: the end of a run.
    pub fn finish(&mut self, t: u64) {
        for bus in 0..self.buses.len() {
            self.buses[bus].finish(t);
            self.collect_events(bus);
        }
    }

    /// Queue a node's batch of frames at the current time: on a bus with frame packing, the batch goes as its
    /// containers (`Packing::pack`). Returns how many frames the node's full queue refused.
    pub fn send_batch(&mut self, bus: usize, node: usize, frames: &[(u32, &[u8])]) -> Result<usize, FrameError> {
        let mut refused = 0;
        match self.buses[bus].packing.clone() {
            Some(packing) => {
                let b = &self.buses[bus];
                for &(id, data) in frames {
                    frame::validate_as(id, data.len(), b.extended, b.format.is_fd())?;
                }
                for (id, data) in packing.pack(frames) {
                    refused += usize::from(!self.send(bus, node, id, data.as_slice())?);
                }
            }
            None => {
                for &(id, data) in frames {
                    refused += usize::from(!self.send(bus, node, id, data)?);
                }
            }
        }
        Ok(refused)
    }

    fn arbitrate(&mut self, bus: usize) -> Result<(), FrameError> {
        self.arbitration_pending[bus] = false;
        let started = self.buses[bus].arbitrate(self.queue.now);
        self.collect_events(bus);
        if let Some(end) = started? {
            self.queue.at(end, Event::End(bus));
        }
        Ok(())
    }

    fn end<E: From<FrameError>>(&mut self, bus: usize, refill: &mut dyn FnMut(usize) -> Result<Draws, E>) -> Result<(), E> {
        let tx = self.buses[bus].complete();
        self.collect_events(bus);
        if tx.error.is_none() {
            // destroyed frames (`error`) are not delivered: their sender retransmits them
            let receivers = self.buses[bus].take_receivers(tx.frame_id);
            let packing = self.buses[bus].packing.clone();
            let parts = packing.as_deref().and_then(|p| p.unpack(tx.frame_id, tx.data.as_slice()));
            let delivered = match parts {
                // a container: each receiver takes the parts its filter accepts, as the frames they were
                Some(mut parts) => parts.try_for_each(|(id, data)| self.deliver(bus, &receivers, &tx, id, Payload::new(data), true, refill)),
                None => self.deliver(bus, &receivers, &tx, tx.frame_id, tx.data, false, refill),
            };
            self.buses[bus].put_receivers(tx.frame_id, receivers);
            delivered?;
        }
        if self.arbitration_pending[bus] || !self.buses[bus].pending() {
            return Ok(());
        }
        if self.queue.next_time() == Some(self.queue.now) {
            // other events at this same instant may queue frames: arbitrate after them so they compete
            self.arbitration_pending[bus] = true;
            self.queue.at(self.queue.now, Event::Arbitrate(bus));
            Ok(())
        } else {
            Ok(self.arbitrate(bus)?)
        }
    }

    /// Hand frame `frame_id` (a transmission, or with `part` one part of a container: only to the receivers whose
    /// filter accepts it) to each of `receivers`' sinks.
    #[allow(clippy::too_many_arguments)]
    fn deliver<E>(&mut self, bus: usize, receivers: &[usize], tx: &Transmission, frame_id: u32, data: Payload, part: bool,
                  refill: &mut dyn FnMut(usize) -> Result<Draws, E>) -> Result<(), E> {
        for &node in receivers {
            let n = &self.buses[bus].nodes[node];
            if (node == tx.node && !n.receive_own) || (part && !n.accepts(frame_id)) {
                continue;
            }
            match n.sink {
                Sink::None => {}
                Sink::Mailbox(m) => {
                    self.mailboxes[m].lock().unwrap().put(frame_id, data.as_slice(), tx.t_end as f64 * 1e-9);
                }
                Sink::Inbox(i) => self.inbox.push((i, frame_id, data, tx.t_end)),
                Sink::Commands(i) => {
                    match self.command_tables[i].decode(frame_id, data.as_slice(), tx.t_end, &mut self.scratch) {
                        Some(cmd) => self.commands.push(cmd),
                        None => self.rejected.push((i, frame_id, data, tx.t_end)),
                    }
                }
                Sink::Gateway(b) => self.forward(b, frame_id, data, tx.t_end, refill)?,
            }
        }
        Ok(())
    }

    /// Offer a frame heard on `bus` to every matching route of the gateway.
    fn forward<E>(&mut self, bus: usize, frame_id: u32, data: Payload, t: u64,
                  refill: &mut dyn FnMut(usize) -> Result<Draws, E>) -> Result<(), E> {
        let pos = self.position_layouts.get(&frame_id).and_then(|l| l.first_value(data.as_slice()));
        for (dst_bus, dst_id, deliver) in self.gateway.forward(bus, frame_id, pos, t as i64, refill)? {
            let at = (deliver.max(0) as u64).max(self.queue.now);
            self.queue.at(at, Event::RadioSend { bus: dst_bus, frame_id: dst_id, data });
        }
        Ok(())
    }

    /// Run every event before `until` ns. Returns the token of an external event that is due (the clock is at
    /// its time; call again after handling it), or None when the clock reached `until`.
    pub fn advance<E: From<FrameError>>(&mut self, until: u64, refill: &mut dyn FnMut(usize) -> Result<Draws, E>)
                                        -> Result<Option<u64>, E> {
        if let Some((token, t, period)) = self.reschedule.take() {
            self.queue.at(t, Event::External { token, period });
        }
        while let Some(event) = self.queue.pop_before(until) {
            match event {
                Event::Arbitrate(bus) => self.arbitrate(bus)?,
                Event::End(bus) => self.end(bus, refill)?,
                Event::RadioSend { bus, frame_id, data } => {
                    let node = self.gateway_nodes[bus].expect("radio delivery to a bus without a gateway node");
                    self.send(bus, node, frame_id, data.as_slice())?;
                }
                Event::External { token, period } => {
                    if period > 0 {
                        self.reschedule = Some((token, self.queue.now + period, period));
                    }
                    return Ok(Some(token));
                }
            }
        }
        self.queue.now = self.queue.now.max(until);
        Ok(None)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::bus::Policy;
    use crate::frame::BitTiming;

    fn no_draws(_: usize) -> Result<Draws, FrameError> {
        Ok(Draws::default())
    }

    /// TractionCmd_U01 (ID 0x80, signals Mode and Force) driving unit 3.
    pub(crate) fn command_table() -> CommandTable {
        let layout = crate::codec::MessageLayout {
            name: "TractionCmd_U01".into(), frame_id: 0x80, dlc: 8, data_id: 0x10,
            signals: vec![
                crate::codec::SignalSpec { name: "Mode".into(), start: 12, length: 4, signed: false, scale: 1.0, offset: 0.0, raw_min: 0, raw_max: 15 },
                crate::codec::SignalSpec { name: "Force".into(), start: 16, length: 24, signed: true, scale: 1.0, offset: 0.0, raw_min: -(1 << 23), raw_max: (1 << 23) - 1 },
            ],
        };
        let mut table = CommandTable { valid_modes: vec![0, 1, 2], ..Default::default() };
        table.by_id.insert(0x80, (3, Arc::new(layout)));
        table
    }

    pub(crate) fn command_frame(table: &CommandTable, mode: f64, force: f64, counter: i64) -> Vec<u8> {
        let (mut sat, mut out) = ([0u64; 2], [0u8; frame::MAX_DATA]);
        let n = table.by_id[&0x80].1.encode(&[mode, force], counter, &mut sat, &mut out).unwrap();
        out[..n].to_vec()
    }

    #[test]
    fn a_command_table_decodes_its_frames_and_refuses_what_the_plant_must_not_apply() {
        let (table, mut scratch) = (command_table(), Vec::new());
        let good = command_frame(&table, 1.0, -1200.0, 7);
        assert_eq!(table.check(0x80, &good, &mut scratch), Some((3, -1200.0, 1, 7)));
        assert_eq!(table.check(0x81, &good, &mut scratch), None, "not one of its IDs");
        assert_eq!(table.check(0x80, &good[..7], &mut scratch), None, "wrong length");
        let mut corrupt = good.clone();
        corrupt[4] ^= 0x01;
        assert_eq!(table.check(0x80, &corrupt, &mut scratch), None, "CRC");
        let unknown_mode = command_frame(&table, 5.0, 0.0, 8);
        assert_eq!(table.check(0x80, &unknown_mode, &mut scratch), None, "mode not valid");
        assert_eq!(table.decode(0x80, &good, 2_500_000, &mut scratch), Some((3, -1200.0, 1, 0.0025, 7)));
    }

    #[test]
    fn frames_queued_by_one_task_arbitrate_together_and_reach_the_inbox() {
        let mut net = Network::default();
        let b = net.add_bus(Bus::new("bus1", BitTiming::new(500_000, 500_000).unwrap(), Policy::Priority, 8, false, 100_000_000));
        let inbox = net.add_inbox();
        let sender = net.buses[b].attach("ECU", Sink::None, None, false);
        net.buses[b].attach("Plant", Sink::Inbox(inbox), Some(vec![0x010, 0x020]), false);
        let tick = net.every(0, 10_000_000);
        assert_eq!(net.advance(1_000_000_000, &mut no_draws).unwrap(), Some(tick));
        net.send(b, sender, 0x020, &[0; 8]).unwrap();
        net.send(b, sender, 0x010, &[0; 8]).unwrap();
        net.send(b, sender, 0x030, &[0; 8]).unwrap();
        assert_eq!(net.advance(10_000_000, &mut no_draws).unwrap(), None);
        assert!(net.inbox.iter().all(|f| f.0 == inbox));
        let got: Vec<u32> = net.inbox.iter().map(|f| f.1).collect();
        assert_eq!(got, vec![0x010, 0x020]); // lowest ID first; 0x030 is not in the plant's filter
        assert_eq!(net.buses[b].stats.frames_sent, 3);
        assert_eq!(net.advance(20_000_000, &mut no_draws).unwrap(), Some(tick));
        assert_eq!(net.queue.now, 10_000_000);
    }

    #[test]
    fn bad_frames_are_refused_at_the_sender() {
        let mut net = Network::default();
        let b = net.add_bus(Bus::new("bus1", BitTiming::new(500_000, 500_000).unwrap(), Policy::Priority, 8, false, 100_000_000));
        let n = net.buses[b].attach("X", Sink::None, None, false);
        assert!(net.send(b, n, 0x800, &[]).is_err());
        assert!(net.send(b, n, 0x100, &[0; 9]).is_err());
    }

    #[test]
    fn a_packed_batch_is_one_frame_on_the_bus_and_its_parts_at_each_receiver() {
        use crate::bus::Format;
        use crate::packing::{Container, Packing, Part};
        let mut net = Network::default();
        let bus = Bus::new("bus1", BitTiming::new(1_000_000, 5_000_000).unwrap(), Policy::Priority, 8, false, 100_000_000)
            .with_format(Format::FdBrs);
        let b = net.add_bus(bus);
        let packing = Packing::new(vec![Container { id: 0x70, len: 20, parts: vec![
            Part { id: 0x80, offset: 0, len: 5 }, Part { id: 0x100, offset: 5, len: 8 }, Part { id: 0x120, offset: 13, len: 7 }] }]).unwrap();
        net.buses[b].set_packing(Some(Arc::new(packing)));
        let (plant, neighbour) = (net.add_inbox(), net.add_inbox());
        let ecu = net.buses[b].attach("ECU", Sink::None, None, false);
        net.buses[b].attach("Plant", Sink::Inbox(plant), Some(vec![0x80]), false);
        net.buses[b].attach("ECU2", Sink::Inbox(neighbour), Some(vec![0x100, 0x120]), false);
        let tick = net.every(0, 10_000_000);
        assert_eq!(net.advance(1_000_000_000, &mut no_draws).unwrap(), Some(tick));
        let (cmd, state, aux) = ([1u8; 5], [2u8; 8], [3u8; 7]);
        assert_eq!(net.send_batch(b, ecu, &[(0x80, &cmd), (0x100, &state), (0x120, &aux)]).unwrap(), 0);
        net.send_batch(b, ecu, &[(0x80, &cmd)]).unwrap(); // a command alone goes as itself
        assert_eq!(net.advance(10_000_000, &mut no_draws).unwrap(), None);
        assert_eq!(net.buses[b].stats.frames_sent, 2);
        let got: Vec<(usize, u32, Vec<u8>)> = net.inbox.iter().map(|f| (f.0, f.1, f.2.as_slice().to_vec())).collect();
        assert_eq!(got, vec![(plant, 0x80, cmd.to_vec()), (neighbour, 0x100, state.to_vec()), (neighbour, 0x120, aux.to_vec()),
                             (plant, 0x80, cmd.to_vec())]);
    }
}
