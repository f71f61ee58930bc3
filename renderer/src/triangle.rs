//! Watertight ray-triangle intersection (Woop, Benthin and Wald, JCGT 2013).
//!
//! The ray is sheared so that it runs along +Z through the origin; the edge functions of the
//! triangle's projection are then evaluated in a way that gives the same answer for the same
//! edge whichever of its two triangles is tested, so no ray slips between neighbours. When
//! an edge function rounds to exactly zero it is recomputed in f64, as the paper prescribes.

use glam::Vec3A;

use crate::{math::gamma, ray::RayQuery};

/// Where a ray met a triangle: the ray parameter and barycentric weights of v0, v1, v2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub b0: f32,
    pub b1: f32,
    pub b2: f32,
}

/// Returns the hit with `0 < t < tmax`, if any. Back faces are hit too; culling is a
/// material decision, not a geometric one.
#[inline(always)]
pub fn intersect(q: &RayQuery, v0: Vec3A, v1: Vec3A, v2: Vec3A, tmax: f32) -> Option<TriHit> {
    intersect_upto(q, v0, v1, v2, tmax).filter(|h| h.t < tmax)
}

/// Returns the hit with `0 < t <= tmax`, if any: the closest-hit kernel admits a hit at
/// exactly the best distance so far, to break the tie by triangle index.
///
/// The operations are those of the lane kernel ([`crate::accel`]), in the same order
/// and with the same fused multiply-adds, so the two give the same bits: the kernel filters
/// four or eight triangles at once and this function makes the final decision for a candidate. The
/// shear of each vertex may be fused (it is the same computation for a vertex in every
/// triangle that shares it); the edge functions must not be, or the two triangles of an
/// edge would no longer compute exactly opposite values for it.
#[inline(always)]
pub fn intersect_upto(q: &RayQuery, v0: Vec3A, v1: Vec3A, v2: Vec3A, tmax: f32) -> Option<TriHit> {
    let [kx, ky, kz] = q.axes();
    let a = v0 - q.origin;
    let b = v1 - q.origin;
    let c = v2 - q.origin;

    let ax = (-q.sx).mul_add(a[kz], a[kx]);
    let ay = (-q.sy).mul_add(a[kz], a[ky]);
    let bx = (-q.sx).mul_add(b[kz], b[kx]);
    let by = (-q.sy).mul_add(b[kz], b[ky]);
    let cx = (-q.sx).mul_add(c[kz], c[kx]);
    let cy = (-q.sy).mul_add(c[kz], c[ky]);

    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;

    if u == 0.0 || v == 0.0 || w == 0.0 {
        let (ax, ay, bx, by, cx, cy) = (
            ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64,
        );
        u = (cx * by - cy * bx) as f32;
        v = (ax * cy - ay * cx) as f32;
        w = (bx * ay - by * ax) as f32;
    }

    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }

    let az = q.sz * a[kz];
    let bz = q.sz * b[kz];
    let cz = q.sz * c[kz];
    let t_scaled = u.mul_add(az, v.mul_add(bz, w * cz));

    // Compare t against (0, tmax] without dividing, in the sign of det.
    let det_sign = det.to_bits() & 0x8000_0000;
    let t_signed = f32::from_bits(t_scaled.to_bits() ^ det_sign);
    let det_abs = det.abs();
    if !(t_signed > 0.0) || t_signed > tmax * det_abs {
        return None;
    }

    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    if !(t > 0.0 && t <= tmax) {
        return None;
    }

    // Conservatively positive t (pbrt-v4's bound on the rounding error of t): a hit closer
    // than the error of its own computation may be the surface the ray just left.
    let max_z = az.abs().max(bz.abs()).max(cz.abs());
    let max_x = ax.abs().max(bx.abs()).max(cx.abs());
    let max_y = ay.abs().max(by.abs()).max(cy.abs());
    let delta_z = gamma(3) * max_z;
    let delta_x = gamma(5) * (max_x + max_z);
    let delta_y = gamma(5) * (max_y + max_z);
    let delta_e = 2.0 * (gamma(2) * max_x * max_y + delta_y * max_x + delta_x * max_y);
    let max_e = u.abs().max(v.abs()).max(w.abs());
    let delta_t =
        3.0 * (gamma(3) * max_e * max_z + delta_e * max_z + delta_z * max_e) * inv_det.abs();
    if t <= delta_t {
        return None;
    }
    Some(TriHit {
        t,
        b0: u * inv_det,
        b1: v * inv_det,
        b2: w * inv_det,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ray::Ray;
    use glam::Vec3;

    fn q(o: Vec3, d: Vec3) -> RayQuery {
        RayQuery::new(&Ray::infinite(o, d))
    }

    #[test]
    fn hits_centre_and_reports_barycentrics() {
        let (v0, v1, v2) = (
            Vec3A::new(-1.0, -1.0, 0.0),
            Vec3A::new(1.0, -1.0, 0.0),
            Vec3A::new(0.0, 1.0, 0.0),
        );
        let hit = intersect(
            &q(Vec3::new(0.0, 0.0, 5.0), -Vec3::Z),
            v0,
            v1,
            v2,
            f32::INFINITY,
        )
        .expect("hit");
        assert!((hit.t - 5.0).abs() < 1e-6);
        let p = v0 * hit.b0 + v1 * hit.b1 + v2 * hit.b2;
        assert!(p.length() < 1e-6);
        assert!((hit.b0 + hit.b1 + hit.b2 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn misses_outside_and_behind() {
        let (v0, v1, v2) = (
            Vec3A::new(-1.0, -1.0, 0.0),
            Vec3A::new(1.0, -1.0, 0.0),
            Vec3A::new(0.0, 1.0, 0.0),
        );
        assert!(intersect(&q(Vec3::new(2.0, 0.0, 5.0), -Vec3::Z), v0, v1, v2, 1e30).is_none());
        assert!(intersect(&q(Vec3::new(0.0, 0.0, 5.0), Vec3::Z), v0, v1, v2, 1e30).is_none());
        assert!(intersect(&q(Vec3::new(0.0, 0.0, 5.0), -Vec3::Z), v0, v1, v2, 4.0).is_none());
    }

    #[test]
    fn shared_edge_is_hit_exactly_once_or_more_never_zero() {
        // Two triangles sharing the diagonal of a unit square; rays aimed exactly at it.
        let a = Vec3A::new(0.0, 0.0, 0.0);
        let b = Vec3A::new(1.0, 0.0, 0.0);
        let c = Vec3A::new(1.0, 1.0, 0.0);
        let d = Vec3A::new(0.0, 1.0, 0.0);
        // Interior points of the diagonal (its ends are corners of the square's outline,
        // where a ray may legitimately pass outside).
        for i in 1..1000 {
            let s = i as f32 / 1000.0;
            let dir = Vec3::new(0.123, -0.07, -1.0);
            let origin = Vec3::new(s, s, 0.0) - dir * 3.0;
            let qq = q(origin, dir);
            let h1 = intersect(&qq, a, b, c, 1e30).is_some();
            let h2 = intersect(&qq, a, c, d, 1e30).is_some();
            assert!(h1 || h2, "ray {i} slipped through the shared edge");
        }
    }
}
