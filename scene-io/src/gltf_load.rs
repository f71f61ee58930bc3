//! glTF 2.0 (`.gltf` with external or embedded buffers, and `.glb`) to [`SceneDesc`].
//!
//! The file is parsed with the `gltf` crate; buffers and images are resolved here (so that a
//! missing or short file is reported by name), and every accessor is range-checked before it
//! is read. The node tree is flattened into world space in f64 and the whole scene is moved
//! so its bounding box is centred on the origin (cameras and lights with it): f32 then keeps
//! full precision for a scene placed a million units from the origin, and the picture is
//! the same.
//!
//! Supported beyond the core: KHR_materials_emissive_strength, KHR_materials_specular,
//! KHR_materials_transmission, KHR_materials_ior, KHR_materials_volume, KHR_texture_transform,
//! KHR_lights_punctual and EXT_mesh_gpu_instancing. Anything else a file uses is named in one
//! warning; an unsupported extension the file *requires* is an error, as the specification
//! demands.

use std::{
    cell::RefCell,
    collections::{BTreeSet, HashMap},
    path::{Path, PathBuf},
};

use base64::Engine;
use glam::{DMat3, DMat4, DVec3, Mat3, Vec2, Vec3, Vec4};
use gltf::{
    accessor::{DataType, Dimensions},
    mesh::Mode,
};
use renderer::{
    Camera, Projection, SceneDesc,
    chunk::MeshData,
    light::Light,
    material::{AlphaMode, Material, TexRef, UvTransform},
    scene::TextureDesc,
    texture::{Filter, Wrap},
};

/// Extensions magg implements; a file may require only these.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_materials_emissive_strength",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_ior",
    "KHR_materials_volume",
    "KHR_texture_transform",
    "KHR_lights_punctual",
    "EXT_mesh_gpu_instancing",
];

/// Largest image accepted, in pixels per side, so a hostile file cannot ask for gigabytes.
const MAX_IMAGE_SIDE: u32 = 16384;

/// Most bytes the accessors without a bufferView (zeros but for their sparse parts) may stand
/// for together, where the file's buffers hold less: see [`check_accessor`].
const MAX_UNBACKED_BYTES: usize = 16 << 20;

#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not a valid glTF file: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: requires extension {extension}, which magg does not implement")]
    UnsupportedRequiredExtension { path: PathBuf, extension: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
}

/// A loaded scene, with what was skipped or ignored along the way.
#[derive(Debug)]
pub struct Loaded {
    pub desc: SceneDesc,
    pub warnings: Vec<String>,
    /// World-space offset that was subtracted to centre the scene.
    pub origin_shift: DVec3,
}

struct Ctx<'a> {
    path: &'a Path,
    dir: PathBuf,
    warnings: Vec<String>,
    unsupported: BTreeSet<String>,
    /// Accessors without a bufferView already admitted, and the bytes they stand for
    /// together: their bound is the file's, not each one's (see [`check_accessor`]).
    unbacked: RefCell<(BTreeSet<usize>, usize)>,
}

impl Ctx<'_> {
    fn invalid(&self, message: impl Into<String>) -> LoadError {
        LoadError::Invalid {
            path: self.path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// Loads a `.gltf` or `.glb` file.
pub fn load_gltf(path: &Path) -> Result<Loaded, LoadError> {
    let bytes = std::fs::read(path).map_err(|source| LoadError::Io {
        path: path.into(),
        source,
    })?;
    load_gltf_bytes(path, &bytes)
}

/// The files a glTF file names for its buffers and images, where the loader would open
/// them, so that a command can refuse to write over a scene's own data (`-o` onto its
/// texture, `--stats` onto its `.bin` replaced them and the scene no longer loaded). Only
/// the JSON is read (a GLB's first chunk, not its binary one); a file that cannot be read or
/// parsed names nothing here, and loading it says why.
pub fn files_named(path: &Path) -> Vec<PathBuf> {
    use std::io::Read;
    let json = (|| -> std::io::Result<Vec<u8>> {
        let mut file = std::fs::File::open(path)?;
        let mut head = [0u8; 20];
        let n = file.read(&mut head)?;
        if n == 20 && head.starts_with(b"glTF") && &head[16..20] == b"JSON" {
            let len = u32::from_le_bytes([head[12], head[13], head[14], head[15]]);
            let mut json = Vec::new();
            file.take(len as u64).read_to_end(&mut json)?;
            return Ok(json);
        }
        let mut json = head[..n].to_vec();
        file.read_to_end(&mut json)?;
        Ok(json)
    })();
    let Ok(json) = json else {
        return Vec::new();
    };
    let Ok(doc) = serde_json::from_slice::<serde_json::Value>(&json) else {
        return Vec::new();
    };
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    ["buffers", "images"]
        .iter()
        .filter_map(|list| doc.get(list)?.as_array())
        .flatten()
        .filter_map(|named| local_file(&dir, named.get("uri")?.as_str()?))
        .collect()
}

/// Checks a GLB container's header and chunk headers, so that a truncated or foreign file
/// is said as such: the `gltf` crate's words for these ("failed to fill whole buffer",
/// "could not completely read the object", "JSON chunk length exceeds that of slice") name
/// neither the part nor the sizes.
fn check_glb(bytes: &[u8]) -> Result<(), String> {
    let word = |at: usize| {
        bytes
            .get(at..at + 4)
            .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
    };
    let (Some(version), Some(total)) = (word(4), word(8)) else {
        return Err(format!(
            "a GLB file starts with a 12-byte header; this one has {} bytes in all",
            bytes.len()
        ));
    };
    if version != 2 {
        return Err(format!("GLB version {version}; only version 2 is read"));
    }
    if total as usize != bytes.len() {
        return Err(format!(
            "its header gives its length as {total} bytes, but the file has {} (cut short, \
             or more than one file)",
            bytes.len()
        ));
    }
    let mut at = 12;
    let mut first = true;
    while at < bytes.len() {
        let (Some(len), Some(kind)) = (word(at), bytes.get(at + 4..at + 8)) else {
            return Err(format!(
                "a chunk header at byte {at} needs 8 bytes; {} are left",
                bytes.len() - at
            ));
        };
        let name = if kind == b"JSON" {
            "JSON".to_string()
        } else if kind == b"BIN\0" {
            "BIN".to_string()
        } else {
            format!("{:?}", String::from_utf8_lossy(kind))
        };
        if first && kind != b"JSON" {
            return Err(format!(
                "its first chunk is {name}, where a GLB file's is JSON"
            ));
        }
        let left = bytes.len() - at - 8;
        if len as usize > left {
            return Err(format!(
                "its {name} chunk at byte {at} gives {len} bytes, but only {left} follow (cut \
                 short?)"
            ));
        }
        at += 8 + len as usize;
        first = false;
    }
    if first {
        return Err("it has no JSON chunk (the header alone)".into());
    }
    Ok(())
}

/// Loads glTF from bytes; `path` names the file in messages and anchors relative URIs.
pub fn load_gltf_bytes(path: &Path, bytes: &[u8]) -> Result<Loaded, LoadError> {
    let parse = |message: String| LoadError::Parse {
        path: path.into(),
        message,
    };
    if bytes.starts_with(b"glTF") {
        check_glb(bytes).map_err(&parse)?;
    }
    let raw = gltf::Gltf::from_slice_without_validation(bytes).map_err(|e| parse(e.to_string()))?;
    for ext in raw.extensions_required() {
        if !SUPPORTED_EXTENSIONS.contains(&ext) {
            return Err(LoadError::UnsupportedRequiredExtension {
                path: path.into(),
                extension: ext.to_string(),
            });
        }
    }
    let blob = raw.blob.clone();
    let json = raw.document.into_json();
    precheck_indices(&json).map_err(|e| parse(e.to_string()))?;
    // The gltf crate's validation indexes some arrays before checking them; the check above
    // covers the cases known to panic, and this stops any other at the library boundary.
    let validated = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || {
        gltf::Document::from_json(json)
    }));
    let doc = match validated {
        Ok(r) => r.map_err(|e| parse(e.to_string()))?,
        Err(_) => {
            return Err(parse(
                "the file's structure is inconsistent (validation failed)".into(),
            ));
        }
    };
    let mut ctx = Ctx {
        path,
        dir: path.parent().map(Path::to_path_buf).unwrap_or_default(),
        warnings: Vec::new(),
        unsupported: BTreeSet::new(),
        unbacked: RefCell::default(),
    };
    for ext in doc.extensions_used() {
        if !SUPPORTED_EXTENSIONS.contains(&ext) {
            ctx.unsupported.insert(format!("extension {ext}"));
        }
    }

    let buffers = load_buffers(&mut ctx, &doc, blob)?;
    let (textures, texture_map) = load_textures(&mut ctx, &doc, &buffers)?;
    let mut materials: Vec<Material> = doc
        .materials()
        .map(|m| convert_material(&mut ctx, &m, &texture_map))
        .collect();
    let default_material = materials.len() as u32;
    materials.push(Material::default());

    let scene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| ctx.invalid("the file has no scene"))?;

    // Flatten the node tree.
    let mut placed: Vec<PlacedPrimitive> = Vec::new();
    let mut cameras: Vec<(usize, String, DMat4, Projection, Option<f32>)> = Vec::new();
    let mut lights: Vec<(DMat4, gltf::khr_lights_punctual::Light)> = Vec::new();
    let mut stack: Vec<(gltf::Node, DMat4, usize, Option<usize>)> = scene
        .nodes()
        .map(|n| (n, DMat4::IDENTITY, 0, None))
        .collect();
    // The parent each node was first reached from (`Some(None)`: a root of the scene).
    let mut reached: Vec<Option<Option<usize>>> = vec![None; doc.nodes().len()];
    while let Some((node, parent, depth, from)) = stack.pop() {
        if depth > 256 {
            return Err(ctx.invalid(format!(
                "node hierarchy is deeper than 256 levels (at node {})",
                node_name(&node)
            )));
        }
        if let Some(first) = reached[node.index()] {
            return Err(ctx.invalid(reached_twice(&node, first, from, &reached)));
        }
        reached[node.index()] = Some(from);
        let local =
            DMat4::from_cols_array_2d(&node.transform().matrix().map(|c| c.map(|v| v as f64)));
        let world = parent * local;
        if !world.is_finite() {
            ctx.warnings.push(format!(
                "node {}: non-finite transform, skipped with its children",
                node_name(&node)
            ));
            continue;
        }
        if node.skin().is_some() {
            ctx.unsupported
                .insert("skins (meshes are drawn in their bind pose)".into());
        }
        if let Some(camera) = node.camera()
            && let Some(c) = convert_camera(&mut ctx, &camera, &node)
        {
            cameras.push((camera.index(), c.0, world, c.1, c.2));
        }
        if let Some(light) = node.light() {
            lights.push((world, light));
        }
        if let Some(mesh) = node.mesh() {
            let instances = instance_transforms(&mut ctx, &node, &doc, &buffers)?;
            for prim in mesh.primitives() {
                let material = prim
                    .material()
                    .index()
                    .map_or(default_material, |i| i as u32);
                if prim.morph_targets().next().is_some() {
                    ctx.unsupported
                        .insert("morph targets (the base shape is drawn)".into());
                }
                let Some(data) = read_primitive(
                    &mut ctx,
                    &prim,
                    &mesh,
                    &buffers,
                    &materials[material as usize],
                )?
                else {
                    continue;
                };
                let data = std::rc::Rc::new(data);
                match &instances {
                    None => placed.push(PlacedPrimitive {
                        data: data.clone(),
                        world,
                        material,
                    }),
                    Some(list) => {
                        for inst in list {
                            placed.push(PlacedPrimitive {
                                data: data.clone(),
                                world: world * *inst,
                                material,
                            });
                        }
                    }
                }
            }
        }
        for child in node.children() {
            stack.push((child, world, depth + 1, Some(node.index())));
        }
    }

    // Centre the scene on the origin, in f64.
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in &placed {
        for v in &p.data.positions {
            // A vertex at NaN or infinity takes no part: its triangles are skipped below.
            let w = p.world.transform_point3(*v);
            if w.is_finite() {
                lo = lo.min(w);
                hi = hi.max(w);
            }
        }
    }
    let shift = if lo.is_finite() && hi.is_finite() {
        DVec3::from_array([0, 1, 2].map(|k| exact_shift(lo[k], hi[k])))
    } else {
        DVec3::ZERO
    };

    let mut meshes = Vec::with_capacity(placed.len());
    let mut degenerate = 0usize;
    for p in &placed {
        let (mesh, skipped) = place_primitive(p, shift);
        degenerate += skipped;
        if !mesh.triangles.is_empty() {
            meshes.push(mesh);
        }
    }
    if degenerate > 0 {
        ctx.warnings.push(format!(
            "{degenerate} degenerate triangles (zero area or non-finite) skipped"
        ));
    }

    // "The first camera" is the first of the file's camera list, whatever the node order.
    cameras.sort_by_key(|c| c.0);
    let cameras = cameras
        .into_iter()
        .map(|(_, name, world, projection, aspect_ratio)| Camera {
            name,
            position: (world.transform_point3(DVec3::ZERO) - shift).as_vec3(),
            orientation: camera_axes(world),
            projection,
            aspect_ratio,
        })
        .collect();

    let lights = lights
        .into_iter()
        .filter_map(|(world, l)| convert_light(&mut ctx, world, &l, shift))
        .collect();

    if !ctx.unsupported.is_empty() {
        let list: Vec<String> = ctx.unsupported.iter().cloned().collect();
        ctx.warnings
            .insert(0, format!("not supported, ignored: {}", list.join("; ")));
    }
    let warnings = ctx.warnings;
    Ok(Loaded {
        desc: SceneDesc {
            meshes,
            materials,
            textures,
            lights,
            cameras,
            environment: None,
        },
        warnings,
        origin_shift: shift,
    })
}

