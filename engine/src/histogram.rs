//! Durations in log-linear bins, for the bus server's latency and lateness figures.

/// Durations in log-linear bins (1 us wide below 1.024 ms, then 1/512 of the value): bounded memory, exact max.
#[derive(Debug, Clone)]
pub struct Histogram {
    counts: Vec<u64>,
    pub n: u64,
    pub max_ns: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram { counts: vec![0; 1024 + 40 * 512], n: 0, max_ns: 0 }
    }
}

impl Histogram {
    pub fn add(&mut self, ns: i64) {
        let ns = ns.max(0) as u64;
        let us = ns / 1000;
        let i = if us < 1024 {
            us as usize
        } else {
            let e = (64 - us.leading_zeros()) as u64 - 10;
            (1024 + (e - 1) * 512 + (us >> e) - 512) as usize
        };
        let last = self.counts.len() - 1;
        self.counts[i.min(last)] += 1;
        self.n += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    fn upper_us(i: usize) -> u64 {
        if i < 1024 {
            return i as u64 + 1;
        }
        let (e, m) = ((i - 1024) / 512, (i - 1024) % 512);
        ((m + 512 + 1) as u64) << (e + 1)
    }

    /// Upper edge of the bin holding quantile q (capped at the maximum), in seconds.
    pub fn quantile_s(&self, q: f64) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let rank = q * self.n as f64;
        let mut seen = 0u64;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if c > 0 && seen as f64 >= rank {
                return Some((Self::upper_us(i) as f64 * 1e-6).min(self.max_ns as f64 * 1e-9));
            }
        }
        Some(self.max_ns as f64 * 1e-9)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_quantiles_and_max() {
        let mut h = Histogram::default();
        for us in 1..=100 {
            h.add(us * 1000);
        }
        assert_eq!(h.n, 100);
        assert!((h.quantile_s(0.5).unwrap() - 50e-6).abs() < 2e-6);
        assert_eq!(h.quantile_s(1.0).unwrap(), 100e-6);
        h.add(5_000_000);
        assert_eq!(h.max_ns, 5_000_000);
    }
}
