//! A wave's Lambertian hits, shaded together.
//!
//! Most hits in most scenes land on a plain diffuse surface, and between its two ray queries
//! (the shadow ray and the next bounce) such a hit is only arithmetic: the shading frame,
//! the direction drawn, the point on the light, the BSDF's value and densities, the weights.
//! The path tracer's wave ([`crate::render`]) collects the hits of one bounce that are of
//! this kind here, and this module does that arithmetic for all of them at once, in eight
//! SIMD lanes ([`crate::simd::F32x8`]).
//!
//! Each lane does the operations of the one-path bounce
//! ([`PathState::shade`](crate::integrator::PathState)) in the same order, rounding for
//! rounding: the same products, sums, quotients and square roots, comparisons where it
//! branches, and the same fused multiply-adds in the sine and cosine. So the bits, and the
//! images, are the same as path by path, and render nodes stepping paths one at a time
//! with memory-coherent rays still agree with this to the last bit. `tests::compute_lane`
//! is that one-path arithmetic, written with the very functions the bounce calls; a test
//! holds the SIMD lanes to it. What cannot be done lane by lane stays with the path: the
//! ray queries, the light's choice (in f64), and moving ray origins off the surface.
//! A light other than a triangle of constant radiance (the environment, a punctual light,
//! a textured emitter) is sampled by the path's own next-event estimation; a hit that needs
//! more (a shading normal that must be bent, a tangent frame) is shaded by
//! [`PathState::shade`] instead.

use glam::{Vec3, Vec3A};

use crate::{
    bsdf::{Bsdf, Facing, is_lambertian},
    integrator::{
        LightChoice, Met, PathState, ROULETTE_FROM_BOUNCE, ROULETTE_MAX_SURVIVAL,
        ROULETTE_THROUGHPUT, choose_light, next_event,
    },
    light::Light,
    math::{COS_TAYLOR, INV_PI, SIN_TAYLOR, offset_ray_origin},
    sampler::Draws,
    simd::{AlignedFrame, F32x8, M8},
    source::{DataError, SceneData},
    trace::{AlphaKey, Tracer, shadow_ray},
};

const LANES: usize = 8;

/// Three coordinates of eight lanes.
type V3 = [[f32; LANES]; 3];

#[inline(always)]
fn get(v: &V3, k: usize) -> Vec3 {
    Vec3::new(v[0][k], v[1][k], v[2][k])
}

#[inline(always)]
fn put(v: &mut V3, k: usize, x: Vec3) {
    v[0][k] = x.x;
    v[1][k] = x.y;
    v[2][k] = x.z;
}

#[inline(always)]
fn load3(v: &V3) -> [F32x8; 3] {
    v.each_ref().map(F32x8::load)
}

#[inline(always)]
fn store3(x: [F32x8; 3], out: &mut V3) {
    for (x, o) in x.into_iter().zip(out) {
        x.store(o);
    }
}

/// `Vec3::dot`: (x x' + y y') + z z'.
#[inline(always)]
fn dot8(a: [F32x8; 3], b: [F32x8; 3]) -> F32x8 {
    a[0].mul(b[0]).add(a[1].mul(b[1])).add(a[2].mul(b[2]))
}

#[inline(always)]
fn mul3(a: [F32x8; 3], b: [F32x8; 3]) -> [F32x8; 3] {
    [a[0].mul(b[0]), a[1].mul(b[1]), a[2].mul(b[2])]
}

/// `Vec3::max_element`: max(max(x, y), z), each `a > b ? a : b` (the SSE rule).
#[inline(always)]
fn max_element8(v: [F32x8; 3]) -> F32x8 {
    v[0].max(v[1]).max(v[2])
}

/// `bsdf::diffuse_cosine`: whether light from `wi` reflects towards `wo`, and the cosine.
#[inline(always)]
fn diffuse_cosine8(n: [F32x8; 3], ng: [F32x8; 3], wo: [F32x8; 3], wi: [F32x8; 3]) -> (M8, F32x8) {
    let zero = F32x8::splat(0.0);
    let (cos_o, cos_i) = (dot8(wo, n), dot8(wi, n));
    let ok = cos_o
        .gt(zero)
        .and(cos_i.gt(zero))
        .and(dot8(wi, ng).gt(zero));
    (ok, cos_i)
}

