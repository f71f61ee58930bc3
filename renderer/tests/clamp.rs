//! `clamp_indirect` touches caustic paths only: a scene without mirrors or glass renders the
//! same bytes clamped or not, and the demo scene (glass and mirror spheres) loses its
//! brightest caustic samples, never gains light.

use std::sync::atomic::AtomicBool;

use renderer::{
    Image, PrepareOptions, RenderSettings, SceneDesc, demo::demo_scene, material::Material,
    render::render_image,
};

fn render(desc: SceneDesc, clamp: f32) -> Image {
    let (scene, data) = renderer::prepare(desc, &PrepareOptions::default());
    let camera = scene.camera(None, 4.0 / 3.0).unwrap();
    let s = RenderSettings {
        width: 40,
        height: 30,
        spp: 8,
        clamp_indirect: clamp,
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

#[test]
fn without_mirrors_or_glass_clamping_changes_nothing() {
    let mut desc = demo_scene();
    // The mirror and the glass sphere become plain diffuse surfaces.
    for m in desc.materials.iter_mut() {
        if m.name == "mirror" || m.name == "glass" {
            *m = Material::diffuse(&m.name, glam::Vec3::splat(0.5));
        }
    }
    assert_eq!(render(desc.clone(), 0.5).pixels, render(desc, 0.0).pixels);
}

#[test]
fn clamping_removes_caustic_fireflies_and_adds_no_light() {
    let free = render(demo_scene(), 0.0);
    let clamped = render(demo_scene(), 1.0);
    let peak = |img: &Image| img.pixels.iter().flatten().fold(0.0f32, |a, &v| a.max(v));
    let (mut darker, mut brighter) = (0, 0);
    for (a, b) in clamped.pixels.iter().zip(&free.pixels) {
        for c in 0..3 {
            darker += (a[c] < b[c]) as u32;
            brighter += (a[c] > b[c] * (1.0 + 1e-6)) as u32;
        }
    }
    assert_eq!(brighter, 0, "clamping added light");
    assert!(darker > 0, "the demo's caustics were not clamped");
    assert!(peak(&clamped) <= peak(&free));
}
