//! Broken and hostile scene files: each gives a clear message naming the file and the
//! problem (or, for optional data, a warning and a fallback), never a panic.

mod common;
use common::*;

use std::path::{Path, PathBuf};

use base64::Engine;

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A one-triangle glTF with the given positions and indices in an embedded buffer, and extra
/// top-level JSON merged in.
fn triangle_gltf(
    positions: &[[f32; 3]],
    indices: &[u16],
    count_override: Option<usize>,
    extra: &str,
) -> String {
    let mut buf = Vec::new();
    for i in indices {
        buf.extend_from_slice(&i.to_le_bytes());
    }
    while buf.len() % 4 != 0 {
        buf.push(0);
    }
    let index_bytes = buf.len();
    for p in positions {
        for c in p {
            buf.extend_from_slice(&c.to_le_bytes());
        }
    }
    let count = count_override.unwrap_or(positions.len());
    format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "scene": 0,
  "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"mesh": 0}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 1}}, "indices": 0}}]}}],
  "buffers": [{{"byteLength": {len}, "uri": "data:application/octet-stream;base64,{data}"}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": {ib}}},
    {{"buffer": 0, "byteOffset": {ib}, "byteLength": {pb}}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5123, "count": {ni}, "type": "SCALAR"}},
    {{"bufferView": 1, "componentType": 5126, "count": {count}, "type": "VEC3", "min": [0,0,0], "max": [1,1,1]}}
  ]{extra}
}}"#,
        len = buf.len(),
        data = b64(&buf),
        ib = index_bytes,
        pb = buf.len() - index_bytes,
        ni = indices.len(),
    )
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// Renders `scene` in one process; returns (success, stderr).
fn try_render(scene: &Path, out: &Path) -> (bool, String) {
    let o = run(host()
        .args([
            "render",
            "--in-process",
            "--width",
            "16",
            "--height",
            "16",
            "--spp",
            "1",
            "--log",
            "warn",
        ])
        .arg(scene)
        .arg("-o")
        .arg(out));
    let err = stderr(&o);
    assert!(
        !err.contains("panicked"),
        "{}: panic: {err}",
        scene.display()
    );
    (o.status.success(), err)
}

fn expect_refused(scene: &Path, dir: &Path, needles: &[&str]) {
    let out = dir.join("out.png");
    let (ok, err) = try_render(scene, &out);
    assert!(!ok, "{} should be refused", scene.display());
    let name = scene.file_name().unwrap().to_string_lossy();
    assert!(
        err.contains(name.as_ref()),
        "the error should name the file: {err}"
    );
    for n in needles {
        assert!(
            err.contains(n),
            "{}: {err:?} should mention {n:?}",
            scene.display()
        );
    }
    assert!(!out.exists());
}

const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

#[test]
fn a_valid_generated_file_renders() {
    let dir = scratch("hostile-valid");
    let p = write(&dir, "ok.gltf", &triangle_gltf(&TRI, &[0, 1, 2], None, ""));
    let (ok, err) = try_render(&p, &dir.join("o.png"));
    assert!(ok, "{err}");
}

#[test]
fn truncated_glb_is_refused() {
    let dir = scratch("hostile-glb");
    let src =
        std::fs::read(data().join("scenes/khronos/DamagedHelmet/glTF-Binary/DamagedHelmet.glb"))
            .unwrap();
    for (name, cut) in [
        ("half.glb", src.len() / 2),
        ("header.glb", 30),
        ("empty.glb", 0),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, &src[..cut]).unwrap();
        expect_refused(&p, &dir, &[]);
    }
}

#[test]
fn buffer_shorter_than_its_accessor_is_refused() {
    let dir = scratch("hostile-short");
    let p = write(
        &dir,
        "short.gltf",
        &triangle_gltf(&TRI, &[0, 1, 2], Some(1000), ""),
    );
    expect_refused(&p, &dir, &["accessor"]);
}

