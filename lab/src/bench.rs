//! `magg-host bench`: the renderer core's speed, as figures to compare between runs.
//!
//! Measures BVH build time per million triangles, closest-hit rays per second on one core
//! for primary (coherent) and random (incoherent) rays on a mesh of a million triangles
//! or more, and path-traced samples per second on the Cornell box. Times are wall clock on
//! a shared machine: compare ratios measured in one run, not absolute values across runs.

use std::{path::PathBuf, sync::atomic::AtomicBool, time::Instant};

use glam::{Vec2, Vec3};
use renderer::{
    Camera, IntegratorKind, MemoryData, PrepareOptions, RenderSettings, SceneDesc, SceneHeader,
    chunk::MeshData,
    material::Material,
    ray::Ray,
    render::render_image,
    sampler::Sampler,
    trace::{AlphaKey, Tracer},
};
use serde::Serialize;

#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// A glTF file to use as the big mesh instead of the procedural one.
    pub mesh: Option<PathBuf>,
    /// Triangles of the procedural mesh.
    pub triangles: usize,
    pub cornell: Option<PathBuf>,
    /// A textured scene, rendered with and without its textures.
    pub textured: Option<PathBuf>,
    pub rays: usize,
    pub threads: usize,
    pub chunk_triangles: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub mesh: String,
    pub triangles: u64,
    pub chunks: usize,
    pub build_seconds: f64,
    pub build_seconds_per_million: f64,
    pub primary_rays_per_second: f64,
    pub incoherent_rays_per_second: f64,
    pub primary_hit_fraction: f64,
    pub incoherent_hit_fraction: f64,
    pub cornell_samples_per_second: Option<f64>,
    /// Samples per second of the textured scene, with its textures and with them replaced
    /// by constant factors (their mean colours).
    pub textured_samples_per_second: Option<f64>,
    pub untextured_samples_per_second: Option<f64>,
    pub cornell_threads: usize,
}

/// A closed, bumpy sphere of about `triangles` triangles: big, with no easy empty space.
pub fn bumpy_sphere(triangles: usize) -> MeshData {
    let rings = ((triangles as f64 / 4.0).sqrt().max(4.0)) as u32;
    let segments = rings * 2;
    let mut m = renderer::demo::sphere(Vec3::ZERO, 1.0, segments, rings, 0);
    for (p, n) in m.positions.iter_mut().zip(m.normals.iter()) {
        let bump = 1.0 + 0.05 * ((p.x * 40.0).sin() * (p.y * 37.0).sin() * (p.z * 43.0).cos());
        *p = *n * bump;
    }
    m.normals.clear();
    m.uv0 = vec![Vec2::ZERO; m.positions.len()];
    m
}

fn big_scene(config: &BenchConfig) -> Result<(String, SceneDesc), crate::LabError> {
    match &config.mesh {
        Some(path) => {
            let loaded = scene_io::load_gltf(path)?;
            Ok((path.display().to_string(), loaded.desc))
        }
        None => {
            let mesh = bumpy_sphere(config.triangles);
            let desc = SceneDesc {
                meshes: vec![mesh],
                materials: vec![Material::diffuse("grey", Vec3::splat(0.5))],
                ..Default::default()
            };
            Ok((
                format!(
                    "procedural bumpy sphere ({} triangles requested)",
                    config.triangles
                ),
                desc,
            ))
        }
    }
}

/// Closest-hit rays per second on this thread, and the fraction that hit.
fn trace_rate(scene: &SceneHeader, data: &MemoryData, rays: &[Ray]) -> (f64, f64) {
    let tracer = Tracer::new(scene, data);
    let key = AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0);
    let start = Instant::now();
    let mut hits = 0usize;
    for r in rays {
        if let Ok(Some(_)) = tracer.closest(r, key) {
            hits += 1;
        }
    }
    let secs = start.elapsed().as_secs_f64();
    (
        rays.len() as f64 / secs,
        hits as f64 / rays.len().max(1) as f64,
    )
}

