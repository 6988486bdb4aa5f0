//! The train-to-train radio: one `Link` per direction (range, tunnels, rate cap, loss, latency and jitter per
//! frame) and the `Gateway`, a cangw-style routing table that forwards frames between adjacent train buses.
//!
//! The random numbers come in blocks from the caller (`Draws`), one transition, one loss and one jitter value
//! per offered frame whatever happens to it (common random numbers across configurations). The rig fills the
//! blocks from the same numpy streams as the Python model, so both draw identical losses and jitter.

use std::collections::HashMap;

/// The `refill` argument that asks for a block of the injected radio faults' draws (in `Draws::u_loss`) instead of
/// a link's: one stream for every impaired link, taken in the order of the offers.
pub const FAULT_DRAWS: usize = usize::MAX;

/// One block of per-frame random numbers.
#[derive(Debug, Default, Clone)]
pub struct Draws {
    pub u_step: Vec<f64>,
    pub u_loss: Vec<f64>,
    pub jitter_ns: Vec<i64>,
    pub next: usize,
}

impl Draws {
    fn exhausted(&self) -> bool {
        self.next >= self.u_step.len()
    }
}

/// Loss model of a link.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Loss {
    None,
    Bernoulli { p: f64 },
    GilbertElliott { p_gb: f64, p_bg: f64, loss_good: f64, loss_bad: f64 },
}

/// Counters of one link, in the order of `STAT_KEYS`.
#[derive(Debug, Default, Clone, Copy)]
pub struct LinkStats {
    pub offered: u64,
    pub delivered: u64,
    pub out_of_range: u64,
    pub blackout: u64,
    pub lost: u64,
    pub rate_capped: u64,
    /// Dropped by an injected fault (`Impairment`).
    pub fault: u64,
}

/// The injected radio faults of one link direction (hil/faults/radio.py): a blackout drops every frame, each burst
/// loss drops a frame with its probability (one draw each, in order, until one hits), latency adds up.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Impairment {
    pub blackout: bool,
    pub losses: Vec<f64>,
    pub extra_ns: i64,
}

/// The fault draws every impaired link takes from, in the order of the offers (one stream, as in Python).
#[derive(Debug, Clone, Default)]
pub struct FaultDraws {
    pub u: Vec<f64>,
    pub next: usize,
}

impl FaultDraws {
    /// How many draws are left.
    pub fn left(&self) -> usize {
        self.u.len() - self.next
    }

    /// Append a block, dropping the ones already taken.
    pub fn extend(&mut self, block: &[f64]) {
        self.u.drain(..self.next);
        self.next = 0;
        self.u.extend_from_slice(block);
    }

    fn take(&mut self) -> f64 {
        let u = self.u[self.next];
        self.next += 1;
        u
    }
}

impl Impairment {
    /// None: drop the frame; else the extra delay (ns). Needs `losses.len()` draws left in `draws`.
    fn apply(&self, draws: &mut FaultDraws) -> Option<i64> {
        if self.blackout {
            return None;
        }
        for &p in &self.losses {
            if draws.take() < p {
                return None;
            }
        }
        Some(self.extra_ns)
    }
}

/// One direction of a radio link.
#[derive(Debug, Clone)]
pub struct Link {
    pub name: String,
    pub range_m: f64,
    pub blackouts: Vec<(f64, f64)>,
    pub latency_ns: i64,
    pub period_ns: Option<i64>,
    pub loss: Loss,
    pub bad: bool,
    pub stats: LinkStats,
    pub draws: Draws,
    /// Injected faults (after range and tunnels, which are the physics; before the rate cap and the loss model).
    pub impairment: Option<Impairment>,
    next_token_ns: Option<i64>,
    last_offer_ns: Option<i64>,
    last_delivery_ns: i64,
}

impl Link {
    pub fn new(name: &str, range_m: f64, blackouts: Vec<(f64, f64)>, latency_ns: i64, period_ns: Option<i64>, loss: Loss,
               initially_bad: bool) -> Link {
        Link { name: name.into(), range_m, blackouts, latency_ns, period_ns, loss, bad: initially_bad,
               stats: LinkStats::default(), draws: Draws::default(), impairment: None, next_token_ns: None, last_offer_ns: None,
               last_delivery_ns: -(1i64 << 62) }
    }