#[test]
fn index_out_of_range_is_refused() {
    let dir = scratch("hostile-index");
    let p = write(
        &dir,
        "index.gltf",
        &triangle_gltf(&TRI, &[0, 1, 7], None, ""),
    );
    expect_refused(&p, &dir, &["index 7 out of range"]);
}

#[test]
fn unknown_required_extension_is_refused_by_name() {
    let dir = scratch("hostile-ext");
    let extra = r#", "extensionsUsed": ["EXT_magic_teleport"], "extensionsRequired": ["EXT_magic_teleport"]"#;
    let p = write(
        &dir,
        "ext.gltf",
        &triangle_gltf(&TRI, &[0, 1, 2], None, extra),
    );
    expect_refused(&p, &dir, &["EXT_magic_teleport"]);
}

/// A vertex at NaN or infinity: the triangles using it are skipped with a warning, and the
/// render goes on, in one process and on a cluster alike (the same image bytes). The cluster
/// once refused the file: the loader dropped the triangles but kept the vertex, which the
/// fork node's check of the description (every position finite) then refused.
#[test]
fn nan_positions_are_skipped_with_a_warning() {
    let _one = serial();
    let dir = scratch("hostile-nan");
    for (name, bad) in [("nan", f32::NAN), ("inf", f32::INFINITY)] {
        let pos = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [bad, 0.0, 0.0],
        ];
        let p = write(
            &dir,
            &format!("{name}.gltf"),
            &triangle_gltf(&pos, &[0, 1, 2, 0, 3, 2], None, ""),
        );
        let out = dir.join(format!("{name}-one.pfm"));
        let (ok, err) = try_render(&p, &out);
        assert!(ok, "{name}: {err}");
        assert!(
            err.contains("degenerate"),
            "{name}: a warning should say what was skipped: {err}"
        );
        let img = scene_io::read_image(&out).unwrap();
        assert!(img.pixels.iter().flatten().all(|v| v.is_finite()));

        let cluster = dir.join(format!("{name}-cluster.pfm"));
        let o = run(host()
            .args([
                "render", "--spawn", "tiny", "--width", "16", "--height", "16",
            ])
            .args(["--spp", "1", "--log", "warn"])
            .arg(&p)
            .arg("-o")
            .arg(&cluster));
        let err = stderr(&o);
        assert!(o.status.success(), "{name} on a cluster: {err}");
        assert!(
            err.contains("degenerate"),
            "{name} on a cluster: a warning should say what was skipped: {err}"
        );
        same_bytes(&out, &cluster);
    }
}

/// A sparse accessor without a bufferView stands for `count` elements, all zero but the
/// few it lists: a count of 10^12 in a file of a few hundred bytes once asked the loader
/// for 24 TB (an abort). Such a file is refused by name, for positions and for indices.
#[test]
fn sparse_accessor_with_a_huge_count_is_refused() {
    let dir = scratch("hostile-sparse");
    // The sparse part's one index (u32 0) and its one value (a VEC3 of floats).
    let mut buf = 0u32.to_le_bytes().to_vec();
    for v in [1.0f32, 1.0, 1.0] {
        buf.extend_from_slice(&v.to_le_bytes());
    }
    let huge = 1_000_000_000_000u64;
    for (name, attribute, indices, index_count) in [
        ("positions.gltf", 0, "", 3),
        ("indices.gltf", 1, r#", "indices": 2"#, huge),
    ] {
        let text = format!(
            r#"{{
  "asset": {{"version": "2.0"}},
  "scene": 0,
  "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"mesh": 0}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": {attribute}}}{indices}}}]}}],
  "buffers": [{{"byteLength": {len}, "uri": "data:application/octet-stream;base64,{data}"}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 4}},
    {{"buffer": 0, "byteOffset": 4, "byteLength": 12}}
  ],
  "accessors": [
    {{"componentType": 5126, "count": {huge}, "type": "VEC3", "min": [0,0,0], "max": [1,1,1],
      "sparse": {{"count": 1, "indices": {{"bufferView": 0, "componentType": 5125}},
                  "values": {{"bufferView": 1}}}}}},
    {{"componentType": 5126, "count": 3, "type": "VEC3", "min": [0,0,0], "max": [1,1,1],
      "sparse": {{"count": 1, "indices": {{"bufferView": 0, "componentType": 5125}},
                  "values": {{"bufferView": 1}}}}}},
    {{"componentType": 5125, "count": {index_count}, "type": "SCALAR",
      "sparse": {{"count": 1, "indices": {{"bufferView": 0, "componentType": 5125}},
                  "values": {{"bufferView": 0}}}}}}
  ]
}}"#,
            len = buf.len(),
            data = b64(&buf),
        );
        let p = write(&dir, name, &text);
        let accessor = if attribute == 0 {
            "accessor 0"
        } else {
            "accessor 2"
        };
        expect_refused(&p, &dir, &[accessor, "no bufferView"]);
    }
}