/// Why `node`, reached again from `from` after first from `first`, is refused: a cycle where
/// it is an ancestor of `from` along the ways first taken, else a node with two parents (or
/// a root that is also a child, or listed twice), which glTF forbids (its nodes form
/// disjoint trees) and which would place its subtree once per way down.
fn reached_twice(
    node: &gltf::Node,
    first: Option<usize>,
    from: Option<usize>,
    reached: &[Option<Option<usize>>],
) -> String {
    let mut up = from;
    while let Some(a) = up {
        if a == node.index() {
            return format!(
                "node hierarchy has a cycle (node {} is its own ancestor)",
                node_name(node)
            );
        }
        up = reached[a].flatten();
    }
    let way = |p: Option<usize>| match p {
        Some(p) => format!("a child of node {p}"),
        None => "a root of the scene".to_string(),
    };
    let how = if first == from {
        format!("listed twice as {}", way(first))
    } else {
        format!("both {} and {}", way(first), way(from))
    };
    format!(
        "node {} is {how}: glTF requires the node hierarchy to be disjoint trees",
        node_name(node)
    )
}

/// A primitive that names an accessor the file does not have.
#[derive(Debug, thiserror::Error)]
#[error(
    "meshes[{mesh}].primitives[{primitive}] uses accessor {accessor}, but the file has {accessors}"
)]
struct MissingAccessor {
    mesh: usize,
    primitive: usize,
    accessor: usize,
    accessors: usize,
}

/// Index checks the `gltf` crate's own validation relies on before it makes them itself:
/// every attribute, index and morph target accessor of every primitive must exist.
fn precheck_indices(json: &gltf::json::Root) -> Result<(), MissingAccessor> {
    let accessors = json.accessors.len();
    for (m, mesh) in json.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let mut used: Vec<usize> = prim.attributes.values().map(|a| a.value()).collect();
            used.extend(prim.indices.map(|i| i.value()));
            for t in prim.targets.iter().flatten() {
                used.extend(
                    [t.positions, t.normals, t.tangents]
                        .iter()
                        .flatten()
                        .map(|a| a.value()),
                );
            }
            if let Some(&bad) = used.iter().find(|&&a| a >= accessors) {
                return Err(MissingAccessor {
                    mesh: m,
                    primitive: p,
                    accessor: bad,
                    accessors,
                });
            }
        }
    }
    Ok(())
}

/// Orthonormal, right-handed camera axes (right, up, back) from a node's world matrix,
/// keeping its viewing direction (-Z) exactly and dropping scale and shear.
fn camera_axes(world: DMat4) -> Mat3 {
    let m = DMat3::from_mat4(world);
    let back = m.z_axis.normalize_or(DVec3::Z);
    let up_hint = if back.cross(m.y_axis).length_squared() > 1e-20 {
        m.y_axis
    } else {
        DVec3::Y
    };
    let right = up_hint.cross(back).normalize_or(DVec3::X);
    let up = back.cross(right);
    Mat3::from_cols(right.as_vec3(), up.as_vec3(), back.as_vec3())
}

fn node_name(node: &gltf::Node) -> String {
    match node.name() {
        Some(n) => format!("{} ({n:?})", node.index()),
        None => node.index().to_string(),
    }
}

fn decode_data_uri(uri: &str) -> Option<Vec<u8>> {
    let rest = uri.strip_prefix("data:")?;
    let (meta, data) = rest.split_once(',')?;
    if meta.ends_with(";base64") {
        base64::engine::general_purpose::STANDARD
            .decode(data.trim())
            .ok()
    } else {
        Some(percent_encoding::percent_decode_str(data).collect())
    }
}

/// The file a buffer's or image's URI names, relative to the scene's folder `dir`
/// (percent-decoded); `None` for an embedded data URI or another scheme, which name no file.
/// Loading and [`files_named`] both resolve URIs here, so the files a command refuses to
/// write over are the ones the loader reads.
fn local_file(dir: &Path, uri: &str) -> Option<PathBuf> {
    if uri.starts_with("data:") || uri.contains("://") {
        return None;
    }
    Some(dir.join(&*percent_encoding::percent_decode_str(uri).decode_utf8_lossy()))
}

/// Reads a URI relative to the scene file (percent-decoded), or an embedded data URI.
fn read_uri(ctx: &Ctx, uri: &str) -> Result<Vec<u8>, String> {
    if uri.starts_with("data:") {
        return decode_data_uri(uri).ok_or_else(|| "malformed data URI".to_string());
    }
    let Some(file) = local_file(&ctx.dir, uri) else {
        return Err(format!("URI {uri:?} is not a local file"));
    };
    std::fs::read(&file).map_err(|e| format!("{}: {e}", file.display()))
}

fn load_buffers(
    ctx: &mut Ctx,
    doc: &gltf::Document,
    blob: Option<Vec<u8>>,
) -> Result<Vec<Vec<u8>>, LoadError> {
    let mut blob = blob;
    let mut out = Vec::new();
    for b in doc.buffers() {
        let data = match b.source() {
            gltf::buffer::Source::Bin => blob.take().ok_or_else(|| {
                ctx.invalid(format!(
                    "buffer {} refers to the GLB binary chunk, which is missing",
                    b.index()
                ))
            })?,
            gltf::buffer::Source::Uri(uri) => {
                read_uri(ctx, uri).map_err(|e| ctx.invalid(format!("buffer {}: {e}", b.index())))?
            }
        };
        if data.len() < b.length() {
            return Err(ctx.invalid(format!(
                "buffer {} holds {} bytes but the file says {} (truncated?)",
                b.index(),
                data.len(),
                b.length()
            )));
        }
        out.push(data);
    }
    Ok(out)
}

