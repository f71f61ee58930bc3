//! Light sources: KHR_lights_punctual lights and emissive triangles, and the choice of one
//! light per shading point in proportion to estimated power.

use glam::{Vec2, Vec3, Vec3A};
use serde::{Deserialize, Serialize};

use crate::{
    math::{PI, luminance, safe_sqrt, sincos_turn},
    scene::SceneHeader,
    source::{DataError, SceneData},
    texture,
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Light {
    /// Radiant intensity in W/sr (glTF: candela).
    Point { position: Vec3, intensity: Vec3 },
    Spot {
        position: Vec3,
        direction: Vec3,
        intensity: Vec3,
        cos_inner: f32,
        cos_outer: f32,
    },
    /// `direction` is where the light travels; `irradiance` in W/m^2 (glTF: lux).
    Directional { direction: Vec3, irradiance: Vec3 },
    /// One emissive triangle. Radiance comes from its material (factor, strength, texture).
    /// Made by [`Light::triangle`], which works out its unit normal and twice its area once
    /// (every light sample needs them); a header received is checked to agree.
    Triangle {
        p: [Vec3; 3],
        /// Unit normal, following the winding (zero for a triangle of no area).
        n: Vec3,
        /// Twice the area: the length of the corners' cross product.
        area2: f32,
        uv: [Vec2; 3],
        material: u32,
        two_sided: bool,
    },
    /// Radiance from every direction, seen by rays that leave the scene.
    Environment(Environment),
}

/// The world around the scene: radiance `zenith` straight up (+Y), `nadir` straight down,
/// blended linearly in between; a uniform environment has the two equal.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Environment {
    pub zenith: Vec3,
    pub nadir: Vec3,
}

impl Environment {
    pub fn uniform(radiance: Vec3) -> Environment {
        Environment {
            zenith: radiance,
            nadir: radiance,
        }
    }

    /// The default for scenes without lights: a bright sky over a darker ground, so that
    /// shapes show their relief as they would outdoors.
    pub fn sky() -> Environment {
        Environment {
            zenith: Vec3::ONE,
            nadir: Vec3::splat(0.25),
        }
    }

    /// Radiance arriving from direction `d` (unit), i.e. seen looking along `d`.
    #[inline]
    pub fn radiance(&self, d: Vec3) -> Vec3 {
        let t = (0.5 + 0.5 * d.y).clamp(0.0, 1.0);
        self.nadir + (self.zenith - self.nadir) * t
    }

    pub fn mean(&self) -> Vec3 {
        (self.zenith + self.nadir) * 0.5
    }

    pub fn is_black(&self) -> bool {
        self.zenith.max_element() <= 0.0 && self.nadir.max_element() <= 0.0
    }

    pub fn is_finite(&self) -> bool {
        self.zenith.is_finite() && self.nadir.is_finite()
    }
}

/// Density of a uniformly sampled direction on the sphere.
pub const UNIFORM_SPHERE_PDF: f32 = 1.0 / (4.0 * PI);

/// A uniformly distributed unit vector.
pub fn uniform_sphere(u: (f32, f32)) -> Vec3 {
    let z = 1.0 - 2.0 * u.0;
    let r = safe_sqrt(1.0 - z * z);
    let (sin, cos) = sincos_turn(u.1);
    Vec3::new(r * cos, r * sin, z)
}

/// A point on a light seen from a shading point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction from the shading point to the light.
    pub wi: Vec3,
    /// Target of the shadow ray; for directional lights, `None` (unbounded).
    pub point: Option<Vec3A>,
    /// Incident radiance (or, for delta lights, irradiance-like intensity / d^2).
    pub li: Vec3,
    /// Density in solid angle times the probability of choosing this light; for delta lights
    /// just the choice probability.
    pub pdf: f32,
    pub delta: bool,
}

/// The largest f32 below 1.
const ONE_BELOW_ONE: f32 = 1.0 - f32::EPSILON / 2.0;

