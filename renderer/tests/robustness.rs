//! Geometric robustness, property-tested: no ray slips through a closed mesh, no secondary
//! ray hits the surface it leaves, and extreme material and light values stay finite.

use std::sync::atomic::AtomicBool;

use glam::{Vec3, Vec3A, Vec4};
use proptest::prelude::*;
use renderer::{
    Camera, PrepareOptions, Projection, RenderSettings, SceneDesc,
    chunk::MeshData,
    demo::sphere,
    light::Light,
    material::Material,
    math::offset_ray_origin,
    ray::Ray,
    render::render_image,
    sampler::Sampler,
    trace::{AlphaKey, Tracer},
};

fn key() -> AlphaKey {
    AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0)
}

/// A closed, lumpy sphere: one vertex per pole, the seam's columns shared, every vertex
/// then moved radially by a random factor.
fn lumpy(seed: u64, scale: f32, offset: Vec3) -> MeshData {
    let (segments, rings) = (24u32, 12u32);
    let mut m = MeshData::default();
    m.positions.push(Vec3::Y);
    for r in 1..rings {
        let theta = r as f32 / rings as f32 * std::f32::consts::PI;
        for s in 0..segments {
            let phi = s as f32 / segments as f32 * std::f32::consts::TAU;
            m.positions.push(Vec3::new(
                theta.sin() * phi.cos(),
                theta.cos(),
                theta.sin() * phi.sin(),
            ));
        }
    }
    m.positions.push(-Vec3::Y);
    let south = m.positions.len() as u32 - 1;
    let at = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
    for s in 0..segments {
        m.triangles.push([0, at(1, s + 1), at(1, s)]);
        m.triangles
            .push([south, at(rings - 1, s), at(rings - 1, s + 1)]);
    }
    for r in 1..rings - 1 {
        for s in 0..segments {
            m.triangles.push([at(r, s), at(r, s + 1), at(r + 1, s)]);
            m.triangles
                .push([at(r, s + 1), at(r + 1, s + 1), at(r + 1, s)]);
        }
    }
    for (i, p) in m.positions.iter_mut().enumerate() {
        let mut s = Sampler::new(seed, i as u32, 0, 0);
        s.start_bounce(0);
        *p = *p * (0.7 + 0.6 * s.get_1d()) * scale + offset;
    }
    m
}