/// Bytes of a buffer view, range-checked.
fn view_bytes<'b>(
    ctx: &Ctx,
    view: &gltf::buffer::View,
    buffers: &'b [Vec<u8>],
) -> Result<&'b [u8], LoadError> {
    let buf = &buffers[view.buffer().index()];
    let end = view.offset().checked_add(view.length());
    end.and_then(|end| buf.get(view.offset()..end))
        .ok_or_else(|| {
            ctx.invalid(format!(
                "bufferView {} (bytes {}..{}) lies outside its buffer of {} bytes",
                view.index(),
                view.offset(),
                view.offset().saturating_add(view.length()),
                buf.len()
            ))
        })
}

/// Width, height and RGBA8 texels.
type DecodedImage = (u32, u32, Vec<u8>);

fn load_textures(
    ctx: &mut Ctx,
    doc: &gltf::Document,
    buffers: &[Vec<u8>],
) -> Result<(Vec<TextureDesc>, Vec<Option<u32>>), LoadError> {
    // Decode each image once.
    let mut images: Vec<Option<DecodedImage>> = Vec::new();
    for img in doc.images() {
        // `Image::source` unwraps fields the gltf crate's validation does not check (an
        // image with neither `uri` nor `bufferView`, or a `bufferView` without `mimeType`),
        // so the JSON is read directly and such images become warnings.
        let json = &doc.as_json().images[img.index()];
        let bytes = match (&json.buffer_view, &json.uri) {
            (Some(view), _) => match doc.views().nth(view.value()) {
                Some(view) => view_bytes(ctx, &view, buffers)
                    .map(|b| b.to_vec())
                    .map_err(|e| e.to_string()),
                None => Err(format!("bufferView {} does not exist", view.value())),
            },
            (None, Some(uri)) => read_uri(ctx, uri),
            (None, None) => Err("it has neither a uri nor a bufferView".to_string()),
        };
        let decoded = bytes.and_then(|b| decode_image(&b));
        match decoded {
            Ok((w, h, rgba)) => images.push(Some((w, h, rgba))),
            Err(e) => {
                ctx.warnings.push(format!(
                    "image {}: {e}; textures using it are ignored",
                    img.index()
                ));
                images.push(None);
            }
        }
    }
    // Textures alike (one image, one sampler's settings) become one texture, which the
    // materials naming any of them share: a file may name one image in many textures.
    // Under other settings an image makes another texture, which shares the first's
    // texels and tiles (`texels_of`).
    let mut alike: HashMap<(usize, [u8; 3]), u32> = HashMap::new();
    let mut kept: Vec<(usize, String, Wrap, Wrap, Filter)> = Vec::new();
    let mut map = Vec::new();
    for t in doc.textures() {
        let source = t.source().index();
        if !matches!(images.get(source), Some(Some(_))) {
            map.push(None);
            continue;
        }
        let sampler = t.sampler();
        let wrap = |m: gltf::texture::WrappingMode| match m {
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
        };
        let filter = match sampler.mag_filter() {
            Some(gltf::texture::MagFilter::Nearest) => Filter::Nearest,
            _ => Filter::Linear,
        };
        let (wrap_s, wrap_t) = (wrap(sampler.wrap_s()), wrap(sampler.wrap_t()));
        let key = (source, [wrap_s as u8, wrap_t as u8, filter as u8]);
        let index = *alike.entry(key).or_insert_with(|| {
            let name = t
                .name()
                .map(str::to_string)
                .unwrap_or_else(|| format!("texture {}", t.index()));
            kept.push((source, name, wrap_s, wrap_t, filter));
            (kept.len() - 1) as u32
        });
        map.push(Some(index));
    }
    // An image's first texture holds its texels; the others sample them.
    let mut holder: Vec<Option<u32>> = vec![None; images.len()];
    let mut textures = Vec::with_capacity(kept.len());
    for (i, (source, name, wrap_s, wrap_t, filter)) in kept.into_iter().enumerate() {
        let (width, height, rgba, texels_of) = match holder[source] {
            Some(of) => {
                let o: &TextureDesc = &textures[of as usize];
                (o.width, o.height, Vec::new(), Some(of))
            }
            None => {
                holder[source] = Some(i as u32);
                let (w, h, rgba) = images[source]
                    .take()
                    .expect("kept textures name decoded images");
                (w, h, rgba, None)
            }
        };
        textures.push(TextureDesc {
            name,
            width,
            height,
            rgba,
            wrap_s,
            wrap_t,
            filter,
            texels_of,
        });
    }
    Ok((textures, map))
}

fn decode_image(bytes: &[u8]) -> Result<(u32, u32, Vec<u8>), String> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| e.to_string())?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    reader.limits(limits);
    let img = reader.decode().map_err(|e| format!("cannot decode: {e}"))?;
    let rgba = img.to_rgba8();
    let (w, h) = rgba.dimensions();
    if w == 0 || h == 0 {
        return Err("image is empty (0 pixels)".into());
    }
    Ok((w, h, rgba.into_raw()))
}

fn transform_from_json(v: Option<&serde_json::Value>) -> (Option<UvTransform>, Option<u32>) {
    let Some(v) = v else { return (None, None) };
    let pair = |key: &str, default: [f32; 2]| -> Vec2 {
        v.get(key)
            .and_then(|a| a.as_array())
            .filter(|a| a.len() == 2)
            .map(|a| {
                Vec2::new(
                    a[0].as_f64().unwrap_or(default[0] as f64) as f32,
                    a[1].as_f64().unwrap_or(default[1] as f64) as f32,
                )
            })
            .unwrap_or(Vec2::from(default))
    };
    let rotation = v.get("rotation").and_then(|r| r.as_f64()).unwrap_or(0.0) as f32;
    let t = UvTransform {
        offset: pair("offset", [0.0, 0.0]),
        rotation,
        scale: pair("scale", [1.0, 1.0]),
    };
    let tex_coord = v.get("texCoord").and_then(|c| c.as_u64()).map(|c| c as u32);
    let valid = t.offset.is_finite() && t.scale.is_finite() && t.rotation.is_finite();
    (valid.then_some(t), tex_coord)
}

fn tex_ref(info: Option<gltf::texture::Info>, map: &[Option<u32>]) -> Option<TexRef> {
    let info = info?;
    let texture = (*map.get(info.texture().index())?)?;
    let mut tex_coord = info.tex_coord();
    let transform = info.texture_transform().map(|t| {
        if let Some(c) = t.tex_coord() {
            tex_coord = c;
        }
        UvTransform {
            offset: Vec2::from(t.offset()),
            rotation: t.rotation(),
            scale: Vec2::from(t.scale()),
        }
    });
    let transform =
        transform.filter(|t| t.offset.is_finite() && t.scale.is_finite() && t.rotation.is_finite());
    Some(TexRef {
        texture,
        tex_coord,
        transform,
    })
}

fn finite_or(v: f32, default: f32) -> f32 {
    if v.is_finite() { v } else { default }
}

