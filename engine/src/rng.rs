//! numpy's default bit generator (PCG64, XSL-RR 128/64) and its `Generator.random()`, so a random stream handed
//! over from Python (`Generator.bit_generator.state`) goes on in the engine exactly as it would have in numpy.

/// PCG64 as numpy implements it: a 128-bit LCG stepped before each output, XSL-RR output.
#[derive(Debug, Clone, Copy)]
pub struct Pcg64 {
    state: u128,
    inc: u128,
}

const MULTIPLIER: u128 = 0x2360_ED05_1FC6_5DA4_4385_DF64_9FCC_F645;

impl Pcg64 {
    /// The generator in the state numpy reports (`bit_generator.state["state"]`: `state` and `inc`).
    pub fn from_state(state: u128, inc: u128) -> Pcg64 {
        Pcg64 { state, inc }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_mul(MULTIPLIER).wrapping_add(self.inc);
        let s = self.state;
        (((s >> 64) as u64) ^ (s as u64)).rotate_right((s >> 122) as u32)
    }

    /// A double in [0, 1): numpy's `Generator.random()` (the top 53 bits).
    pub fn random(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }

    /// An integer in [0, n) from one `random()`: the portable draw both bus models make (floor of u * n).
    pub fn below(&mut self, n: u32) -> u32 {
        (self.random() * n as f64) as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continues_numpys_stream() {
        // np.random.default_rng(12345): its state, then .random(3)
        let mut g = Pcg64::from_state(33261208707367790463622745601869196757, 268209174141567072605526753992732310247);
        assert_eq!([g.random(), g.random(), g.random()], [0.22733602246716966, 0.31675833970975287, 0.7973654573327341]);
    }
}
