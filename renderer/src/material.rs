//! Materials as glTF 2.0 describes them (metallic-roughness PBR with the KHR extensions
//! magg supports), and their evaluation at a surface point into shading parameters.

use glam::{Vec2, Vec3, Vec4};
use serde::{Deserialize, Serialize};

use crate::{
    chunk::{Reads, SurfaceAttributes},
    scene::SceneHeader,
    source::{DataError, SceneData},
    texture,
};

/// KHR_texture_transform, applied as offset * rotation * scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UvTransform {
    pub offset: Vec2,
    pub rotation: f32,
    pub scale: Vec2,
}

impl UvTransform {
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let s = uv * self.scale;
        let (sin, cos) = self.rotation.sin_cos();
        Vec2::new(cos * s.x + sin * s.y, -sin * s.x + cos * s.y) + self.offset
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexRef {
    pub texture: u32,
    pub tex_coord: u32,
    pub transform: Option<UvTransform>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum AlphaMode {
    #[default]
    Opaque,
    Mask,
    Blend,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    pub base_color: Vec4,
    pub base_color_tex: Option<TexRef>,
    pub metallic: f32,
    pub roughness: f32,
    /// Roughness in G, metalness in B.
    pub metallic_roughness_tex: Option<TexRef>,
    pub normal_tex: Option<TexRef>,
    pub normal_scale: f32,
    /// Emitted radiance in W/(sr m^2): emissiveFactor times KHR_materials_emissive_strength.
    pub emissive: Vec3,
    pub emissive_tex: Option<TexRef>,
    pub ior: f32,
    /// KHR_materials_specular.
    pub specular: f32,
    pub specular_tex: Option<TexRef>,
    pub specular_color: Vec3,
    pub specular_color_tex: Option<TexRef>,
    /// KHR_materials_transmission.
    pub transmission: f32,
    pub transmission_tex: Option<TexRef>,
    /// KHR_materials_volume: a thickness above zero makes the mesh a refracting volume
    /// boundary; zero means thin-walled.
    pub thickness: f32,
    pub attenuation_color: Vec3,
    pub attenuation_distance: f32,
    pub alpha_mode: AlphaMode,
    pub alpha_cutoff: f32,
    pub double_sided: bool,
}

impl Default for Material {
    /// The glTF default material: white, fully metallic... except that the spec's default
    /// material (used when a primitive names none) is metallic 1, roughness 1. We follow it.
    fn default() -> Material {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_tex: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_tex: None,
            normal_tex: None,
            normal_scale: 1.0,
            emissive: Vec3::ZERO,
            emissive_tex: None,
            ior: 1.5,
            specular: 1.0,
            specular_tex: None,
            specular_color: Vec3::ONE,
            specular_color_tex: None,
            transmission: 0.0,
            transmission_tex: None,
            thickness: 0.0,
            attenuation_color: Vec3::ONE,
            attenuation_distance: f32::INFINITY,
            alpha_mode: AlphaMode::Opaque,
            alpha_cutoff: 0.5,
            double_sided: false,
        }
    }
}

impl Material {
    /// What shading this material reads of a hit beyond its point and normals: texture
    /// coordinates if it has a texture, the tangent frame if it has a normal map.
    #[inline]
    pub fn reads(&self) -> Reads {
        Reads {
            uv: self.textures().next().is_some(),
            frame: self.normal_tex.is_some(),
        }
    }

    /// A plain Lambertian surface of the given colour.
    pub fn diffuse(name: &str, color: Vec3) -> Material {
        Material {
            name: name.into(),
            base_color: color.extend(1.0),
            metallic: 0.0,
            roughness: 1.0,
            specular: 0.0,
            double_sided: true,
            ..Material::default()
        }
    }

    /// Clear, smooth glass with a volume (refraction in and out), index of refraction 1.5.
    pub fn glass(name: &str) -> Material {
        Material {
            name: name.into(),
            base_color: Vec4::ONE,
            metallic: 0.0,
            roughness: 0.0,
            transmission: 1.0,
            ior: 1.5,
            thickness: 1.0,
            ..Material::default()
        }
    }

    pub fn is_emissive(&self) -> bool {
        self.emissive.max_element() > 0.0
    }

    pub fn textures(&self) -> impl Iterator<Item = &TexRef> {
        [
            &self.base_color_tex,
            &self.metallic_roughness_tex,
            &self.normal_tex,
            &self.emissive_tex,
            &self.specular_tex,
            &self.specular_color_tex,
            &self.transmission_tex,
        ]
        .into_iter()
        .flatten()
    }
}

/// Texture coordinates a texture reference reads at a surface point.
#[inline]
pub fn uv_for(t: &TexRef, s: &SurfaceAttributes) -> Vec2 {
    let uv = match t.tex_coord {
        0 => s.uv0,
        1 => s.uv1,
        _ => None,
    }
    .unwrap_or(Vec2::ZERO);
    match &t.transform {
        Some(x) => x.apply(uv),
        None => uv,
    }
}

/// Samples a texture reference, or returns `None` when the material has no texture there.
#[inline]
pub fn sample_ref<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    t: &Option<TexRef>,
    s: &SurfaceAttributes,
    srgb: bool,
) -> Result<Option<Vec4>, DataError> {
    match t {
        None => Ok(None),
        Some(t) => {
            let info = &scene.textures[t.texture as usize];
            texture::sample(data, info, uv_for(t, s), srgb).map(Some)
        }
    }
}

