//! Integrators: the radiance arriving along one camera ray.
//!
//! * `path`: unbiased path tracing with next-event estimation, multiple importance sampling
//!   (power heuristic) between light and BSDF sampling, and Russian roulette.
//! * `whitted`: the paper's ray tracer: direct light from every punctual light (area lights
//!   sampled as points), hard shadows, mirror reflection and refraction with Fresnel weights,
//!   texture mapping, to a bounded depth; branches are pruned on the product of the weights
//!   along their path and limited to a budget of specular rays per camera ray, so glass facing
//!   glass costs a bounded number of rays, not 2^depth.

use glam::{Vec3, Vec3A};
use serde::{Deserialize, Serialize};

use crate::{
    bsdf::Bsdf,
    chunk::{NO_LIGHT, SurfaceAttributes},
    light::UNIFORM_SPHERE_PDF,
    material::{self, Material, ShadingParams},
    math::{offset_ray_origin, power_heuristic},
    ray::Ray,
    render::RenderSettings,
    sampler::{Draws, PIXEL_DIM, SampleKey, Sampler},
    scene::SceneHeader,
    source::{DataError, SceneData},
    trace::{AlphaKey, Tracer, shadow_ray},
};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum IntegratorKind {
    #[default]
    Path,
    Whitted,
}

/// An integrator name magg does not have.
#[derive(Debug, thiserror::Error)]
#[error("unknown integrator {0:?} (expected path or whitted)")]
pub struct UnknownIntegrator(pub String);

impl std::str::FromStr for IntegratorKind {
    type Err = UnknownIntegrator;
    fn from_str(s: &str) -> Result<Self, UnknownIntegrator> {
        match s {
            "path" => Ok(IntegratorKind::Path),
            "whitted" => Ok(IntegratorKind::Whitted),
            other => Err(UnknownIntegrator(other.to_string())),
        }
    }
}

impl std::fmt::Display for IntegratorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            IntegratorKind::Path => "path",
            IntegratorKind::Whitted => "whitted",
        })
    }
}

impl IntegratorKind {
    /// The longest path when the user names none. Whitted's is shorter: its tree of mirror
    /// and glass branches, not one path, grows with the depth.
    pub fn default_max_depth(self) -> u32 {
        match self {
            IntegratorKind::Path => 64,
            IntegratorKind::Whitted => 16,
        }
    }
}

/// How far the Whitted integrator follows mirror and glass branches. The defaults cost no
/// visible energy (on the shared glass scenes, relMSE below 1e-3 against ten times tighter
/// thresholds and twice the budget: `magg-host bench whitted`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WhittedLimits {
    /// A reflected or refracted branch is traced only while the product of the weights along
    /// its path (Fresnel terms, tints, absorption) can still add more than this to the pixel
    /// (Hall and Greenberg's adaptive depth control). Pruning on one branch's own weight
    /// instead lets the tree double at every dielectric: 2^depth rays.
    pub min_contribution: f32,
    /// At most this many reflected or refracted rays per camera ray, spent depth first.
    /// Total internal reflection keeps a branch's weight near 1, so this is what bounds such
    /// loops. Deterministic, so images stay the same bytes anywhere.
    pub max_specular_rays: u32,
}

impl Default for WhittedLimits {
    fn default() -> Self {
        WhittedLimits {
            min_contribution: 1e-3,
            max_specular_rays: 256,
        }
    }
}

/// Radiance along `ray` (a camera ray) for one sample.
pub fn radiance<D: SceneData>(
    t: &Tracer<D>,
    settings: &RenderSettings,
    ray: Ray,
    sampler: &mut Sampler<'_>,
) -> Result<Vec3, DataError> {
    let max_depth = settings.max_depth;
    match settings.integrator {
        IntegratorKind::Path => path(t, ray, sampler, max_depth, settings.clamp_indirect),
        IntegratorKind::Whitted => whitted(
            t,
            ray,
            sampler,
            Branch {
                depth: 0,
                max_depth,
                medium: None,
                throughput: Vec3::ONE,
            },
            &mut Budget {
                rays_left: settings.whitted.max_specular_rays,
                min_contribution: settings.whitted.min_contribution,
            },
        ),
    }
}

