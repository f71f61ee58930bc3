//! Rays, and the per-ray constants that traversal and the watertight triangle test
//! precompute once instead of per node or per triangle.

use glam::{Vec3, Vec3A};

use crate::simd::F32x8;

#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: Vec3A,
    /// Not necessarily unit length: shadow rays use the segment to the light as direction.
    pub dir: Vec3A,
    /// Hits must lie in (0, tmax), measured in units of `dir`.
    pub tmax: f32,
}

impl Ray {
    pub fn new(origin: Vec3A, dir: Vec3A, tmax: f32) -> Ray {
        Ray { origin, dir, tmax }
    }

    pub fn infinite(origin: Vec3, dir: Vec3) -> Ray {
        Ray {
            origin: origin.into(),
            dir: dir.into(),
            tmax: f32::INFINITY,
        }
    }

    pub fn at(&self, t: f32) -> Vec3A {
        self.origin + self.dir * t
    }
}

/// Reciprocals that stay finite: a zero or denormal direction component gives a huge value of
/// the right sign instead of infinity, so that `0 * inv` is 0, never NaN. All three lanes at
/// once, without a branch (each lane is the correctly rounded `1 / x` or `±1e20`).
#[inline(always)]
fn safe_recip(x: Vec3A) -> Vec3A {
    const LIMIT: f32 = 1e-20;
    let tiny = x.abs().cmplt(Vec3A::splat(LIMIT));
    Vec3A::select(tiny, Vec3A::splat(1e20).copysign(x), Vec3A::ONE / x)
}

/// Bytes between two plane arrays of a node: plane indices are kept multiplied by this, so
/// that the box test adds them to the node's address as they are (x86 addressing scales an
/// index by at most 8; an index of arrays of 32 bytes would cost a shift per plane and node
/// wherever the walk has no spare register to keep the shifted values in).
pub const PLANE_BYTES: usize = 32;

/// Per sign pattern of the inverse direction (bit k set: axis k's inverse is >= 0), the byte
/// offsets of the plane arrays the ray meets first (near) and last (far) on each axis.
const PLANE_OFFSETS: [([usize; 3], [usize; 3]); 8] = {
    let mut table = [([0; 3], [0; 3]); 8];
    let mut signs = 0;
    while signs < 8 {
        let mut k = 0;
        while k < 3 {
            let positive = (signs >> k) & 1;
            table[signs].0[k] = (2 * k + 1 - positive) * PLANE_BYTES;
            table[signs].1[k] = (2 * k + positive) * PLANE_BYTES;
            k += 1;
        }
        signs += 1;
    }
    table
};

/// The watertight test's axes (x, y, z) by the axis of largest |dir| and whether the
/// direction is negative along it (which swaps x and y to keep the winding).
const AXES: [[usize; 3]; 6] = [
    [1, 2, 0],
    [2, 1, 0],
    [2, 0, 1],
    [0, 2, 1],
    [0, 1, 2],
    [1, 0, 2],
];

#[derive(Clone, Copy, Debug)]
pub struct RayQuery {
    pub origin: Vec3A,
    pub dir: Vec3A,
    /// Watertight test: the shear of the axes (x, y) onto the axis of largest |dir| (z).
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
    /// Box test ([`crate::accel`]), in lanes: per axis the inverse direction, and
    /// `-origin * inv_dir` less (near plane distances) or plus (far ones) the bound of its
    /// own rounding.
    pub inv8: [F32x8; 3],
    pub near_off8: [F32x8; 3],
    pub far_off8: [F32x8; 3],
    /// The watertight test's axes: x, y, then z (the axis of largest |dir|).
    axes: [usize; 3],
    /// Per axis, where in a node's planes the array the ray meets first and last begins, in
    /// bytes (pre-scaled, see [`PLANE_BYTES`]).
    near_plane: [usize; 3],
    far_plane: [usize; 3],
    /// Whether the ray and its box constants are finite numbers. A ray that is not (a NaN or
    /// infinite origin or direction, or an origin so far out that `origin / dir` overflows)
    /// meets nothing: its box distances could be NaN, and NaN compares so that an empty
    /// child slot, which no finite ray enters, might be entered, and the walk might loop.
    finite: bool,
}

