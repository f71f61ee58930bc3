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
    Triangle {
        p: [Vec3; 3],
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

/// Cumulative distribution over lights by power.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct LightDistribution {
    /// Normalised running sums; the last is 1.
    pub cdf: Vec<f32>,
}

impl LightDistribution {
    pub fn new(weights: &[f64]) -> LightDistribution {
        let total: f64 = weights
            .iter()
            .map(|w| if w.is_finite() && *w > 0.0 { *w } else { 0.0 })
            .sum();
        if weights.is_empty() {
            return LightDistribution { cdf: Vec::new() };
        }
        let mut acc = 0.0f64;
        let n = weights.len() as f64;
        let cdf = weights
            .iter()
            .map(|w| {
                let w = if w.is_finite() && *w > 0.0 { *w } else { 0.0 };
                acc += if total > 0.0 { w / total } else { 1.0 / n };
                acc.min(1.0) as f32
            })
            .collect::<Vec<_>>();
        let mut cdf = cdf;
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        LightDistribution { cdf }
    }

    pub fn is_empty(&self) -> bool {
        self.cdf.is_empty()
    }

    /// Chooses a light; returns its index and probability.
    pub fn sample(&self, u: f32) -> Option<(usize, f32)> {
        if self.cdf.is_empty() {
            return None;
        }
        let i = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.cdf.len() - 1);
        Some((i, self.pmf(i)))
    }

    /// Chooses a light like [`LightDistribution::sample`] and also returns `u` stretched
    /// back to [0, 1) within the chosen light's share of the interval. That number is
    /// uniform and independent of the choice, so it can place the point on the light: one
    /// stratified 2D draw then covers every light together (the two triangles of a quad
    /// light get the draw's stratification between them instead of a coin toss each).
    pub fn sample_reusing(&self, u: f32) -> Option<(usize, f32, f32)> {
        let (i, pmf) = self.sample(u)?;
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        let reused = if pmf > 0.0 {
            ((u - lo) / pmf).clamp(0.0, ONE_BELOW_ONE)
        } else {
            0.0
        };
        Some((i, pmf, reused))
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
                p,
                material,
                two_sided,
                ..
            } => {
                let area = 0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length();
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
                uv,
                material,
                two_sided,
            } => {
                // Uniform point on the triangle.
                let su = safe_sqrt(u.0);
                let (b0, b1) = (1.0 - su, u.1 * su);
                let b2 = 1.0 - b0 - b1;
                let q = v[0] * b0 + v[1] * b1 + v[2] * b2;
                let n = (v[1] - v[0]).cross(v[2] - v[0]);
                let area2 = n.length();
                if !(area2 > 0.0) {
                    return Ok(None);
                }
                let n = n / area2;
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
            Light::Triangle { p: v, .. } => {
                let n = (v[1] - v[0]).cross(v[2] - v[0]);
                let area2 = n.length();
                if !(area2 > 0.0) {
                    return 0.0;
                }
                let d = q - p;
                let d2 = d.length_squared();
                let cos_l = (n / area2).dot(d / d2.sqrt()).abs();
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

    #[test]
    fn distribution_follows_weights() {
        let d = LightDistribution::new(&[1.0, 3.0, 0.0, 4.0]);
        assert!((d.pmf(0) - 0.125).abs() < 1e-6);
        assert!((d.pmf(1) - 0.375).abs() < 1e-6);
        assert_eq!(d.pmf(2), 0.0);
        assert!((d.pmf(3) - 0.5).abs() < 1e-6);
        assert_eq!(d.sample(0.0).unwrap().0, 0);
        assert_eq!(d.sample(0.2).unwrap().0, 1);
        assert_eq!(d.sample(0.9999).unwrap().0, 3);
    }

    #[test]
    fn reused_number_is_uniform_within_the_choice() {
        let d = LightDistribution::new(&[1.0, 3.0]);
        assert_eq!(d.sample_reusing(0.0), Some((0, 0.25, 0.0)));
        let (i, pmf, u) = d.sample_reusing(0.125).unwrap();
        assert_eq!((i, pmf), (0, 0.25));
        assert!((u - 0.5).abs() < 1e-6);
        let (i, _, u) = d.sample_reusing(0.625).unwrap();
        assert_eq!(i, 1);
        assert!((u - 0.5).abs() < 1e-6);
        let (_, _, u) = d.sample_reusing(0.999_999_94).unwrap();
        assert!(u < 1.0);
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