/// Beer-Lambert extinction of a volume material per unit length.
fn extinction(m: &Material) -> Vec3 {
    if !(m.attenuation_distance.is_finite() && m.attenuation_distance > 0.0) {
        return Vec3::ZERO;
    }
    let c = m.attenuation_color.clamp(Vec3::splat(1e-6), Vec3::ONE);
    Vec3::new(-c.x.ln(), -c.y.ln(), -c.z.ln()) / m.attenuation_distance
}

fn attenuate(t: f32, ray: &Ray, medium: Option<&Material>) -> Vec3 {
    match medium {
        Some(m) => {
            let sigma = extinction(m);
            let dist = t * ray.dir.length();
            Vec3::new(
                (-sigma.x * dist).exp(),
                (-sigma.y * dist).exp(),
                (-sigma.z * dist).exp(),
            )
        }
        None => Vec3::ONE,
    }
}

/// After a transmission through a refracting volume's surface: entering it if we came from
/// its front, leaving it otherwise.
fn next_medium(m: &Material, material_id: u32, front: bool, current: Option<u32>) -> Option<u32> {
    if m.thickness > 0.0 && m.transmission > 0.0 {
        if front { Some(material_id) } else { None }
    } else {
        current
    }
}

/// Light found by a caustic path (a rough bounce, then mirrors or glass, then the light:
/// what light sampling cannot find, so only rare lucky paths carry it), limited to `clamp`
/// in its largest channel when clamping is on (`clamp > 0`). Biased: it removes the energy
/// of the brightest such paths along with their noise (fireflies); off unless asked for.
#[inline]
fn clamped(c: Vec3, caustic: bool, clamp: f32) -> Vec3 {
    let peak = c.max_element();
    if caustic && clamp > 0.0 && peak > clamp {
        c * (clamp / peak)
    } else {
        c
    }
}

/// Russian roulette starts at this bounce...
pub(crate) const ROULETTE_FROM_BOUNCE: u32 = 3;
/// ...and keeps a path with probability (largest channel of its throughput) / this, at most
/// [`ROULETTE_MAX_SURVIVAL`]. Survivors are weighted up to about this throughput, so it bounds
/// how much one surviving path can add. With 1 (survival = throughput) the Cornell box's
/// hits past the fourth carried 36% of its variance for 3.5% of its light; 0.5 costs 5% more
/// instructions there for 19% less relMSE at equal samples, and leaves the demo scene's
/// time x relMSE as it was (+2% instructions, -3% relMSE: its error is caustics).
pub(crate) const ROULETTE_THROUGHPUT: f32 = 0.5;
/// Even a path of full throughput (mirrors, glass) ends sometimes, so that loops of total
/// internal reflection stop.
pub(crate) const ROULETTE_MAX_SURVIVAL: f32 = 0.95;

fn path<D: SceneData>(
    t: &Tracer<D>,
    ray: Ray,
    sampler: &mut Sampler<'_>,
    max_depth: u32,
    clamp: f32,
) -> Result<Vec3, DataError> {
    let mut state = PathState::new(ray, sampler);
    while state.step(t, sampler, max_depth, clamp)? {}
    Ok(state.radiance())
}

/// A path between its bounces: everything the path tracer carries from one hit to the next.
/// A bounce reads only this and the sampler's numbers for that bounce (which the sample
/// index and the bounce number fix), so a bounce that stopped for data a render node lacks
/// can be run again from the same state later and give the same bits: what lets a render
/// node put such a path aside while it traces others (memory-coherent rays,
/// [`crate::render::render_rect_coherent`]).
#[derive(Clone, Copy, Debug)]
pub struct PathState {
    ray: Ray,
    l: Vec3,
    beta: Vec3,
    /// Where the previous bounce sampled its direction, its density and whether it was a delta.
    prev: Option<(Vec3, f32, bool)>,
    medium: Option<u32>,
    /// Whether the path has scattered off a rough surface: light it then finds right after a
    /// mirror or glass bounce came by a caustic path.
    scattered_rough: bool,
    bounce: u32,
    /// The dimension of the draw that chose this ray's direction (the pixel position's for
    /// the camera ray): the light sample where the ray lands continues it
    /// ([`Sampler::get_2d_after`]).
    direction_dim: u32,
    /// The sample's key for draws not on the sampler's dimensions (alpha).
    sample: SampleKey,
}

