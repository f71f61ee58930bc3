//! The Whitted integrator's cost stays bounded where every surface splits the ray in two:
//! a row of glass spheres seen down a corridor of thin glass panes, each pane reflecting and
//! passing light to the next at grazing angles.

use std::sync::atomic::AtomicBool;

use glam::Vec3;
use renderer::{
    Camera, IntegratorKind, PrepareOptions, Projection, RenderSettings, SceneDesc, demo::sphere,
    light::Light, material::Material, render::render_image,
};

/// The budget of reflected and refracted rays per camera ray (`WHITTED_MAX_SPECULAR_RAYS`).
const BUDGET: u64 = 256;

#[test]
fn glass_behind_glass_costs_a_bounded_number_of_rays() {
    let glass = Material::glass("glass");
    let floor = Material::diffuse("floor", Vec3::splat(0.6));
    let pane = Material {
        name: "pane".into(),
        thickness: 0.0,
        double_sided: true,
        ..glass.clone()
    };
    // Eight spheres one behind the other on the camera's axis, and a floor below them.
    let mut meshes: Vec<_> = (0..8)
        .map(|i| sphere(Vec3::new(0.0, 0.0, -3.0 * i as f32), 1.0, 24, 12, 0))
        .collect();
    meshes.push(renderer::chunk::MeshData {
        positions: vec![
            Vec3::new(-50.0, -1.5, 10.0),
            Vec3::new(50.0, -1.5, 10.0),
            Vec3::new(50.0, -1.5, -50.0),
            Vec3::new(-50.0, -1.5, -50.0),
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        material: 1,
        ..Default::default()
    });
    // Four panes on each side of the corridor, parallel to it.
    for x in [-2.5f32, -2.0, -1.5, -1.2, 1.2, 1.5, 2.0, 2.5] {
        meshes.push(renderer::chunk::MeshData {
            positions: vec![
                Vec3::new(x, -1.5, 10.0),
                Vec3::new(x, -1.5, -60.0),
                Vec3::new(x, 3.0, -60.0),
                Vec3::new(x, 3.0, 10.0),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            material: 2,
            ..Default::default()
        });
    }
    let camera = Camera::look_at(
        "axis",
        Vec3::new(0.3, 0.2, 4.0),
        Vec3::new(0.0, 0.0, -10.0),
        Projection::Perspective { yfov: 0.4 },
    );
    let desc = SceneDesc {
        meshes,
        materials: vec![glass, floor, pane],
        lights: vec![Light::Point {
            position: Vec3::new(2.0, 5.0, 3.0),
            intensity: Vec3::splat(50.0),
        }],
        cameras: vec![camera.clone()],
        ..SceneDesc::default()
    };
    let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
    let s = RenderSettings {
        width: 16,
        height: 12,
        spp: 1,
        integrator: IntegratorKind::Whitted,
        // Deep enough that splitting at every surface without a bound would cast 2^14 rays
        // a pixel, and the assertion below could not hold.
        max_depth: 14,
        ..RenderSettings::default()
    };
    let (img, stats) = render_image(
        &scene,
        &data,
        &camera,
        &s,
        2,
        4,
        &AtomicBool::new(false),
        &|_, _| {},
    )
    .unwrap();
    let camera_rays = u64::from(s.width * s.height * s.spp);
    assert!(
        stats.secondary_rays > camera_rays,
        "the glass should split rays: {} secondary rays",
        stats.secondary_rays
    );
    assert!(
        stats.secondary_rays <= BUDGET * camera_rays,
        "{} secondary rays for {camera_rays} camera rays",
        stats.secondary_rays
    );
    assert!(img.pixels.iter().flatten().all(|v| v.is_finite()));
    assert!(img.pixels.iter().flatten().any(|&v| v > 0.0));
}

#[test]
fn a_hundred_nested_glass_shells_stay_within_the_budget() {
    let desc = renderer::demo::glass_shells(100);
    let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
    let camera = scene.camera(None, 1.0).unwrap();
    let s = RenderSettings {
        width: 16,
        height: 16,
        spp: 1,
        integrator: IntegratorKind::Whitted,
        max_depth: IntegratorKind::Whitted.default_max_depth(),
        ..RenderSettings::default()
    };
    let (img, stats) = render_image(
        &scene,
        &data,
        &camera,
        &s,
        2,
        4,
        &AtomicBool::new(false),
        &|_, _| {},
    )
    .unwrap();
    let camera_rays = u64::from(s.width * s.height);
    assert!(stats.secondary_rays > 4 * camera_rays, "{stats:?}");
    assert!(stats.secondary_rays <= BUDGET * camera_rays, "{stats:?}");
    // Each secondary ray's hit may send one shadow ray per light (one here).
    assert!(stats.shadow_rays <= (BUDGET + 1) * camera_rays, "{stats:?}");
    assert!(img.pixels.iter().flatten().all(|v| v.is_finite()));
}
