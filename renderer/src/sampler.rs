//! Random numbers keyed on what they are for, never on who draws them.
//!
//! Every value is a hash of (seed, pixel, sample index, dimension), where the dimension is
//! fixed by the bounce and the purpose of the draw. A pixel therefore gets the same numbers
//! whichever thread, tile, subscreen or node renders it, which is what makes images
//! byte-identical across every way of dividing the work.

/// Dimensions reserved per bounce. Draws within a bounce past this budget spill into the
/// next bounce's range only if an integrator uses more than this many, which none does.
pub const DIMS_PER_BOUNCE: u32 = 16;
/// Dimensions reserved for the camera (pixel position, lens).
const CAMERA_DIMS: u32 = 4;

#[inline(always)]
fn mix64(mut z: u64) -> u64 {
    // splitmix64 finaliser: a bijection with full avalanche.
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[derive(Clone, Copy, Debug)]
pub struct Sampler {
    key: u64,
    dim: u32,
}

impl Sampler {
    pub fn new(seed: u64, px: u32, py: u32, sample: u32) -> Sampler {
        let pixel = ((py as u64) << 32) | px as u64;
        let key = mix64(mix64(mix64(seed ^ 0x6a09_e667_f3bc_c909) ^ pixel) ^ sample as u64);
        Sampler { key, dim: 0 }
    }

    /// Moves to the dimensions of bounce `bounce` (0 = the camera ray's first hit).
    #[inline]
    pub fn start_bounce(&mut self, bounce: u32) {
        self.dim = CAMERA_DIMS + bounce.saturating_mul(DIMS_PER_BOUNCE);
    }

    #[inline]
    fn next_u64(&mut self) -> u64 {
        let h = mix64(self.key ^ (self.dim as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        self.dim = self.dim.wrapping_add(1);
        h
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn get_1d(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    #[inline]
    pub fn get_2d(&mut self) -> (f32, f32) {
        let h = self.next_u64();
        let a = (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32);
        let b = ((h >> 8) & 0xff_ffff) as f32 * (1.0 / (1u64 << 24) as f32);
        (a, b)
    }

    /// The position of the sample within its pixel.
    #[inline]
    pub fn pixel_2d(&mut self) -> (f32, f32) {
        self.dim = 0;
        self.get_2d()
    }

    /// A value keyed on this sample and on arbitrary ids rather than on the dimension
    /// budget, for draws whose number is open-ended (stochastic transparency: one per
    /// surface crossed) or whose order is not fixed (traversal visits surfaces in any order).
    #[inline]
    pub fn keyed(&self, bounce: u32, a: u32, b: u32) -> f32 {
        let h = mix64(
            self.key
                ^ mix64(
                    ((bounce as u64) << 32 | a as u64) ^ mix64(b as u64 ^ 0xa5a5_5a5a_dead_beef),
                ),
        );
        (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_key_same_numbers() {
        let mut a = Sampler::new(7, 10, 20, 3);
        let mut b = Sampler::new(7, 10, 20, 3);
        a.start_bounce(2);
        b.start_bounce(2);
        assert_eq!(a.get_2d(), b.get_2d());
        assert_eq!(a.get_1d(), b.get_1d());
    }

    #[test]
    fn uniform_mean_and_range() {
        let mut sum = 0.0f64;
        let n = 100_000;
        for i in 0..n {
            let mut s = Sampler::new(1, i % 317, i / 317, i);
            s.start_bounce(0);
            let v = s.get_1d();
            assert!((0.0..1.0).contains(&v));
            sum += v as f64;
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.005);
    }
}