impl PathState {
    /// A path about to follow its camera ray, for the sample `sampler` draws.
    pub fn new(ray: Ray, sampler: &impl Draws) -> PathState {
        PathState {
            ray,
            l: Vec3::ZERO,
            beta: Vec3::ONE,
            prev: None,
            medium: None,
            scattered_rough: false,
            bounce: 0,
            direction_dim: PIXEL_DIM,
            sample: sampler.key(),
        }
    }

    /// The light the path has gathered so far (all of it once it is done).
    pub fn radiance(&self) -> Vec3 {
        self.l
    }

    /// The bounce the path is at (0: its camera ray's hit).
    pub(crate) fn bounce(&self) -> u32 {
        self.bounce
    }

    /// The dimension of the draw that chose the path's ray, which the light draw where the
    /// ray lands continues.
    pub(crate) fn direction_dim(&self) -> u32 {
        self.direction_dim
    }

    /// The light gathered, written by a bounce taken outside [`PathState::step`].
    pub(crate) fn set_radiance(&mut self, l: Vec3) {
        self.l = l;
    }

    /// Ends a bounce taken outside [`PathState::step`] as it would: whether the path goes
    /// on after it (`more`: the bounce did not end it).
    pub(crate) fn end_bounce(&mut self, more: bool, max_depth: u32) -> bool {
        self.bounce += 1;
        more && self.bounce < max_depth
    }

    /// Follows the path through one more hit; false once it has ended (then it is not to be
    /// stepped again). On an error the state may be half updated: keep a copy to run the
    /// bounce again.
    #[inline(always)]
    pub fn step<D: SceneData>(
        &mut self,
        t: &Tracer<D>,
        sampler: &mut impl Draws,
        max_depth: u32,
        clamp: f32,
    ) -> Result<bool, DataError> {
        if self.bounce >= max_depth {
            return Ok(false);
        }
        let more = self.bounce_once(t, sampler, clamp)?;
        Ok(self.end_bounce(more, max_depth))
    }

    #[inline(always)]
    fn bounce_once<D: SceneData>(
        &mut self,
        t: &Tracer<D>,
        sampler: &mut impl Draws,
        clamp: f32,
    ) -> Result<bool, DataError> {
        match self.meet(t, sampler, clamp)? {
            Some(met) => self.shade(t, sampler, met),
            None => Ok(false),
        }
    }

