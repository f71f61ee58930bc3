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
#[inline]
fn safe_recip(x: Vec3A) -> [f32; 3] {
    const LIMIT: f32 = 1e-20;
    let tiny = x.abs().cmplt(Vec3A::splat(LIMIT));
    Vec3A::select(tiny, Vec3A::splat(1e20).copysign(x), Vec3A::ONE / x).to_array()
}

/// A ray with everything the walk and the triangle tests need, computed once per ray.
///
/// The axis and plane indices are private so that they keep the bounds [`RayQuery::new`]
/// gives them (an axis below 3, a plane below 6), which lets the kernels index with them
/// unchecked.
#[derive(Clone, Copy, Debug)]
pub struct RayQuery {
    pub origin: Vec3A,
    pub dir: Vec3A,
    /// Watertight test: the shear of the axes (x, y) onto the axis of largest |dir| (z).
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
    /// Box test ([`crate::accel`]), in lanes: per axis the inverse direction, and
    /// `-origin * inv_dir` less and plus the bound of its own rounding (the offsets of the
    /// near and far plane distances).
    pub inv8: [F32x8; 3],
    pub near_off8: [F32x8; 3],
    pub far_off8: [F32x8; 3],
    /// The watertight test's axes: x, y, then z (the axis of largest |dir|).
    axes: [usize; 3],
    /// Per axis, which of a node's six plane arrays the ray meets first and last.
    near_plane: [usize; 3],
    far_plane: [usize; 3],
}

impl RayQuery {
    pub fn new(ray: &Ray) -> RayQuery {
        let d = ray.dir;
        let dir = d.to_array();
        let inv = safe_recip(d);
        let abs = d.abs();
        let kz = if abs.x > abs.y {
            if abs.x > abs.z { 0 } else { 2 }
        } else if abs.y > abs.z {
            1
        } else {
            2
        };
        let (mut kx, mut ky) = [(1, 2), (2, 0), (0, 1)][kz];
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sz = 1.0 / dir[kz];
        let origin = ray.origin.to_array();
        let r = [0, 1, 2].map(|k| origin[k] * inv[k]);
        // `r` and the sums below each round by half an ulp of their size.
        let slack = r.map(|r| r.abs() * (3.0 * f32::EPSILON * 0.5));
        let positive = inv.map(|i| usize::from(i >= 0.0));
        RayQuery {
            origin: ray.origin,
            dir: d,
            sx: dir[kx] * sz,
            sy: dir[ky] * sz,
            sz,
            inv8: inv.map(F32x8::splat),
            near_off8: [0, 1, 2].map(|k| F32x8::splat(-r[k] - slack[k])),
            far_off8: [0, 1, 2].map(|k| F32x8::splat(-r[k] + slack[k])),
            axes: [kx, ky, kz],
            near_plane: [0, 2, 4].map(|p| p + 1 - positive[p / 2]),
            far_plane: [0, 2, 4].map(|p| p + positive[p / 2]),
        }
    }

    /// The watertight test's axes: x, y, then z (the axis of largest |dir|); each below 3.
    #[inline(always)]
    pub fn axes(&self) -> [usize; 3] {
        self.axes
    }

    /// Per axis, the plane arrays of a node the ray meets first and last; each below 6.
    #[inline(always)]
    pub fn planes(&self) -> ([usize; 3], [usize; 3]) {
        (self.near_plane, self.far_plane)
    }
}