pub fn run(config: &BenchConfig) -> Result<BenchReport, crate::LabError> {
    let (name, desc) = big_scene(config)?;
    let start = Instant::now();
    let (scene, data) = renderer::prepare(
        desc,
        &PrepareOptions {
            chunk_triangles: config.chunk_triangles,
        },
    );
    let build = start.elapsed().as_secs_f64();
    let triangles = scene.triangle_count();

    // Primary rays: a pinhole camera framing the mesh, one ray per pixel centre.
    let side = (config.rays as f64).sqrt().ceil() as u32;
    let camera = Camera::framing(scene.bounds_min, scene.bounds_max, 1.0);
    let mut primary = Vec::with_capacity((side * side) as usize);
    for y in 0..side {
        for x in 0..side {
            primary.push(camera.ray(side, side, x as f32 + 0.5, y as f32 + 0.5));
        }
    }
    // Incoherent rays: random origins in the bounds, random directions.
    let ext = scene.bounds_max - scene.bounds_min;
    let incoherent: Vec<Ray> = (0..primary.len() as u32)
        .map(|i| {
            let mut s = Sampler::new(1, i, 0, 0);
            s.start_bounce(0);
            let o = scene.bounds_min + ext * Vec3::new(s.get_1d(), s.get_1d(), s.get_1d());
            let (u, v) = s.get_2d();
            let z = 1.0 - 2.0 * u;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = std::f32::consts::TAU * v;
            Ray::infinite(o, Vec3::new(r * phi.cos(), r * phi.sin(), z))
        })
        .collect();
    // Warm the caches once, then measure.
    let _ = trace_rate(&scene, &data, &primary[..primary.len().min(10_000)]);
    let (primary_rate, primary_hits) = trace_rate(&scene, &data, &primary);
    let (incoherent_rate, incoherent_hits) = trace_rate(&scene, &data, &incoherent);

    let textured = match &config.textured {
        Some(path) if path.exists() => Some(texture_cost(path, config.threads)?),
        _ => None,
    };
    let cornell = match &config.cornell {
        Some(path) if path.exists() => {
            let loaded = scene_io::load_gltf(path)?;
            let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
            let settings = RenderSettings {
                width: 128,
                height: 128,
                spp: 32,
                integrator: IntegratorKind::Path,
                ..RenderSettings::default()
            };
            let camera = scene.camera(None, 1.0)?;
            let start = Instant::now();
            let (_, stats) = render_image(
                &scene,
                &data,
                &camera,
                &settings,
                config.threads,
                16,
                &AtomicBool::new(false),
                &|_, _| {},
            )?;
            Some(stats.samples as f64 / start.elapsed().as_secs_f64())
        }
        _ => None,
    };
    Ok(BenchReport {
        mesh: name,
        triangles,
        chunks: scene.chunks.len(),
        build_seconds: build,
        build_seconds_per_million: build / (triangles as f64 / 1e6),
        primary_rays_per_second: primary_rate,
        incoherent_rays_per_second: incoherent_rate,
        primary_hit_fraction: primary_hits,
        incoherent_hit_fraction: incoherent_hits,
        cornell_samples_per_second: cornell,
        cornell_threads: config.threads,
        textured_samples_per_second: textured.map(|t| t.0),
        untextured_samples_per_second: textured.map(|t| t.1),
    })
}

/// Samples per second of a scene as it is, and with every texture replaced by a constant
/// factor of its mean colour (same geometry, same light transport, no texture reads).
pub fn texture_cost(path: &std::path::Path, threads: usize) -> Result<(f64, f64), crate::LabError> {
    let loaded = scene_io::load_gltf(path)?;
    let mut textured = loaded.desc;
    // The same world around both, whatever their emission decides by default.
    textured.environment = Some(renderer::light::Environment::sky());
    let mut plain = textured.clone();
    let mean = |t: u32| -> glam::Vec4 {
        let (_, srgb) = renderer::texture::averages(textured.texels(t as usize));
        glam::Vec4::from(srgb)
    };
    for m in &mut plain.materials {
        if let Some(t) = m.base_color_tex.take() {
            m.base_color *= mean(t.texture);
        }
        if let Some(t) = m.emissive_tex.take() {
            m.emissive *= mean(t.texture).truncate();
        }
        if let Some(t) = m.metallic_roughness_tex.take() {
            let (lin, _) = renderer::texture::averages(textured.texels(t.texture as usize));
            m.roughness *= lin[1];
            m.metallic *= lin[2];
        }
        m.normal_tex = None;
        m.specular_tex = None;
        m.specular_color_tex = None;
        m.transmission_tex = None;
    }
    plain.textures.clear();
    let rate = |desc: renderer::SceneDesc| -> Result<f64, crate::LabError> {
        let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
        let camera = scene.camera(None, 1.0)?;
        let settings = RenderSettings {
            width: 128,
            height: 128,
            spp: 16,
            ..RenderSettings::default()
        };
        let start = Instant::now();
        let (_, stats) = render_image(
            &scene,
            &data,
            &camera,
            &settings,
            threads,
            16,
            &AtomicBool::new(false),
            &|_, _| {},
        )?;
        Ok(stats.samples as f64 / start.elapsed().as_secs_f64())
    };
    let a = rate(textured)?;
    let b = rate(plain)?;
    Ok((a, b))
}