impl RayQuery {
    /// Everything is computed three lanes at once and the small choices are table lookups:
    /// one of these is made per ray (camera, bounce and shadow rays alike), so it costs as
    /// much as the first levels of the walk.
    #[inline(always)]
    pub fn new(ray: &Ray) -> RayQuery {
        let d = ray.dir;
        let inv = safe_recip(d);
        let abs = d.abs();
        let kz = if abs.x > abs.y {
            if abs.x > abs.z { 0 } else { 2 }
        } else if abs.y > abs.z {
            1
        } else {
            2
        };
        let dir = d.to_array();
        let dz = dir[kz];
        let axes = AXES[2 * kz + usize::from(dz < 0.0)];
        let sz = 1.0 / dz;
        // `r` and the sums below each round by half an ulp of their size: the slack moves
        // the near offset down and the far one up by more than that.
        let r = ray.origin * inv;
        let slack = r.abs() * (3.0 * f32::EPSILON * 0.5);
        let (near, far) = (-r - slack, -r + slack);
        let signs = inv.cmpge(Vec3A::ZERO).bitmask() as usize & 7;
        let (near_plane, far_plane) = PLANE_OFFSETS[signs];
        // x * 0 is 0 for a finite x and NaN otherwise: one test for all nine numbers (an
        // origin that is not finite makes `near` so, unless `dir` is infinite, tested here).
        let finite = (near * 0.0 + far * 0.0 + d * 0.0).is_finite() && !ray.tmax.is_nan();
        let lanes = |v: Vec3A| [F32x8::splat(v.x), F32x8::splat(v.y), F32x8::splat(v.z)];
        RayQuery {
            origin: ray.origin,
            dir: d,
            sx: dir[axes[0]] * sz,
            sy: dir[axes[1]] * sz,
            sz,
            inv8: lanes(inv),
            near_off8: lanes(near),
            far_off8: lanes(far),
            axes,
            near_plane,
            far_plane,
            finite,
        }
    }

    /// Whether the ray can meet anything (see the field): the walks test this once.
    #[inline(always)]
    pub fn is_finite(&self) -> bool {
        self.finite
    }

    /// The watertight test's axes: x, y, then z (the axis of largest |dir|); each below 3.
    #[inline(always)]
    pub fn axes(&self) -> [usize; 3] {
        self.axes
    }

    /// Per axis, the byte offsets within a node's planes of the plane arrays the ray meets
    /// first and last: multiples of [`PLANE_BYTES`], each below `6 * PLANE_BYTES`.
    #[inline(always)]
    pub fn planes(&self) -> ([usize; 3], [usize; 3]) {
        (self.near_plane, self.far_plane)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tables give what the definitions say: the axis of largest |dir| last, x and y
    /// swapped when the direction is negative along it; per axis, the minimum plane first
    /// when the direction is positive.
    #[test]
    fn axes_and_planes_follow_the_direction() {
        for (dir, axes) in [
            (Vec3::new(3.0, 1.0, -2.0), [1, 2, 0]),
            (Vec3::new(-3.0, 1.0, 2.0), [2, 1, 0]),
            (Vec3::new(0.5, 1.0, -0.0), [2, 0, 1]),
            (Vec3::new(0.5, -1.0, 0.0), [0, 2, 1]),
            (Vec3::new(0.0, 0.0, 1.0), [0, 1, 2]),
            (Vec3::new(0.1, -0.2, -1.0), [1, 0, 2]),
        ] {
            let q = RayQuery::new(&Ray::infinite(Vec3::ZERO, dir));
            assert_eq!(q.axes(), axes, "{dir}");
            let (near, far) = q.planes();
            for k in 0..3 {
                let positive = usize::from(1.0f32.copysign(dir[k]) > 0.0);
                assert_eq!(
                    near[k],
                    (2 * k + 1 - positive) * PLANE_BYTES,
                    "{dir} axis {k}"
                );
                assert_eq!(far[k], (2 * k + positive) * PLANE_BYTES, "{dir} axis {k}");
            }
        }
    }
}