fn convert_material(ctx: &mut Ctx, m: &gltf::Material, map: &[Option<u32>]) -> Material {
    let pbr = m.pbr_metallic_roughness();
    let name = m
        .name()
        .map(str::to_string)
        .unwrap_or_else(|| format!("material {}", m.index().unwrap_or(0)));
    let mut out = Material {
        name: name.clone(),
        base_color: Vec4::from(pbr.base_color_factor()),
        base_color_tex: tex_ref(pbr.base_color_texture(), map),
        metallic: finite_or(pbr.metallic_factor(), 1.0).clamp(0.0, 1.0),
        roughness: finite_or(pbr.roughness_factor(), 1.0).clamp(0.0, 1.0),
        metallic_roughness_tex: tex_ref(pbr.metallic_roughness_texture(), map),
        emissive: Vec3::from(m.emissive_factor())
            * finite_or(m.emissive_strength().unwrap_or(1.0), 1.0),
        emissive_tex: tex_ref(m.emissive_texture(), map),
        double_sided: m.double_sided(),
        alpha_cutoff: finite_or(m.alpha_cutoff().unwrap_or(0.5), 0.5),
        alpha_mode: match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
            gltf::material::AlphaMode::Mask => AlphaMode::Mask,
            gltf::material::AlphaMode::Blend => AlphaMode::Blend,
        },
        ..Material::default()
    };
    if !out.base_color.is_finite() {
        ctx.warnings.push(format!(
            "material {name:?}: non-finite base colour, using white"
        ));
        out.base_color = Vec4::ONE;
    }
    if !out.emissive.is_finite() || out.emissive.min_element() < 0.0 {
        ctx.warnings
            .push(format!("material {name:?}: invalid emission, ignored"));
        out.emissive = Vec3::ZERO;
    }
    if let Some(n) = m.normal_texture()
        && let Some(Some(texture)) = map.get(n.texture().index())
    {
        let (transform, coord) = transform_from_json(n.extension_value("KHR_texture_transform"));
        out.normal_tex = Some(TexRef {
            texture: *texture,
            tex_coord: coord.unwrap_or(n.tex_coord()),
            transform,
        });
        out.normal_scale = finite_or(n.scale(), 1.0);
    }
    if let Some(ior) = m.ior() {
        // IOR 0 means "no refraction, no Fresnel" in the spec's limit; keep it physical.
        out.ior = if ior.is_finite() && ior >= 1.0 {
            ior
        } else {
            1.5
        };
        if ior.is_finite() && ior < 1.0 && ior != 0.0 {
            ctx.warnings
                .push(format!("material {name:?}: IOR {ior} below 1, using 1.5"));
        }
    }
    if let Some(s) = m.specular() {
        out.specular = finite_or(s.specular_factor(), 1.0).clamp(0.0, 1.0);
        out.specular_tex = tex_ref(s.specular_texture(), map);
        out.specular_color = Vec3::from(s.specular_color_factor()).max(Vec3::ZERO);
        if !out.specular_color.is_finite() {
            out.specular_color = Vec3::ONE;
        }
        out.specular_color_tex = tex_ref(s.specular_color_texture(), map);
    }
    if let Some(t) = m.transmission() {
        out.transmission = finite_or(t.transmission_factor(), 0.0).clamp(0.0, 1.0);
        out.transmission_tex = tex_ref(t.transmission_texture(), map);
    }
    if let Some(v) = m.volume() {
        out.thickness = finite_or(v.thickness_factor(), 0.0).max(0.0);
        out.attenuation_distance = v.attenuation_distance();
        if !(out.attenuation_distance > 0.0) {
            out.attenuation_distance = f32::INFINITY;
        }
        out.attenuation_color = Vec3::from(v.attenuation_color()).clamp(Vec3::ZERO, Vec3::ONE);
        if v.thickness_texture().is_some() {
            ctx.unsupported
                .insert("volume thickness textures (the factor is used)".into());
        }
    }
    if m.occlusion_texture().is_some() {
        // A path tracer computes occlusion itself; the baked map would count it twice.
    }
    // Meshes keep texture coordinate sets 0 and 1: a texture naming another read (0, 0) at
    // its surfaces but set 0 where an emissive one lit the scene, and said nothing.
    for (what, t) in [
        ("base colour", &mut out.base_color_tex),
        ("metallic-roughness", &mut out.metallic_roughness_tex),
        ("normal", &mut out.normal_tex),
        ("emissive", &mut out.emissive_tex),
        ("specular", &mut out.specular_tex),
        ("specular colour", &mut out.specular_color_tex),
        ("transmission", &mut out.transmission_tex),
    ] {
        if let Some(t) = t
            && t.tex_coord > 1
        {
            ctx.warnings.push(format!(
                "material {name:?}: the {what} texture reads texture coordinate set {} \
                 (sets 0 and 1 are supported): using set 0",
                t.tex_coord
            ));
            t.tex_coord = 0;
        }
    }
    out
}

fn convert_camera(
    ctx: &mut Ctx,
    camera: &gltf::Camera,
    node: &gltf::Node,
) -> Option<(String, Projection, Option<f32>)> {
    let name = camera
        .name()
        .or(node.name())
        .map(str::to_string)
        .unwrap_or_else(|| format!("camera {}", camera.index()));
    let mut aspect = None;
    let projection = match camera.projection() {
        gltf::camera::Projection::Perspective(p) => {
            let yfov = p.yfov();
            if !(yfov.is_finite() && yfov > 1e-6 && yfov < std::f32::consts::PI - 1e-4) {
                ctx.warnings.push(format!(
                    "camera {name:?}: field of view {yfov} rad is not usable, camera skipped"
                ));
                return None;
            }
            aspect = p
                .aspect_ratio()
                .filter(|a| a.is_finite() && *a > 1e-3 && *a < 1e3);
            Projection::Perspective { yfov }
        }
        gltf::camera::Projection::Orthographic(o) => {
            let ymag = o.ymag().abs();
            if !(ymag.is_finite() && ymag > 0.0) {
                ctx.warnings.push(format!(
                    "camera {name:?}: ymag {} is not usable, camera skipped",
                    o.ymag()
                ));
                return None;
            }
            let xmag = o.xmag().abs();
            if xmag.is_finite() && xmag > 0.0 {
                aspect = Some(xmag / ymag);
            }
            Projection::Orthographic { ymag }
        }
    };
    Some((name, projection, aspect))
}

fn convert_light(
    ctx: &mut Ctx,
    world: DMat4,
    l: &gltf::khr_lights_punctual::Light,
    shift: DVec3,
) -> Option<Light> {
    use gltf::khr_lights_punctual::Kind;
    let color = Vec3::from(l.color()) * l.intensity();
    if !color.is_finite() || color.min_element() < 0.0 {
        ctx.warnings.push(format!(
            "light {}: invalid colour or intensity, skipped",
            l.index()
        ));
        return None;
    }
    let position = (world.transform_point3(DVec3::ZERO) - shift).as_vec3();
    let direction = world
        .transform_vector3(DVec3::NEG_Z)
        .normalize_or_zero()
        .as_vec3();
    if l.range().is_some() {
        ctx.unsupported
            .insert("light range (lights fall off physically, without a cut-off)".into());
    }
    Some(match l.kind() {
        Kind::Point => Light::Point {
            position,
            intensity: color,
        },
        Kind::Directional => {
            if direction == Vec3::ZERO {
                return None;
            }
            Light::Directional {
                direction,
                irradiance: color,
            }
        }
        Kind::Spot {
            inner_cone_angle,
            outer_cone_angle,
        } => {
            if direction == Vec3::ZERO {
                return None;
            }
            let outer = outer_cone_angle.clamp(0.0, std::f32::consts::FRAC_PI_2);
            let inner = inner_cone_angle.clamp(0.0, outer);
            Light::Spot {
                position,
                direction,
                intensity: color,
                cos_inner: inner.cos(),
                cos_outer: outer.cos(),
            }
        }
    })
}

/// Per-instance local transforms of EXT_mesh_gpu_instancing, if the node has them.
fn instance_transforms(
    ctx: &mut Ctx,
    node: &gltf::Node,
    doc: &gltf::Document,
    buffers: &[Vec<u8>],
) -> Result<Option<Vec<DMat4>>, LoadError> {
    let Some(ext) = node
        .extensions()
        .and_then(|e| e.get("EXT_mesh_gpu_instancing"))
    else {
        return Ok(None);
    };
    let Some(attrs) = ext.get("attributes").and_then(|a| a.as_object()) else {
        return Ok(None);
    };
    let read =
        |ctx: &mut Ctx, name: &str, dims: Dimensions| -> Result<Option<Vec<Vec4>>, LoadError> {
            let Some(index) = attrs.get(name).and_then(|v| v.as_u64()) else {
                return Ok(None);
            };
            let acc = doc.accessors().nth(index as usize).ok_or_else(|| {
                ctx.invalid(format!(
                    "node {}: instancing {name} names accessor {index}, which does not exist",
                    node.index()
                ))
            })?;
            if acc.dimensions() != dims || acc.data_type() != DataType::F32 {
                ctx.warnings.push(format!(
                    "node {}: instancing {name} is not float {dims:?}, ignored",
                    node.index()
                ));
                return Ok(None);
            }
            check_accessor(ctx, &acc, buffers)?;
            let get = |b: gltf::Buffer| buffers.get(b.index()).map(|v| v.as_slice());
            let vals: Vec<Vec4> = match dims {
                Dimensions::Vec3 => gltf::accessor::Iter::<[f32; 3]>::new(acc, get)
                    .map(|it| it.map(|v| Vec3::from(v).extend(0.0)).collect())
                    .unwrap_or_default(),
                _ => gltf::accessor::Iter::<[f32; 4]>::new(acc, get)
                    .map(|it| it.map(Vec4::from).collect())
                    .unwrap_or_default(),
            };
            Ok(Some(vals))
        };
    let t = read(ctx, "TRANSLATION", Dimensions::Vec3)?;
    let r = read(ctx, "ROTATION", Dimensions::Vec4)?;
    let s = read(ctx, "SCALE", Dimensions::Vec3)?;
    let count = [&t, &r, &s]
        .iter()
        .filter_map(|v| v.as_ref().map(Vec::len))
        .max()
        .unwrap_or(0);
    let mut out = Vec::with_capacity(count);
    for i in 0..count {
        let tr = t
            .as_ref()
            .and_then(|v| v.get(i))
            .map_or(DVec3::ZERO, |v| v.truncate().as_dvec3());
        let rot = r
            .as_ref()
            .and_then(|v| v.get(i))
            .map_or(glam::DQuat::IDENTITY, |v| {
                glam::DQuat::from_xyzw(v.x as f64, v.y as f64, v.z as f64, v.w as f64).normalize()
            });
        let sc = s
            .as_ref()
            .and_then(|v| v.get(i))
            .map_or(DVec3::ONE, |v| v.truncate().as_dvec3());
        let m = DMat4::from_scale_rotation_translation(sc, rot, tr);
        if m.is_finite() {
            out.push(m);
        }
    }
    Ok(Some(out))
}

