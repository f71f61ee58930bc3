//! Rays, and the per-ray constants that traversal and the watertight triangle test
//! precompute once instead of per node or per triangle.

use glam::{Vec3, Vec3A};

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

/// Reciprocal that stays finite: a zero or denormal direction component gives a huge value of
/// the right sign instead of infinity, so that `0 * inv` is 0, never NaN.
#[inline]
fn safe_recip(x: f32) -> f32 {
    const LIMIT: f32 = 1e-20;
    if x.abs() < LIMIT {
        1e20f32.copysign(x)
    } else {
        1.0 / x
    }
}

/// A ray with everything the traversal needs precomputed.
#[derive(Clone, Copy, Debug)]
pub struct RayQuery {
    pub origin: Vec3A,
    pub dir: Vec3A,
    pub inv_dir: Vec3A,
    /// Octant of the direction, in the encoding the wide BVH uses to order children.
    pub oct_inv4: u32,
    /// Watertight test: the axis of largest |dir| and the other two, and the shear.
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
}

impl RayQuery {
    pub fn new(ray: &Ray) -> RayQuery {
        let d = ray.dir;
        let inv_dir = Vec3A::new(safe_recip(d.x), safe_recip(d.y), safe_recip(d.z));
        let oct_inv4 = (if d.x < 0.0 { 0 } else { 0x0404_0404 })
            | (if d.y < 0.0 { 0 } else { 0x0202_0202 })
            | (if d.z < 0.0 { 0 } else { 0x0101_0101 });
        let abs = d.abs();
        let kz = if abs.x > abs.y {
            if abs.x > abs.z { 0 } else { 2 }
        } else if abs.y > abs.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if d[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sz = 1.0 / d[kz];
        RayQuery {
            origin: ray.origin,
            dir: d,
            inv_dir,
            oct_inv4,
            kx,
            ky,
            kz,
            sx: d[kx] * sz,
            sy: d[ky] * sz,
            sz,
        }
    }
}