/// `math::power_heuristic`.
#[inline(always)]
fn power_heuristic8(f_pdf: F32x8, g_pdf: F32x8) -> F32x8 {
    let (f, g) = (f_pdf.mul(f_pdf), g_pdf.mul(g_pdf));
    let sum = f.add(g);
    let zero = F32x8::splat(0.0);
    let w = sum.eq(zero).select(zero, f.div(sum));
    f.abs()
        .eq(F32x8::splat(f32::INFINITY))
        .select(F32x8::splat(1.0), w)
}

/// `math::sincos_octant`, the same coefficients and fused multiply-adds.
#[inline(always)]
fn sincos_octant(x: F32x8) -> (F32x8, F32x8) {
    let [s0, s1, s2, s3] = SIN_TAYLOR.map(F32x8::splat);
    let [c0, c1, c2, c3, c4, c5] = COS_TAYLOR.map(F32x8::splat);
    let x2 = x.mul(x);
    let sin = x2
        .mul_add(s0, s1)
        .mul_add(x2, s2)
        .mul_add(x2, s3)
        .mul_add(x2.mul(x), x);
    let cos = x2
        .mul_add(c0, c1)
        .mul_add(x2, c2)
        .mul_add(x2, c3)
        .mul_add(x2, c4)
        .mul_add(x2, c5);
    (sin, cos)
}

/// What a lane keeps outside the arithmetic: where the path is and what it asks of the
/// ray queries.
#[derive(Clone, Copy)]
struct LaneState {
    lane: usize,
    l: Vec3,
    p: Vec3A,
    p_error: Vec3A,
    key: AlphaKey,
    direction_dim: u32,
    u_roulette: f32,
    light: LaneLight,
}

/// What the light draw of a lane chose.
#[derive(Clone, Copy)]
enum LaneLight {
    /// No light: the scene has none.
    None,
    /// A triangle of constant radiance: sampled in the SIMD lanes.
    Triangle,
    /// Another light (the environment, a punctual light, a textured emitter): sampled by
    /// [`next_event`], the path's own, with this choice.
    Other(LightChoice),
}

/// The Lambertian hits of one bounce of a wave, structure of arrays.
pub(crate) struct DiffuseWave {
    len: usize,
    bounce: u32,
    state: [Option<LaneState>; LANES],
    input: Input,
    output: Output,
}

/// What the arithmetic of a lane reads.
#[derive(Clone, Copy, Default)]
struct Input {
    wo: V3,
    /// The shading and the true normal, turned to `wo` ([`Facing`]).
    n: V3,
    ng: V3,
    base: V3,
    beta: V3,
    p: V3,
    u_dir: [[f32; LANES]; 2],
    /// The point's draw on the chosen light (the light draw's part that chose none, then its
    /// second number), and the light's probability.
    u_point: [[f32; LANES]; 2],
    pmf: [f32; LANES],
    /// The chosen triangle light: its corners, unit normal, twice its area, whether it
    /// emits from both sides (1 or 0) and its radiance. Zero area where none was chosen.
    light_v: [V3; 3],
    light_n: V3,
    light_area2: [f32; LANES],
    light_two_sided: [f32; LANES],
    light_le: V3,
}

/// What the arithmetic of a lane gives.
#[derive(Clone, Copy, Default)]
struct Output {
    /// The direction drawn, its density, and whether the path goes on that way (bit k for
    /// lane k), with its throughput then and Russian roulette's chance of keeping it.
    wi: V3,
    pdf: [f32; LANES],
    goes_on: u32,
    beta_next: V3,
    survive: [f32; LANES],
    /// The point drawn on the light and the direction to it, whether light comes that way
    /// (bit k for lane k), and how much, should nothing block it.
    light_point: V3,
    light_dir: V3,
    lit: u32,
    light_add: V3,
}

