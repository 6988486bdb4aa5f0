//! The bus's error path, the hooks the bus model calls where a frame can go wrong: a frame destroyed by a
//! corruption or an injected error flag (error frame, retransmission), delivered undetected, or sent intact (the
//! counters), error-state changes and recoveries, the error episodes, and the injected effects and babblers.
//! The error model's state (`BusErrors`) and the confinement rules are `errors.rs`.

use super::{Bus, Item, Payload, Transmission};
use crate::errors::*;
use crate::frame::{fd_frame_bits, FD_TAIL_BITS};
use crate::rng::Pcg64;
use crate::wire::{corrupt, pick_positions, receive, wire_bits};

impl Bus {
    /// Model CAN errors and fault confinement on this bus, drawing from `rng` (error flag and corruption positions).
    pub fn enable_errors(&mut self, rng: Pcg64) {
        self.errors = Some(Box::new(BusErrors::new(rng, self.timing.nominal_bit_ns)));
    }

    /// Run `f` with the error model taken out of the bus (so it can change the bus); nothing without one.
    fn with_errors<R: Default>(&mut self, f: impl FnOnce(&mut Bus, &mut BusErrors) -> R) -> R {
        let Some(mut e) = self.errors.take() else { return R::default() };
        let r = f(self, &mut e);
        self.errors = Some(e);
        r
    }

    fn event(&mut self, t_ns: i64, kind: EventKind) {
        self.events.push(BusEvent { t_ns, kind });
    }

    /// A bus-off node may queue again once it has recovered by t.
    pub(crate) fn admits(&mut self, node: usize, t: u64) -> bool {
        self.with_errors(|bus, e| bus.recoveries(e, t as i64));
        !self.nodes[node].bus_off
    }

    /// At a start of frame: recoveries due by now, then close the recessive run.
    pub(crate) fn before_arbitrate(&mut self, t: u64) {
        self.with_errors(|bus, e| {
            let t = t as i64;
            bus.recoveries(e, t);
            e.sequences += (t - e.run_start).max(0) / e.seq_ns;
            e.run_start = t;
        })
    }

    /// Frame drops: a hit frame vanishes from its sender's queue; the next pending frame competes instead.
    pub(crate) fn filter_winner(&mut self, mut won: Option<Item>, t: u64) -> Option<Item> {
        let Some(mut e) = self.errors.take() else { return won };
        while let Some(item) = won {
            if e.drops.is_empty() || !e.drops.iter_mut().any(|d| d.hit(item.frame_id)) {
                break;
            }
            let n = &mut self.nodes[item.node];
            n.queued -= 1;
            n.dropped += 1;
            e.stats.dropped_by_fault += 1;
            won = self.pop_winner(t);
        }
        self.errors = Some(e);
        won
    }

    /// Decide what happens to the frame now on the wire (`current`): destroyed by an error flag, corrupted (the
    /// receivers judge it bit by bit), or clean. A destroyed frame ends early, its error frame included.
    pub(crate) fn on_start(&mut self, won: Item) {
        let Some(mut e) = self.errors.take() else { return };
        e.item = Some(won);
        let tx = self.current.expect("on_start without a transmission");
        for k in 0..e.babblers.len() {
            if e.babblers[k].node == tx.node {
                let b = &mut e.babblers[k];
                b.sent += 1;
                e.stats.babbled += 1;
                let (node, id, data, ext) = (b.node, b.frame_id, b.data, b.extended);
                self.enqueue_as(node, id, data.as_slice(), tx.t_start, Some(ext), tx.format); // keep it babbling
            }
        }
        let mut tx = tx;
        if e.error_flags.iter_mut().any(|s| s.hit(tx.frame_id)) {
            let n_bits = if tx.format.is_fd() {
                let b = self.fd_phases(&tx);
                b.0 + b.1 - 3
            } else {
                wire_bits(tx.frame_id, tx.data.as_slice(), tx.extended).len() as u32
            };
            let at = 1 + e.rng.below(n_bits - 8); // after SOF .. the ACK delimiter
            e.stats.injected_error_flags += 1;
            self.fail(&mut tx, ErrorKind::ErrorFlag, at);
        } else if let Some(k) = e.corruptions.iter_mut().position(|s| s.hit(tx.frame_id)) {
            let bits = e.corruptions[k].bits;
            self.corrupt_frame(&mut e, &mut tx, bits);
        }
        self.current = Some(tx);
        self.errors = Some(e);
    }