/// Checks that an accessor's data lies inside its buffer view and buffer, with strides and
/// counts that cannot overflow, so the `gltf` crate's reader can be trusted with it.
fn check_accessor(ctx: &Ctx, acc: &gltf::Accessor, buffers: &[Vec<u8>]) -> Result<(), LoadError> {
    let elem = acc.size();
    let count = acc.count();
    let what = || format!("accessor {}", acc.index());
    if count == 0 {
        return Err(ctx.invalid(format!("{} has count 0", what())));
    }
    if acc.view().is_none() {
        // Without a bufferView every element is zero but the few a sparse part lists, so
        // `count` is bounded by nothing in the file, and reading the accessor allocates for
        // all of them. All such accessors together may stand for no more data than the file's
        // buffers hold (as ones with a bufferView cannot), or than a floor that small files
        // stay under: a bound per accessor let a file of many small accessors ask for 16 MiB
        // each. An accessor read again (a mesh under many nodes) counts once, as one with
        // a bufferView does.
        let held: usize = buffers.iter().map(Vec::len).sum();
        let limit = held.max(MAX_UNBACKED_BYTES);
        let mut unbacked = ctx.unbacked.borrow_mut();
        let (admitted, total) = &mut *unbacked;
        if !admitted.contains(&acc.index()) {
            let others = *total;
            match count
                .checked_mul(elem)
                .and_then(|bytes| bytes.checked_add(others))
            {
                Some(sum) if sum <= limit => {
                    admitted.insert(acc.index());
                    *total = sum;
                }
                _ => {
                    let besides = if others > 0 {
                        format!(" (besides the {others} bytes of the file's other such accessors)")
                    } else {
                        String::new()
                    };
                    return Err(ctx.invalid(format!(
                        "{} has no bufferView and count {count} ({elem} bytes each){besides}: \
                         more data than the file's buffers hold ({held} bytes) or {} MiB",
                        what(),
                        MAX_UNBACKED_BYTES >> 20
                    )));
                }
            }
        }
    }
    let check_range = |view: &gltf::buffer::View,
                       offset: usize,
                       stride: usize,
                       n: usize,
                       elem: usize|
     -> Result<(), LoadError> {
        let bytes = view_bytes(ctx, view, buffers)?;
        if stride < elem {
            return Err(ctx.invalid(format!(
                "{}: byteStride {stride} is smaller than its element ({elem} bytes)",
                what()
            )));
        }
        let end = stride
            .checked_mul(n - 1)
            .and_then(|v| v.checked_add(elem))
            .and_then(|v| v.checked_add(offset));
        match end {
            Some(end) if end <= bytes.len() => Ok(()),
            _ => Err(ctx.invalid(format!(
                "{} needs bytes {offset}..{} of bufferView {}, which has {} (buffer shorter than its accessor)",
                what(),
                end.map_or("overflow".to_string(), |e| e.to_string()),
                view.index(),
                bytes.len()
            ))),
        }
    };
    if let Some(view) = acc.view() {
        check_range(
            &view,
            acc.offset(),
            view.stride().unwrap_or(elem),
            count,
            elem,
        )?;
    }
    if let Some(sparse) = acc.sparse() {
        let n = sparse.count();
        if n == 0 || n > count {
            return Err(ctx.invalid(format!("{}: sparse count {n} out of range", what())));
        }
        let idx = sparse.indices();
        let isz = idx.index_type().size();
        check_range(
            &idx.view(),
            idx.offset(),
            idx.view().stride().unwrap_or(isz),
            n,
            isz,
        )?;
        let vals = sparse.values();
        check_range(
            &vals.view(),
            vals.offset(),
            vals.view().stride().unwrap_or(elem),
            n,
            elem,
        )?;
        // Sparse indices must be in range and strictly increasing (the spec demands it;
        // the reader relies on it).
        let get = |b: gltf::Buffer| buffers.get(b.index()).map(|v| v.as_slice());
        let view_data = get(idx.view().buffer()).unwrap_or(&[]);
        let base = idx.view().offset() + idx.offset();
        let stride = idx.view().stride().unwrap_or(isz);
        let mut last: Option<u64> = None;
        for i in 0..n {
            let at = base + i * stride;
            let v = u64::from(le_index(&view_data[at..at + isz]));
            if v >= count as u64 || last.is_some_and(|l| v <= l) {
                return Err(ctx.invalid(format!(
                    "{}: sparse index {v} out of order or range",
                    what()
                )));
            }
            last = Some(v);
        }
    }
    Ok(())
}

/// A primitive's vertex data in its mesh's space, compacted to the vertices its triangles use.
struct PrimitiveData {
    positions: Vec<DVec3>,
    normals: Vec<Vec3>,
    uv0: Vec<Vec2>,
    uv1: Vec<Vec2>,
    tangents: Vec<Vec4>,
    colors: Vec<Vec4>,
    triangles: Vec<[u32; 3]>,
}

struct PlacedPrimitive {
    data: std::rc::Rc<PrimitiveData>,
    world: DMat4,
    material: u32,
}

/// The bytes of a plain accessor whose elements lie packed one after another (no byte
/// stride other than the element's, no sparse substitution), `elem` bytes each; `None` for
/// any other accessor, which the gltf crate's reader then reads element by element.
fn packed_bytes<'b>(acc: &gltf::Accessor, buffers: &'b [Vec<u8>], elem: usize) -> Option<&'b [u8]> {
    if acc.sparse().is_some() || acc.size() != elem {
        return None;
    }
    let view = acc.view()?;
    if view.stride().is_some_and(|s| s != elem) {
        return None;
    }
    let len = acc.count().checked_mul(elem)?;
    if acc.offset().checked_add(len)? > view.length() {
        return None;
    }
    let start = view.offset().checked_add(acc.offset())?;
    buffers
        .get(view.buffer().index())?
        .get(start..start.checked_add(len)?)
}

/// A packed accessor of `N` floats an element, read in one pass over its bytes: the reader's
/// iterator, which checks and converts each element on its own, was most of the time taken
/// to read a large mesh. `None` where the accessor is not that (another type, strided,
/// sparse): the caller reads it with the reader.
fn packed_floats<const N: usize>(
    acc: &gltf::Accessor,
    buffers: &[Vec<u8>],
) -> Option<Vec<[f32; N]>> {
    if acc.data_type() != DataType::F32 || acc.dimensions().multiplicity() != N {
        return None;
    }
    let bytes = packed_bytes(acc, buffers, 4 * N)?;
    Some(
        bytes
            .chunks_exact(4 * N)
            .map(|e| {
                std::array::from_fn(|i| {
                    f32::from_le_bytes([e[4 * i], e[4 * i + 1], e[4 * i + 2], e[4 * i + 3]])
                })
            })
            .collect(),
    )
}

/// Attribute `semantic` of `prim` where `wanted` (else none): straight from its bytes where it
/// is packed floats ([`packed_floats`]), else by `read`, the gltf crate's reader, which
/// converts whatever else it may be.
fn read_attribute<const N: usize, T: From<[f32; N]>>(
    prim: &gltf::Primitive,
    buffers: &[Vec<u8>],
    wanted: bool,
    semantic: gltf::Semantic,
    read: impl FnOnce() -> Option<Vec<T>>,
) -> Vec<T> {
    if !wanted {
        return Vec::new();
    }
    match prim
        .get(&semantic)
        .and_then(|a| packed_floats::<N>(&a, buffers))
    {
        Some(values) => values.into_iter().map(T::from).collect(),
        None => read().unwrap_or_default(),
    }
}

/// A packed accessor of unsigned integer indices, as [`packed_floats`] reads floats.
fn packed_indices(acc: &gltf::Accessor, buffers: &[Vec<u8>]) -> Option<Vec<u32>> {
    if acc.dimensions() != Dimensions::Scalar {
        return None;
    }
    let width = match acc.data_type() {
        DataType::U8 => 1,
        DataType::U16 => 2,
        DataType::U32 => 4,
        _ => return None,
    };
    let bytes = packed_bytes(acc, buffers, width)?;
    // One loop per width, so that each reads its width without asking.
    Some(match width {
        1 => bytes.chunks_exact(1).map(le_index).collect(),
        2 => bytes.chunks_exact(2).map(le_index).collect(),
        _ => bytes.chunks_exact(4).map(le_index).collect(),
    })
}

/// An unsigned index of glTF's 1, 2 or 4 bytes, little-endian (0 for any other length,
/// which callers never pass).
#[inline(always)]
fn le_index(bytes: &[u8]) -> u32 {
    match *bytes {
        [a] => u32::from(a),
        [a, b] => u32::from(u16::from_le_bytes([a, b])),
        [a, b, c, d] => u32::from_le_bytes([a, b, c, d]),
        _ => 0,
    }
}