    /// The first half of a bounce: the ray's hit, its surface and material, and the light
    /// the surface emits towards the path; `None` once the ray has left the scene (the
    /// path then ends, with the environment's light added). Writes the state only then.
    #[inline(always)]
    pub(crate) fn meet<'s, D: SceneData>(
        &mut self,
        t: &Tracer<'s, D>,
        sampler: &mut impl Draws,
        clamp: f32,
    ) -> Result<Option<Met<'s>>, DataError> {
        let scene = t.scene;
        let bounce = self.bounce;
        // Read in place, not copied: the last bounce wrote them field by field, and a copy
        // may read them in wider words than were written, which the processor cannot
        // forward from its store buffer (the load then waits for the stores to reach the
        // cache: part of an 11% slowdown of one build on the Cornell box).
        let ray = &self.ray;
        let prev = &self.prev;
        sampler.start_bounce(bounce);
        let key = AlphaKey {
            sample: self.sample,
            bounce,
        };
        let Some(hit) = t.closest(ray, key)? else {
            // The ray leaves the scene: the environment, weighted against light sampling.
            if let Some(env) = scene.environment_light {
                let weight = match prev {
                    None | Some((_, _, true)) => 1.0,
                    Some((_, pdf_bsdf, false)) => {
                        let pmf = scene.light_distribution.pmf(env as usize);
                        power_heuristic(*pdf_bsdf, pmf * UNIFORM_SPHERE_PDF)
                    }
                };
                let c = self.beta
                    * scene.environment.radiance(Vec3::from(ray.dir).normalize())
                    * weight;
                let caustic = self.scattered_rough && matches!(prev, Some((_, _, true)));
                self.l += clamped(c, caustic, clamp);
            }
            return Ok(None);
        };
        // Whatever below may still fail for data (a texture tile), the state is only
        // written once nothing can: a bounce run again must start from the same state.
        // Most paths travel through no medium: no call and no product by one for them.
        let beta = match self.medium {
            Some(m) => {
                self.beta * attenuate(hit.tri_hit.t, ray, Some(&scene.materials[m as usize]))
            }
            None => self.beta,
        };
        let mut l = self.l;

        let m = &scene.materials[hit.chunk.header().material as usize];
        let s = hit
            .chunk
            .surface_reading(hit.tri, &hit.tri_hit, || m.reads());
        let params = material::shading_params(scene, t.data, m, &s)?;
        let wo = -Vec3::from(ray.dir).normalize();
        let front = wo.dot(s.ng) > 0.0;

        // Emission, weighted against the light sampling that could also have found it.
        if params.emission.max_element() > 0.0 && (front || m.double_sided) {
            let weight = match prev {
                None | Some((_, _, true)) => 1.0,
                Some((p_prev, pdf_bsdf, false)) => {
                    if s.light == NO_LIGHT || s.light as usize >= scene.lights.len() {
                        1.0
                    } else {
                        let pmf = scene.light_distribution.pmf(s.light as usize);
                        let pdf_light =
                            pmf * scene.lights[s.light as usize].pdf_at(*p_prev, Vec3::from(s.p));
                        power_heuristic(*pdf_bsdf, pdf_light)
                    }
                }
            };
            let caustic = self.scattered_rough && matches!(prev, Some((_, _, true)));
            l += clamped(beta * params.emission * weight, caustic, clamp);
        }
        Ok(Some(Met {
            material: m,
            s,
            params,
            wo,
            front,
            beta,
            l,
            key,
        }))
    }

    /// The second half of a bounce, after [`PathState::meet`]: light sampled at the hit,
    /// then the direction the path goes on in; false when it ends here.
    #[inline(always)]
    pub(crate) fn shade<D: SceneData>(
        &mut self,
        t: &Tracer<D>,
        sampler: &mut impl Draws,
        met: Met<'_>,
    ) -> Result<bool, DataError> {
        let Met {
            material: m,
            s,
            params,
            wo,
            front,
            mut beta,
            mut l,
            key,
        } = met;
        let bounce = self.bounce;
        let bsdf = Bsdf::new(&params, s.ng, wo);
        let ng = Vec3A::from(bsdf.geometric_normal());

        // Next-event estimation. One 2D draw picks the light and the point on it, so the
        // points of a pixel's samples are stratified over all the lights together.
        let u_light = sampler.get_2d_after(self.direction_dim);

        // Where the path goes on is drawn now, though used only after the light sample: it
        // depends on nothing the light sample finds, and placed here its chain of divisions
        // and square roots runs while the processor works on the light sample and its shadow
        // ray, instead of after them. The draws keep their dimensions (each is keyed by its
        // dimension), so the numbers, and the image, are the same.
        let direction_dim = sampler.dim();
        let u_dir = sampler.get_2d();
        // A Lambertian surface has one lobe: no number is spent choosing it.
        let u_lobe = if bsdf.is_lambert() {
            0.0
        } else {
            sampler.get_1d()
        };
        let next = bsdf.sample(wo, u_lobe, u_dir);
        if !bsdf.is_pure_delta()
            && let Some(choice) = choose_light(t.scene, u_light)
            && let Some(c) = next_event(t, &bsdf, wo, (s.p, s.p_error), choice, beta, key)?
        {
            l += c;
        }
        // Nothing below asks for data.
        self.l = l;

        // Continue the path.
        let Some(bs) = next else {
            return Ok(false);
        };
        beta *= bs.weight;
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            return Ok(false);
        }
        // Russian roulette from the fourth hit, relative to half the throughput. Starting it
        // at the sixth hit instead (Mitsuba's default) was measured with survival = the
        // throughput: the Cornell box's time x relMSE fell 11-16%, but the demo scene (a
        // closed, bright room with caustics) took 30% longer for 10% worse time x relMSE.
        if bounce >= ROULETTE_FROM_BOUNCE {
            let survive = roulette_survival(beta);
            if sampler.get_1d() >= survive {
                return Ok(false);
            }
            beta /= survive;
        }
        if bs.transmitted {
            self.medium = next_medium(m, s.material, front, self.medium);
        }
        self.go_on(
            t,
            beta,
            (s.p, s.p_error),
            ng,
            bs.wi,
            bs.pdf,
            bs.delta,
            direction_dim,
        );
        Ok(true)
    }

    /// The path leaves the surface point `p` (with its rounding error bound, and `ng` its
    /// true normal turned to the path's side) in direction `wi`, drawn with density `pdf`
    /// (a delta or not) from the draw at `direction_dim`, carrying `beta`.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn go_on<D: SceneData>(
        &mut self,
        t: &Tracer<D>,
        beta: Vec3,
        (p, p_error): (Vec3A, Vec3A),
        ng: Vec3A,
        wi: Vec3,
        pdf: f32,
        delta: bool,
        direction_dim: u32,
    ) {
        self.beta = beta;
        let origin = offset_ray_origin(p, p_error, ng, wi.into());
        self.ray = Ray::new(origin, wi.into(), f32::INFINITY);
        t.count_secondary_ray();
        self.prev = Some((Vec3::from(p), pdf, delta));
        self.direction_dim = direction_dim;
        self.scattered_rough |= !delta;
    }
}