    fn fd_phases(&self, tx: &Transmission) -> (u32, u32) {
        let b = fd_frame_bits(tx.frame_id, tx.data.as_slice(), tx.extended, tx.format.brs(), false)
            .expect("a frame on the wire has a valid FD length");
        (b.nominal, b.data)
    }

    fn corrupt_frame(&mut self, e: &mut BusErrors, tx: &mut Transmission, bits: u32) {
        e.stats.corrupted += 1;
        if tx.format.is_fd() {
            // CRC-17/21 with the stuff count: found after the ACK delimiter, no residual error to model
            let (nominal, data) = self.fd_phases(tx);
            e.stats.rejected += 1;
            self.fail(tx, ErrorKind::Crc, nominal + data - FD_EOF_IFS_BITS - 1);
            return;
        }
        let wire = wire_bits(tx.frame_id, tx.data.as_slice(), tx.extended);
        let span = wire.len() as u32 - 10; // bits after SOF up to and including the CRC delimiter
        let flips = pick_positions(&mut e.rng, span, bits);
        let seen = receive(&corrupt(&wire, &flips));
        match seen.error {
            Some(error) => {
                e.stats.rejected += 1;
                self.fail(tx, error, seen.at);
            }
            None => {
                // CAN's residual error: delivered as decoded, for the E2E check to catch
                e.stats.undetected += 1;
                let delivered = Payload::new(&seen.data);
                e.undetected.push(Undetected { t_ns: tx.t_start, sent_id: tx.frame_id, delivered_id: seen.can_id, delivered,
                                               sent: tx.data, flipped: flips });
                tx.frame_id = seen.can_id;
                tx.data = delivered;
                tx.extended = seen.extended;
            }
        }
    }

    fn fail(&mut self, tx: &mut Transmission, error: ErrorKind, at: u32) {
        tx.error = Some(error);
        tx.t_end = tx.t_start + self.bits_ns(tx, at + 1) + ERROR_TAIL_BITS * self.timing.nominal_bit_ns;
        self.busy_until = tx.t_end;
    }

    /// The time of a frame's first `k` bits (CAN FD with BRS: the data phase at the data rate).
    fn bits_ns(&self, tx: &Transmission, k: u32) -> u64 {
        let bit = self.timing.nominal_bit_ns;
        if !tx.format.brs() {
            return k as u64 * bit;
        }
        let (nominal, data) = self.fd_phases(tx);
        let arbitration = nominal as i64 - FD_TAIL_BITS as i64;
        let fast = (k as i64 - arbitration).max(0).min(data as i64) as u64;
        (k as u64 - fast) * bit + fast * self.timing.data_bit_ns
    }

    /// End of a transmission: counters and events; a destroyed frame is requeued (false: do not deliver it).
    pub(crate) fn on_complete(&mut self, tx: &Transmission) -> bool {
        let Some(mut e) = self.errors.take() else { return true };
        let t_end = tx.t_end as i64;
        e.run_start = t_end - e.seq_ns; // every transmission ends with 11 recessive bits
        let item = e.item.take();
        let Some(error) = tx.error else {
            self.success(&mut e, tx);
            self.errors = Some(e);
            return true;
        };
        e.stats.error_frames += 1;
        count_kind(&mut e.by_error, error);
        self.log_error(&mut e, tx, error);
        for node in 0..self.nodes.len() {
            let n = &self.nodes[node];
            if node != tx.node && n.attached && !n.bus_off {
                if !e.receiving.contains(&node) {
                    e.receiving.push(node);
                }
                let new = e.counters_of(node).rx_error();
                self.changed(&mut e, node, new, t_end);
            }
        }
        let new = e.counters_of(tx.node).tx_error();
        self.changed(&mut e, tx.node, new, t_end);
        // a destroyed frame and its error frame occupy the bus: they count in the load
        self.close_windows(tx.t_end, false);
        self.window_busy += tx.t_end - tx.t_start;
        if self.nodes[tx.node].bus_off || !self.nodes[tx.node].attached {
            self.nodes[tx.node].dropped += 1;
            e.stats.dropped_bus_off += 1;
        } else if let Some(item) = item {
            self.requeue(item);
            e.stats.retransmissions += 1;
        }
        self.errors = Some(e);
        false
    }

