//! Every real glTF scene loads, except the one that requires an extension magg does not
//! implement, which is refused with that extension's name: the scenes of `tests/data`
//! always, and every scene of `../shared/scenes/khronos` when that folder is beside the
//! repository.

mod common;
use common::*;

use renderer::PrepareOptions;

/// The glTF files under `root`, sorted.
fn gltf_files(root: std::path::PathBuf) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(p.extension().and_then(|e| e.to_str()), Some("gltf" | "glb")) {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The scenes to sweep: the shared folder's, else the repository's own.
fn khronos_files() -> Vec<std::path::PathBuf> {
    match shared_if_present("the sweep over ../shared/scenes/khronos") {
        Some(shared) => gltf_files(shared.join("scenes/khronos")),
        None => gltf_files(data().join("scenes/khronos")),
    }
}

#[test]
fn every_khronos_scene_loads_or_is_refused_by_name() {
    let files = khronos_files();
    if let Some(shared) = shared_if_present("the count of ../shared/scenes/khronos") {
        // The folder's own index says how many scene files it holds ("All N files pass").
        let index = std::fs::read_to_string(shared.join("scenes/khronos/INDEX.md")).unwrap();
        let stated: usize = index
            .split("All ")
            .nth(1)
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .expect("INDEX.md states how many files it holds");
        assert_eq!(files.len(), stated);
    } else {
        assert_eq!(files.len(), 7, "the scenes of tests/data/scenes/khronos");
    }
    for f in files {
        let name = f.file_name().unwrap().to_string_lossy().into_owned();
        match scene_io::load_gltf(&f) {
            Ok(loaded) => {
                let tris = loaded.desc.triangle_count();
                let (scene, _data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
                scene.validate().unwrap();
                eprintln!(
                    "{name}: {tris} triangles, {} chunks, {} lights, warnings {:?}",
                    scene.chunks.len(),
                    scene.lights.len(),
                    loaded.warnings
                );
                if name != "MeshPrimitiveModes.gltf" {
                    assert!(tris > 0, "{name} has no triangles");
                }
            }
            Err(e) => {
                assert_eq!(name, "IridescenceSuzanne.glb", "{name} failed to load: {e}");
                assert!(e.to_string().contains("KHR_materials_iridescence"), "{e}");
            }
        }
    }
}

#[test]
fn every_khronos_scene_renders_finite_with_both_integrators() {
    use renderer::{IntegratorKind, RenderSettings, render::render_image};
    let cancel = std::sync::atomic::AtomicBool::new(false);
    for f in khronos_files() {
        let Ok(loaded) = scene_io::load_gltf(&f) else {
            continue;
        };
        let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
        let camera = scene.camera(None, 1.0).unwrap();
        for integrator in [IntegratorKind::Path, IntegratorKind::Whitted] {
            let s = RenderSettings {
                width: 24,
                height: 24,
                spp: 2,
                integrator,
                max_depth: 16,
                ..RenderSettings::default()
            };
            let (img, stats) =
                render_image(&scene, &data, &camera, &s, 2, 8, &cancel, &|_, _| {}).unwrap();
            let name = f.file_name().unwrap().to_string_lossy();
            assert_eq!(
                stats.bad_samples, 0,
                "{name} ({integrator}): NaN or infinite samples"
            );
            assert!(
                img.pixels
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite() && *v >= 0.0),
                "{name} ({integrator})"
            );
        }
    }
}

/// One image under two samplers' settings (BoxTextured's logo as base colour, linear and
/// repeating, and again as emission, nearest and clamped) is held once and sampled both
/// ways: the image is the same bytes as with the image given twice (two images of one
/// file, each holding its texels, as every texture did before), in one process and on a
/// cluster, whose render nodes fetch the shared tiles by demand.
#[test]
fn one_image_under_two_samplers_renders_as_two_copies_do() {
    let dir = scratch("shared-texels");
    let src = data().join("scenes/khronos/BoxTextured/glTF");
    for f in ["BoxTextured0.bin", "CesiumLogoFlat.png"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let text = std::fs::read_to_string(src.join("BoxTextured.gltf")).unwrap();
    let mut shared: serde_json::Value = serde_json::from_str(&text).unwrap();
    shared["samplers"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"magFilter": 9728, "wrapS": 33071, "wrapT": 33071}));
    shared["textures"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"sampler": 1, "source": 0}));
    let material = &mut shared["materials"][0];
    material["emissiveTexture"] = serde_json::json!({"index": 1});
    material["emissiveFactor"] = serde_json::json!([0.5, 0.5, 0.5]);
    let mut copies = shared.clone();
    copies["images"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"uri": "CesiumLogoFlat.png"}));
    copies["textures"][1]["source"] = serde_json::json!(1);
    let write = |name: &str, v: &serde_json::Value| {
        let p = dir.join(name);
        std::fs::write(&p, serde_json::to_string(v).unwrap()).unwrap();
        p
    };
    let shared = write("shared.gltf", &shared);
    let copies = write("copies.gltf", &copies);
    let flags = ["--width", "48", "--height", "48", "--spp", "4"];
    let render = |scene: &std::path::Path, out: &str| {
        let args: Vec<&std::ffi::OsStr> = std::iter::once(scene.as_os_str())
            .chain(flags.iter().map(std::ffi::OsStr::new))
            .collect();
        in_process_to(&dir.join(out), &args)
    };
    let one = render(&shared, "shared.png");
    same_bytes(&one, &render(&copies, "copies.png"));

    let cluster = dir.join("cluster.png");
    let o = run(host()
        .args(["render", "--quiet", "--spawn", "tiny", "--cache", "50"])
        .args(flags)
        .arg(&shared)
        .arg("-o")
        .arg(&cluster));
    assert!(o.status.success(), "{}", stderr(&o));
    same_bytes(&one, &cluster);
}