fn closed_scene(
    seed: u64,
    scale: f32,
    offset: Vec3,
    chunk: usize,
) -> (renderer::SceneHeader, renderer::MemoryData) {
    // The lumps move vertices off the seam; the same index on both sides keeps it closed.
    let desc = SceneDesc {
        meshes: vec![lumpy(seed, scale, offset)],
        materials: vec![Material {
            double_sided: true,
            ..Material::diffuse("m", Vec3::ONE)
        }],
        ..SceneDesc::default()
    };
    renderer::prepare(
        desc,
        &PrepareOptions {
            chunk_triangles: chunk,
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn rays_from_inside_a_closed_mesh_always_hit_it(
        seed in 0u64..1000,
        scale_exp in -4i32..5,
        far in proptest::bool::ANY,
        chunk in 8usize..200,
    ) {
        let scale = 10f32.powi(scale_exp);
        // Far from the origin relative to the mesh's size (f32 world coordinates cannot
        // resolve a 1 cm object a thousand kilometres out; the glTF loader recentres scenes).
        let offset = if far { Vec3::new(1.0, -0.3, 0.2) * 1e4 * scale } else { Vec3::ZERO };
        let (scene, data) = closed_scene(seed, scale, offset, chunk);
        let tracer = Tracer::new(&scene, &data);
        for i in 0..400u32 {
            let mut s = Sampler::new(seed, i, 1, 0);
            s.start_bounce(0);
            let o = Vec3::new(s.get_1d() - 0.5, s.get_1d() - 0.5, s.get_1d() - 0.5) * 0.6 * scale;
            let (u, v) = s.get_2d();
            let d = renderer::light::uniform_sphere((u, v));
            // Offsetting the origin far from 0 loses its low bits: inside either way.
            let ray = Ray::infinite(o + offset, d);
            let hit = tracer.closest(&ray, key()).unwrap();
            prop_assert!(hit.is_some(), "ray {i} from inside escaped (scale {scale}, offset {offset})");
        }
    }

    #[test]
    fn rays_through_vertices_never_pass_between_triangles(seed in 0u64..1000, scale_exp in -3i32..4) {
        let scale = 10f32.powi(scale_exp);
        let mesh = lumpy(seed, scale, Vec3::ZERO);
        let vertices: Vec<Vec3> = mesh.triangles.iter().flatten().map(|&v| mesh.positions[v as usize]).collect();
        let (scene, data) = closed_scene(seed, scale, Vec3::ZERO, 64);
        let tracer = Tracer::new(&scene, &data);
        for (i, v) in vertices.iter().enumerate().step_by(7) {
            // From outside, aimed exactly at the vertex along the radius: the mesh is star-shaped
            // about its centre, so the vertex is where the ray must enter it, never beside it.
            let from = *v * 4.0;
            let ray = Ray::infinite(from, *v - from);
            let hit = tracer.closest(&ray, key()).unwrap();
            prop_assert!(hit.is_some_and(|h| (h.tri_hit.t - 1.0).abs() <= 1e-4), "ray {i} at vertex {v} slipped through");
        }
    }

    #[test]
    fn secondary_rays_never_hit_the_surface_they_leave(seed in 0u64..500, scale_exp in -4i32..6, far in proptest::bool::ANY) {
        // Thin, nearly coplanar and intersecting sheets.
        let scale = 10f32.powi(scale_exp);
        let offset = if far { Vec3::new(-2.0, 1.0, 0.5) * 1e4 * scale } else { Vec3::ZERO };
        let p = |x: f32, y: f32, z: f32| Vec3::new(x, y, z) * scale + offset;
        let mut mesh = MeshData { material: 0, ..Default::default() };
        for (k, tilt) in [0.0f32, 1e-6, -2e-6, 1e-3, 0.2].iter().enumerate() {
            let z = k as f32 * 1e-5;
            let b = mesh.positions.len() as u32;
            mesh.positions.extend([p(-1.0, -1.0, z - tilt), p(1.0, -1.0, z + tilt), p(0.0, 1.0, z)]);
            mesh.triangles.push([b, b + 1, b + 2]);
        }
        let desc = SceneDesc {
            meshes: vec![mesh],
            materials: vec![Material { double_sided: true, ..Material::diffuse("m", Vec3::ONE) }],
            ..SceneDesc::default()
        };
        let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
        let tracer = Tracer::new(&scene, &data);
        let chunk = &data.chunks[0];
        let mut self_hits = 0;
        for tri in 0..chunk.tri_count() {
            for i in 0..100u32 {
                let mut s = Sampler::new(seed, i, tri, 0);
                s.start_bounce(0);
                let (a, b) = s.get_2d();
                let (a, b) = if a + b > 1.0 { (1.0 - a, 1.0 - b) } else { (a, b) };
                let h = renderer::triangle::TriHit { t: 1.0, b0: 1.0 - a - b, b1: a, b2: b };
                let surf = chunk.surface(tri, &h);
                let mut d = renderer::light::uniform_sphere(s.get_2d());
                if d.dot(surf.ng) < 0.0 {
                    d = -d;
                }
                for dir in [d, -d] {
                    let n = if dir.dot(surf.ng) > 0.0 { surf.ng } else { -surf.ng };
                    let o = offset_ray_origin(surf.p, surf.p_error, Vec3A::from(n), Vec3A::from(dir));
                    let ray = Ray::new(o, dir.into(), f32::INFINITY);
                    if let Some(hit) = tracer.closest(&ray, key()).unwrap()
                        && hit.tri == tri && hit.chunk.header().chunk_id == chunk.header().chunk_id {
                            self_hits += 1;
                        }
                }
            }
        }
        prop_assert_eq!(self_hits, 0);
    }
}

/// Spheres of every extreme material under lights of zero and enormous power.
#[test]
fn extreme_materials_and_lights_stay_finite() {
    let mut materials = Vec::new();
    let mut meshes = Vec::new();
    let mut i = 0;
    for roughness in [0.0, 1.0] {
        for ior in [1.0, 3.0] {
            for base in [0.0, 1.0] {
                for (metallic, transmission, thickness) in [
                    (0.0, 0.0, 0.0),
                    (1.0, 0.0, 0.0),
                    (0.0, 1.0, 0.0),
                    (0.0, 1.0, 1.0),
                ] {
                    materials.push(Material {
                        name: format!("m{i}"),
                        base_color: Vec4::new(base, base, base, 1.0),
                        metallic,
                        roughness,
                        ior,
                        transmission,
                        thickness,
                        ..Material::default()
                    });
                    let (x, y) = ((i % 8) as f32 * 2.2, (i / 8) as f32 * 2.2);
                    meshes.push(sphere(Vec3::new(x, y, 0.0), 1.0, 16, 8, i));
                    i += 1;
                }
            }
        }
    }
    let camera = Camera::look_at(
        "c",
        Vec3::new(7.7, 3.3, 20.0),
        Vec3::new(7.7, 3.3, 0.0),
        Projection::Perspective { yfov: 0.9 },
    );
    for power in [0.0f32, 1e6] {
        let desc = SceneDesc {
            meshes: meshes.clone(),
            materials: materials.clone(),
            lights: vec![
                Light::Point {
                    position: Vec3::new(3.0, 3.0, 4.0),
                    intensity: Vec3::splat(power),
                },
                // A light lying exactly in the plane of nothing in particular, and one exactly on
                // a sphere's surface.
                Light::Point {
                    position: Vec3::new(0.0, 0.0, 1.0),
                    intensity: Vec3::splat(power),
                },
                Light::Spot {
                    position: Vec3::new(8.0, 8.0, 5.0),
                    direction: Vec3::new(0.0, -1.0, -1.0).normalize(),
                    intensity: Vec3::splat(power),
                    cos_inner: 0.9,
                    cos_outer: 0.8,
                },
                Light::Directional {
                    direction: Vec3::new(0.0, -1.0, -0.3).normalize(),
                    irradiance: Vec3::splat(power),
                },
            ],
            cameras: vec![camera.clone()],
            ..SceneDesc::default()
        };
        let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
        for integrator in [
            renderer::IntegratorKind::Path,
            renderer::IntegratorKind::Whitted,
        ] {
            let s = RenderSettings {
                width: 48,
                height: 24,
                spp: 8,
                integrator,
                max_depth: 32,
                ..RenderSettings::default()
            };
            let (img, stats) = render_image(
                &scene,
                &data,
                &camera,
                &s,
                2,
                8,
                &AtomicBool::new(false),
                &|_, _| {},
            )
            .unwrap();
            assert_eq!(
                stats.bad_samples, 0,
                "power {power}, {integrator}: NaN or infinite samples"
            );
            assert!(
                img.pixels
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite() && *v >= 0.0)
            );
            if power == 0.0 {
                // Nothing lights the scene (it has lights, so no sky either).
                assert!(
                    img.pixels.iter().flatten().all(|v| *v == 0.0),
                    "{integrator}: light from nowhere"
                );
            }
        }
    }
}