/// The distribution of lights by power: its cumulative sums (what travels and is checked,
/// see `SceneHeader::validate`) and, made from them wherever the distribution is built or
/// decoded, an alias table (Walker 1977, Vose 1991) that picks a light in constant time
/// however many there are: one bucket per light, each keeping its own light with some
/// probability and giving another otherwise.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(from = "CdfForm", into = "CdfForm")]
pub struct LightDistribution {
    /// Normalised running sums; the last is 1.
    pub cdf: Vec<f32>,
    /// Per bucket: the probability of keeping its own light, and the light it gives
    /// otherwise (always below the number of lights).
    alias: Vec<(f32, u32)>,
}

/// What a [`LightDistribution`] is on the wire: its cumulative sums alone.
#[derive(Clone, Serialize, Deserialize)]
struct CdfForm {
    cdf: Vec<f32>,
}

impl From<CdfForm> for LightDistribution {
    fn from(form: CdfForm) -> LightDistribution {
        LightDistribution::from_cdf(form.cdf)
    }
}

impl From<LightDistribution> for CdfForm {
    fn from(d: LightDistribution) -> CdfForm {
        CdfForm { cdf: d.cdf }
    }
}

/// The alias table is made from the sums, so they say everything.
impl PartialEq for LightDistribution {
    fn eq(&self, other: &Self) -> bool {
        self.cdf == other.cdf
    }
}

impl LightDistribution {
    pub fn new(weights: &[f64]) -> LightDistribution {
        let total: f64 = weights
            .iter()
            .map(|w| if w.is_finite() && *w > 0.0 { *w } else { 0.0 })
            .sum();
        if weights.is_empty() {
            return LightDistribution::default();
        }
        let mut acc = 0.0f64;
        let n = weights.len() as f64;
        let mut cdf = weights
            .iter()
            .map(|w| {
                let w = if w.is_finite() && *w > 0.0 { *w } else { 0.0 };
                acc += if total > 0.0 { w / total } else { 1.0 / n };
                acc.min(1.0) as f32
            })
            .collect::<Vec<_>>();
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        LightDistribution::from_cdf(cdf)
    }

    /// The distribution of these sums, with its alias table. Sums from the wire are checked
    /// only later, so any numbers give a table (of the probabilities that are finite and
    /// positive, uniform when none is) and never a panic.
    fn from_cdf(cdf: Vec<f32>) -> LightDistribution {
        let n = cdf.len();
        let pmf: Vec<f64> = (0..n)
            .map(|i| {
                let p = cdf[i] as f64 - if i == 0 { 0.0 } else { cdf[i - 1] as f64 };
                if p.is_finite() && p > 0.0 { p } else { 0.0 }
            })
            .collect();
        let total: f64 = pmf.iter().sum();
        // Each light's share times n: buckets of 1 are full. Vose's method fills the
        // buckets of the lights below 1 from those above, one light each.
        let mut scaled: Vec<f64> = pmf
            .iter()
            .map(|&p| {
                if total > 0.0 {
                    p * n as f64 / total
                } else {
                    1.0
                }
            })
            .collect();
        let mut alias: Vec<(f32, u32)> = (0..n as u32).map(|i| (1.0, i)).collect();
        let (mut small, mut large): (Vec<usize>, Vec<usize>) =
            (0..n).partition(|&i| scaled[i] < 1.0);
        while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
            small.pop();
            alias[s] = (scaled[s] as f32, l as u32);
            scaled[l] -= 1.0 - scaled[s];
            if scaled[l] < 1.0 {
                large.pop();
                small.push(l);
            }
        }
        // What is left is 1 but for rounding: those buckets keep their own light.
        LightDistribution { cdf, alias }
    }

    pub fn is_empty(&self) -> bool {
        self.cdf.is_empty()
    }

    /// Chooses a light; returns its index and probability.
    pub fn sample(&self, u: f32) -> Option<(usize, f32)> {
        self.sample_reusing(u).map(|(i, pmf, _)| (i, pmf))
    }

    /// Chooses a light like [`LightDistribution::sample`] and also returns a number that is
    /// uniform in [0, 1) and independent of the choice (the part of `u` the choice did not
    /// use), so it can place the point on the light: one stratified 2D draw then covers
    /// every light together (the two triangles of a quad light get the draw's
    /// stratification between them instead of a coin toss each).
    #[inline]
    pub fn sample_reusing(&self, u: f32) -> Option<(usize, f32, f32)> {
        let n = self.alias.len();
        if n == 0 {
            return None;
        }
        // In f64, u * n and its fraction are exact for any number of lights an index holds.
        let scaled = u as f64 * n as f64;
        let bucket = (scaled as usize).min(n - 1);
        let frac = scaled - bucket as f64;
        let (keep, other) = self.alias[bucket];
        let keep = keep as f64;
        let (i, reused) = if frac < keep {
            (bucket, frac / keep)
        } else {
            (other as usize, (frac - keep) / (1.0 - keep))
        };
        Some((i, self.pmf(i), (reused as f32).clamp(0.0, ONE_BELOW_ONE)))
    }

    pub fn pmf(&self, i: usize) -> f32 {
        let hi = self.cdf.get(i).copied().unwrap_or(0.0);
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        hi - lo
    }
}