fn read_primitive(
    ctx: &mut Ctx,
    prim: &gltf::Primitive,
    mesh: &gltf::Mesh,
    buffers: &[Vec<u8>],
    material: &Material,
) -> Result<Option<PrimitiveData>, LoadError> {
    let mesh_name = match mesh.name() {
        Some(n) => format!("mesh {} ({n:?})", mesh.index()),
        None => format!("mesh {}", mesh.index()),
    };
    match prim.mode() {
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan => {}
        other => {
            ctx.unsupported
                .insert(format!("{other:?} primitives (not surfaces; skipped)"));
            return Ok(None);
        }
    }
    // Type and range checks for every attribute we read.
    let expect = |ctx: &Ctx,
                  acc: &gltf::Accessor,
                  dims: &[Dimensions],
                  types: &[DataType]|
     -> Result<bool, LoadError> {
        check_accessor(ctx, acc, buffers)?;
        Ok(dims.contains(&acc.dimensions()) && types.contains(&acc.data_type()))
    };
    let Some(pos_acc) = prim.get(&gltf::Semantic::Positions) else {
        ctx.warnings
            .push(format!("{mesh_name}: a primitive has no POSITION, skipped"));
        return Ok(None);
    };
    if !expect(ctx, &pos_acc, &[Dimensions::Vec3], &[DataType::F32])? {
        return Err(ctx.invalid(format!("{mesh_name}: POSITION must be float VEC3")));
    }
    let n = pos_acc.count();
    let mut ok_attr =
        |sem: gltf::Semantic, dims: &[Dimensions], types: &[DataType]| -> Result<bool, LoadError> {
            match prim.get(&sem) {
                None => Ok(false),
                Some(acc) => {
                    let good = expect(ctx, &acc, dims, types)?;
                    if !good || acc.count() != n {
                        ctx.warnings.push(format!(
                            "{mesh_name}: attribute {sem:?} has the wrong type or count, ignored"
                        ));
                        return Ok(false);
                    }
                    Ok(true)
                }
            }
        };
    let uv_types = [DataType::F32, DataType::U8, DataType::U16];
    let has_normals = ok_attr(
        gltf::Semantic::Normals,
        &[Dimensions::Vec3],
        &[DataType::F32],
    )?;
    let has_tangents = ok_attr(
        gltf::Semantic::Tangents,
        &[Dimensions::Vec4],
        &[DataType::F32],
    )?;
    let has_uv0 = ok_attr(gltf::Semantic::TexCoords(0), &[Dimensions::Vec2], &uv_types)?;
    let has_uv1 = ok_attr(gltf::Semantic::TexCoords(1), &[Dimensions::Vec2], &uv_types)?;
    let has_colors = ok_attr(
        gltf::Semantic::Colors(0),
        &[Dimensions::Vec3, Dimensions::Vec4],
        &uv_types,
    )?;
    if let Some(idx) = prim.indices() {
        check_accessor(ctx, &idx, buffers)?;
        if idx.dimensions() != Dimensions::Scalar
            || !matches!(
                idx.data_type(),
                DataType::U8 | DataType::U16 | DataType::U32
            )
        {
            return Err(ctx.invalid(format!(
                "{mesh_name}: indices must be unsigned integer scalars"
            )));
        }
    }

    let reader = prim.reader(|b| buffers.get(b.index()).map(|v| v.as_slice()));
    let positions: Vec<DVec3> = match packed_floats::<3>(&pos_acc, buffers) {
        Some(p) => p.into_iter().map(|p| Vec3::from(p).as_dvec3()).collect(),
        None => reader
            .read_positions()
            .ok_or_else(|| ctx.invalid(format!("{mesh_name}: POSITION data unreadable")))?
            .map(|p| Vec3::from(p).as_dvec3())
            .collect(),
    };
    let indices: Vec<u32> = match prim.indices().and_then(|a| packed_indices(&a, buffers)) {
        Some(i) => i,
        None => match reader.read_indices() {
            Some(i) => i.into_u32().collect(),
            None => (0..positions.len() as u32).collect(),
        },
    };
    if let Some(&bad) = indices.iter().find(|&&i| i as usize >= positions.len()) {
        return Err(ctx.invalid(format!(
            "{mesh_name}: index {bad} out of range (the primitive has {} vertices)",
            positions.len()
        )));
    }
    let triangles: Vec<[u32; 3]> = match prim.mode() {
        Mode::Triangles => indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
        Mode::TriangleStrip => (0..indices.len().saturating_sub(2))
            .map(|i| {
                if i % 2 == 0 {
                    [indices[i], indices[i + 1], indices[i + 2]]
                } else {
                    [indices[i + 1], indices[i], indices[i + 2]]
                }
            })
            .collect(),
        Mode::TriangleFan => (1..indices.len().saturating_sub(1))
            .map(|i| [indices[i], indices[i + 1], indices[0]])
            .collect(),
        _ => Vec::new(),
    };

    let normals: Vec<Vec3> =
        read_attribute::<3, _>(prim, buffers, has_normals, gltf::Semantic::Normals, || {
            reader.read_normals().map(|it| it.map(Vec3::from).collect())
        });
    let tangents: Vec<Vec4> = read_attribute::<4, _>(
        prim,
        buffers,
        has_tangents,
        gltf::Semantic::Tangents,
        || {
            reader
                .read_tangents()
                .map(|it| it.map(Vec4::from).collect())
        },
    );
    let uv = |set: u32, has: bool| -> Vec<Vec2> {
        read_attribute::<2, _>(prim, buffers, has, gltf::Semantic::TexCoords(set), || {
            reader
                .read_tex_coords(set)
                .map(|it| it.into_f32().map(Vec2::from).collect())
        })
    };
    let (uv0, uv1) = (uv(0, has_uv0), uv(1, has_uv1));
    // Colors of three components get an alpha of one from the reader: only four are packed.
    let colors: Vec<Vec4> =
        read_attribute::<4, _>(prim, buffers, has_colors, gltf::Semantic::Colors(0), || {
            reader
                .read_colors(0)
                .map(|it| it.into_rgba_f32().map(Vec4::from).collect())
        });

    // Compact to the vertices used (several meshes may share one large accessor).
    // A table over the accessor's vertices (indices were checked against its length above),
    // holding each used vertex's new index plus one: zeroed memory the allocator maps
    // lazily, so a primitive that uses a few vertices of a large shared accessor touches a
    // few pages of it. A hash map here was a third of reading a million-triangle mesh.
    let mut remap = vec![0u32; positions.len()];
    let mut used: Vec<u32> = Vec::new();
    let triangles: Vec<[u32; 3]> = triangles
        .iter()
        .map(|t| {
            t.map(|v| {
                let slot = &mut remap[v as usize];
                if *slot == 0 {
                    used.push(v);
                    *slot = used.len() as u32;
                }
                *slot - 1
            })
        })
        .collect();
    fn pick<T: Copy>(src: &[T], used: &[u32], n: usize) -> Vec<T> {
        if src.len() == n {
            used.iter().map(|&i| src[i as usize]).collect()
        } else {
            Vec::new()
        }
    }
    let mut data = PrimitiveData {
        positions: used.iter().map(|&i| positions[i as usize]).collect(),
        normals: pick(&normals, &used, n),
        uv0: pick(&uv0, &used, n),
        uv1: pick(&uv1, &used, n),
        tangents: pick(&tangents, &used, n),
        colors: pick(&colors, &used, n),
        triangles,
    };
    if material.normal_tex.is_some() && data.tangents.is_empty() && !data.normals.is_empty() {
        let set = material.normal_tex.map_or(0, |t| t.tex_coord);
        let uvs = if set == 1 { &data.uv1 } else { &data.uv0 };
        if !uvs.is_empty() {
            generate_tangents(&mut data, set);
        }
    }
    Ok(Some(data))
}

/// MikkTSpace tangents (the convention glTF normal maps are baked with), computed per
/// triangle corner; corners of one vertex that disagree are split into separate vertices.
fn generate_tangents(d: &mut PrimitiveData, set: u32) {
    struct Geo<'a> {
        d: &'a PrimitiveData,
        uv: &'a [Vec2],
        out: Vec<[f32; 4]>,
    }
    impl bevy_mikktspace::Geometry for Geo<'_> {
        fn num_faces(&self) -> usize {
            self.d.triangles.len()
        }
        fn num_vertices_of_face(&self, _face: usize) -> usize {
            3
        }
        fn position(&self, face: usize, vert: usize) -> [f32; 3] {
            self.d.positions[self.d.triangles[face][vert] as usize]
                .as_vec3()
                .to_array()
        }
        fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
            self.d.normals[self.d.triangles[face][vert] as usize].to_array()
        }
        fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
            // glTF's v runs down the image; MikkTSpace (and the tools that bake normal maps)
            // work with v up, which is what makes the bitangent point "up" in the texture.
            let uv = self.uv[self.d.triangles[face][vert] as usize];
            [uv.x, 1.0 - uv.y]
        }
        fn set_tangent_encoded(&mut self, tangent: [f32; 4], face: usize, vert: usize) {
            self.out[face * 3 + vert] = tangent;
        }
    }
    let uv = if set == 1 {
        d.uv1.clone()
    } else {
        d.uv0.clone()
    };
    let mut geo = Geo {
        d,
        uv: &uv,
        out: vec![[1.0, 0.0, 0.0, 1.0]; d.triangles.len() * 3],
    };
    if !bevy_mikktspace::generate_tangents(&mut geo) {
        return;
    }
    let corner_tangents = geo.out;
    // Split vertices whose corners got different tangents.
    let mut key_to_vertex: HashMap<(u32, [u32; 4]), u32> = HashMap::new();
    let mut new = PrimitiveData {
        positions: Vec::new(),
        normals: Vec::new(),
        uv0: Vec::new(),
        uv1: Vec::new(),
        tangents: Vec::new(),
        colors: Vec::new(),
        triangles: Vec::with_capacity(d.triangles.len()),
    };
    for (f, tri) in d.triangles.iter().enumerate() {
        let mut out = [0u32; 3];
        for k in 0..3 {
            let v = tri[k];
            let t = corner_tangents[f * 3 + k];
            let key = (v, t.map(f32::to_bits));
            out[k] = *key_to_vertex.entry(key).or_insert_with(|| {
                let i = v as usize;
                new.positions.push(d.positions[i]);
                new.normals.push(d.normals[i]);
                if !d.uv0.is_empty() {
                    new.uv0.push(d.uv0[i]);
                }
                if !d.uv1.is_empty() {
                    new.uv1.push(d.uv1[i]);
                }
                if !d.colors.is_empty() {
                    new.colors.push(d.colors[i]);
                }
                new.tangents.push(Vec4::from(t));
                (new.positions.len() - 1) as u32
            });
        }
        new.triangles.push(out);
    }
    *d = new;
}

