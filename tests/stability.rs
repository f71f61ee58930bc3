//! Numerical stability of whole scenes: the same picture at any scale and distance from the
//! origin, and degenerate data skipped with a warning, never a NaN or a panic.

mod common;
use common::*;

use std::sync::atomic::AtomicBool;

use base64::Engine;
use renderer::{PrepareOptions, RenderSettings, render::render_image};

/// The Cornell box under a root node that scales and moves it.
fn transformed_cornell(scale: f64, translation: f64) -> String {
    let text = std::fs::read_to_string(data().join("scenes/cornell/cornell.gltf")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let children = v["scenes"][0]["nodes"].clone();
    let nodes = v["nodes"].as_array_mut().unwrap();
    nodes.push(serde_json::json!({
        "name": "root",
        "children": children,
        "scale": [scale, scale, scale],
        "translation": [translation, -0.5 * translation, 0.25 * translation],
    }));
    let root = nodes.len() - 1;
    v["scenes"][0]["nodes"] = serde_json::json!([root]);
    v.to_string()
}

fn render_text(dir: &std::path::Path, name: &str, text: &str) -> renderer::Image {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    let loaded = scene_io::load_gltf(&p).unwrap();
    let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
    let camera = scene.camera(None, 1.0).unwrap();
    let s = RenderSettings {
        width: 64,
        height: 64,
        spp: 32,
        seed: 3,
        ..RenderSettings::default()
    };
    let (img, stats) = render_image(
        &scene,
        &data,
        &camera,
        &s,
        2,
        16,
        &AtomicBool::new(false),
        &|_, _| {},
    )
    .unwrap();
    assert_eq!(stats.bad_samples, 0, "{name}");
    img
}

#[test]
fn the_same_picture_at_any_scale_and_distance_from_the_origin() {
    let dir = scratch("scales");
    let reference = render_text(&dir, "ref.gltf", &transformed_cornell(1.0, 0.0));
    for (scale, translation) in [(1e-4, 0.0), (1e5, 0.0), (1.0, 1e6), (1e-4, 1e6), (1e5, 1e6)] {
        let img = render_text(&dir, "t.gltf", &transformed_cornell(scale, translation));
        let c = lab::compare::compare(&img, &reference).unwrap();
        // The same seed traces the same paths; only the rounding of the scaled coordinates
        // differs, which moves a path's fate only where it grazes an edge.
        assert!(
            c.rel_mse < 2e-3,
            "scale {scale}, translation {translation}: relMSE {:.3e}",
            c.rel_mse
        );
        for d in c.mean_rel_diff {
            assert!(
                d.abs() < 0.01,
                "scale {scale}, translation {translation}: mean off by {:.2}%",
                d * 100.0
            );
        }
    }
}

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

#[test]
fn degenerate_geometry_cameras_and_transforms_are_skipped_with_warnings() {
    let dir = scratch("degenerate");
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    // Positions: a good triangle, a zero-area one, a needle, a sliver, a duplicate of the
    // good one, one with NaN and one with infinity.
    let tris: Vec<[[f32; 3]; 3]> = vec![
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.0]],
        [[0.0, 0.0, 0.0], [1e-30, 0.0, 0.0], [0.0, 5.0, 0.0]],
        [[0.0, 0.0, 0.0], [3.0, 1e-7, 0.0], [6.0, 0.0, 0.0]],
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[nan, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[inf, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    ];
    let mut pos = Vec::new();
    let mut normals = Vec::new();
    let mut tangents = Vec::new();
    for (i, t) in tris.iter().enumerate() {
        for (k, p) in t.iter().enumerate() {
            pos.extend(p.iter().flat_map(|c| c.to_le_bytes()));
            // Zero-length, NaN and unnormalised normals and tangents mixed in.
            let n: [f32; 3] = match (i + k) % 3 {
                0 => [0.0, 0.0, 0.0],
                1 => [nan, 0.0, 1.0],
                _ => [0.0, 0.0, 7.0],
            };
            normals.extend(n.iter().flat_map(|c| c.to_le_bytes()));
            let tg: [f32; 4] = match (i + k) % 3 {
                0 => [nan, nan, nan, 1.0],
                1 => [5.0, 0.0, 0.0, -1.0],
                _ => [0.0, 0.0, 0.0, 0.0],
            };
            tangents.extend(tg.iter().flat_map(|c| c.to_le_bytes()));
        }
    }
    let count = tris.len() * 3;
    let mut buf = pos.clone();
    let off_n = buf.len();
    buf.extend(&normals);
    let off_t = buf.len();
    buf.extend(&tangents);
    let json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"mesh": 0},
            {"mesh": 0, "scale": [0.0, 0.0, 0.0]},
            {"camera": 0, "translation": [0.5, 0.5, 3.0]},
            {"camera": 1, "translation": [0.5, 0.5, 3.0]}
        ],
        "cameras": [
            {"type": "perspective", "perspective": {"yfov": 0.0, "znear": 0.1}},
            {"type": "perspective", "perspective": {"yfov": std::f64::consts::PI, "znear": 0.1}}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2}}]}],
        "buffers": [{"byteLength": buf.len(), "uri": format!("data:application/octet-stream;base64,{}", b64(&buf))}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": off_n},
            {"buffer": 0, "byteOffset": off_n, "byteLength": off_t - off_n},
            {"buffer": 0, "byteOffset": off_t, "byteLength": buf.len() - off_t}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3", "min": [0.0, 0.0, 0.0], "max": [6.0, 5.0, 0.0]},
            {"bufferView": 1, "componentType": 5126, "count": count, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": count, "type": "VEC4"}
        ]
    });
    let p = dir.join("degenerate.gltf");
    std::fs::write(&p, json.to_string()).unwrap();
    let out = dir.join("o.pfm");
    let o = run(host()
        .args([
            "render",
            "--in-process",
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "4",
            "--log",
            "warn",
        ])
        .arg(&p)
        .arg("-o")
        .arg(&out));
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("panicked"));
    assert!(
        err.contains("degenerate"),
        "skipped triangles should be reported: {err}"
    );
    assert!(
        err.contains("field of view"),
        "unusable cameras should be reported: {err}"
    );
    let img = scene_io::read_image(&out).unwrap();
    assert!(img.pixels.iter().flatten().all(|v| v.is_finite()));
    // Both cameras were refused, so the automatic one shows the good triangles.
    assert!(
        img.pixels.iter().any(|p| p != &img.pixels[0]),
        "the good triangles should be visible"
    );
}
