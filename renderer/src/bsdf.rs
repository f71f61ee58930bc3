//! The glTF 2.0 metallic-roughness BSDF (specification, appendix B), importance sampled.
//!
//! ```text
//! material   = mix(dielectric, metal, metallic)
//! metal      = conductor_fresnel(f0 = baseColor) * specular_brdf(alpha)
//! dielectric = fresnel_mix(base  = mix(diffuse(baseColor), specular_btdf(alpha), transmission),
//!                          layer = specular_brdf(alpha))
//! ```
//!
//! with alpha = roughness^2, GGX (Trowbridge-Reitz) microfacets, height-correlated Smith
//! masking-shadowing, Schlick Fresnel, KHR_materials_specular for the dielectric F0/F90 and
//! KHR_materials_ior for the dielectric F0. Refracting volumes (KHR_materials_volume with a
//! thickness) use the exact dielectric Fresnel term instead of Schlick's, because Schlick's
//! approximation knows nothing of total internal reflection and light leaving glass needs it.
//!
//! One deliberate departure from the appendix: the diffuse base is weighted by albedo scaling,
//! `(1 - E(mu_o)) (1 - E(mu_i)) / (1 - E_avg)` with `E` the directional albedo of the
//! specular layer, instead of `1 - F(VdotH)`. The appendix's weight lets a white surface
//! reflect more than it receives at grazing angles (up to about 11% more at roughness 0.5);
//! albedo scaling keeps the sum at exactly what the specular layer leaves, stays reciprocal,
//! and is the same at normal incidence. Both layers are otherwise as specified.
//!
//! All directions point away from the surface. Lobes are sampled by a cheap estimate of their
//! weight at `wo`; GGX lobes use visible-normal sampling (Heitz 2018). Roughness so low that
//! the distribution is numerically a spike is treated as a perfect mirror or refraction.

use glam::Vec3;

use crate::{
    material::ShadingParams,
    math::{Frame, INV_PI, PI, luminance, safe_sqrt, sincos_quarter_pi, sincos_turn},
};

/// Below this alpha (= roughness^2) a GGX lobe is treated as a delta distribution.
const DELTA_ALPHA: f32 = 1e-3;

#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    frame: Frame,
    /// Geometric normal turned to the side of `wo`.
    ng: Vec3,
    base: Vec3,
    metallic: f32,
    alpha: f32,
    f0: Vec3,
    f90: f32,
    transmission: f32,
    /// Index of refraction of the far side over the near (wo) side.
    eta: f32,
    volume: bool,
    /// Specular-layer albedo at wo (for lobe selection) and its hemispherical average.
    albedo_o: Vec3,
    albedo_avg: Vec3,
    /// Lobe selection probabilities at the `wo` this BSDF was made for.
    p_diffuse: f32,
    p_specular: f32,
    p_transmit: f32,
    /// Nothing but the diffuse base (no metal, no specular layer, no transmission): the
    /// commonest surface, evaluated and sampled without any glossy or layering terms.
    lambert: bool,
}

#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    pub wi: Vec3,
    /// f * |cos| / pdf: the factor the path throughput is multiplied by.
    pub weight: Vec3,
    /// Solid-angle density of the whole mixture, for MIS; meaningless when `delta`.
    pub pdf: f32,
    pub delta: bool,
    pub transmitted: bool,
}

#[inline]
fn schlick_weight(cos: f32) -> f32 {
    let m = (1.0 - cos).clamp(0.0, 1.0);
    let m2 = m * m;
    m2 * m2 * m
}

/// Exact Fresnel reflectance of an unpolarised dielectric interface; `eta` is the index of
/// the far side over the near side, `cos_i` the cosine on the near side.
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = safe_sqrt(1.0 - sin2_t);
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

#[inline]
fn ggx_d(m: Vec3, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let c2 = m.z * m.z;
    let d = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

#[inline]
fn ggx_lambda(w: Vec3, alpha: f32) -> f32 {
    let c2 = w.z * w.z;
    let s2 = (1.0 - c2).max(0.0);
    if c2 == 0.0 {
        return f32::INFINITY;
    }
    let tan2 = s2 / c2;
    0.5 * (-1.0 + (1.0 + alpha * alpha * tan2).sqrt())
}

#[inline]
fn ggx_g1(w: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, alpha))
}

/// Height-correlated masking-shadowing.
#[inline]
fn ggx_g2(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// Density of visible normals seen from `wo` (wo.z > 0).
#[inline]
fn ggx_d_visible(wo: Vec3, m: Vec3, alpha: f32) -> f32 {
    ggx_g1(wo, alpha) * wo.dot(m).max(0.0) * ggx_d(m, alpha) / wo.z
}

/// Samples a visible normal (Heitz 2018) for `wo` in the upper hemisphere.
fn sample_visible_normal(wo: Vec3, alpha: f32, u: (f32, f32)) -> Vec3 {
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z).normalize();
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        Vec3::X
    };
    let t2 = vh.cross(t1);
    let r = u.0.sqrt();
    let (sin, cos) = sincos_turn(u.1);
    let p1 = r * cos;
    let mut p2 = r * sin;
    let s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * safe_sqrt(1.0 - p1 * p1) + s * p2;
    let nh = t1 * p1 + t2 * p2 + vh * safe_sqrt(1.0 - p1 * p1 - p2 * p2);
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-6)).normalize()
}