    fn success(&mut self, e: &mut BusErrors, tx: &Transmission) {
        let t_end = tx.t_end as i64;
        if let Some(c) = e.counters.get_mut(tx.node).and_then(|c| c.as_mut()) {
            if c.tec > 0 {
                let new = c.tx_ok();
                self.changed(e, tx.node, new, t_end);
            }
        }
        if e.receiving.is_empty() {
            return;
        }
        for node in e.receiving.clone() {
            if node != tx.node && !self.nodes[node].bus_off {
                let c = e.counters[node].as_mut().expect("a receiving node has counters");
                let new = c.rx_ok();
                let rec = c.rec;
                self.changed(e, node, new, t_end);
                if rec == 0 {
                    e.receiving.retain(|&n| n != node);
                }
            }
        }
    }

    fn changed(&mut self, e: &mut BusErrors, node: usize, new: Option<ErrorState>, t: i64) {
        let Some(state) = new else { return };
        let c = *e.counters_of(node);
        match state {
            ErrorState::BusOff => {
                self.nodes[node].bus_off = true;
                let lost = self.drop_queued(node) as u64;
                e.stats.dropped_bus_off += lost;
                e.bus_off.push((node, e.sequences, t));
                self.refresh_receivers();
                self.event(t, EventKind::BusOff { node, tec: c.tec, lost });
            }
            _ => self.event(t, EventKind::State { node, state, tec: c.tec, rec: c.rec }),
        }
    }

    /// Bring back every bus-off node that has seen 128 recessive sequences by t (at the exact time it did).
    fn recoveries(&mut self, e: &mut BusErrors, t: i64) {
        if e.bus_off.is_empty() {
            return;
        }
        let idle = self.current.is_none();
        let mut i = 0;
        while i < e.bus_off.len() {
            let (node, seq0, t_off) = e.bus_off[i];
            let need = RECOVERY_SEQUENCES - (e.sequences - seq0);
            let t_rec = if need <= 0 {
                e.run_start // reached at the end of an earlier run: logged at the latest bound
            } else if idle && (t - e.run_start).div_euclid(e.seq_ns) >= need {
                e.run_start + need * e.seq_ns
            } else {
                i += 1;
                continue;
            };
            e.bus_off.remove(i);
            self.nodes[node].bus_off = false;
            e.add_bus_off_ns(node, t_rec - t_off);
            e.counters_of(node).recover();
            self.refresh_receivers();
            self.event(t_rec, EventKind::Recovered { node, after_ns: t_rec - t_off });
        }
    }

    fn log_error(&mut self, e: &mut BusErrors, tx: &Transmission, error: ErrorKind) {
        let t_end = tx.t_end as i64;
        if e.episode.as_ref().is_some_and(|ep| t_end - ep.last_ns > EPISODE_GAP_NS) {
            self.close_episode(e);
        }
        if e.episode.is_none() {
            e.episode = Some(Episode { start_ns: t_end, last_ns: t_end, by_error: Vec::new() });
            self.event(t_end, EventKind::ErrorFrame { error, frame_id: tx.frame_id, node: tx.node });
        }
        let ep = e.episode.as_mut().unwrap();
        ep.last_ns = t_end;
        count_kind(&mut ep.by_error, error);
    }

    fn close_episode(&mut self, e: &mut BusErrors) {
        if let Some(ep) = e.episode.take() {
            let mut by_error = ep.by_error;
            by_error.sort();
            self.event(ep.last_ns, EventKind::Episode { start_ns: ep.start_ns, last_ns: ep.last_ns, by_error });
        }
    }

    /// End of the run for the error model: recoveries due, the open episode, time still spent bus-off.
    pub(crate) fn finish_errors(&mut self, t: u64) {
        self.with_errors(|bus, e| {
            let t = t as i64;
            bus.recoveries(e, t);
            bus.close_episode(e);
            for k in 0..e.bus_off.len() {
                let (node, seq0, t_off) = e.bus_off[k];
                e.add_bus_off_ns(node, (t - t_off).max(0));
                e.bus_off[k] = (node, seq0, t);
            }
        })
    }

    /// Start a fault's selection effect (corruption, error flags, drops) on this bus's error model.
    pub fn add_effect(&mut self, effect: Effect, selection: Selection) {
        if let Some(e) = self.errors.as_mut() {
            e.effects(effect).push(selection);
        }
    }

