//! Golden images: small renders of a few scenes, each exercising a feature (texture, texture
//! transform, normal maps, alpha, transmission), compared with references rendered at many
//! samples per pixel. The tolerance of each is set from measured noise when the goldens are
//! made: three times the worst relative MSE of test-sized renders with other seeds.
//!
//! Regenerate after an intended change of the pictures with
//! `MAGG_UPDATE_GOLDEN=1 cargo test --release --test golden`, look at the PNGs it writes
//! beside the goldens, and commit them.

mod common;
use common::*;

use std::{path::Path, sync::atomic::AtomicBool};

use renderer::{Image, PrepareOptions, RenderSettings, render::render_image};

const SIZE: u32 = 64;
const GOLDEN_SPP: u32 = 1024;
const TEST_SPP: u32 = 32;

const SCENES: &[(&str, &str)] = &[
    ("box-textured", "BoxTextured/glTF/BoxTextured.gltf"),
    (
        "texture-transform",
        "TextureTransformTest/glTF/TextureTransformTest.gltf",
    ),
    (
        "normal-tangent-mirror",
        "NormalTangentMirrorTest/glTF-Binary/NormalTangentMirrorTest.glb",
    ),
    (
        "alpha-blend-mode",
        "AlphaBlendModeTest/glTF/AlphaBlendModeTest.gltf",
    ),
    (
        "transmission",
        "TransmissionTest/glTF-Binary/TransmissionTest.glb",
    ),
];

fn render(file: &str, spp: u32, seed: u64) -> Image {
    let loaded = scene_io::load_gltf(&data().join("scenes/khronos").join(file)).unwrap();
    let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
    let camera = scene.camera(None, 1.0).unwrap();
    let s = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp,
        seed,
        max_depth: 32,
        ..RenderSettings::default()
    };
    render_image(
        &scene,
        &data,
        &camera,
        &s,
        2,
        16,
        &AtomicBool::new(false),
        &|_, _| {},
    )
    .unwrap()
    .0
}

fn golden_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden"))
}

#[test]
fn renders_match_their_golden_images() {
    let update = std::env::var_os("MAGG_UPDATE_GOLDEN").is_some();
    for (name, file) in SCENES {
        let golden_path = golden_dir().join(format!("{name}.pfm"));
        let tolerance_path = golden_dir().join(format!("{name}.tolerance"));
        if update {
            let golden = render(file, GOLDEN_SPP, 1);
            scene_io::write_image(&golden_path, &golden).unwrap();
            scene_io::write_image(&golden_dir().join(format!("{name}.png")), &golden).unwrap();
            let worst = (2..5)
                .map(|seed| {
                    lab::compare::compare(&render(file, TEST_SPP, seed), &golden)
                        .unwrap()
                        .rel_mse
                })
                .fold(0.0f64, f64::max);
            std::fs::write(&tolerance_path, format!("{:.6e}\n", 3.0 * worst)).unwrap();
        }
        let golden = scene_io::read_image(&golden_path)
            .unwrap_or_else(|e| panic!("{e}: run with MAGG_UPDATE_GOLDEN=1 to make it"));
        let tolerance: f64 = std::fs::read_to_string(&tolerance_path)
            .unwrap()
            .trim()
            .parse()
            .unwrap();
        let got = render(file, TEST_SPP, 7);
        let c = lab::compare::compare(&got, &golden).unwrap();
        assert!(
            c.rel_mse < tolerance,
            "{name}: relMSE {:.3e} against its golden image, tolerance {tolerance:.3e}",
            c.rel_mse
        );
    }
}