/// What [`PathState::meet`] found: the surface hit, its material and shading parameters,
/// and the path's throughput and light so far (with what the surface emits).
pub(crate) struct Met<'s> {
    pub material: &'s Material,
    pub s: SurfaceAttributes,
    pub params: ShadingParams,
    pub wo: Vec3,
    pub front: bool,
    pub beta: Vec3,
    pub l: Vec3,
    pub key: AlphaKey,
}

/// The chance that Russian roulette keeps a path of throughput `beta`.
#[inline(always)]
pub(crate) fn roulette_survival(beta: Vec3) -> f32 {
    (beta.max_element() / ROULETTE_THROUGHPUT).min(ROULETTE_MAX_SURVIVAL)
}

/// The light a 2D light draw `u` picks for next-event estimation: its index, its
/// probability, and the draw that places the point on it (the part of `u.0` the choice did
/// not use, then `u.1`); `None` when the scene has no light.
#[inline(always)]
pub(crate) fn choose_light(scene: &SceneHeader, u: (f32, f32)) -> Option<LightChoice> {
    let (i, pmf, u_point) = scene.light_distribution.sample_reusing(u.0)?;
    Some(LightChoice {
        light: i,
        pmf,
        u: (u_point, u.1),
    })
}

/// See [`choose_light`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct LightChoice {
    pub light: usize,
    pub pmf: f32,
    pub u: (f32, f32),
}

/// Next-event estimation at the surface point `p` (with its rounding error bound) for a
/// path of throughput `beta`: the light `choice` picked (and the point on it), weighted
/// against BSDF sampling; `None` when it adds nothing (a light facing away or blocked).
#[inline(always)]
pub(crate) fn next_event<D: SceneData>(
    t: &Tracer<D>,
    bsdf: &Bsdf,
    wo: Vec3,
    (p, p_error): (Vec3A, Vec3A),
    choice: LightChoice,
    beta: Vec3,
    key: AlphaKey,
) -> Result<Option<Vec3>, DataError> {
    let scene = t.scene;
    let pmf = choice.pmf;
    let light = &scene.lights[choice.light];
    let Some(ls) = light.sample(scene, t.data, Vec3::from(p), choice.u)? else {
        return Ok(None);
    };
    let ns = bsdf.shading_normal();
    let f = bsdf.eval(wo, ls.wi) * ls.wi.dot(ns).abs();
    if !(f.max_element() > 0.0 && ls.li.max_element() > 0.0) {
        return Ok(None);
    }
    let ng = Vec3A::from(bsdf.geometric_normal());
    let origin = offset_ray_origin(p, p_error, ng, ls.wi.into());
    let shadow = shadow_ray(origin, ls.point, ls.wi);
    if t.occluded(&shadow, key)? {
        return Ok(None);
    }
    Ok(Some(if ls.delta {
        beta * f * ls.li / pmf
    } else {
        let pdf_light = ls.pdf * pmf;
        let w = power_heuristic(pdf_light, bsdf.pdf(wo, ls.wi));
        beta * f * ls.li * (w / pdf_light)
    }))
}