/// Transforms a primitive into centred world space; returns it and how many triangles were
/// dropped as degenerate.
/// How far to move the scene along one axis, given its extent `lo..hi` there: towards its
/// centre, when the scene lies far enough from the origin for f32 to lose precision there
/// (entirely on one side, at least its own width away), else not at all. The shift is a
/// multiple of the f32 spacing at the largest coordinate, which makes moving a point of the
/// scene given in f32 exact (each point ends up no farther from the origin than it was): a
/// mesh placed without rotation or scale keeps every bit of its shape, and a ray made from
/// the file's own numbers keeps every bit of its position relative to it.
fn exact_shift(lo: f64, hi: f64) -> f64 {
    let far = (lo > 0.0 && hi <= 2.0 * lo) || (hi < 0.0 && lo >= 2.0 * hi);
    if !far {
        return 0.0;
    }
    let m = lo.abs().max(hi.abs());
    let mut m32 = m as f32;
    if (m32 as f64) < m {
        m32 = m32.next_up();
    }
    if !m32.is_finite() {
        return (lo + hi) * 0.5;
    }
    let spacing = (m32.next_up() - m32) as f64;
    ((lo + hi) * 0.5 / spacing).round() * spacing
}

fn place_primitive(p: &PlacedPrimitive, shift: DVec3) -> (MeshData, usize) {
    let d = &p.data;
    let linear = DMat3::from_mat4(p.world);
    let det = linear.determinant();
    let normal_matrix = if det.abs() > 1e-300 {
        linear.inverse().transpose()
    } else {
        linear
    };
    let positions: Vec<Vec3> = d
        .positions
        .iter()
        .map(|v| (p.world.transform_point3(*v) - shift).as_vec3())
        .collect();
    let normals: Vec<Vec3> = d
        .normals
        .iter()
        .map(|n| (normal_matrix * n.as_dvec3()).normalize_or_zero().as_vec3())
        .collect();
    let tangents: Vec<Vec4> = d
        .tangents
        .iter()
        .map(|t| {
            let xyz = (linear * t.truncate().as_dvec3())
                .normalize_or_zero()
                .as_vec3();
            let w = if t.w < 0.0 { -1.0 } else { 1.0 } * if det < 0.0 { -1.0 } else { 1.0 };
            xyz.extend(w)
        })
        .collect();
    let mut skipped = 0;
    let triangles: Vec<[u32; 3]> = d
        .triangles
        .iter()
        .filter_map(|t| {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            let area = (b - a).cross(c - a).length();
            if !(area > 0.0) || !area.is_finite() {
                skipped += 1;
                return None;
            }
            // A mirroring transform turns the winding around; keep the front face in front.
            Some(if det < 0.0 { [t[0], t[2], t[1]] } else { *t })
        })
        .collect();
    let mut mesh = MeshData {
        positions,
        normals,
        uv0: d.uv0.clone(),
        uv1: d.uv1.clone(),
        tangents,
        colors: d.colors.clone(),
        triangles,
        material: p.material,
    };
    // Folded without stopping early, which lets the check of a million vertices run in
    // vector registers (`all` cost 38 M instructions on the spheres' 1.04 M triangles).
    let all_finite = mesh.positions.iter().fold(true, |ok, v| {
        ok & v.x.is_finite() & v.y.is_finite() & v.z.is_finite()
    });
    if !all_finite {
        // Every triangle using a vertex at NaN or infinity was skipped above; the vertex
        // itself goes too, as a description with one is refused where it is checked (a
        // cluster's fork node). A mesh whose positions are all finite is left as it is.
        drop_unused_vertices(&mut mesh);
    }
    (mesh, skipped)
}