    /// Whether the next offer needs a new block of draws first.
    pub fn needs_draws(&self) -> bool {
        self.draws.exhausted()
    }

    fn in_blackout(&self, pos: Option<f64>) -> bool {
        pos.is_some_and(|p| self.blackouts.iter().any(|&(start, end)| start <= p && p < end))
    }

    fn lost(&mut self, u_step: f64, u_loss: f64) -> bool {
        match self.loss {
            Loss::None => false,
            Loss::Bernoulli { p } => u_loss < p,
            Loss::GilbertElliott { p_gb, p_bg, loss_good, loss_bad } => {
                if self.bad {
                    if u_step < p_bg {
                        self.bad = false;
                    }
                } else if u_step < p_gb {
                    self.bad = true;
                }
                u_loss < if self.bad { loss_bad } else { loss_good }
            }
        }
    }

    fn take_token(&mut self, t_ns: i64) -> bool {
        let Some(period) = self.period_ns else { return true };
        if self.next_token_ns.is_some_and(|next| t_ns < next) {
            return false;
        }
        self.next_token_ns = Some(t_ns + period);
        true
    }

    /// Delivery time of a frame handed to the radio at `t_ns`, or None if it is dropped. The caller refills
    /// `draws` first when `needs_draws()`. Checks run range -> blackout -> rate cap -> loss; no overtaking.
    pub fn offer(&mut self, t_ns: i64, sender_pos: Option<f64>, receiver_pos: Option<f64>, faults: &mut FaultDraws) -> Option<i64> {
        self.last_offer_ns = Some(t_ns);
        self.stats.offered += 1;
        let k = self.draws.next;
        self.draws.next += 1;
        let lost = self.lost(self.draws.u_step[k], self.draws.u_loss[k]);
        if let (Some(s), Some(r)) = (sender_pos, receiver_pos) {
            if (s - r).abs() > self.range_m {
                self.stats.out_of_range += 1;
                return None;
            }
        }
        if !self.blackouts.is_empty() && (self.in_blackout(sender_pos) || self.in_blackout(receiver_pos)) {
            self.stats.blackout += 1;
            return None;
        }
        let mut extra = 0;
        if let Some(imp) = &self.impairment {
            match imp.apply(faults) {
                Some(ns) => extra = ns,
                None => {
                    self.stats.fault += 1;
                    return None;
                }
            }
        }
        if !self.take_token(t_ns) {
            self.stats.rate_capped += 1;
            return None;
        }
        if lost {
            self.stats.lost += 1;
            return None;
        }
        let deliver = (t_ns + self.latency_ns + self.draws.jitter_ns[k] + extra).max(self.last_delivery_ns);
        self.last_delivery_ns = deliver;
        self.stats.delivered += 1;
        Some(deliver)
    }
}

/// Why the gateway refused a route or an impairment.
#[derive(Debug, Clone, PartialEq)]
pub enum GatewayError {
    /// A link index that is not one of the gateway's.
    NoLink(String),
    /// A value out of its range.
    Invalid(String),
}

/// One compiled route: forward to `dst_bus` as `dst_id` over link `link`, whose reverse is `reverse`.
#[derive(Debug, Clone)]
pub struct Hop {
    pub dst_bus: usize,
    pub dst_id: u32,
    pub link: usize,
    pub reverse: Option<usize>,
}

/// Routes frames between buses over links, remembering each link's sender-end position.
#[derive(Debug, Default, Clone)]
pub struct Gateway {
    pub links: Vec<Link>,
    /// The draws of the injected burst losses (shared by every link, as the Python faults' one stream).
    pub fault_draws: FaultDraws,
    pub table: HashMap<(usize, u32), Vec<Hop>>,
    /// Last position carried by a frame forwarded over each link (its sender end).
    pub positions: Vec<Option<f64>>,
}

impl Gateway {
    pub fn add_link(&mut self, link: Link) -> usize {
        self.links.push(link);
        self.positions.push(None);
        self.links.len() - 1
    }

    pub fn add_route(&mut self, src_bus: usize, src_id: u32, hop: Hop) {
        self.table.entry((src_bus, src_id)).or_default().push(hop);
    }