/// Directional albedo of a GGX reflection layer, split by Schlick's Fresnel into the part
/// scaled by F0 and the part scaled by F90 - F0, tabulated over (cos theta_o, alpha).
struct AlbedoTable {
    /// [alpha][mu] -> (E0, E1); E = F0 E0 + (F90 - F0) E1.
    e: [[[f32; 2]; ALBEDO_N]; ALBEDO_N],
    /// [alpha] -> cosine-weighted hemispherical averages of (E0, E1).
    avg: [[f32; 2]; ALBEDO_N],
}

const ALBEDO_N: usize = 32;

/// The table, computed once by [`compute_albedo_table`] and kept in the source as bits
/// (`bsdf_albedo.rs`): every process used to compute it at its first shaded ray, some 40 ms
/// of CPU each, which a cluster of 80 render nodes on one machine paid 80 times. A test
/// recomputes it and checks every bit.
static ALBEDO: AlbedoTable = AlbedoTable::from_bits(&albedo_bits::E, &albedo_bits::AVG);

#[path = "bsdf_albedo.rs"]
mod albedo_bits;

/// Computes the albedo table (deterministic: the same bits on every machine this builds for).
#[cfg(test)]
fn compute_albedo_table() -> AlbedoTable {
    let n = ALBEDO_N;
    let strata = 24;
    let mut e = [[[0.0f32; 2]; ALBEDO_N]; ALBEDO_N];
    let mut avg = [[0.0f32; 2]; ALBEDO_N];
    for ai in 0..n {
        let alpha = ai as f32 / (n - 1) as f32;
        for (mi, cell) in e[ai].iter_mut().enumerate() {
            let mu = (mi as f32 / (n - 1) as f32).max(1e-3);
            let wo = Vec3::new(safe_sqrt(1.0 - mu * mu), 0.0, mu);
            let (mut e0, mut e1) = (0.0f64, 0.0f64);
            if alpha < DELTA_ALPHA {
                e0 = 1.0;
                e1 = schlick_weight(mu) as f64;
            } else {
                for i in 0..strata {
                    for j in 0..strata {
                        let u = (
                            (i as f32 + 0.5) / strata as f32,
                            (j as f32 + 0.5) / strata as f32,
                        );
                        let h = sample_visible_normal(wo, alpha, u);
                        let wi = reflect(wo, h);
                        if wi.z <= 0.0 {
                            continue;
                        }
                        let w = (ggx_g2(wo, wi, alpha) / ggx_g1(wo, alpha)) as f64;
                        e0 += w;
                        e1 += w * schlick_weight(wo.dot(h)) as f64;
                    }
                }
                let count = (strata * strata) as f64;
                e0 /= count;
                e1 /= count;
            }
            *cell = [e0 as f32, e1 as f32];
        }
        // 2 * integral of E(mu) mu dmu, trapezoid rule.
        let mut a = [0.0f64; 2];
        for mi in 0..n - 1 {
            let (m0, m1) = (mi as f64 / (n - 1) as f64, (mi + 1) as f64 / (n - 1) as f64);
            for k in 0..2 {
                let f0 = e[ai][mi][k] as f64 * m0;
                let f1 = e[ai][mi + 1][k] as f64 * m1;
                a[k] += (f0 + f1) * 0.5 * (m1 - m0) * 2.0;
            }
        }
        avg[ai] = [a[0] as f32, a[1] as f32];
    }
    AlbedoTable { e, avg }
}

impl AlbedoTable {
    const fn from_bits(
        e: &[[[u32; 2]; ALBEDO_N]; ALBEDO_N],
        avg: &[[u32; 2]; ALBEDO_N],
    ) -> AlbedoTable {
        let mut t = AlbedoTable {
            e: [[[0.0; 2]; ALBEDO_N]; ALBEDO_N],
            avg: [[0.0; 2]; ALBEDO_N],
        };
        let mut a = 0;
        while a < ALBEDO_N {
            let mut m = 0;
            while m < ALBEDO_N {
                t.e[a][m] = [f32::from_bits(e[a][m][0]), f32::from_bits(e[a][m][1])];
                m += 1;
            }
            t.avg[a] = [f32::from_bits(avg[a][0]), f32::from_bits(avg[a][1])];
            a += 1;
        }
        t
    }

    /// The table as the source of `bsdf_albedo.rs`.
    #[cfg(test)]
    fn to_source(&self) -> String {
        use std::fmt::Write;
        let mut s = String::from(
            "//! The GGX albedo table of `bsdf.rs` as f32 bits, written by its test\n\
             //! `albedo_table_in_the_source_is_the_computed_one` when run with\n\
             //! `MAGG_WRITE_ALBEDO=1`; do not edit.\n\n",
        );
        let pair = |p: &[f32; 2]| format!("[{:#010x}, {:#010x}]", p[0].to_bits(), p[1].to_bits());
        s.push_str("pub(super) const E: [[[u32; 2]; 32]; 32] = [\n");
        for row in &self.e {
            s.push_str("    [\n");
            for p in row {
                let _ = writeln!(s, "        {},", pair(p));
            }
            s.push_str("    ],\n");
        }
        s.push_str("];\n\npub(super) const AVG: [[u32; 2]; 32] = [\n");
        for p in &self.avg {
            let _ = writeln!(s, "    {},", pair(p));
        }
        s.push_str("];\n");
        s
    }

    fn lookup(&self, mu: f32, alpha: f32) -> [f32; 2] {
        let n = ALBEDO_N;
        let fa = (alpha.clamp(0.0, 1.0) * (n - 1) as f32).min((n - 1) as f32 - 1e-4);
        let fm = (mu.clamp(0.0, 1.0) * (n - 1) as f32).min((n - 1) as f32 - 1e-4);
        let (a0, m0) = (fa as usize, fm as usize);
        let (ta, tm) = (fa - a0 as f32, fm - m0 as f32);
        let at = |a: usize, m: usize, k: usize| self.e[a][m][k];
        let mut out = [0.0; 2];
        for (k, o) in out.iter_mut().enumerate() {
            let lo = at(a0, m0, k) * (1.0 - tm) + at(a0, m0 + 1, k) * tm;
            let hi = at(a0 + 1, m0, k) * (1.0 - tm) + at(a0 + 1, m0 + 1, k) * tm;
            *o = lo * (1.0 - ta) + hi * ta;
        }
        out
    }