/// Removes the vertices no triangle of `mesh` uses, keeping the others' order.
fn drop_unused_vertices(mesh: &mut MeshData) {
    let n = mesh.positions.len();
    let mut used = vec![false; n];
    for &v in mesh.triangles.iter().flatten() {
        used[v as usize] = true;
    }
    let mut new_index = vec![u32::MAX; n];
    let mut kept = 0u32;
    for (slot, &u) in new_index.iter_mut().zip(&used) {
        if u {
            *slot = kept;
            kept += 1;
        }
    }
    fn keep<T: Copy>(values: &mut Vec<T>, used: &[bool]) {
        if values.len() == used.len() {
            let mut i = 0;
            values.retain(|_| {
                i += 1;
                used[i - 1]
            });
        }
    }
    keep(&mut mesh.positions, &used);
    keep(&mut mesh.normals, &used);
    keep(&mut mesh.uv0, &used);
    keep(&mut mesh.uv1, &used);
    keep(&mut mesh.tangents, &used);
    keep(&mut mesh.colors, &used);
    for t in &mut mesh.triangles {
        *t = t.map(|v| new_index[v as usize]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn data_uris_decode() {
        assert_eq!(
            decode_data_uri("data:application/octet-stream;base64,AAEC").unwrap(),
            vec![0, 1, 2]
        );
        assert!(decode_data_uri("data:application/octet-stream;base64,!!!").is_none());
    }

    /// Bytes as a glTF buffer's embedded URI.
    fn data_uri(bytes: &[u8]) -> String {
        use base64::Engine;
        format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(bytes)
        )
    }

    /// Two primitives indexing one shared position accessor: each keeps exactly the vertices
    /// its triangles use, numbered in order of first use, and its triangles name the same
    /// points as in the file.
    #[test]
    fn primitives_sharing_an_accessor_keep_only_their_vertices() {
        let points: [[f32; 3]; 6] = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [2.0, 0.0, 1.0],
            [0.0, 2.0, 1.0],
            [3.0, 3.0, 2.0],
        ];
        let (first, second): ([u32; 6], [u32; 3]) = ([4, 2, 5, 5, 2, 1], [1, 4, 0]);
        let mut bin: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        bin.extend(first.iter().chain(&second).flat_map(|i| i.to_le_bytes()));
        let uri = data_uri(&bin);
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}},
                                      {{"attributes":{{"POSITION":0}},"indices":2}}]}}],
            "buffers":[{{"byteLength":{len},"uri":"{uri}"}}],
            "bufferViews":[{{"buffer":0,"byteLength":72}},
                           {{"buffer":0,"byteOffset":72,"byteLength":24}},
                           {{"buffer":0,"byteOffset":96,"byteLength":12}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":6,"type":"VEC3",
                           "min":[0,0,0],"max":[3,3,2]}},
                         {{"bufferView":1,"componentType":5125,"count":6,"type":"SCALAR"}},
                         {{"bufferView":2,"componentType":5125,"count":3,"type":"SCALAR"}}]}}"#,
            len = bin.len()
        );
        let loaded = load_gltf_bytes(Path::new("shared.gltf"), json.as_bytes()).unwrap();
        let meshes = &loaded.desc.meshes;
        assert_eq!(meshes.len(), 2);
        let shift = loaded.origin_shift;
        for (mesh, indices, used) in [
            (&meshes[0], &first[..], &[4u32, 2, 5, 1][..]),
            (&meshes[1], &second[..], &[1u32, 4, 0][..]),
        ] {
            assert_eq!(mesh.positions.len(), used.len());
            let expected: Vec<[u32; 3]> = indices
                .chunks_exact(3)
                .map(|t| {
                    [t[0], t[1], t[2]].map(|v| used.iter().position(|&u| u == v).unwrap() as u32)
                })
                .collect();
            assert_eq!(mesh.triangles, expected);
            for (p, &v) in mesh.positions.iter().zip(used) {
                let file = glam::DVec3::from(points[v as usize].map(f64::from)) - shift;
                assert!((p.as_dvec3() - file).length() < 1e-6, "{p} against {file}");
            }
        }
    }

    /// Accessors read straight from their bytes give what the gltf crate's reader gives, for
    /// packed floats and indices of each width; a strided or sparse accessor is left to the
    /// reader.
    #[test]
    fn packed_accessors_read_as_the_reader_reads_them() {
        let points: [[f32; 3]; 4] = [
            [0.5, -1.0, 2.0],
            [3.0, 0.0, -0.25],
            [1e-3, 7.0, 1.0],
            [-2.0, 4.5, 0.0],
        ];
        let mut bin: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect(); // 0..48
        for p in &points {
            // 48..144: each point beside a normal, 24 bytes a vertex.
            bin.extend(
                p.iter()
                    .chain(&[0.0, 0.0, 1.0])
                    .flat_map(|v| v.to_le_bytes()),
            );
        }
        let order = [3u32, 1, 0, 2, 1, 3];
        bin.extend(order.iter().flat_map(|&i| (i as u16).to_le_bytes())); // 144..156
        bin.extend(order.iter().map(|&i| i as u8)); // 156..162
        bin.extend([0, 0]);
        bin.extend(order.iter().flat_map(|&i| i.to_le_bytes())); // 164..188
        bin.push(2); // 188: the sparse accessor's one index
        bin.extend([0, 0, 0]);
        bin.extend([9.0f32, 9.0, 9.0].iter().flat_map(|v| v.to_le_bytes())); // 192..204
        let uri = data_uri(&bin);
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":3}},
                                      {{"attributes":{{"POSITION":1}},"indices":4}},
                                      {{"attributes":{{"POSITION":2}},"indices":5}}]}}],
            "buffers":[{{"byteLength":{len},"uri":"{uri}"}}],
            "bufferViews":[{{"buffer":0,"byteLength":48}},
                           {{"buffer":0,"byteOffset":48,"byteLength":96,"byteStride":24}},
                           {{"buffer":0,"byteOffset":144,"byteLength":44}},
                           {{"buffer":0,"byteOffset":188,"byteLength":1}},
                           {{"buffer":0,"byteOffset":192,"byteLength":12}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3"}},
                         {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3"}},
                         {{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3",
                           "sparse":{{"count":1,"indices":{{"bufferView":3,"componentType":5121}},
                                      "values":{{"bufferView":4}}}}}},
                         {{"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}},
                         {{"bufferView":2,"byteOffset":12,"componentType":5121,"count":6,"type":"SCALAR"}},
                         {{"bufferView":2,"byteOffset":20,"componentType":5125,"count":6,"type":"SCALAR"}}]}}"#,
            len = bin.len()
        );
        let gltf = gltf::Gltf::from_slice_without_validation(json.as_bytes()).unwrap();
        let buffers = vec![bin];
        let prims: Vec<_> = gltf.meshes().next().unwrap().primitives().collect();
        for (n, prim) in prims.iter().enumerate() {
            let reader = prim.reader(|b| buffers.get(b.index()).map(|v| v.as_slice()));
            let read: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
            let position = prim.get(&gltf::Semantic::Positions).unwrap();
            match packed_floats::<3>(&position, &buffers) {
                Some(p) => {
                    assert_eq!(n, 0, "only the first primitive's positions are packed");
                    assert_eq!(p, read);
                }
                None => assert_ne!(n, 0, "strided and sparse positions go to the reader"),
            }
            let indices = prim.indices().unwrap();
            let read: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
            assert_eq!(packed_indices(&indices, &buffers), Some(read.clone()));
            assert_eq!(read, order);
        }
        // The sparse accessor's substitution is the reader's to make.
        let reader = prims[2].reader(|b| buffers.get(b.index()).map(|v| v.as_slice()));
        assert_eq!(
            reader.read_positions().unwrap().nth(2),
            Some([9.0, 9.0, 9.0])
        );
        // Asked for the wrong width, a packed accessor is not read as packed.
        assert!(
            packed_floats::<2>(&prims[0].get(&gltf::Semantic::Positions).unwrap(), &buffers)
                .is_none()
        );
    }

    /// Textures naming one image with the same sampler settings are one texture (the
    /// decoded texels held once: a 16384x16384 image named by four textures was four copies
    /// of a GiB); another sampler's settings keep a texture of their own.
    #[test]
    fn textures_alike_share_one_decoded_image() {
        let mut png = Vec::new();
        image::RgbaImage::from_raw(2, 1, vec![255, 0, 0, 255, 0, 255, 0, 255])
            .unwrap()
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let uri = format!(
            "data:image/png;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&png)
        );
        let material = |t: usize| {
            format!(r#"{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":{t}}}}}}}"#)
        };
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[]}}],
            "images":[{{"uri":"{uri}"}}],
            "samplers":[{{"magFilter":9728}}],
            "textures":[{{"source":0}},{{"source":0}},{{"source":0,"sampler":0}},{{"source":0}}],
            "materials":[{},{},{},{}]}}"#,
            material(0),
            material(1),
            material(2),
            material(3)
        );
        let loaded = load_gltf_bytes(Path::new("shared-image.gltf"), json.as_bytes()).unwrap();
        let textures = &loaded.desc.textures;
        assert_eq!(textures.len(), 2, "one image under two samplers' settings");
        let used: Vec<u32> = loaded.desc.materials[..4]
            .iter()
            .map(|m| m.base_color_tex.unwrap().texture)
            .collect();
        assert_eq!(used, [0, 0, 1, 0]);
        assert_eq!(textures[0].filter, Filter::Linear);
        assert_eq!(textures[1].filter, Filter::Nearest);
        for (i, t) in textures.iter().enumerate() {
            assert_eq!((t.width, t.height), (2, 1));
            assert_eq!(loaded.desc.texels(i), [255, 0, 0, 255, 0, 255, 0, 255]);
        }
        assert_eq!(textures[1].texels_of, Some(0), "texels held once");
        assert!(textures[1].rgba.is_empty());
    }

    /// Accessors without a bufferView (zeros but for a sparse part) are bounded together,
    /// not each on its own: a file of many such accessors, each under the bound, asked for
    /// 16 MiB apiece. One such accessor read by several primitives counts once.
    #[test]
    fn accessors_without_data_are_bounded_together() {
        let scene = |primitives: &[usize], accessors: usize| {
            let primitives: Vec<String> = primitives
                .iter()
                .map(|a| format!(r#"{{"attributes":{{"POSITION":{a}}}}}"#))
                .collect();
            // 1,000,002 positions of 12 bytes: 12 MB, under the 16 MiB floor alone; the
            // sparse part sets the first to zero too (4 bytes of index, 12 of value).
            let accessor = r#"{"componentType":5126,"count":1000002,"type":"VEC3",
                "min":[0,0,0],"max":[0,0,0],"sparse":{"count":1,
                "indices":{"bufferView":0,"componentType":5125},"values":{"bufferView":1}}}"#;
            format!(
                r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
                "nodes":[{{"mesh":0}}],"meshes":[{{"primitives":[{}]}}],"accessors":[{}],
                "buffers":[{{"byteLength":16,"uri":"{}"}}],
                "bufferViews":[{{"buffer":0,"byteLength":4}},
                               {{"buffer":0,"byteOffset":4,"byteLength":12}}]}}"#,
                primitives.join(","),
                vec![accessor; accessors].join(","),
                data_uri(&[0; 16])
            )
        };
        let p = Path::new("unbacked.gltf");
        // One accessor, read by two primitives: within the bound (its triangles are all
        // degenerate, so the file has nothing to render, which is another message).
        let once = load_gltf_bytes(p, scene(&[0, 0], 1).as_bytes());
        if let Err(e) = &once {
            assert!(!e.to_string().contains("no bufferView"), "{e}");
        }
        let twice = load_gltf_bytes(p, scene(&[0, 1], 2).as_bytes())
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(
            twice.contains("accessor 1 has no bufferView")
                && twice.contains("besides the 12000024 bytes"),
            "{twice}"
        );
    }

    /// The files a scene names, from a .gltf and from a GLB's JSON chunk alike: local
    /// URIs, percent-decoded, beside the scene; not data URIs or other schemes.
    #[test]
    fn files_named_are_the_local_buffers_and_images() {
        let dir = std::env::temp_dir().join(format!("magg-files-named-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let json = br#"{"asset":{"version":"2.0"},
            "buffers":[{"byteLength":4,"uri":"a%20b.bin"},{"byteLength":4,"uri":"data:,x"},
                       {"byteLength":4}],
            "images":[{"uri":"tex/c.png"},{"uri":"https://example.com/d.png"}]}"#;
        let mut glb = b"glTF".to_vec();
        glb.extend(2u32.to_le_bytes());
        glb.extend(((20 + json.len()) as u32).to_le_bytes());
        glb.extend((json.len() as u32).to_le_bytes());
        glb.extend(b"JSON");
        glb.extend(json);
        let expected = [dir.join("a b.bin"), dir.join("tex/c.png")];
        for (name, bytes) in [("s.gltf", &json[..]), ("s.glb", &glb[..])] {
            std::fs::write(dir.join(name), bytes).unwrap();
            assert_eq!(files_named(&dir.join(name)), expected, "{name}");
        }
        std::fs::write(dir.join("bad.gltf"), b"{").unwrap();
        assert!(files_named(&dir.join("bad.gltf")).is_empty());
        assert!(files_named(&dir.join("none.gltf")).is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A GLB file cut short, of another version or with its chunks out of place is said as
    /// such, with the sizes (the `gltf` crate said "failed to fill whole buffer" and the
    /// like).
    #[test]
    fn broken_glb_containers_are_said_as_such() {
        let json = br#"{"asset":{"version":"2.0"},"scenes":[{"nodes":[]}]}  "#;
        let glb = |version: u32, total: Option<u32>, chunks: &[(&[u8; 4], &[u8], Option<u32>)]| {
            let mut body = Vec::new();
            for (kind, data, len) in chunks {
                body.extend(len.unwrap_or(data.len() as u32).to_le_bytes());
                body.extend(*kind);
                body.extend(*data);
            }
            let mut out = b"glTF".to_vec();
            out.extend(version.to_le_bytes());
            out.extend(total.unwrap_or(12 + body.len() as u32).to_le_bytes());
            out.extend(body);
            out
        };
        let whole = glb(2, None, &[(b"JSON", json, None)]);
        assert!(load_gltf_bytes(Path::new("ok.glb"), &whole).is_ok());
        let mut trailing = whole.clone();
        trailing.extend(b"more");
        for (bytes, says) in [
            (
                b"glTF\x02\0".to_vec(),
                "12-byte header; this one has 6 bytes",
            ),
            (glb(1, None, &[(b"JSON", json, None)]), "GLB version 1"),
            (
                glb(2, Some(1_000_000), &[(b"JSON", json, None)]),
                "length as 1000000 bytes, but the file has 73",
            ),
            (trailing, "but the file has 77"),
            (
                glb(2, None, &[(b"JSON", json, Some(1000))]),
                "JSON chunk at byte 12 gives 1000 bytes, but only 53 follow",
            ),
            (
                glb(2, None, &[(b"BIN\0", json, None)]),
                "first chunk is BIN",
            ),
            (glb(2, None, &[]), "no JSON chunk"),
        ] {
            let e = load_gltf_bytes(Path::new("broken.glb"), &bytes)
                .map(|_| ())
                .unwrap_err()
                .to_string();
            assert!(e.contains(says), "{e:?} should say {says:?}");
        }
    }

    #[test]
    fn garbage_is_a_parse_error_not_a_panic() {
        let p = Path::new("garbage.gltf");
        for bytes in [
            &b""[..],
            b"{",
            b"glTF\x02\0\0\0\xff\xff\xff\xff",
            b"{\"asset\":{\"version\":\"2.0\"},\"scenes\":[{\"nodes\":[5]}]}",
        ] {
            assert!(load_gltf_bytes(p, bytes).is_err());
        }
    }
}
