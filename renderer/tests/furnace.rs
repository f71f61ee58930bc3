//! Furnace tests: closed scenes whose radiance is known in closed form.

use std::sync::atomic::AtomicBool;

use glam::{Vec3, Vec4};
use renderer::{
    Camera, IntegratorKind, PrepareOptions, Projection, RenderSettings, SceneDesc,
    demo::sphere,
    material::Material,
    render::{Image, render_image},
};

/// A closed cube (inward faces) around a sphere at the centre.
fn enclosure(wall: Material, ball: Material) -> SceneDesc {
    let mut meshes = Vec::new();
    let s = 4.0f32;
    // Each face as two triangles, wound to face the inside.
    let c = |x: f32, y: f32, z: f32| Vec3::new(x, y, z) * s;
    let faces = [
        [
            c(-1., -1., -1.),
            c(1., -1., -1.),
            c(1., -1., 1.),
            c(-1., -1., 1.),
        ],
        [
            c(-1., 1., 1.),
            c(1., 1., 1.),
            c(1., 1., -1.),
            c(-1., 1., -1.),
        ],
        [
            c(-1., -1., 1.),
            c(1., -1., 1.),
            c(1., 1., 1.),
            c(-1., 1., 1.),
        ],
        [
            c(1., -1., -1.),
            c(-1., -1., -1.),
            c(-1., 1., -1.),
            c(1., 1., -1.),
        ],
        [
            c(-1., -1., -1.),
            c(-1., -1., 1.),
            c(-1., 1., 1.),
            c(-1., 1., -1.),
        ],
        [
            c(1., -1., 1.),
            c(1., -1., -1.),
            c(1., 1., -1.),
            c(1., 1., 1.),
        ],
    ];
    for f in faces {
        meshes.push(renderer::chunk::MeshData {
            positions: f.to_vec(),
            triangles: vec![[0, 2, 1], [0, 3, 2]],
            material: 0,
            ..Default::default()
        });
    }
    meshes.push(sphere(Vec3::ZERO, 1.0, 48, 24, 1));
    let camera = Camera::look_at(
        "c",
        Vec3::new(0.0, 0.0, 3.5),
        Vec3::ZERO,
        Projection::Perspective { yfov: 0.9 },
    );
    SceneDesc {
        meshes,
        materials: vec![wall, ball],
        textures: vec![],
        lights: vec![],
        cameras: vec![camera],
        environment: None,
    }
}

fn render(desc: SceneDesc, spp: u32) -> Image {
    let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
    let camera = scene.camera(None, 1.0).unwrap();
    let s = RenderSettings {
        width: 32,
        height: 32,
        spp,
        seed: 3,
        integrator: IntegratorKind::Path,
        max_depth: 1000,
        ..RenderSettings::default()
    };
    render_image(
        &scene,
        &data,
        &camera,
        &s,
        2,
        8,
        &AtomicBool::new(false),
        &|_, _| {},
    )
    .unwrap()
    .0
}

fn emitter(le: f32, albedo: f32) -> Material {
    Material {
        emissive: Vec3::splat(le),
        base_color: Vec4::new(albedo, albedo, albedo, 1.0),
        double_sided: true,
        ..Material::diffuse("wall", Vec3::splat(albedo))
    }
}

#[test]
fn black_emitting_walls_light_a_grey_ball_to_albedo_times_radiance() {
    // Walls emit 1 and reflect nothing; the convex ball sees radiance 1 from every
    // direction, so it returns exactly its albedo.
    let img = render(
        enclosure(
            emitter(1.0, 0.0),
            Material::diffuse("ball", Vec3::splat(0.5)),
        ),
        64,
    );
    let centre = |x: u32, y: u32| img.pixels[(y * 32 + x) as usize];
    let mut ball = [0f64; 3];
    let mut n = 0;
    for y in 13..19 {
        for x in 13..19 {
            for (sum, v) in ball.iter_mut().zip(centre(x, y)) {
                *sum += v as f64;
            }
            n += 1;
        }
    }
    for c in ball {
        let mean = c / n as f64;
        assert!(
            (mean - 0.5).abs() < 0.01,
            "ball radiance {mean}, expected 0.5"
        );
    }
    // A corner pixel sees a wall: exactly its emission.
    assert_eq!(centre(0, 0), [1.0, 1.0, 1.0]);
}

#[test]
fn white_furnace_sums_every_bounce() {
    // Everything emits 0.5 and reflects half: radiance is 0.5 / (1 - 0.5) = 1 everywhere,
    // reached only by summing paths of every length (Russian roulette included).
    let img = render(enclosure(emitter(0.5, 0.5), emitter(0.5, 0.5)), 128);
    let mean = img.channel_means();
    for m in mean {
        assert!((m - 1.0).abs() < 0.01, "image mean {m}, expected 1");
    }
    assert!(img.pixels.iter().all(|p| p.iter().all(|c| c.is_finite())));
}

#[test]
fn a_grey_ball_under_a_uniform_white_sky_returns_its_albedo() {
    // Only a uniform environment of radiance 1: a convex grey ball then reflects exactly its
    // albedo, by any mix of light and BSDF sampling.
    let desc = SceneDesc {
        meshes: vec![sphere(Vec3::ZERO, 1.0, 48, 24, 0)],
        materials: vec![Material::diffuse("ball", Vec3::splat(0.5))],
        cameras: vec![Camera::look_at(
            "c",
            Vec3::new(0.0, 0.0, 3.5),
            Vec3::ZERO,
            Projection::Perspective { yfov: 0.9 },
        )],
        environment: Some(renderer::light::Environment::uniform(Vec3::ONE)),
        ..SceneDesc::default()
    };
    let img = render(desc, 64);
    let px = |x: u32, y: u32| img.pixels[(y * 32 + x) as usize];
    let mut sum = 0.0f64;
    for y in 13..19 {
        for x in 13..19 {
            sum += px(x, y)[1] as f64;
        }
    }
    let mean = sum / 36.0;
    assert!((mean - 0.5).abs() < 0.01, "ball {mean}, expected 0.5");
    assert_eq!(px(0, 0), [1.0, 1.0, 1.0], "the sky itself");
}
