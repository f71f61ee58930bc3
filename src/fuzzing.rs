//! What the fuzz targets (`fuzz/`) feed hostile bytes to, shared with the corpus replay in
//! `tests/fuzz_corpus.rs` so that every saved input is checked on every test run, with no
//! fuzzer installed. Each function must return, never panic, whatever the bytes.

use std::{path::Path, sync::atomic::AtomicBool};

use protocol::{FrameHeader, HEADER_LEN, Message};
use renderer::{
    Camera, MemoryData, Projection, RenderSettings, SceneHeader, chunk::Chunk, render::render_rect,
};

/// The targets, by name (the folder names under `fuzz/corpus/`).
pub const TARGETS: &[&str] = &["gltf", "topology", "frame", "chunk", "scene_header"];

pub fn run(target: &str, data: &[u8]) {
    match target {
        "gltf" => gltf(data),
        "topology" => topology(data),
        "frame" => frame(data),
        "chunk" => chunk(data),
        "scene_header" => scene_header(data),
        _ => {}
    }
}

/// A scene file (glTF JSON or GLB), as the host would read it, then prepared.
pub fn gltf(data: &[u8]) {
    if let Ok(loaded) =
        scene_io::gltf_load::load_gltf_bytes(Path::new("/nonexistent/fuzz.gltf"), data)
        && loaded.desc.triangle_count() < 200_000
    {
        let _ = renderer::prepare(loaded.desc, &renderer::PrepareOptions::default());
    }
}

/// A topology or cluster file.
pub fn topology(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data)
        && let Ok(t) = fabric::Topology::from_toml(text)
    {
        // Routes are made when first asked for: ask for every destination's.
        let routes = fabric::routing::Routes::all_alive(&t);
        for dest in 0..t.len() as protocol::NodeId {
            let _ = routes.next_hop(0, dest);
            let _ = routes.broadcast_children(0, dest);
        }
    }
}

/// Bytes off a socket: a frame header, then a control message.
pub fn frame(data: &[u8]) {
    if data.len() >= HEADER_LEN {
        let header: [u8; HEADER_LEN] = data[..HEADER_LEN].try_into().expect("length checked");
        let _ = FrameHeader::decode(&header);
        let _ = Message::decode(&data[HEADER_LEN..]);
    }
    let _ = Message::decode(data);
}

/// A chunk as a render node receives it; if it validates, rays must be able to use it.
pub fn chunk(data: &[u8]) {
    let Ok(c) = Chunk::from_bytes(data) else {
        return;
    };
    let bounds = c.bounds();
    let center = (bounds.min + bounds.max) * 0.5;
    for i in 0..16 {
        let a = i as f32 * 0.7;
        let dir = glam::Vec3::new(a.cos(), (a * 1.3).sin(), 0.3).normalize();
        let origin = glam::Vec3::from(center) - dir * 10.0;
        let q = renderer::ray::RayQuery::new(&renderer::ray::Ray::infinite(origin, dir));
        let mut tmax = f32::INFINITY;
        if let Some((tri, hit)) = c.intersect(&q, &mut tmax) {
            let _ = c.surface(tri, &hit);
        }
    }
}

/// A scene header as a fork or render node receives it; if it validates, rendering with it
/// (and no data at all) must end in errors, not panics.
pub fn scene_header(data: &[u8]) {
    let Ok(scene) = protocol::decode_value::<SceneHeader>(data) else {
        return;
    };
    if scene.validate().is_err() {
        return;
    }
    let camera = Camera::look_at(
        "fuzz",
        glam::Vec3::new(0.0, 0.0, 5.0),
        glam::Vec3::ZERO,
        Projection::Perspective { yfov: 1.0 },
    );
    let settings = RenderSettings {
        width: 4,
        height: 4,
        spp: 1,
        ..RenderSettings::default()
    };
    let mut out = vec![[0.0; 3]; 16];
    let rect = renderer::Rect {
        x: 0,
        y: 0,
        width: 4,
        height: 4,
    };
    let _ = render_rect(
        &scene,
        &MemoryData::default(),
        &camera,
        &settings,
        rect,
        &mut out,
        &AtomicBool::new(false),
    );
}

/// Seed inputs for every target, made here (nothing copied in): (target, name, bytes).
pub fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    let mut out = Vec::new();
    // A small glTF with an embedded buffer, and the demo scene's pieces for the rest.
    let tri = r#"{"asset":{"version":"2.0"},"scene":0,"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}],
"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],
"buffers":[{"byteLength":36,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}],
"bufferViews":[{"buffer":0,"byteLength":36}],
"accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}]}"#;
    out.push(("gltf", "triangle.gltf".into(), tri.as_bytes().to_vec()));
    out.push(("gltf", "triangle.glb".into(), glb(tri.as_bytes(), &[])));
    for preset in ["tiny", "magg", "grid:2x3x2"] {
        let t = fabric::Topology::preset(preset).expect("preset");
        out.push((
            "topology",
            format!("{}.toml", preset.replace(':', "-")),
            t.to_toml().into_bytes(),
        ));
    }
    out.push((
        "topology",
        "grid.toml".into(),
        b"name = \"g\"\n[grid]\ncards = 2\nrows = 2\ncols = 2\n[model]\nlink = \"paper\"\n"
            .to_vec(),
    ));
    for (i, m) in [
        Message::Go,
        Message::Refused {
            reason: "no".into(),
        },
        Message::DataRequest {
            id: protocol::DataId::Chunk(3),
            transfer: protocol::Transfer::Dma,
            owner: 2,
        },
        Message::Pixels {
            subscreen: 1,
            y: 2,
            x: 3,
            width: 4,
        },
        Message::Peers {
            addresses: vec![(1, "127.0.0.1:9".into(), "b".into())],
        },
    ]
    .iter()
    .enumerate()
    {
        let f = protocol::Frame::new(1, 2, m, vec![7u32; 3].into_boxed_slice());
        let mut bytes = f.header.encode().to_vec();
        bytes.extend_from_slice(&f.meta);
        out.push(("frame", format!("frame-{i}"), bytes));
    }
    let (scene, data) = renderer::prepare(
        renderer::demo::demo_scene(),
        &renderer::PrepareOptions {
            chunk_triangles: 64,
        },
    );
    for (i, c) in data.chunks.iter().take(3).enumerate() {
        out.push(("chunk", format!("chunk-{i}"), c.as_bytes().to_vec()));
    }
    out.push((
        "scene_header",
        "demo".into(),
        protocol::encode_value(&scene),
    ));
    out
}

/// A GLB container around a JSON chunk and an optional binary chunk.
fn glb(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let pad = |v: &[u8], with: u8| {
        let mut v = v.to_vec();
        while !v.len().is_multiple_of(4) {
            v.push(with);
        }
        v
    };
    let (json, bin) = (pad(json, b' '), pad(bin, 0));
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let mut out = b"glTF".to_vec();
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&json);
    if !bin.is_empty() {
        out.extend((bin.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(&bin);
    }
    out
}