/// glTF's smooth spot cone falloff.
pub fn spot_falloff(cos: f32, cos_inner: f32, cos_outer: f32) -> f32 {
    let scale = 1.0 / (cos_inner - cos_outer).max(1e-3);
    let a = ((cos - cos_outer) * scale).clamp(0.0, 1.0);
    a * a
}

/// Emitted radiance of a triangle light's material at `uv`.
pub fn triangle_radiance<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    material: u32,
    uv: Vec2,
) -> Result<Vec3, DataError> {
    let m = &scene.materials[material as usize];
    let mut le = m.emissive;
    if let Some(t) = &m.emissive_tex {
        let info = &scene.textures[t.texture as usize];
        let uv = t.transform.map_or(uv, |x| x.apply(uv));
        le *= texture::sample(data, info, uv, true)?.truncate();
    }
    Ok(le)
}

impl Light {
    /// An emissive triangle with corners `p` (counter-clockwise seen from its front).
    pub fn triangle(p: [Vec3; 3], uv: [Vec2; 3], material: u32, two_sided: bool) -> Light {
        let cross = (p[1] - p[0]).cross(p[2] - p[0]);
        let area2 = cross.length();
        let n = if area2 > 0.0 {
            cross / area2
        } else {
            Vec3::ZERO
        };
        Light::Triangle {
            p,
            n,
            area2,
            uv,
            material,
            two_sided,
        }
    }

    pub fn is_delta(&self) -> bool {
        !matches!(self, Light::Triangle { .. } | Light::Environment(_))
    }

    /// Estimated emitted power (luminance), for choosing among lights.
    pub fn power(&self, scene: &SceneHeader, scene_radius: f32) -> f64 {
        let p = match self {
            Light::Point { intensity, .. } => 4.0 * PI * luminance(*intensity),
            Light::Spot {
                intensity,
                cos_inner,
                cos_outer,
                ..
            } => 2.0 * PI * (1.0 - 0.5 * (cos_inner + cos_outer)) * luminance(*intensity),
            Light::Directional { irradiance, .. } => {
                PI * scene_radius * scene_radius * luminance(*irradiance)
            }
            Light::Environment(env) => {
                4.0 * PI * PI * scene_radius * scene_radius * luminance(env.mean())
            }
            Light::Triangle {
                area2,
                material,
                two_sided,
                ..
            } => {
                let area = 0.5 * area2;
                let m = &scene.materials[*material as usize];
                let mut le = m.emissive;
                if let Some(t) = &m.emissive_tex {
                    le *= Vec3::from_slice(&scene.textures[t.texture as usize].average_srgb[..3]);
                }
                let sides = if *two_sided { 2.0 } else { 1.0 };
                // Textured emitters whose average is black still get a little weight, so
                // that no emitting point has zero probability (which would bias the image).
                PI * area * sides * luminance(le).max(luminance(m.emissive) * 1e-3)
            }
        };
        if p.is_finite() {
            p.max(0.0) as f64
        } else {
            0.0
        }
    }