/// glTF's nodes form disjoint trees. A node reached twice (two parents, one parent naming it
/// twice, a root that is also a child) is refused by name: it was placed once per way down,
/// and 18 levels of `children [i+1, i+1]` gave 262,144 copies of a mesh and a render that
/// did not end. Cycles and depth keep their own messages.
#[test]
fn nodes_reached_twice_are_refused() {
    let dir = scratch("hostile-nodes");
    let with_nodes = |roots: &str, nodes: &str| {
        triangle_gltf(&TRI, &[0, 1, 2], None, "")
            .replace(
                r#""scenes": [{"nodes": [0]}]"#,
                &format!(r#""scenes": [{{"nodes": {roots}}}]"#),
            )
            .replace(r#""nodes": [{"mesh": 0}]"#, &format!(r#""nodes": {nodes}"#))
    };
    let chain = |levels: usize, children: &str| {
        let mut nodes: Vec<String> = (0..levels)
            .map(|i| children.replace('N', &(i + 1).to_string()))
            .collect();
        nodes.push(r#"{"mesh": 0}"#.into());
        format!("[{}]", nodes.join(", "))
    };
    for (name, roots, nodes, needles) in [
        (
            "listed-twice.gltf",
            "[0]".to_string(),
            chain(3, r#"{"children": [N, N]}"#),
            &["node 3 is listed twice as a child of node 2"][..],
        ),
        (
            "two-parents.gltf",
            "[0, 1]".to_string(),
            r#"[{"children": [2]}, {"children": [2]}, {"mesh": 0}]"#.to_string(),
            &["node 2 is both a child of node 1 and a child of node 0"][..],
        ),
        (
            "root-and-child.gltf",
            "[0, 1]".to_string(),
            r#"[{"children": [1]}, {"mesh": 0}]"#.to_string(),
            &["node 1 is both", "a root of the scene", "a child of node 0"][..],
        ),
        (
            "cycle.gltf",
            "[0]".to_string(),
            r#"[{"children": [1]}, {"children": [0], "mesh": 0}]"#.to_string(),
            &["cycle", "node 0"][..],
        ),
        (
            "deep.gltf",
            "[0]".to_string(),
            chain(300, r#"{"children": [N]}"#),
            &["deeper than 256 levels"][..],
        ),
    ] {
        let p = write(&dir, name, &with_nodes(&roots, &nodes));
        expect_refused(&p, &dir, needles);
    }
}

#[test]
fn missing_or_empty_textures_fall_back_with_a_warning() {
    let dir = scratch("hostile-texture");
    // BoxTextured without its image file.
    let src = data().join("scenes/khronos/BoxTextured/glTF");
    for f in ["BoxTextured.gltf", "BoxTextured0.bin"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let (ok, err) = try_render(&dir.join("BoxTextured.gltf"), &dir.join("o.png"));
    assert!(ok, "{err}");
    assert!(
        err.contains("CesiumLogoFlat.png"),
        "the warning should name the missing file: {err}"
    );

    // A 0x0 PNG (a valid signature and header chunk claiming no pixels).
    let mut png = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0\0\0\0\0\0\x08\x06\0\0\0".to_vec();
    png.extend_from_slice(&[0, 0, 0, 0]);
    let extra = format!(
        r#", "images": [{{"uri": "data:image/png;base64,{}"}}], "textures": [{{"source": 0}}],
        "materials": [{{"pbrMetallicRoughness": {{"baseColorTexture": {{"index": 0}}}}}}]"#,
        b64(&png)
    );
    let text = triangle_gltf(&TRI, &[0, 1, 2], None, &extra)
        .replace(r#""indices": 0}"#, r#""indices": 0, "material": 0}"#);
    let p = write(&dir, "empty-image.gltf", &text);
    let (ok, err) = try_render(&p, &dir.join("o2.png"));
    assert!(ok, "{err}");
    assert!(
        err.contains("image 0"),
        "the warning should name the image: {err}"
    );
}

#[test]
fn images_without_a_source_or_mime_type_fall_back_with_a_warning() {
    // Found by the fuzzer: the gltf crate unwraps these fields when asked for an image's
    // source, so they must be caught before.
    let dir = scratch("hostile-image-source");
    for (name, image) in [
        ("no-source.gltf", r#"{"name": "nothing"}"#),
        ("view-no-mime.gltf", r#"{"bufferView": 0}"#),
    ] {
        let extra = format!(
            r#", "images": [{image}], "textures": [{{"source": 0}}],
            "materials": [{{"pbrMetallicRoughness": {{"baseColorTexture": {{"index": 0}}}}}}]"#
        );
        let text = triangle_gltf(&TRI, &[0, 1, 2], None, &extra)
            .replace(r#""indices": 0}"#, r#""indices": 0, "material": 0}"#);
        let p = write(&dir, name, &text);
        let (ok, err) = try_render(&p, &dir.join("o.png"));
        assert!(ok, "{name}: {err}");
        assert!(
            err.contains("image 0"),
            "{name}: the warning should name the image: {err}"
        );
    }
}

/// A texture naming a texture coordinate set beyond 0 and 1 (which meshes keep) is said and
/// read from set 0: it read (0, 0) at surfaces, and set 0 where an emissive one lit the
/// scene, and said nothing.
#[test]
fn texture_coordinate_sets_beyond_one_are_said() {
    let dir = scratch("hostile-texcoord");
    let png = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0\x01\0\0\0\x01\x08\x02\0\0\0\x90wS\xde\0\0\0\x0cIDATx\x9cc\xf8\xcf\xc0\0\0\x03\x01\x01\0\xc9\xfe\x92\xef\0\0\0\0IEND\xaeB`\x82";
    let extra = format!(
        r#", "images": [{{"uri": "data:image/png;base64,{}"}}], "textures": [{{"source": 0}}],
        "materials": [{{"pbrMetallicRoughness": {{"baseColorTexture": {{"index": 0, "texCoord": 2}}}},
                        "emissiveTexture": {{"index": 0, "texCoord": 3}}, "emissiveFactor": [1, 1, 1]}}]"#,
        b64(png)
    );
    let text = triangle_gltf(&TRI, &[0, 1, 2], None, &extra)
        .replace(r#""indices": 0}"#, r#""indices": 0, "material": 0}"#);
    let p = write(&dir, "texcoord2.gltf", &text);
    let (ok, err) = try_render(&p, &dir.join("o.png"));
    assert!(ok, "{err}");
    for needle in [
        "the base colour texture reads texture coordinate set 2",
        "the emissive texture reads texture coordinate set 3",
    ] {
        assert!(err.contains(needle), "{err}");
    }
}