    fn average(&self, alpha: f32) -> [f32; 2] {
        let n = ALBEDO_N;
        let fa = (alpha.clamp(0.0, 1.0) * (n - 1) as f32).min((n - 1) as f32 - 1e-4);
        let a0 = fa as usize;
        let t = fa - a0 as f32;
        [0, 1].map(|k| self.avg[a0][k] * (1.0 - t) + self.avg[a0 + 1][k] * t)
    }
}

#[inline]
fn reflect(wo: Vec3, m: Vec3) -> Vec3 {
    -wo + m * 2.0 * wo.dot(m)
}

/// Refracts `wo` about `m` (both on the same side); `eta` = far index / near index.
#[inline]
fn refract(wo: Vec3, m: Vec3, eta: f32) -> Option<Vec3> {
    let cos_i = wo.dot(m);
    let sin2_t = (1.0 - cos_i * cos_i).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some(-wo / eta + m * (cos_i / eta - cos_t))
}

/// For a Lambertian surface of shading normal `n` and true normal `ng` (turned to `wo`):
/// the cosine of `wi` to `n` when light from `wi` reflects towards `wo` (both above the
/// shading and the true surface).
#[inline(always)]
pub(crate) fn diffuse_cosine(n: Vec3, ng: Vec3, wo: Vec3, wi: Vec3) -> Option<f32> {
    let (cos_o, cos_i) = (wo.dot(n), wi.dot(n));
    (cos_o > 0.0 && cos_i > 0.0 && wi.dot(ng) > 0.0).then_some(cos_i)
}

/// Whether [`Bsdf::new`] makes a plain Lambertian BSDF of these parameters (no layer on
/// top of the diffuse base: no metal, no specular layer, no transmission).
#[inline(always)]
pub fn is_lambertian(p: &ShadingParams) -> bool {
    p.metallic == 0.0 && p.specular == 0.0 && p.transmission == 0.0
}

#[inline(always)]
pub(crate) fn cosine_hemisphere(u: (f32, f32)) -> Vec3 {
    // Concentric disk mapping (Shirley-Chiu), lifted to the hemisphere.
    let (a, b) = (2.0 * u.0 - 1.0, 2.0 * u.1 - 1.0);
    // The angle is pi/4 (b/a), or pi/2 - pi/4 (a/b), whose cosine and sine are the sine and
    // cosine of pi/4 (a/b): one short polynomial sincos either way.
    let (x, y) = if a == 0.0 && b == 0.0 {
        (0.0, 0.0)
    } else if a.abs() > b.abs() {
        let (sin, cos) = sincos_quarter_pi(b / a);
        (a * cos, a * sin)
    } else {
        let (sin, cos) = sincos_quarter_pi(a / b);
        (b * sin, b * cos)
    };
    Vec3::new(x, y, safe_sqrt(1.0 - x * x - y * y))
}

/// How far the mirror direction of `wo` about a shading normal must clear the surface.
const CLEARANCE: f32 = 0.01;

/// The normals of a surface point as seen from `wo`: the first step of [`Bsdf::new`], on
/// its own so that a wave of Lambertian hits takes it in SIMD lanes with the same bits.
#[derive(Clone, Copy, Debug)]
pub struct Facing {
    /// Whether `wo` is on the side the mesh's winding makes the front.
    pub front: bool,
    /// The true normal, turned to `wo`'s side.
    pub ng: Vec3,
    /// The shading normal turned to that side, or the true normal where it hides `wo`.
    pub n: Vec3,
    /// Whether `n` is tilted so far that the mirror direction of `wo` dips below the
    /// surface, and [`Bsdf::new`] bends it.
    pub tilted: bool,
}

impl Facing {
    /// `normal` is the shading normal, `ng` the true one as the mesh winds it.
    #[inline(always)]
    pub fn new(normal: Vec3, ng: Vec3, wo: Vec3) -> Facing {
        let front = wo.dot(ng) >= 0.0;
        let ng = if front { ng } else { -ng };
        let mut n = if normal.dot(ng) < 0.0 {
            -normal
        } else {
            normal
        };
        // A shading normal that hides wo (possible with interpolated or mapped normals)
        // would make the BSDF black from a visible side: fall back to the true normal.
        if n.dot(wo) <= 1e-4 {
            n = ng;
        }
        let r = n * (2.0 * n.dot(wo)) - wo;
        Facing {
            front,
            ng,
            n,
            tilted: r.dot(ng) < CLEARANCE,
        }
    }
}