    /// Samples light arriving at `p` (a point on a surface, or anywhere).
    pub fn sample<D: SceneData>(
        &self,
        scene: &SceneHeader,
        data: &D,
        p: Vec3,
        u: (f32, f32),
    ) -> Result<Option<LightSample>, DataError> {
        Ok(match self {
            Light::Point {
                position,
                intensity,
            } => {
                let d = *position - p;
                let d2 = d.length_squared();
                (d2 > 0.0).then(|| LightSample {
                    wi: d / d2.sqrt(),
                    point: Some((*position).into()),
                    li: *intensity / d2,
                    pdf: 1.0,
                    delta: true,
                })
            }
            Light::Spot {
                position,
                direction,
                intensity,
                cos_inner,
                cos_outer,
            } => {
                let d = *position - p;
                let d2 = d.length_squared();
                if d2 <= 0.0 {
                    return Ok(None);
                }
                let wi = d / d2.sqrt();
                let falloff = spot_falloff((-wi).dot(*direction), *cos_inner, *cos_outer);
                (falloff > 0.0).then(|| LightSample {
                    wi,
                    point: Some((*position).into()),
                    li: *intensity * falloff / d2,
                    pdf: 1.0,
                    delta: true,
                })
            }
            Light::Directional {
                direction,
                irradiance,
            } => Some(LightSample {
                wi: -*direction,
                point: None,
                li: *irradiance,
                pdf: 1.0,
                delta: true,
            }),
            Light::Environment(env) => {
                let wi = uniform_sphere(u);
                Some(LightSample {
                    wi,
                    point: None,
                    li: env.radiance(wi),
                    pdf: UNIFORM_SPHERE_PDF,
                    delta: false,
                })
            }
            Light::Triangle {
                p: v,
                n,
                area2,
                uv,
                material,
                two_sided,
            } => {
                let (n, area2) = (*n, *area2);
                if !(area2 > 0.0) {
                    return Ok(None);
                }
                // Uniform point on the triangle.
                let su = safe_sqrt(u.0);
                let (b0, b1) = (1.0 - su, u.1 * su);
                let b2 = 1.0 - b0 - b1;
                let q = v[0] * b0 + v[1] * b1 + v[2] * b2;
                let d = q - p;
                let d2 = d.length_squared();
                if !(d2 > 0.0) {
                    return Ok(None);
                }
                let wi = d / d2.sqrt();
                let cos_l = -n.dot(wi);
                if cos_l <= 0.0 && !two_sided || cos_l == 0.0 {
                    return Ok(None);
                }
                let le = triangle_radiance(
                    scene,
                    data,
                    *material,
                    uv[0] * b0 + uv[1] * b1 + uv[2] * b2,
                )?;
                let pdf = d2 / (cos_l.abs() * 0.5 * area2);
                Some(LightSample {
                    wi,
                    point: Some(q.into()),
                    li: le,
                    pdf,
                    delta: false,
                })
            }
        })
    }