    /// `add_route`, once its link and reverse link are known to exist.
    pub fn add_checked_route(&mut self, src_bus: usize, src_id: u32, hop: Hop) -> Result<(), GatewayError> {
        let n = self.links.len();
        if hop.link >= n || hop.reverse.is_some_and(|r| r >= n) {
            return Err(GatewayError::NoLink(format!("route {src_bus}:{src_id:#x}: no radio link {}", hop.link)));
        }
        self.add_route(src_bus, src_id, hop);
        Ok(())
    }

    /// Injected faults on link `link`: a blackout, burst losses (probabilities in [0, 1]), an extra latency; all
    /// off: no impairment.
    pub fn set_impairment(&mut self, link: usize, blackout: bool, losses: Vec<f64>, extra_ns: i64) -> Result<(), GatewayError> {
        let l = self.links.get_mut(link).ok_or_else(|| GatewayError::NoLink(format!("no radio link {link}")))?;
        if let Some(p) = losses.iter().find(|p| !(0.0..=1.0).contains(*p)) {
            return Err(GatewayError::Invalid(format!("radio link {}: loss probability {p} is not in [0, 1]", l.name)));
        }
        let on = blackout || !losses.is_empty() || extra_ns != 0;
        l.impairment = on.then_some(Impairment { blackout, losses, extra_ns });
        Ok(())
    }

    /// Offer a frame heard on `bus` at `t` ns (carrying position `pos`, if any) to every route of its ID:
    /// (destination bus, destination ID, delivery time ns) per frame the links deliver. `refill(link)` gives a
    /// link its next block of draws, `refill(FAULT_DRAWS)` a block of the injected faults' draws (in `u_loss`).
    pub fn forward<E>(&mut self, bus: usize, frame_id: u32, pos: Option<f64>, t: i64,
                      refill: &mut dyn FnMut(usize) -> Result<Draws, E>) -> Result<Vec<(usize, u32, i64)>, E> {
        let Some(hops) = self.table.get(&(bus, frame_id)) else { return Ok(Vec::new()) };
        let hops = hops.clone();
        let mut out = Vec::with_capacity(hops.len());
        for hop in hops {
            if pos.is_some() {
                self.positions[hop.link] = pos;
            }
            let sender = self.positions[hop.link];
            let receiver = hop.reverse.and_then(|r| self.positions[r]);
            if self.links[hop.link].needs_draws() {
                self.links[hop.link].draws = refill(hop.link)?;
            }
            let need = self.links[hop.link].impairment.as_ref().map_or(0, |imp| imp.losses.len());
            while self.fault_draws.left() < need {
                let block = refill(FAULT_DRAWS)?;
                self.fault_draws.extend(&block.u_loss);
            }
            if let Some(deliver) = self.links[hop.link].offer(t, sender, receiver, &mut self.fault_draws) {
                out.push((hop.dst_bus, hop.dst_id, deliver));
            }
        }
        Ok(out)
    }