impl DiffuseWave {
    /// An empty wave, for as many bounces as [`DiffuseWave::begin`] starts: its arrays
    /// (2 KB) are written once, not at every bounce.
    pub(crate) fn new() -> DiffuseWave {
        DiffuseWave {
            len: 0,
            bounce: 0,
            state: [None; LANES],
            input: Input::default(),
            output: Output::default(),
        }
    }

    /// Empties the wave for the hits of bounce `bounce`. What earlier hits left in the
    /// arrays stays: lanes past the hits taken are computed and never read, and a hit with
    /// no light chosen never reads the light's arrays.
    pub(crate) fn begin(&mut self, bounce: u32) {
        self.len = 0;
        self.bounce = bounce;
    }

    /// Takes the hit `met` of the path in wave lane `lane`, with that lane's draws, if it is
    /// of the kind shaded here; gives it back otherwise, with the draws as they were (none
    /// made) so that [`PathState::shade`] makes them.
    #[inline(always)]
    pub(crate) fn push<'s, D: SceneData>(
        &mut self,
        t: &Tracer<'s, D>,
        lane: usize,
        path: &PathState,
        met: Met<'s>,
        draws: &mut impl Draws,
    ) -> Option<Met<'s>> {
        let scene = t.scene;
        let p = &met.params;
        if !is_lambertian(p) || p.tangent.is_some() || self.len == LANES {
            return Some(met);
        }
        let facing = Facing::new(p.normal, met.s.ng, met.wo);
        if facing.tilted {
            return Some(met);
        }
        let u_light = draws.get_2d_after(path.direction_dim());
        let chosen = choose_light(scene, u_light);
        // A light sample that reads a texture, or of another kind, is taken by the path's
        // own next-event estimation, in `shade`.
        let light = match chosen.map(|c| &scene.lights[c.light]) {
            Some(&Light::Triangle {
                p: v,
                n,
                area2,
                material,
                two_sided,
                ..
            }) if scene.materials[material as usize].emissive_tex.is_none() => {
                let le = scene.materials[material as usize].emissive;
                Some((v, n, area2, two_sided, le))
            }
            _ => None,
        };
        let direction_dim = draws.dim();
        let u_dir = draws.get_2d();
        let u_roulette = if self.bounce >= ROULETTE_FROM_BOUNCE {
            draws.get_1d()
        } else {
            0.0
        };

        let k = self.len;
        self.len += 1;
        let i = &mut self.input;
        put(&mut i.wo, k, met.wo);
        put(&mut i.n, k, facing.n);
        put(&mut i.ng, k, facing.ng);
        put(&mut i.base, k, p.base_color);
        put(&mut i.beta, k, met.beta);
        put(&mut i.p, k, Vec3::from(met.s.p));
        i.u_dir[0][k] = u_dir.0;
        i.u_dir[1][k] = u_dir.1;
        if let (Some(choice), Some((v, n, area2, two_sided, le))) = (chosen, light) {
            i.pmf[k] = choice.pmf;
            i.u_point[0][k] = choice.u.0;
            i.u_point[1][k] = choice.u.1;
            for (corner, at) in i.light_v.iter_mut().zip(v) {
                put(corner, k, at);
            }
            put(&mut i.light_n, k, n);
            i.light_area2[k] = area2;
            i.light_two_sided[k] = if two_sided { 1.0 } else { 0.0 };
            put(&mut i.light_le, k, le);
        }
        self.state[k] = Some(LaneState {
            lane,
            l: met.l,
            p: met.s.p,
            p_error: met.s.p_error,
            key: met.key,
            direction_dim,
            u_roulette,
            light: match (chosen, light) {
                (_, Some(_)) => LaneLight::Triangle,
                (Some(choice), None) => LaneLight::Other(choice),
                (None, _) => LaneLight::None,
            },
        });
        None
    }

    /// The arithmetic of every lane at once; `tests::compute_lane` is that of one lane, as
    /// the one-path bounce does it.
    #[inline(always)]
    fn compute(input: &Input, out: &mut Output) {
        let one = F32x8::splat(1.0);
        let zero = F32x8::splat(0.0);
        let inv_pi = F32x8::splat(INV_PI);
        let (wo, n, ng) = (load3(&input.wo), load3(&input.n), load3(&input.ng));
        let (base, beta) = (load3(&input.base), load3(&input.beta));

        // Frame::from_normal.
        let sign = n[2].one_with_sign_of();
        let a = one.neg().div(sign.add(n[2]));
        let b = n[0].mul(n[1]).mul(a);
        let t = [
            one.add(sign.mul(n[0]).mul(n[0]).mul(a)),
            sign.mul(b),
            sign.neg().mul(n[0]),
        ];
        let bt = [b, sign.add(n[1].mul(n[1]).mul(a)), n[1].neg()];
        // cosine_hemisphere: the concentric disk, lifted.
        let u0 = F32x8::load(&input.u_dir[0]);
        let u1 = F32x8::load(&input.u_dir[1]);
        let two = F32x8::splat(2.0);
        let (da, db) = (two.mul(u0).sub(one), two.mul(u1).sub(one));
        let wide = da.abs().gt(db.abs());
        let ratio = wide.select(db, da).div(wide.select(da, db));
        let (sin, cos) = sincos_octant(F32x8::splat(std::f32::consts::FRAC_PI_4).mul(ratio));
        let r = wide.select(da, db);
        let centre = da.eq(zero).and(db.eq(zero));
        let x = centre.select(zero, r.mul(wide.select(cos, sin)));
        let y = centre.select(zero, r.mul(wide.select(sin, cos)));
        let z = one.sub(x.mul(x)).sub(y.mul(y)).max(zero).sqrt();
        // Frame::to_world.
        let wi: [F32x8; 3] =
            std::array::from_fn(|c| t[c].mul(x).add(bt[c].mul(y)).add(n[c].mul(z)));
        let (cos_ok, cos_i) = diffuse_cosine8(n, ng, wo, wi);
        let pdf = cos_ok.select(cos_i, zero).mul(inv_pi);
        let sampled = cos_ok.and(pdf.gt(zero));
        let beta_next = mul3(beta, base);
        let finite = beta_next[0]
            .is_finite()
            .and(beta_next[1].is_finite())
            .and(beta_next[2].is_finite());
        let peak = max_element8(beta_next);
        let goes_on = sampled.and(finite).and(peak.gt(zero));
        store3(wi, &mut out.wi);
        pdf.store(&mut out.pdf);
        out.goes_on = goes_on.bits();
        store3(beta_next, &mut out.beta_next);
        peak.div(F32x8::splat(ROULETTE_THROUGHPUT))
            .min(F32x8::splat(ROULETTE_MAX_SURVIVAL))
            .store(&mut out.survive);

        // Light::sample of a triangle light.
        let p = load3(&input.p);
        let su = F32x8::load(&input.u_point[0]).max(zero).sqrt();
        let b0 = one.sub(su);
        let b1 = F32x8::load(&input.u_point[1]).mul(su);
        let b2 = one.sub(b0).sub(b1);
        let v = input.light_v.map(|c| load3(&c));
        let q: [F32x8; 3] =
            std::array::from_fn(|c| v[0][c].mul(b0).add(v[1][c].mul(b1)).add(v[2][c].mul(b2)));
        let d: [F32x8; 3] = std::array::from_fn(|c| q[c].sub(p[c]));
        let d2 = dot8(d, d);
        let len = d2.sqrt();
        let wl: [F32x8; 3] = std::array::from_fn(|c| d[c].div(len));
        let cos_l = dot8(load3(&input.light_n), wl).neg();
        let two_sided = F32x8::load(&input.light_two_sided).eq(zero).not();
        let faces = cos_l.le(zero).and(two_sided.not()).or(cos_l.eq(zero)).not();
        let area2 = F32x8::load(&input.light_area2);
        let light_pdf = d2.div(cos_l.abs().mul(F32x8::splat(0.5)).mul(area2));
        let le = load3(&input.light_le);
        let (towards, cos_l_i) = diffuse_cosine8(n, ng, wo, wl);
        let cos_wl = dot8(wl, n).abs();
        let f: [F32x8; 3] =
            std::array::from_fn(|c| towards.select(base[c].mul(inv_pi), zero).mul(cos_wl));
        let pdf_light = light_pdf.mul(F32x8::load(&input.pmf));
        let w = power_heuristic8(pdf_light, towards.select(cos_l_i.mul(inv_pi), zero));
        let lit = area2
            .gt(zero)
            .and(d2.gt(zero))
            .and(faces)
            .and(max_element8(f).gt(zero))
            .and(max_element8(le).gt(zero));
        out.lit = lit.bits();
        let scale = w.div(pdf_light);
        let add: [F32x8; 3] = std::array::from_fn(|c| beta[c].mul(f[c]).mul(le[c]).mul(scale));
        store3(add, &mut out.light_add);
        store3(wl, &mut out.light_dir);
        store3(q, &mut out.light_point);
    }

    /// Next-event estimation for lane `k`, whose light draw chose a light other than a
    /// triangle of constant radiance: the path's own, with the lane's BSDF. Out of line,
    /// so that the triangle lights' loop stays as small as it was.
    #[inline(never)]
    fn other_light<D: SceneData>(
        &self,
        t: &Tracer<D>,
        k: usize,
        at: (Vec3A, Vec3A),
        choice: LightChoice,
        key: AlphaKey,
    ) -> Result<Option<Vec3>, DataError> {
        let i = &self.input;
        let bsdf = Bsdf::lambertian(get(&i.n, k), get(&i.ng, k), get(&i.base, k));
        next_event(t, &bsdf, get(&i.wo, k), at, choice, get(&i.beta, k), key)
    }

    /// Shades every hit taken, tracing their shadow rays, and ends their bounce as
    /// [`PathState::step`] would: a path that ends leaves `paths` with its light in
    /// `radiance` (both by wave lane). Returns how many go on.
    pub(crate) fn shade<D: SceneData>(
        &mut self,
        t: &Tracer<D>,
        paths: &mut [Option<PathState>; LANES],
        radiance: &mut [Vec3; LANES],
        max_depth: u32,
    ) -> Result<usize, DataError> {
        if self.len == 0 {
            return Ok(0);
        }
        let _frame = AlignedFrame::new();
        DiffuseWave::compute(&self.input, &mut self.output);
        let o = &self.output;
        let mut live = 0;
        for k in 0..self.len {
            let Some(st) = self.state[k] else { continue };
            let Some(path) = paths[st.lane].as_mut() else {
                continue;
            };
            let ng = Vec3A::from(get(&self.input.ng, k));
            let mut l = st.l;
            match st.light {
                LaneLight::Triangle if o.lit >> k & 1 != 0 => {
                    let wl = get(&o.light_dir, k);
                    let origin = offset_ray_origin(st.p, st.p_error, ng, wl.into());
                    let shadow = shadow_ray(origin, Some(get(&o.light_point, k).into()), wl);
                    if !t.occluded(&shadow, st.key)? {
                        l += get(&o.light_add, k);
                    }
                }
                LaneLight::Other(choice) => {
                    if let Some(c) = self.other_light(t, k, (st.p, st.p_error), choice, st.key)? {
                        l += c;
                    }
                }
                _ => {}
            }
            path.set_radiance(l);
            let mut more = o.goes_on >> k & 1 != 0;
            if more {
                let mut beta = get(&o.beta_next, k);
                if self.bounce >= ROULETTE_FROM_BOUNCE {
                    let survive = o.survive[k];
                    more = st.u_roulette < survive;
                    beta /= survive;
                }
                if more {
                    path.go_on(
                        t,
                        beta,
                        (st.p, st.p_error),
                        ng,
                        get(&o.wi, k),
                        o.pdf[k],
                        false,
                        st.direction_dim,
                    );
                }
            }
            if path.end_bounce(more, max_depth) {
                live += 1;
            } else {
                radiance[st.lane] = path.radiance();
                paths[st.lane] = None;
            }
        }
        Ok(live)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{
        bsdf::{cosine_hemisphere, diffuse_cosine},
        integrator::roulette_survival,
        math::{Frame, power_heuristic, safe_sqrt},
    };

    /// The arithmetic of lane `k` (of `input`) as the one-path bounce does it:
    /// [`PathState::shade`]'s for a Lambertian BSDF, with [`Light::sample`]'s for a
    /// triangle light, with the very functions they call. The definition the SIMD lanes
    /// of [`DiffuseWave::compute`] are held to.
    fn compute_lane(input: &Input, k: usize, out: &mut Output) {
        let i = input;
        let (wo, n, ng) = (get(&i.wo, k), get(&i.n, k), get(&i.ng, k));
        let (base, beta) = (get(&i.base, k), get(&i.beta, k));

        // Bsdf::sample: a cosine-weighted direction about the shading normal.
        let frame = Frame::from_normal(n);
        let wi = frame.to_world(cosine_hemisphere((i.u_dir[0][k], i.u_dir[1][k])));
        let cos_i = diffuse_cosine(n, ng, wo, wi);
        let pdf = cos_i.unwrap_or(0.0) * INV_PI;
        let sampled = cos_i.is_some() && pdf > 0.0;
        put(&mut out.wi, k, wi);
        out.pdf[k] = pdf;
        let beta_next = beta * base;
        let goes_on = sampled && beta_next.is_finite() && beta_next.max_element() > 0.0;
        out.goes_on |= (goes_on as u32) << k;
        put(&mut out.beta_next, k, beta_next);
        out.survive[k] = roulette_survival(beta_next);

        // Light::sample of a triangle light: a uniform point on it.
        let p = get(&i.p, k);
        let su = safe_sqrt(i.u_point[0][k]);
        let (b0, b1) = (1.0 - su, i.u_point[1][k] * su);
        let b2 = 1.0 - b0 - b1;
        let v = i.light_v.map(|c| get(&c, k));
        let q = v[0] * b0 + v[1] * b1 + v[2] * b2;
        let d = q - p;
        let d2 = d.length_squared();
        let wl = d / d2.sqrt();
        let cos_l = -get(&i.light_n, k).dot(wl);
        let two_sided = i.light_two_sided[k] != 0.0;
        let faces = !(cos_l <= 0.0 && !two_sided || cos_l == 0.0);
        let area2 = i.light_area2[k];
        let light_pdf = d2 / (cos_l.abs() * 0.5 * area2);
        let le = get(&i.light_le, k);
        // Bsdf::eval and Bsdf::pdf towards the light, and the weight against BSDF sampling.
        let cos_l_i = diffuse_cosine(n, ng, wo, wl);
        let f_bsdf = if cos_l_i.is_some() {
            base * INV_PI
        } else {
            Vec3::ZERO
        };
        let f = f_bsdf * wl.dot(n).abs();
        let pdf_light = light_pdf * i.pmf[k];
        let w = power_heuristic(pdf_light, cos_l_i.map_or(0.0, |c| c * INV_PI));
        let lit =
            area2 > 0.0 && d2 > 0.0 && faces && f.max_element() > 0.0 && le.max_element() > 0.0;
        out.lit |= (lit as u32) << k;
        put(&mut out.light_add, k, beta * f * le * (w / pdf_light));
        put(&mut out.light_dir, k, wl);
        put(&mut out.light_point, k, q);
    }

    /// A small deterministic generator (splitmix64).
    struct Numbers(u64);

    impl Numbers {
        fn next(&mut self) -> f32 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        }

        fn unit(&mut self) -> Vec3 {
            loop {
                let v = Vec3::new(self.next(), self.next(), self.next()) * 2.0 - Vec3::ONE;
                if v.length_squared() > 1e-4 {
                    return v.normalize();
                }
            }
        }

        fn vec(&mut self, scale: f32) -> Vec3 {
            (Vec3::new(self.next(), self.next(), self.next()) * 2.0 - Vec3::ONE) * scale
        }
    }

    /// Same bits, or both NaN (whose payload no one reads).
    fn agree(a: f32, b: f32) -> bool {
        a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
    }

    /// Eight lanes of SIMD arithmetic give, bit for bit, what the one-path bounce's own
    /// functions give lane by lane, over random hits and lights and over the edge cases:
    /// draws of exactly zero and one half (the disk's centre, its diagonals), normals along
    /// the axes (the frame's sign), lights of no area, one- and two-sided lights seen from
    /// behind, a point on the light itself, black surfaces and throughputs that overflow.
    #[test]
    fn simd_lanes_give_the_bits_of_the_one_path_bounce() {
        let mut r = Numbers(7);
        let specials = [0.0, 0.5, 0.25, 0.75, 1.0 - f32::EPSILON / 2.0];
        for round in 0..4000 {
            let mut input = Input::default();
            for k in 0..LANES {
                let case = (round * LANES + k) % 11;
                let wo = r.unit();
                let mut n = r.unit();
                let ng = if case == 1 { n } else { r.unit() };
                if case == 2 {
                    n = [Vec3::Z, -Vec3::Z, Vec3::X, -Vec3::Y][k % 4];
                }
                put(&mut input.wo, k, wo);
                put(&mut input.n, k, n);
                put(&mut input.ng, k, ng);
                let base = if case == 3 {
                    Vec3::ZERO
                } else {
                    r.vec(1.0).abs()
                };
                put(&mut input.base, k, base);
                let beta = if case == 4 {
                    Vec3::splat(f32::MAX)
                } else {
                    r.vec(2.0).abs()
                };
                put(&mut input.beta, k, beta);
                let p = r.vec(3.0);
                put(&mut input.p, k, p);
                for d in 0..2 {
                    input.u_dir[d][k] = if case == 5 {
                        specials[(round + d + k) % specials.len()]
                    } else {
                        r.next()
                    };
                    input.u_point[d][k] = if case == 6 { 0.0 } else { r.next() };
                }
                input.pmf[k] = r.next();
                let v = [r.vec(3.0), r.vec(3.0), r.vec(3.0)];
                let v = match case {
                    7 => [v[0], v[0], v[0]],
                    // The shaded point is the light's corner the draw lands on.
                    6 => [p, v[1], v[2]],
                    _ => v,
                };
                let Light::Triangle { n: ln, area2, .. } =
                    Light::triangle(v, [glam::Vec2::ZERO; 3], 0, false)
                else {
                    unreachable!("Light::triangle makes a triangle light")
                };
                for (c, at) in input.light_v.iter_mut().zip(v) {
                    put(c, k, at);
                }
                put(&mut input.light_n, k, ln);
                input.light_area2[k] = area2;
                input.light_two_sided[k] = (case % 2) as f32;
                put(&mut input.light_le, k, r.vec(5.0).abs());
            }
            let (mut simd, mut lanes) = (Output::default(), Output::default());
            DiffuseWave::compute(&input, &mut simd);
            for k in 0..LANES {
                compute_lane(&input, k, &mut lanes);
            }
            assert_eq!(simd.goes_on, lanes.goes_on, "round {round}");
            assert_eq!(simd.lit, lanes.lit, "round {round}");
            let v3 = |o: &Output| [o.wi, o.beta_next, o.light_point, o.light_dir, o.light_add];
            for (which, (a, b)) in v3(&simd).iter().zip(v3(&lanes)).enumerate() {
                for c in 0..3 {
                    for k in 0..LANES {
                        assert!(
                            agree(a[c][k], b[c][k]),
                            "round {round}, vector {which}, coordinate {c}, lane {k}: {} against {}",
                            a[c][k],
                            b[c][k]
                        );
                    }
                }
            }
            for k in 0..LANES {
                assert!(
                    agree(simd.pdf[k], lanes.pdf[k]),
                    "round {round} pdf lane {k}"
                );
                assert!(
                    agree(simd.survive[k], lanes.survive[k]),
                    "round {round} survival lane {k}"
                );
            }
        }
    }
}