/// Everything shading needs, after textures are applied.
#[derive(Clone, Copy, Debug)]
pub struct ShadingParams {
    pub base_color: Vec3,
    pub alpha: f32,
    pub metallic: f32,
    pub roughness: f32,
    pub ior: f32,
    pub specular: f32,
    pub specular_color: Vec3,
    pub transmission: f32,
    pub thin_walled: bool,
    pub emission: Vec3,
    /// Shading normal after normal mapping (world space, unit).
    pub normal: Vec3,
    /// Tangent of the normal map's frame (unit, orthogonal to `normal`); `None` without a
    /// normal map, where any frame about the normal does.
    pub tangent: Option<(Vec3, f32)>,
}

/// Alpha of a material at a surface point (base colour alpha times texture and vertex colour).
pub fn alpha_at<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    m: &Material,
    s: &SurfaceAttributes,
) -> Result<f32, DataError> {
    let mut a = m.base_color.w;
    if let Some(t) = sample_ref(scene, data, &m.base_color_tex, s, true)? {
        a *= t.w;
    }
    if let Some(c) = s.color {
        a *= c.w;
    }
    Ok(a)
}

/// Applies the material's textures at a surface point.
#[inline(always)]
pub fn shading_params<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    m: &Material,
    s: &SurfaceAttributes,
) -> Result<ShadingParams, DataError> {
    let mut base = m.base_color;
    if let Some(t) = sample_ref(scene, data, &m.base_color_tex, s, true)? {
        base *= t;
    }
    if let Some(c) = s.color {
        base *= c;
    }
    let mut metallic = m.metallic;
    let mut roughness = m.roughness;
    if let Some(t) = sample_ref(scene, data, &m.metallic_roughness_tex, s, false)? {
        roughness *= t.y;
        metallic *= t.z;
    }
    let mut emission = m.emissive;
    if emission.max_element() > 0.0
        && let Some(t) = sample_ref(scene, data, &m.emissive_tex, s, true)?
    {
        emission *= t.truncate();
    }
    let mut specular = m.specular;
    if let Some(t) = sample_ref(scene, data, &m.specular_tex, s, false)? {
        specular *= t.w;
    }
    let mut specular_color = m.specular_color;
    if let Some(t) = sample_ref(scene, data, &m.specular_color_tex, s, true)? {
        specular_color *= t.truncate();
    }
    let mut transmission = m.transmission;
    if transmission > 0.0
        && let Some(t) = sample_ref(scene, data, &m.transmission_tex, s, false)?
    {
        transmission *= t.x;
    }

    // Normal mapping in the tangent frame of the first UV set (glTF: +Y is "up" in the
    // texture, i.e. towards decreasing v, which is why the bitangent is -dp/dv's direction).
    // Without a normal map no tangent is worked out: every BSDF here is isotropic, so the
    // shading frame may turn freely about the normal.
    let mut normal = s.ns;
    let mut tangent = None;
    let frame_tangent = m
        .normal_tex
        .and(s.tangent)
        .filter(|t| t.truncate().length_squared() > 1e-12 && t.is_finite())
        .map(|t| (t.truncate(), if t.w < 0.0 { -1.0 } else { 1.0 }))
        .or_else(|| {
            m.normal_tex.and(s.dpdu).map(|(dpdu, dpdv)| {
                // Handedness from the UV parameterisation: the bitangent points "up" in the
                // texture, towards decreasing v (glTF's v runs down the image).
                let sign = if s.ns.cross(dpdu).dot(dpdv) > 0.0 {
                    -1.0
                } else {
                    1.0
                };
                (dpdu, sign)
            })
        });
    if let Some((t, sign)) = frame_tangent {
        let t_orth = t - normal * normal.dot(t);
        if t_orth.length_squared() > 1e-20 {
            let t_unit = t_orth.normalize();
            tangent = Some((t_unit, sign));
            if let Some(tex) = sample_ref(scene, data, &m.normal_tex, s, false)? {
                let mut tn = tex.truncate() * 2.0 - Vec3::ONE;
                tn.x *= m.normal_scale;
                tn.y *= m.normal_scale;
                let b = normal.cross(t_unit) * sign;
                let n = (t_unit * tn.x + b * tn.y + normal * tn.z).normalize_or_zero();
                if n != Vec3::ZERO && n.is_finite() {
                    normal = n;
                }
            }
        }
    }

    Ok(ShadingParams {
        base_color: base.truncate().clamp(Vec3::ZERO, Vec3::ONE),
        alpha: base.w,
        metallic: metallic.clamp(0.0, 1.0),
        roughness: roughness.clamp(0.0, 1.0),
        ior: m.ior,
        specular: specular.clamp(0.0, 1.0),
        specular_color: specular_color.max(Vec3::ZERO),
        transmission: transmission.clamp(0.0, 1.0),
        thin_walled: m.thickness <= 0.0,
        emission: emission.max(Vec3::ZERO),
        normal,
        tangent,
    })
}