impl Bsdf {
    /// The BSDF at a surface point for light leaving towards `wo` (world space, unit).
    /// `ng` is the geometric normal as the mesh winds it; `front` says whether `wo` is on
    /// that side, which decides the direction of refraction.
    #[inline(always)]
    pub fn new(p: &ShadingParams, ng: Vec3, wo: Vec3) -> Bsdf {
        let Facing {
            front,
            ng,
            mut n,
            tilted,
        } = Facing::new(p.normal, ng, wo);
        // A normal tilted so far that the mirror direction of wo dips below the surface
        // would leave a black fringe (strong normal maps at grazing angles). Bend it towards
        // the true normal until that direction just clears the surface (Keller et al. 2017,
        // "Towards Accurate and Practical Normal Mapping").
        if tilted {
            let r = n * (2.0 * n.dot(wo)) - wo;
            let flat = r - ng * r.dot(ng);
            let lifted = (flat.normalize_or_zero() * (1.0 - CLEARANCE * CLEARANCE).sqrt()
                + ng * CLEARANCE)
                .normalize_or(ng);
            let bent = (wo + lifted).normalize_or(ng);
            if bent.dot(ng) > 0.0 && bent.is_finite() {
                n = bent;
            }
        }
        let frame = match p.tangent {
            Some((t, sign)) => Frame::from_normal_tangent(n, t, sign),
            None => Frame::from_normal(n),
        };
        let volume = !p.thin_walled && p.transmission > 0.0;
        let ior = if p.ior.is_finite() && p.ior >= 1.0 {
            p.ior
        } else {
            1.5
        };
        let eta = if volume && !front { 1.0 / ior } else { ior };
        let r0 = ((ior - 1.0) / (ior + 1.0)).powi(2);
        let f0 = (p.specular_color * r0).min(Vec3::ONE) * p.specular;
        let alpha = p.roughness * p.roughness;

        let mut bsdf = Bsdf {
            frame,
            ng,
            base: p.base_color,
            metallic: p.metallic,
            alpha,
            f0,
            f90: p.specular,
            transmission: if p.metallic >= 1.0 {
                0.0
            } else {
                p.transmission
            },
            eta,
            volume,
            albedo_o: Vec3::ZERO,
            albedo_avg: Vec3::ZERO,
            p_diffuse: 0.0,
            p_specular: 0.0,
            p_transmit: 0.0,
            lambert: false,
        };
        // With no metal, the transmission kept above is the parameters' own.
        if is_lambertian(p) {
            // With no layer on top, the general lobe weights below come out as exactly
            // (1, 0, 0); say so directly.
            bsdf.lambert = true;
            bsdf.p_diffuse = 1.0;
            return bsdf;
        }
        let cos_o = frame.to_local(wo).z.max(1e-4);
        bsdf.albedo_o = bsdf.layer_albedo(cos_o);
        if p.specular > 0.0 {
            let avg = ALBEDO.average(alpha);
            bsdf.albedo_avg = f0 * avg[0] + (Vec3::splat(p.specular) - f0) * avg[1];
        }
        let fd = luminance(bsdf.dielectric_fresnel(cos_o));
        let fm = luminance(bsdf.base + (Vec3::ONE - bsdf.base) * schlick_weight(cos_o));
        let m = bsdf.metallic;
        let tr = bsdf.transmission;
        let lb = luminance(bsdf.base).max(1e-3);
        let mut pd = (1.0 - m) * (1.0 - tr) * (1.0 - luminance(bsdf.albedo_o)) * lb;
        let mut ps = (1.0 - m) * fd + m * fm;
        let mut pt = (1.0 - m) * tr * (1.0 - fd) * lb;
        let sum = pd + ps + pt;
        if sum > 0.0 && sum.is_finite() {
            pd /= sum;
            ps /= sum;
            pt /= sum;
        } else {
            (pd, ps, pt) = (0.0, 0.0, 0.0);
        }
        bsdf.p_diffuse = pd;
        bsdf.p_specular = ps;
        bsdf.p_transmit = pt;
        bsdf
    }

    /// The plain Lambertian BSDF [`Bsdf::new`] makes of parameters that
    /// [`is_lambertian`] accepts, with no tangent, from what it takes of them: the shading
    /// normal `n` and the true normal `ng` as [`Facing`] turned them (and `n` bent where
    /// it was tilted), and the base colour. It samples, evaluates and weighs exactly as
    /// that one does (they read only these).
    #[inline(always)]
    pub(crate) fn lambertian(n: Vec3, ng: Vec3, base: Vec3) -> Bsdf {
        Bsdf {
            frame: Frame::from_normal(n),
            ng,
            base,
            metallic: 0.0,
            alpha: 1.0,
            f0: Vec3::ZERO,
            f90: 0.0,
            transmission: 0.0,
            eta: 1.5,
            volume: false,
            albedo_o: Vec3::ZERO,
            albedo_avg: Vec3::ZERO,
            p_diffuse: 1.0,
            p_specular: 0.0,
            p_transmit: 0.0,
            lambert: true,
        }
    }

    pub fn shading_normal(&self) -> Vec3 {
        self.frame.n
    }

    pub fn geometric_normal(&self) -> Vec3 {
        self.ng
    }

    fn is_delta_lobe(&self) -> bool {
        self.alpha < DELTA_ALPHA
    }

    /// True when every lobe is a delta (perfect mirror/glass): light sampling cannot help.
    pub fn is_pure_delta(&self) -> bool {
        self.is_delta_lobe() && self.p_diffuse == 0.0
    }

    /// Nothing but a diffuse base: [`Bsdf::sample`] ignores its lobe number.
    pub fn is_lambert(&self) -> bool {
        self.lambert
    }

    pub fn has_transmission(&self) -> bool {
        self.p_transmit > 0.0
    }

    /// Fresnel of the dielectric layer at a microfacet cosine `cos` on the `wo` side.
    #[inline]
    fn dielectric_fresnel(&self, cos: f32) -> Vec3 {
        if self.volume {
            Vec3::splat(fresnel_dielectric(cos, self.eta) * self.f90)
        } else {
            self.f0 + (Vec3::splat(self.f90) - self.f0) * schlick_weight(cos)
        }
    }