/// Surfaces smoother than this are mirrors to the Whitted integrator.
const WHITTED_MIRROR_ROUGHNESS: f32 = 0.2;

/// What one camera ray's Whitted tree may still spend.
struct Budget {
    rays_left: u32,
    min_contribution: f32,
}

/// Where a Whitted branch stands: its depth, the medium it travels in, and the product of
/// the weights that lead to it.
#[derive(Clone, Copy)]
struct Branch {
    depth: u32,
    max_depth: u32,
    medium: Option<u32>,
    throughput: Vec3,
}

fn whitted<D: SceneData>(
    t: &Tracer<D>,
    ray: Ray,
    sampler: &mut Sampler<'_>,
    branch: Branch,
    budget: &mut Budget,
) -> Result<Vec3, DataError> {
    let Branch {
        depth,
        max_depth,
        medium,
        throughput,
    } = branch;
    let scene = t.scene;
    sampler.start_bounce(depth);
    let key = AlphaKey::new(sampler, depth);
    let Some(hit) = t.closest(&ray, key)? else {
        return Ok(scene.environment.radiance(Vec3::from(ray.dir).normalize()));
    };
    let atten = attenuate(
        hit.tri_hit.t,
        &ray,
        medium.map(|m| &scene.materials[m as usize]),
    );
    let m = &scene.materials[hit.chunk.header().material as usize];
    let s = hit
        .chunk
        .surface_reading(hit.tri, &hit.tri_hit, || m.reads());
    let params = material::shading_params(scene, t.data, m, &s)?;
    let wo = -Vec3::from(ray.dir).normalize();
    let front = wo.dot(s.ng) > 0.0;
    let mut l = Vec3::ZERO;
    if front || m.double_sided {
        l += params.emission;
    }
    let bsdf = Bsdf::new(&params, s.ng, wo);
    let ns = bsdf.shading_normal();
    let ng = Vec3A::from(bsdf.geometric_normal());
    let p = Vec3::from(s.p);

    // Direct light: every punctual light, plus one point on an area light chosen by power.
    let direct = |ls: crate::light::LightSample, scale: f32| -> Result<Vec3, DataError> {
        let f = bsdf.eval(wo, ls.wi) * ls.wi.dot(ns).abs();
        if f.max_element() <= 0.0 || ls.li.max_element() <= 0.0 {
            return Ok(Vec3::ZERO);
        }
        let origin = offset_ray_origin(s.p, s.p_error, ng, ls.wi.into());
        if t.occluded(&shadow_ray(origin, ls.point, ls.wi), key)? {
            return Ok(Vec3::ZERO);
        }
        Ok(f * ls.li * scale)
    };
    let u_light = sampler.get_1d();
    let u_point = sampler.get_2d();
    for light in scene.punctual_lights() {
        if let Some(ls) = light.sample(scene, t.data, p, (0.5, 0.5))? {
            l += direct(ls, 1.0)?;
        }
    }
    if let Some((li, pmf)) = scene.light_distribution.sample(u_light) {
        let light = &scene.lights[li];
        if !light.is_delta()
            && let Some(ls) = light.sample(scene, t.data, p, u_point)?
            && ls.pdf > 0.0
        {
            l += direct(ls, 1.0 / (ls.pdf * pmf))?;
        }
    }

    // Mirror reflection and refraction.
    if depth + 1 < max_depth {
        for (wi, weight, transmitted) in
            bsdf.specular_paths(wo, params.roughness < WHITTED_MIRROR_ROUGHNESS)
        {
            let path_weight = throughput * atten * weight;
            if path_weight.max_element() <= budget.min_contribution {
                continue;
            }
            let Some(left) = budget.rays_left.checked_sub(1) else {
                break;
            };
            budget.rays_left = left;
            let origin = offset_ray_origin(s.p, s.p_error, ng, wi.into());
            t.count_secondary_ray();
            let next = if transmitted {
                next_medium(m, s.material, front, medium)
            } else {
                medium
            };
            l += weight
                * whitted(
                    t,
                    Ray::new(origin, wi.into(), f32::INFINITY),
                    sampler,
                    Branch {
                        depth: depth + 1,
                        max_depth,
                        medium: next,
                        throughput: path_weight,
                    },
                    budget,
                )?;
        }
    }
    Ok(l * atten)
}