    /// Density (solid angle, at `p`) with which [`Light::sample`] would produce the point `q`
    /// on this triangle light. Zero for delta lights and the environment (see
    /// [`UNIFORM_SPHERE_PDF`]).
    pub fn pdf_at(&self, p: Vec3, q: Vec3) -> f32 {
        match self {
            Light::Triangle { n, area2, .. } => {
                let area2 = *area2;
                if !(area2 > 0.0) {
                    return 0.0;
                }
                let d = q - p;
                let d2 = d.length_squared();
                let cos_l = n.dot(d / d2.sqrt()).abs();
                if cos_l == 0.0 {
                    0.0
                } else {
                    d2 / (cos_l * 0.5 * area2)
                }
            }
            _ => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sweeps `u` over a fine grid: how often each light is chosen, and a histogram of the
    /// reused numbers of each light.
    fn sweep(d: &LightDistribution, n: usize) -> (Vec<f64>, Vec<[usize; 4]>) {
        let lights = d.cdf.len();
        let (mut freq, mut hist) = (vec![0.0; lights], vec![[0usize; 4]; lights]);
        for k in 0..n {
            let u = (k as f64 + 0.5) as f32 / n as f32;
            let (i, pmf, reused) = d.sample_reusing(u).unwrap();
            assert_eq!(pmf, d.pmf(i));
            assert!((0.0..1.0).contains(&reused), "{reused}");
            freq[i] += 1.0 / n as f64;
            hist[i][(reused * 4.0) as usize] += 1;
        }
        (freq, hist)
    }

    #[test]
    fn distribution_follows_weights() {
        let d = LightDistribution::new(&[1.0, 3.0, 0.0, 4.0]);
        assert!((d.pmf(0) - 0.125).abs() < 1e-6);
        assert!((d.pmf(1) - 0.375).abs() < 1e-6);
        assert_eq!(d.pmf(2), 0.0);
        assert!((d.pmf(3) - 0.5).abs() < 1e-6);
        let (freq, _) = sweep(&d, 1 << 16);
        for (i, f) in freq.iter().enumerate() {
            assert!((f - d.pmf(i) as f64).abs() < 1e-4, "light {i}: {f}");
        }
        assert_eq!(d.sample(0.0).unwrap().0, 0);
        assert_ne!(d.sample(0.999_999_94).unwrap().0, 2);
    }

    #[test]
    fn reused_number_is_uniform_within_the_choice() {
        for weights in [&[1.0, 3.0][..], &[5.0, 1.0, 1.0, 2.0, 0.5, 7.0, 3.0]] {
            let d = LightDistribution::new(weights);
            let n = 1 << 16;
            let (freq, hist) = sweep(&d, n);
            for (i, h) in hist.iter().enumerate() {
                let per_bin = freq[i] * n as f64 / 4.0;
                for &c in h {
                    assert!((c as f64 - per_bin).abs() <= 2.0 + 1e-3 * per_bin, "{h:?}");
                }
            }
        }
        let d = LightDistribution::new(&[1.0, 3.0]);
        assert_eq!(d.sample_reusing(0.0), Some((0, 0.25, 0.0)));
        let (_, _, u) = d.sample_reusing(0.999_999_94).unwrap();
        assert!(u < 1.0);
    }

    /// Two equal lights (the triangles of a quad light) split `u` in halves, each reused
    /// whole: what inverting the cumulative sums gave.
    #[test]
    fn equal_lights_split_the_interval_in_order() {
        let d = LightDistribution::new(&[2.0, 2.0]);
        assert_eq!(d.sample_reusing(0.25), Some((0, 0.5, 0.5)));
        assert_eq!(d.sample_reusing(0.75), Some((1, 0.5, 0.5)));
    }

    /// The table is made again from the sums on decoding: the same choices on both ends.
    #[test]
    fn a_decoded_distribution_chooses_the_same_lights() {
        let d = LightDistribution::new(&[5.0, 1.0, 1.0, 2.0, 0.5]);
        // What serde does on both ends (`serde(into, from)`).
        let back = LightDistribution::from(CdfForm::from(d.clone()));
        for k in 0..1000 {
            let u = k as f32 / 1000.0;
            assert_eq!(back.sample_reusing(u), d.sample_reusing(u));
        }
        // Garbage sums give a table, not a panic (validation refuses them afterwards).
        for cdf in [vec![f32::NAN, 0.5], vec![1.0, 0.2, -3.0], vec![0.0; 3]] {
            let d = LightDistribution::from_cdf(cdf);
            assert!(d.sample_reusing(0.7).unwrap().0 < 3);
        }
    }

    #[test]
    fn all_zero_weights_become_uniform() {
        let d = LightDistribution::new(&[0.0, 0.0]);
        assert!((d.pmf(0) - 0.5).abs() < 1e-6);
    }

    #[test]
    fn spot_falloff_edges() {
        let (ci, co) = (0.9f32, 0.8f32);
        assert_eq!(spot_falloff(1.0, ci, co), 1.0);
        assert_eq!(spot_falloff(0.7, ci, co), 0.0);
        assert!(spot_falloff(0.85, ci, co) > 0.0 && spot_falloff(0.85, ci, co) < 1.0);
    }
}