    /// Attach a babbling node for fault `fault`; returns the node (the caller queues its first frame).
    pub fn start_babbler(&mut self, fault: u64, name: &str, frame_id: u32, data: &[u8], extended: bool) -> Option<usize> {
        self.errors.as_ref()?;
        let node = self.attach(name, crate::bus::Sink::None, None, false);
        let b = Babbler { fault, node, frame_id, data: Payload::new(data), extended, sent: 0 };
        self.errors.as_mut().unwrap().babblers.push(b);
        Some(node)
    }

    /// End fault `fault` on this bus (a babbler leaves the bus).
    pub fn end_fault(&mut self, fault: u64) {
        let node = self.errors.as_mut().and_then(|e| e.remove_fault(fault));
        if let Some(node) = node {
            if self.nodes[node].attached {
                self.detach(node);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::{Policy, Sink};
    use crate::frame::BitTiming;

    fn error_bus() -> (Bus, usize, usize) {
        let mut b = Bus::new("b", BitTiming::new(500_000, 500_000).unwrap(), Policy::Priority, 8, false, 100_000_000);
        let a = b.attach("A", Sink::None, None, false);
        let r = b.attach("R", Sink::Inbox(0), None, false);
        b.enable_errors(Pcg64::from_state(7, 9));
        (b, a, r)
    }

    /// A frame destroyed by an error flag every time: TEC +8 per attempt, each retransmitted at once, error passive
    /// after 16, bus-off after 32 attempts (the queue dropped), back after 128 x 11 recessive bits of idle bus.
    #[test]
    fn a_node_whose_frames_are_always_destroyed_goes_passive_then_bus_off_then_recovers() {
        let (mut b, a, r) = error_bus();
        b.add_effect(Effect::ErrorFlags, Selection { fault: 1, rng: Pcg64::from_state(1, 1), probability: 1.0, frame_ids: None,
                                                     count: None, hits: 0, bits: 1 });
        b.enqueue(a, 0x10, &[1, 2], 0, None);
        b.enqueue(a, 0x11, &[1, 2], 0, None);
        let mut t = 0;
        let mut attempts = 0;
        while let Some(end) = b.arbitrate(t).unwrap() {
            let tx = b.complete();
            assert!(tx.error == Some(ErrorKind::ErrorFlag) && end < t + 200_000);
            attempts += 1;
            t = end;
        }
        assert_eq!(attempts, 32);
        let e = b.errors.as_ref().unwrap();
        let c = e.counters(a).unwrap();
        assert_eq!((c.state, c.tec, c.passive_count), (ErrorState::BusOff, 256, 1));
        assert_eq!(e.counters(r).unwrap().rec, 32);
        assert_eq!(e.stats.retransmissions, 31);
        assert_eq!((b.nodes[a].dropped, e.stats.dropped_bus_off), (2, 2)); // 0x11 at bus-off, 0x10 after its last attempt
        assert!(!b.enqueue(a, 0x12, &[], t + 1000, None)); // still bus-off: refused and counted
        assert_eq!(b.nodes[a].dropped, 3);
        // the error frame's last 11 recessive bits are the first sequence: back 127 sequences after it ended
        let back = t + 127 * 11 * 2000;
        assert!(!b.enqueue(a, 0x12, &[], back - 1, None));
        assert!(b.enqueue(a, 0x12, &[], back, None));
        assert!(b.events.iter().any(|ev| ev.kind == EventKind::Recovered { node: a, after_ns: 127 * 11 * 2000 }));
        assert!(b.events.iter().any(|ev| matches!(ev.kind, EventKind::State { node, state: ErrorState::Passive, .. } if node == a)));
    }

    #[test]
    fn a_babbler_keeps_its_frame_queued_and_leaves_at_the_end() {
        let (mut b, a, _) = error_bus();
        let n = b.start_babbler(5, "Babbler#5", 0x001, &[0xA5; 8], false).unwrap();
        b.enqueue(n, 0x001, &[0xA5; 8], 0, None);
        b.enqueue(a, 0x100, &[], 0, None);
        let mut t = 0;
        for _ in 0..10 {
            t = b.arbitrate(t).unwrap().unwrap();
            assert_eq!(b.complete().frame_id, 0x001); // 0x100 starves
        }
        b.end_fault(5);
        assert!(!b.nodes[n].attached);
        b.arbitrate(t).unwrap();
        assert_eq!(b.complete().frame_id, 0x100);
        assert_eq!(b.errors.as_ref().unwrap().stats.babbled, 10); // one per frame it started
    }
}