    /// The IDs the gateway listens to on `bus`.
    pub fn ids_for_bus(&self, bus: usize) -> Vec<u32> {
        let mut ids: Vec<u32> = self.table.keys().filter(|(b, _)| *b == bus).map(|&(_, id)| id).collect();
        ids.sort_unstable();
        ids
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn draws(n: usize, u: f64, jitter: i64) -> Draws {
        Draws { u_step: vec![u; n], u_loss: vec![u; n], jitter_ns: vec![jitter; n], next: 0 }
    }

    #[test]
    fn a_route_or_impairment_naming_a_missing_link_or_a_bad_probability_is_refused() {
        let mut g = Gateway::default();
        let l = g.add_link(Link::new("1>2", 1e4, vec![], 0, None, Loss::None, false));
        assert!(g.add_checked_route(0, 0x100, Hop { dst_bus: 1, dst_id: 0x300, link: l, reverse: Some(1) }).is_err());
        assert!(g.table.is_empty());
        assert_eq!(g.add_checked_route(0, 0x100, Hop { dst_bus: 1, dst_id: 0x300, link: l, reverse: None }), Ok(()));
        assert!(matches!(g.set_impairment(0, false, vec![1.5], 0), Err(GatewayError::Invalid(_))));
        assert!(matches!(g.set_impairment(3, true, vec![], 0), Err(GatewayError::NoLink(_))));
        assert_eq!(g.set_impairment(0, false, vec![0.5], 10), Ok(()));
        assert_eq!(g.links[0].impairment, Some(Impairment { blackout: false, losses: vec![0.5], extra_ns: 10 }));
        assert_eq!(g.set_impairment(0, false, vec![], 0), Ok(()));
        assert_eq!(g.links[0].impairment, None);
    }

    #[test]
    fn latency_jitter_and_no_overtaking() {
        let mut l = Link::new("1>2", 1e4, vec![], 1_000, None, Loss::None, false);
        l.draws = Draws { u_step: vec![0.5; 2], u_loss: vec![0.5; 2], jitter_ns: vec![500, 0], next: 0 };
        let f = &mut FaultDraws::default();
        assert_eq!(l.offer(0, None, None, f), Some(1_500));
        assert_eq!(l.offer(100, None, None, f), Some(1_500)); // would be 1100: waits behind the first
        assert!(l.needs_draws());
    }

    #[test]
    fn range_blackout_rate_cap_and_loss_in_order() {
        let mut l = Link::new("1>2", 100.0, vec![(50.0, 60.0)], 0, Some(1_000), Loss::Bernoulli { p: 0.3 }, false);
        l.draws = draws(8, 0.5, 0);
        let f = &mut FaultDraws::default();
        assert_eq!(l.offer(0, Some(0.0), Some(200.0), f), None);
        assert_eq!(l.stats.out_of_range, 1);
        assert_eq!(l.offer(1, Some(55.0), Some(0.0), f), None);
        assert_eq!(l.stats.blackout, 1);
        assert_eq!(l.offer(2, Some(0.0), Some(0.0), f), Some(2));
        assert_eq!(l.offer(3, Some(0.0), Some(0.0), f), None); // within the rate-cap period
        assert_eq!(l.stats.rate_capped, 1);
        l.draws.u_loss[4] = 0.1;
        assert_eq!(l.offer(2_000, None, None, f), None);
        assert_eq!(l.stats.lost, 1);
        assert_eq!(l.stats.offered, 5);
    }

    #[test]
    fn gilbert_elliott_steps_before_the_loss_draw() {
        let ge = Loss::GilbertElliott { p_gb: 0.5, p_bg: 0.1, loss_good: 0.0, loss_bad: 1.0 };
        let mut l = Link::new("1>2", 1e9, vec![], 0, None, ge, false);
        l.draws = Draws { u_step: vec![0.4, 0.9, 0.05], u_loss: vec![0.5; 3], jitter_ns: vec![0; 3], next: 0 };
        let f = &mut FaultDraws::default();
        assert_eq!(l.offer(0, None, None, f), None); // good -> bad (0.4 < 0.5), then lost
        assert_eq!(l.offer(1, None, None, f), None); // stays bad
        assert_eq!(l.offer(2, None, None, f), Some(2)); // bad -> good (0.05 < 0.1)
    }

    #[test]
    fn an_impairment_drops_or_delays_after_the_physics_and_before_the_rate_cap() {
        let mut l = Link::new("1>2", 1e9, vec![], 1_000, Some(1_000), Loss::None, false);
        l.draws = draws(8, 0.5, 0);
        let f = &mut FaultDraws { u: vec![0.9, 0.1, 0.9], next: 0 };
        l.impairment = Some(Impairment { blackout: false, losses: vec![0.5], extra_ns: 250 });
        assert_eq!(l.offer(0, None, None, f), Some(1_250)); // draw 0.9 >= 0.5: kept, 250 ns later
        assert_eq!(l.offer(5_000, None, None, f), None); // draw 0.1 < 0.5: dropped by the fault ...
        assert_eq!((l.stats.fault, l.stats.rate_capped), (1, 0)); // ... before it took a rate-cap token
        assert_eq!(l.offer(5_001, None, None, f), Some(6_251));
        l.impairment = Some(Impairment { blackout: true, losses: vec![], extra_ns: 0 });
        assert_eq!(l.offer(9_000, None, None, f), None);
        assert_eq!((l.stats.fault, f.left()), (2, 0)); // a blackout takes no draw
    }
}