    /// Directional albedo of the dielectric specular layer (Schlick Fresnel).
    fn layer_albedo(&self, mu: f32) -> Vec3 {
        if self.f90 == 0.0 {
            // No specular layer (KHR_materials_specular factor 0): nothing to take away.
            return Vec3::ZERO;
        }
        let [e0, e1] = ALBEDO.lookup(mu, self.alpha);
        self.f0 * e0 + (Vec3::splat(self.f90) - self.f0) * e1
    }

    /// The diffuse base's share of energy for the pair (mu_o, mu_i) by albedo scaling.
    #[inline]
    fn diffuse_weight(&self, mu_o: f32, mu_i: f32) -> Vec3 {
        let denom = (Vec3::ONE - self.albedo_avg).max(Vec3::splat(1e-4));
        (Vec3::ONE - self.layer_albedo(mu_o)) * (Vec3::ONE - self.layer_albedo(mu_i)) / denom
    }

    #[inline]
    fn metal_fresnel(&self, cos: f32) -> Vec3 {
        self.base + (Vec3::ONE - self.base) * schlick_weight(cos)
    }

    /// f(wo, wi) of the non-delta lobes (world directions, unit). The Lambertian case is
    /// inlined where it is called and the layered one kept out of line, as in
    /// [`Bsdf::sample`] and [`Bsdf::pdf`]: whole, each of the three was a call on every hit,
    /// even on the commonest surface, whose terms take a few instructions.
    #[inline]
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        if self.lambert {
            return if self.reflects_diffusely(wo, wi).is_some() {
                self.base * INV_PI
            } else {
                Vec3::ZERO
            };
        }
        self.eval_layered(wo, wi)
    }

    /// [`Bsdf::eval`] of a BSDF with more than a diffuse base.
    fn eval_layered(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let lo = self.frame.to_local(wo);
        let li = self.frame.to_local(wi);
        if lo.z <= 0.0 {
            return Vec3::ZERO;
        }
        let geo_reflect = wi.dot(self.ng) > 0.0;
        let m = self.metallic;
        let tr = self.transmission;
        if li.z > 0.0 && geo_reflect {
            let mut f =
                (1.0 - m) * (1.0 - tr) * self.diffuse_weight(lo.z, li.z) * self.base * INV_PI;
            // Without a specular layer (a dielectric of specular factor 0, as Lambertian
            // surfaces are given) the glossy term is zero: skip its GGX evaluation.
            if !self.is_delta_lobe() && (m > 0.0 || self.f90 > 0.0) {
                let h = (lo + li).normalize();
                let voh = lo.dot(h).max(0.0);
                let fd = self.dielectric_fresnel(voh);
                let spec = ggx_d(h, self.alpha) * ggx_g2(lo, li, self.alpha) / (4.0 * lo.z * li.z);
                f += ((1.0 - m) * fd + m * self.metal_fresnel(voh)) * spec;
            }
            f
        } else if li.z < 0.0 && !geo_reflect && tr > 0.0 && !self.is_delta_lobe() {
            let weight = (1.0 - m) * tr * self.base;
            if self.volume {
                let Some((h, voh, ioh)) = self.refraction_half(lo, li) else {
                    return Vec3::ZERO;
                };
                let f = fresnel_dielectric(voh, self.eta) * self.f90;
                let denom = (ioh + voh / self.eta).powi(2) * li.z.abs() * lo.z;
                let ft =
                    ggx_d(h, self.alpha) * ggx_g2(lo, li, self.alpha) * (ioh * voh).abs() / denom;
                // Radiance is compressed by eta^2 entering a denser medium.
                weight * (1.0 - f) * ft / (self.eta * self.eta)
            } else {
                let lm = Vec3::new(li.x, li.y, -li.z);
                let h = (lo + lm).normalize();
                let voh = lo.dot(h).max(0.0);
                let fd = self.dielectric_fresnel(voh);
                let spec = ggx_d(h, self.alpha) * ggx_g2(lo, lm, self.alpha) / (4.0 * lo.z * lm.z);
                weight * (Vec3::ONE - fd) * spec
            }
        } else {
            Vec3::ZERO
        }
    }

    /// Generalised half vector of a refraction pair, facing +z, with the two cosines.
    fn refraction_half(&self, lo: Vec3, li: Vec3) -> Option<(Vec3, f32, f32)> {
        let mut h = lo + li * self.eta;
        if h.length_squared() == 0.0 {
            return None;
        }
        h = h.normalize();
        if h.z < 0.0 {
            h = -h;
        }
        let voh = lo.dot(h);
        let ioh = li.dot(h);
        // Microfacets must face wo and be seen from below by wi.
        if voh <= 0.0 || ioh >= 0.0 {
            return None;
        }
        Some((h, voh, ioh))
    }

    /// For a Lambertian surface: the cosine of `wi` to the shading normal when light
    /// from `wi` reflects towards `wo` (both above the shading and the true surface).
    #[inline]
    fn reflects_diffusely(&self, wo: Vec3, wi: Vec3) -> Option<f32> {
        diffuse_cosine(self.frame.n, self.ng, wo, wi)
    }

    /// Density of sampling `wi` by the three lobes proper (non-delta only).
    fn pdf_lobes(&self, wo: Vec3, wi: Vec3) -> f32 {
        let lo = self.frame.to_local(wo);
        let li = self.frame.to_local(wi);
        if lo.z <= 0.0 {
            return 0.0;
        }
        let geo_reflect = wi.dot(self.ng) > 0.0;
        if li.z > 0.0 && geo_reflect {
            let mut pdf = self.p_diffuse * li.z * INV_PI;
            if !self.is_delta_lobe() && self.p_specular > 0.0 {
                let h = (lo + li).normalize();
                pdf += self.p_specular * ggx_d_visible(lo, h, self.alpha) / (4.0 * lo.dot(h));
            }
            pdf
        } else if li.z < 0.0 && !geo_reflect && self.p_transmit > 0.0 && !self.is_delta_lobe() {
            if self.volume {
                let Some((h, voh, ioh)) = self.refraction_half(lo, li) else {
                    return 0.0;
                };
                // A refraction sample is drawn as a visible normal, then kept with
                // probability 1 - F (reflected otherwise).
                let f = fresnel_dielectric(voh, self.eta) * self.f90;
                let dwh_dwi = ioh.abs() / (ioh + voh / self.eta).powi(2);
                self.p_transmit * (1.0 - f) * ggx_d_visible(lo, h, self.alpha) * dwh_dwi
            } else {
                let lm = Vec3::new(li.x, li.y, -li.z);
                let h = (lo + lm).normalize();
                self.p_transmit * ggx_d_visible(lo, h, self.alpha) / (4.0 * lo.dot(h))
            }
        } else {
            0.0
        }
    }

    /// Draws an incident direction. `u_lobe` picks the lobe, `u` drives it.
    #[inline]
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: (f32, f32)) -> Option<BsdfSample> {
        if self.lambert {
            let wi = self.frame.to_world(cosine_hemisphere(u));
            let cos_i = self.reflects_diffusely(wo, wi)?;
            let pdf = cos_i * INV_PI;
            if !(pdf > 0.0) {
                return None;
            }
            // f cos / pdf = (base / pi) cos / (cos / pi).
            return Some(BsdfSample {
                wi,
                weight: self.base,
                pdf,
                delta: false,
                transmitted: false,
            });
        }
        self.sample_layered(wo, u_lobe, u)
    }

    /// [`Bsdf::sample`] of a BSDF with more than a diffuse base.
    fn sample_layered(&self, wo: Vec3, u_lobe: f32, u: (f32, f32)) -> Option<BsdfSample> {
        let lo = self.frame.to_local(wo);
        if lo.z <= 0.0 {
            return None;
        }
        let delta = self.is_delta_lobe();
        if u_lobe < self.p_diffuse {
            let li = cosine_hemisphere(u);
            return self.finish(wo, self.frame.to_world(li), false);
        }
        if u_lobe < self.p_diffuse + self.p_specular {
            if delta {
                return self.delta_mirror(lo);
            }
            let li = reflect(lo, sample_visible_normal(lo, self.alpha, u));
            return self.finish(wo, self.frame.to_world(li), false);
        }
        if self.p_transmit <= 0.0 {
            return None;
        }
        let m = self.metallic;
        let tint = (1.0 - m) * self.transmission * self.base;
        if self.volume {
            let h = if delta {
                Vec3::Z
            } else {
                sample_visible_normal(lo, self.alpha, u)
            };
            let f = fresnel_dielectric(lo.dot(h), self.eta) * self.f90;
            // Refract with probability 1 - F; otherwise reflect off the same facet.
            let u_choice = (u_lobe - self.p_diffuse - self.p_specular) / self.p_transmit;
            if u_choice < f {
                return if delta {
                    self.delta_mirror(lo)
                } else {
                    self.finish(wo, self.frame.to_world(reflect(lo, h)), false)
                };
            }
            let li = refract(lo, h, self.eta)?;
            let wi = self.frame.to_world(li);
            if !delta {
                return self.finish(wo, wi, true);
            }
            if li.z >= 0.0 || wi.dot(self.ng) >= 0.0 {
                return None;
            }
            // (1 - F) tint / eta^2 over the probability p_t (1 - F) of this choice.
            let weight = tint / (self.eta * self.eta * self.p_transmit);
            return Some(BsdfSample {
                wi,
                weight,
                pdf: self.p_transmit * (1.0 - f),
                delta: true,
                transmitted: true,
            });
        }
        // Thin-walled: a reflection lobe mirrored through the surface.
        let li = if delta {
            Vec3::new(-lo.x, -lo.y, lo.z)
        } else {
            reflect(lo, sample_visible_normal(lo, self.alpha, u))
        };
        let wi = self.frame.to_world(Vec3::new(li.x, li.y, -li.z));
        if !delta {
            return self.finish(wo, wi, true);
        }
        if wi.dot(self.ng) >= 0.0 {
            return None;
        }
        let fd = self.dielectric_fresnel(lo.z);
        Some(BsdfSample {
            wi,
            weight: tint * (Vec3::ONE - fd) / self.p_transmit,
            pdf: self.p_transmit,
            delta: true,
            transmitted: true,
        })
    }

    /// The perfectly specular continuations a Whitted ray tracer follows from `wo`, with
    /// their weights: mirror reflection (when `mirror`, or always for refracting volumes),
    /// and refraction or straight transmission for transmissive materials.
    pub fn specular_paths(&self, wo: Vec3, mirror: bool) -> [(Vec3, Vec3, bool); 2] {
        let none = (Vec3::Z, Vec3::ZERO, false);
        let lo = self.frame.to_local(wo);
        if lo.z <= 0.0 {
            return [none, none];
        }
        let m = self.metallic;
        let tint = (1.0 - m) * self.transmission * self.base;
        let reflect_dir = self.frame.to_world(Vec3::new(-lo.x, -lo.y, lo.z));
        let reflect_ok = reflect_dir.dot(self.ng) > 0.0;
        let mut reflection = none;
        if reflect_ok && (mirror || self.volume) {
            let r = (1.0 - m) * self.dielectric_fresnel(lo.z) + m * self.metal_fresnel(lo.z);
            reflection = (reflect_dir, r, false);
        }
        let mut transmission = none;
        if self.transmission > 0.0 && m < 1.0 {
            if self.volume {
                let f = fresnel_dielectric(lo.z, self.eta) * self.f90;
                match refract(lo, Vec3::Z, self.eta) {
                    Some(li) => {
                        let wi = self.frame.to_world(li);
                        if wi.dot(self.ng) < 0.0 {
                            transmission = (wi, tint * (1.0 - f) / (self.eta * self.eta), true);
                        }
                    }
                    // Total internal reflection: the transmitted share is reflected too.
                    None if reflect_ok => reflection.1 += tint,
                    None => {}
                }
            } else {
                let fd = self.dielectric_fresnel(lo.z);
                transmission = (-wo, tint * (Vec3::ONE - fd), true);
            }
        }
        [reflection, transmission]
    }

    /// The perfect mirror direction of a smooth surface. Both the specular lobe and the
    /// reflecting half of a smooth refracting interface produce it, so its weight is the
    /// reflectance over the sum of both probabilities.
    fn delta_mirror(&self, lo: Vec3) -> Option<BsdfSample> {
        let wi = self.frame.to_world(Vec3::new(-lo.x, -lo.y, lo.z));
        if wi.dot(self.ng) <= 0.0 {
            return None;
        }
        let m = self.metallic;
        let reflectance = (1.0 - m) * self.dielectric_fresnel(lo.z) + m * self.metal_fresnel(lo.z);
        let mut prob = self.p_specular;
        if self.volume {
            prob += self.p_transmit * fresnel_dielectric(lo.z, self.eta) * self.f90;
        }
        if !(prob > 0.0) {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight: reflectance / prob,
            pdf: prob,
            delta: true,
            transmitted: false,
        })
    }

    fn finish(&self, wo: Vec3, wi: Vec3, transmitted: bool) -> Option<BsdfSample> {
        let li = self.frame.to_local(wi);
        // The sampled side must agree with the geometric side, or the direction would
        // leak through the surface (interpolated normals can disagree with the triangle).
        let geo_front = wi.dot(self.ng) > 0.0;
        if transmitted == geo_front || (li.z > 0.0) != geo_front {
            return None;
        }
        let pdf = self.pdf(wo, wi);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        let weight = self.eval(wo, wi) * li.z.abs() / pdf;
        if !weight.is_finite() {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight,
            pdf,
            delta: false,
            transmitted,
        })
    }

    /// Density of sampling `wi` by any lobe, including the reflecting half of a rough
    /// refracting interface (drawn by the transmission lobe); pairs with [`Bsdf::eval`].
    #[inline]
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if self.lambert {
            return self.reflects_diffusely(wo, wi).map_or(0.0, |c| c * INV_PI);
        }
        self.pdf_layered(wo, wi)
    }

    /// [`Bsdf::pdf`] of a BSDF with more than a diffuse base.
    fn pdf_layered(&self, wo: Vec3, wi: Vec3) -> f32 {
        let mut pdf = self.pdf_lobes(wo, wi);
        if self.volume && !self.is_delta_lobe() && self.p_transmit > 0.0 {
            let lo = self.frame.to_local(wo);
            let li = self.frame.to_local(wi);
            if lo.z > 0.0 && li.z > 0.0 && wi.dot(self.ng) > 0.0 {
                let h = (lo + li).normalize();
                let voh = lo.dot(h);
                let fr = fresnel_dielectric(voh, self.eta) * self.f90;
                pdf += self.p_transmit * fr * ggx_d_visible(lo, h, self.alpha) / (4.0 * voh);
            }
        }
        pdf
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn albedo_table_in_the_source_is_the_computed_one() {
        let computed = super::compute_albedo_table();
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/src/bsdf_albedo.rs");
        if std::env::var_os("MAGG_WRITE_ALBEDO").is_some() {
            std::fs::write(path, computed.to_source()).unwrap();
        }
        let bits = |t: &super::AlbedoTable| {
            (
                t.e.map(|r| r.map(|p| p.map(f32::to_bits))),
                t.avg.map(|p| p.map(f32::to_bits)),
            )
        };
        assert!(
            bits(&computed) == bits(&super::ALBEDO),
            "{path} is stale: rerun this test with MAGG_WRITE_ALBEDO=1"
        );
    }

    use super::*;

    fn params(
        base: Vec3,
        metallic: f32,
        roughness: f32,
        transmission: f32,
        thin: bool,
    ) -> ShadingParams {
        ShadingParams {
            base_color: base,
            alpha: 1.0,
            metallic,
            roughness,
            ior: 1.5,
            specular: 1.0,
            specular_color: Vec3::ONE,
            transmission,
            thin_walled: thin,
            emission: Vec3::ZERO,
            normal: Vec3::Z,
            tangent: None,
        }
    }

    /// Hash-based uniform numbers for the tests.
    fn rng(i: u32, k: u32) -> f32 {
        let mut s = crate::sampler::Sampler::new(99, i, k, 0);
        s.start_bounce(0);
        s.get_1d()
    }

    /// Estimates the directional albedo by sampling, and the integral of the pdf.
    fn albedo(b: &Bsdf, wo: Vec3, n: u32) -> Vec3 {
        let mut sum = Vec3::ZERO;
        for i in 0..n {
            if let Some(s) = b.sample(wo, rng(i, 0), (rng(i, 1), rng(i, 2))) {
                sum += s.weight;
            }
        }
        sum / n as f32
    }

    #[test]
    fn white_furnace_albedo_never_exceeds_one() {
        for &(m, r, t, thin) in &[
            (0.0, 1.0, 0.0, true),
            (0.0, 0.5, 0.0, true),
            (0.0, 0.05, 0.0, true),
            (1.0, 0.3, 0.0, true),
            (1.0, 0.0, 0.0, true),
            (0.5, 0.7, 0.0, true),
            (0.0, 0.3, 1.0, true),
            (0.0, 0.3, 1.0, false),
            (0.0, 0.0, 1.0, false),
        ] {
            for cos in [0.95f32, 0.5, 0.1] {
                let wo = Vec3::new(safe_sqrt(1.0 - cos * cos), 0.0, cos);
                let b = Bsdf::new(&params(Vec3::ONE, m, r, t, thin), Vec3::Z, wo);
                let a = albedo(&b, wo, 200_000);
                assert!(
                    a.max_element() <= 1.02,
                    "albedo {a} for m={m} r={r} t={t} cos={cos}"
                );
                assert!(a.min_element() >= 0.0);
            }
        }
    }

    #[test]
    fn reciprocity_of_reflection() {
        for &(m, r) in &[(0.0, 0.5), (1.0, 0.4), (0.3, 0.9)] {
            let b0 = Bsdf::new(
                &params(Vec3::new(0.8, 0.5, 0.2), m, r, 0.0, true),
                Vec3::Z,
                Vec3::Z,
            );
            for i in 0..200 {
                let a = Vec3::new(rng(i, 3) - 0.5, rng(i, 4) - 0.5, rng(i, 5) + 0.05).normalize();
                let c = Vec3::new(rng(i, 6) - 0.5, rng(i, 7) - 0.5, rng(i, 8) + 0.05).normalize();
                let f1 = b0.eval(a, c);
                let f2 = b0.eval(c, a);
                assert!(
                    (f1 - f2).abs().max_element() <= 1e-4 * f1.max_element().max(1.0),
                    "{f1} vs {f2}"
                );
            }
        }
    }

    /// The sampling density integrates what eval/pdf claim: E[f cos / pdf] over samples
    /// equals the integral of f cos computed by uniform hemisphere quadrature.
    #[test]
    fn sampled_weight_matches_quadrature_of_eval() {
        for &(m, r) in &[(0.0, 1.0), (0.0, 0.4), (1.0, 0.25), (0.5, 0.6), (1.0, 0.8)] {
            let wo = Vec3::new(0.6, 0.0, 0.8);
            let b = Bsdf::new(
                &params(Vec3::new(0.9, 0.6, 0.3), m, r, 0.0, true),
                Vec3::Z,
                wo,
            );
            let mc = albedo(&b, wo, 400_000);
            // Quadrature: uniform sphere directions.
            let n = 400_000;
            let mut q = Vec3::ZERO;
            for i in 0..n {
                let z = rng(i, 11);
                let phi = 2.0 * PI * rng(i, 12);
                let s = safe_sqrt(1.0 - z * z);
                let wi = Vec3::new(s * phi.cos(), s * phi.sin(), z);
                q += b.eval(wo, wi) * z * (2.0 * PI);
            }
            q /= n as f32;
            let err = (mc - q).abs().max_element();
            assert!(
                err < 0.02 * q.max_element().max(0.1),
                "m={m} r={r}: sampled {mc} vs quadrature {q}"
            );
        }
    }

    /// Integrates a function over the sphere on a midpoint grid in (cos theta, phi), which
    /// is exact enough for peaked densities where random points are too noisy.
    fn sphere_grid(n: u32, mut f: impl FnMut(Vec3) -> f64) -> f64 {
        let mut sum = 0.0;
        for i in 0..n {
            for j in 0..n {
                let z = 2.0 * (i as f32 + 0.5) / n as f32 - 1.0;
                let phi = 2.0 * PI * (j as f32 + 0.5) / n as f32;
                let s = safe_sqrt(1.0 - z * z);
                sum += f(Vec3::new(s * phi.cos(), s * phi.sin(), z));
            }
        }
        sum * 4.0 * PI as f64 / (n as f64 * n as f64)
    }

    #[test]
    fn pdf_integrates_to_at_most_one() {
        for &(m, r, t, thin) in &[
            (0.0, 0.5, 0.0, true),
            (1.0, 0.3, 0.0, true),
            (0.0, 0.5, 1.0, false),
            (0.0, 0.4, 1.0, true),
        ] {
            let wo = Vec3::new(0.3, 0.1, 0.9).normalize();
            let b = Bsdf::new(&params(Vec3::ONE, m, r, t, thin), Vec3::Z, wo);
            let total = sphere_grid(1500, |wi| b.pdf(wo, wi) as f64);
            assert!(
                total <= 1.01 && total > 0.9,
                "pdf integrates to {total} for m={m} r={r} t={t}"
            );
        }
    }

    #[test]
    fn specular_zero_is_lambertian() {
        let mut p = params(Vec3::splat(0.5), 0.0, 0.2, 0.0, true);
        p.specular = 0.0;
        let wo = Vec3::new(0.0, 0.6, 0.8);
        let b = Bsdf::new(&p, Vec3::Z, wo);
        let wi = Vec3::new(0.3, -0.2, 0.93).normalize();
        let f = b.eval(wo, wi);
        assert!((f - Vec3::splat(0.5 * INV_PI)).abs().max_element() < 1e-6);
    }

    #[test]
    fn fresnel_limits() {
        assert!((fresnel_dielectric(1.0, 1.5) - 0.04).abs() < 1e-3);
        assert_eq!(fresnel_dielectric(0.1, 1.0 / 1.5), 1.0);
        assert!(fresnel_dielectric(1.0, 1.0) < 1e-6);
    }
}
