//! Helpers shared by the unit tests of several modules.

use glam::Vec3;

/// A small deterministic generator (the tests need no statistical quality).
pub(crate) struct Lcg(pub u64);

impl Lcg {
    /// Uniform in [0, 1).
    pub fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in the cube of half-side `scale` around the origin.
    pub fn vec(&mut self, scale: f32) -> Vec3 {
        Vec3::new(self.next(), self.next(), self.next()) * 2.0 * scale - scale
    }
}
