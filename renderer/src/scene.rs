//! Scenes in two forms.
//!
//! [`SceneDesc`] is what a loader produces: world-space meshes, materials, images, lights and
//! cameras. [`prepare`] turns it into the form rendering uses, split the way the cluster
//! moves it: a [`SceneHeader`] (cameras, materials, lights, texture descriptions, the
//! top-level tree over chunk bounds; small, sent to every render node) and [`MemoryData`]
//! (the chunks and texture tiles, which render nodes fetch on demand).

use std::sync::Arc;

use glam::{Vec2, Vec3};
use obvhs::aabb::Aabb;
use serde::{Deserialize, Serialize};

use crate::{
    accel::{Bvh8, FlatLayout, Node8, WalkPlace},
    bvh,
    camera::Camera,
    chunk::{self, Chunk, MeshData},
    light::{Environment, Light, LightDistribution},
    material::Material,
    region::{self, Block, BlockMut, Region},
    source::{FlatTree, MemoryData},
    texture::{self, Filter, TextureInfo, Wrap},
};

/// An image a material uses, decoded to RGBA8.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextureDesc {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// As one byte string: the same bytes on the wire as a sequence of `u8`, but written
    /// and hashed in one piece instead of a call per byte (a quarter of a textured scene's
    /// load time went there).
    /// Empty where `texels_of` names another texture.
    #[serde(with = "pod_vec")]
    pub rgba: Vec<u8>,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    pub filter: Filter,
    /// An earlier texture whose texels (and, once prepared, tiles) this one samples with
    /// its own wrap and filter: one image under several samplers' settings is held once,
    /// where a copy for each let a small file ask for gigabytes. Use
    /// [`SceneDesc::texels`] to read a texture's texels either way.
    pub texels_of: Option<u32>,
}

/// A scene as loaders build it, in world space.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneDesc {
    pub meshes: Vec<MeshData>,
    pub materials: Vec<Material>,
    pub textures: Vec<TextureDesc>,
    /// Punctual lights; emissive triangles become lights in [`prepare`].
    pub lights: Vec<Light>,
    pub cameras: Vec<Camera>,
    /// The world around the scene. `None`: a sky ([`Environment::sky`]) when the scene has
    /// no light of its own, neither punctual lights nor untextured emitters (most published
    /// glTF files have none, and would otherwise render black), else darkness.
    #[serde(default)]
    pub environment: Option<Environment>,
}

impl SceneDesc {
    /// Texture `i`'s texels, RGBA8 row by row, its own or those it shares
    /// ([`TextureDesc::texels_of`]).
    pub fn texels(&self, i: usize) -> &[u8] {
        let t = &self.textures[i];
        match t.texels_of {
            Some(of) => &self.textures[of as usize].rgba,
            None => &t.rgba,
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.meshes.iter().map(|m| m.triangles.len()).sum()
    }

    /// Checks a description received from elsewhere before [`prepare`] trusts it: every
    /// index in range, every attribute array the right length, every number finite.
    pub fn validate(&self) -> Result<(), SceneError> {
        let bad = |m: String| Err(SceneError::Invalid(m));
        for (i, m) in self.meshes.iter().enumerate() {
            let n = m.positions.len();
            if m.material as usize >= self.materials.len() {
                return bad(format!(
                    "mesh {i} uses material {} of {}",
                    m.material,
                    self.materials.len()
                ));
            }
            for (name, len) in [
                ("normals", m.normals.len()),
                ("uv0", m.uv0.len()),
                ("uv1", m.uv1.len()),
                ("tangents", m.tangents.len()),
                ("colors", m.colors.len()),
            ] {
                if len != 0 && len != n {
                    return bad(format!(
                        "mesh {i}: {name} has {len} entries for {n} positions"
                    ));
                }
            }
            if m.triangles.iter().flatten().any(|&v| v as usize >= n) {
                return bad(format!("mesh {i}: a triangle index is out of range"));
            }
            if !m.positions.iter().all(|p| p.is_finite()) {
                return bad(format!("mesh {i}: non-finite position"));
            }
        }
        for (i, t) in self.textures.iter().enumerate() {
            if let Some(of) = t.texels_of {
                let same = match self.textures.get(of as usize) {
                    Some(o) if (of as usize) < i && o.texels_of.is_none() => {
                        (o.width, o.height) == (t.width, t.height) && t.rgba.is_empty()
                    }
                    _ => false,
                };
                if !same {
                    return bad(format!(
                        "texture {i}: its texels are texture {of}'s, which is not an earlier \
                         texture of its size holding its own"
                    ));
                }
                continue;
            }
            if t.width == 0
                || t.height == 0
                || t.rgba.len() as u64 != t.width as u64 * t.height as u64 * 4
            {
                return bad(format!(
                    "texture {i}: {}x{} with {} bytes",
                    t.width,
                    t.height,
                    t.rgba.len()
                ));
            }
        }
        for (i, m) in self.materials.iter().enumerate() {
            for t in m.textures() {
                if t.texture as usize >= self.textures.len() {
                    return bad(format!(
                        "material {i} uses texture {} of {}",
                        t.texture,
                        self.textures.len()
                    ));
                }
            }
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug)]
pub struct PrepareOptions {
    /// Most triangles in one chunk.
    pub chunk_triangles: usize,
}

impl Default for PrepareOptions {
    fn default() -> Self {
        PrepareOptions {
            chunk_triangles: 4096,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChunkInfo {
    pub bounds_min: Vec3,
    pub bounds_max: Vec3,
    pub tri_count: u32,
    /// Bytes of the chunk's words: what crosses a link when it is fetched.
    pub byte_len: u32,
    /// Bytes it takes once it can be walked, its words and its walking form together: what
    /// a render node's cache budget counts ([`crate::chunk::Chunk::memory_bytes`]).
    pub memory_bytes: u32,
    /// The material of every triangle of the chunk.
    pub material: u32,
}

/// What a chunk received from elsewhere must agree with, from the header: its id, material,
/// triangle count and lights, so that shading it cannot index outside the header's lists.
#[derive(Clone, Debug, Default)]
pub struct ChunkRules {
    /// (material, triangles) by chunk id.
    chunks: Vec<(u32, u32)>,
    lights: u64,
}

impl ChunkRules {
    /// Rules for chunks of these (material, triangle count) and a light list this long.
    pub fn new(chunks: Vec<(u32, u32)>, lights: usize) -> ChunkRules {
        ChunkRules {
            chunks,
            lights: lights as u64,
        }
    }

    /// How many chunks the scene has.
    pub fn len(&self) -> usize {
        self.chunks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.chunks.is_empty()
    }

    /// Whether `chunk` may be used as chunk `id` of this scene.
    pub fn check(&self, id: u32, chunk: &Chunk) -> Result<(), ChunkMismatch> {
        let h = chunk.header();
        let Some(&(material, tris)) = self.chunks.get(id as usize) else {
            return Err(ChunkMismatch::NotInScene { id });
        };
        if h.chunk_id != id {
            return Err(ChunkMismatch::OtherChunk {
                id,
                got: h.chunk_id,
            });
        }
        if (h.material, h.tri_count) != (material, tris) {
            return Err(ChunkMismatch::Shape {
                id,
                material: h.material,
                tris: h.tri_count,
                scene_material: material,
                scene_tris: tris,
            });
        }
        if h.light_base != crate::chunk::NO_LIGHT
            && h.light_base as u64 + h.tri_count as u64 > self.lights
        {
            return Err(ChunkMismatch::Lights {
                id,
                base: h.light_base,
                lights: self.lights,
            });
        }
        Ok(())
    }
}

/// How a chunk from elsewhere disagrees with the scene it is meant for.
#[derive(Debug, thiserror::Error)]
pub enum ChunkMismatch {
    #[error("chunk {id} is not in the scene")]
    NotInScene { id: u32 },
    #[error("asked for chunk {id}, got chunk {got}")]
    OtherChunk { id: u32, got: u32 },
    #[error(
        "chunk {id} has material {material} and {tris} triangles; the scene says {scene_material} and {scene_tris}"
    )]
    Shape {
        id: u32,
        material: u32,
        tris: u32,
        scene_material: u32,
        scene_tris: u32,
    },
    #[error("chunk {id}'s triangles are lights {base}.. of {lights}")]
    Lights { id: u32, base: u32, lights: u64 },
}

/// The top-level tree over chunk bounds: its compact form (sent with the header) and, once
/// the header is known to be valid, the form rays walk, each leaf one chunk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Tlas {
    #[serde(with = "pod_vec")]
    pub nodes: Vec<bvh::WideNode>,
    /// Leaf slot to chunk id.
    pub slots: Vec<u32>,
    #[serde(skip)]
    accel: WalkForm,
}

/// The walking form of the top-level tree, built once from a prepared or validated header.
/// It is derived data: it never decides equality, and it is not sent.
#[derive(Clone, Debug, Default)]
struct WalkForm(std::sync::OnceLock<Bvh8>);

impl PartialEq for WalkForm {
    fn eq(&self, _: &WalkForm) -> bool {
        true
    }
}

impl Tlas {
    /// The tree rays walk; empty until the header was prepared here or validated.
    #[inline(always)]
    pub fn accel(&self) -> &Bvh8 {
        static NONE: Bvh8 = Bvh8 {
            nodes: Region::empty(),
            leaves: Region::empty(),
            tris: 0,
        };
        self.accel.0.get().unwrap_or(&NONE)
    }

    fn build_accel(&self, chunks: &[ChunkInfo]) {
        let bounds: Vec<([f32; 3], [f32; 3])> = chunks
            .iter()
            .map(|c| (c.bounds_min.to_array(), c.bounds_max.to_array()))
            .collect();
        let _ = self
            .accel
            .0
            .set(Bvh8::for_chunks(&self.nodes, &self.slots, &bounds));
    }
}

/// Everything about a scene except its shape and texture data.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct SceneHeader {
    pub cameras: Vec<Camera>,
    pub materials: Vec<Material>,
    pub textures: Vec<TextureInfo>,
    /// Punctual (delta) lights first, then emissive triangles, then the environment: the
    /// Whitted integrator visits every punctual light at every hit, and finds them as a
    /// prefix instead of searching a list that may hold a million triangles.
    pub lights: Vec<Light>,
    pub light_distribution: LightDistribution,
    /// Radiance of rays that leave the scene (black: none).
    pub environment: Environment,
    /// Index of the environment in `lights`, when it is not black.
    pub environment_light: Option<u32>,
    pub chunks: Vec<ChunkInfo>,
    pub tlas: Tlas,
    pub bounds_min: Vec3,
    pub bounds_max: Vec3,
    /// Total bytes of all chunks' words (what a render node would fetch to hold them all).
    pub shape_bytes: u64,
    pub tile_count: u32,
}

impl SceneHeader {
    /// Bytes the whole scene takes on a render node once every chunk and tile is ready to
    /// use: the base of cache percentages, so that a cache of 100% holds everything.
    pub fn memory_bytes(&self) -> u64 {
        self.chunks
            .iter()
            .map(|c| c.memory_bytes as u64)
            .sum::<u64>()
            + self.tile_count as u64 * crate::texture::TILE_TEXELS as u64 * 4
    }

    /// The most one chunk takes once ready to walk: a cache must hold at least this much.
    pub fn largest_chunk_memory(&self) -> u64 {
        self.chunks
            .iter()
            .map(|c| c.memory_bytes as u64)
            .max()
            .unwrap_or(0)
    }

    /// The punctual lights: the prefix of `lights` that are points, spots and suns.
    pub fn punctual_lights(&self) -> &[Light] {
        let n = self.lights.iter().take_while(|l| l.is_delta()).count();
        &self.lights[..n]
    }

    /// What chunks from elsewhere must agree with (see [`ChunkRules`]).
    pub fn chunk_rules(&self) -> ChunkRules {
        ChunkRules::new(
            self.chunks
                .iter()
                .map(|c| (c.material, c.tri_count))
                .collect(),
            self.lights.len(),
        )
    }

    pub fn radius(&self) -> f32 {
        ((self.bounds_max - self.bounds_min).length() * 0.5).max(0.0)
    }

    pub fn has_transmission(&self) -> bool {
        self.materials.iter().any(|m| m.transmission > 0.0)
    }

    pub fn triangle_count(&self) -> u64 {
        self.chunks.iter().map(|c| c.tri_count as u64).sum()
    }

    /// Checks every index and number of a header received from elsewhere, so that
    /// rendering with it cannot index out of bounds; then builds the form of the top-level
    /// tree that rays walk (a header is used only after this).
    pub fn validate(&self) -> Result<(), SceneError> {
        let bad = |what: String| Err(SceneError::Invalid(what));
        let finite3 = |v: Vec3| v.is_finite();
        for (i, m) in self.materials.iter().enumerate() {
            for t in m.textures() {
                if t.texture as usize >= self.textures.len() {
                    return bad(format!(
                        "material {i} uses texture {} of {}",
                        t.texture,
                        self.textures.len()
                    ));
                }
            }
            if !m.base_color.is_finite() || !finite3(m.emissive) || !m.ior.is_finite() {
                return bad(format!("material {i} has non-finite factors"));
            }
        }
        let mut tiles = 0u64;
        let mut made = std::collections::HashSet::new();
        for (i, t) in self.textures.iter().enumerate() {
            if t.width == 0 || t.height == 0 || t.width > 1 << 16 || t.height > 1 << 16 {
                return bad(format!("texture {i} is {}x{}", t.width, t.height));
            }
            // A texture's tiles follow the textures' before it, or are an earlier one's of
            // the same size (one image under several samplers' settings).
            if !made.insert((t.first_tile, t.width, t.height)) {
                continue;
            }
            if t.first_tile as u64 != tiles {
                return bad(format!(
                    "texture {i} starts at tile {}, expected {tiles} or an earlier texture's \
                     of its size",
                    t.first_tile
                ));
            }
            tiles += t.tile_count() as u64;
        }
        if tiles != self.tile_count as u64 {
            return bad(format!(
                "textures hold {tiles} tiles, header says {}",
                self.tile_count
            ));
        }
        let punctual = self.punctual_lights().len();
        if let Some(i) = self.lights[punctual..].iter().position(|l| l.is_delta()) {
            return bad(format!(
                "punctual light {} follows other lights",
                punctual + i
            ));
        }
        for (i, l) in self.lights.iter().enumerate() {
            if let Light::Triangle {
                p,
                uv,
                material,
                two_sided,
                ..
            } = l
            {
                if *material as usize >= self.materials.len() {
                    return bad(format!("light {i} uses material {material}"));
                }
                if Light::triangle(*p, *uv, *material, *two_sided) != *l {
                    return bad(format!(
                        "light {i}'s normal or area disagrees with its corners"
                    ));
                }
            }
        }
        if let Some(e) = self.environment_light
            && !matches!(self.lights.get(e as usize), Some(Light::Environment(_)))
        {
            return bad("environment light index is wrong".into());
        }
        if !self.environment.is_finite() {
            return bad("non-finite environment".into());
        }
        if self.light_distribution.cdf.len() != self.lights.len() {
            return bad("light distribution does not match the lights".into());
        }
        if self
            .light_distribution
            .cdf
            .windows(2)
            .any(|w| !(w[0] <= w[1]))
        {
            return bad("light distribution is not increasing".into());
        }
        if self
            .tlas
            .slots
            .iter()
            .any(|&s| s as usize >= self.chunks.len())
        {
            return bad("top-level tree points at a chunk that does not exist".into());
        }
        bvh::validate_tree(&self.tlas.nodes, self.tlas.slots.len())
            .map_err(|e| SceneError::Invalid(format!("top-level tree: {e}")))?;
        if !self
            .chunks
            .iter()
            .all(|c| c.bounds_min.is_finite() && c.bounds_max.is_finite())
        {
            return bad("a chunk's bounds are not finite".into());
        }
        if let Some(i) = self
            .chunks
            .iter()
            .position(|c| c.material as usize >= self.materials.len())
        {
            return bad(format!("chunk {i} uses a material that does not exist"));
        }
        self.tlas.build_accel(&self.chunks);
        Ok(())
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SceneError {
    #[error("invalid scene header: {0}")]
    Invalid(String),
    /// `--camera NAME` names none of the scene's cameras (a choice, not a broken header).
    #[error("no camera named {name:?}; the scene has {}", match names.as_slice() {
        [] => "none (\"auto\" frames the scene)".to_string(),
        names => format!("{names:?} (and \"auto\" frames the scene)"),
    })]
    NoSuchCamera { name: String, names: Vec<String> },
}

/// The chunks of `meshes`: each mesh cut into pieces (`chunk::split_mesh`), each piece's
/// tree built and the piece written as a chunk, in mesh order and piece order, numbered in
/// that order. Pieces are built on up to `threads` threads, each on its own, so the chunks
/// are the same bytes whatever the number of threads (a scene of a million triangles takes
/// a third of a second on one: the first render of a large scene waits for it, and so does
/// a cluster, whose other processes are idle meanwhile). Each chunk gets its walking form
/// too when `transcode`; otherwise the caller places them (`walks_in_block`).
fn build_chunks(
    meshes: &[MeshData],
    opts: &PrepareOptions,
    threads: usize,
    transcode: bool,
) -> Vec<Chunk> {
    let pieces: Vec<(usize, Vec<u32>)> = meshes
        .iter()
        .enumerate()
        .flat_map(|(m, mesh)| {
            chunk::split_mesh(mesh, opts.chunk_triangles)
                .into_iter()
                .filter(|p| !p.is_empty())
                .map(move |p| (m, p))
        })
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let work = || {
        let mut builder = bvh::Builder::default();
        let mut remap = Vec::new();
        let mut done = Vec::new();
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let Some((m, piece)) = pieces.get(i) else {
                return done;
            };
            done.push((
                i,
                piece_chunks(
                    &meshes[*m],
                    *m as u32,
                    piece,
                    &mut builder,
                    &mut remap,
                    transcode,
                ),
            ));
        }
    };
    let threads = threads.clamp(1, pieces.len().max(1));
    let mut built: Vec<(usize, Vec<Chunk>)> = if threads == 1 {
        work()
    } else {
        std::thread::scope(|scope| {
            let others: Vec<_> = (1..threads).map(|_| scope.spawn(work)).collect();
            let mut all = work();
            for t in others {
                // A panic in a builder thread is a bug here, not bad input: pass it on.
                all.extend(t.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
            }
            all
        })
    };
    built.sort_unstable_by_key(|(i, _)| *i);
    let mut chunks: Vec<Chunk> = built.into_iter().flat_map(|(_, c)| c).collect();
    for (id, c) in chunks.iter_mut().enumerate() {
        c.set_chunk_id(id as u32);
    }
    chunks
}

/// Builds the walking forms of `chunks` (which have none yet) into one block from `make`,
/// `threads` at a time, and has the chunks walked there. A chunk whose form could not be
/// placed (a block too small or misaligned; an empty one is how a caller declines) gets one
/// of its own, built on those threads too.
fn walks_in_block(chunks: &mut [Chunk], make: MakeBlock<'_>, threads: usize) {
    let (places, end) = region::line_places(chunks.iter().map(|c| c.walk_words_len()));
    let mut block = make(end);
    let words = block.words_mut();
    let usable = words.len() >= end && (words.as_ptr() as usize).is_multiple_of(64);
    // Each chunk's own range, cut from the block in order, if the block can hold them.
    let mut ranges: Vec<Option<&mut [u32]>> = (0..chunks.len()).map(|_| None).collect();
    if usable {
        let mut rest = &mut words[..end];
        let mut at = 0;
        for (&(start, end), slot) in places.iter().zip(&mut ranges) {
            let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - at);
            let (range, tail) = tail.split_at_mut(end - start);
            rest = tail;
            at = end;
            *slot = Some(range);
        }
    }
    let mut placed = vec![false; chunks.len()];
    let mut jobs: Vec<_> = chunks.iter_mut().zip(ranges).zip(&mut placed).collect();
    let per = jobs.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        for group in jobs.chunks_mut(per) {
            scope.spawn(move || {
                for ((c, range), done) in group {
                    match range {
                        Some(range) => **done = c.transcode_into(range),
                        None => c.transcode(),
                    }
                }
            });
        }
    });
    if !usable {
        return;
    }
    let block: Arc<dyn BlockMut> = Arc::from(block);
    let block: Arc<dyn Block> = block;
    for ((c, (start, end)), done) in chunks.iter_mut().zip(places).zip(placed) {
        let place = WalkPlace {
            block: block.clone(),
            start,
            end,
        };
        // A form built here from a valid tree passes the check read-in-place forms get; if
        // one did not, its chunk would still be walked, from a copy of its own.
        if !done || c.walk_in(place).is_err() {
            c.transcode();
        }
    }
}

/// Builds the flat tree of `data`'s chunks (which have no walking forms) and `scene`'s
/// top-level tree straight into one block from `make`, each chunk's part on one of `threads`
/// threads (see [`FlatLayout`]); in the heap where `make` gives a block too small. False,
/// the chunks left without forms, where the trees do not fit one tree.
fn flat_in_block(
    data: &mut MemoryData,
    scene: &SceneHeader,
    make: MakeBlock<'_>,
    threads: usize,
) -> bool {
    let counts: Vec<(usize, usize)> = data.chunks.iter().map(|c| c.walk_counts()).collect();
    let top = scene.tlas.accel();
    let Some(layout) = FlatLayout::new(top, &counts) else {
        return false;
    };
    let words = layout.words_len();
    let mut block = make(words);
    let out = block.words_mut();
    if out.len() < words || !(out.as_ptr() as usize).is_multiple_of(64) {
        // Too small to be worth a block: the chunks' forms in the heap, made one tree there.
        for c in &mut data.chunks {
            c.transcode();
        }
        if data.flatten(scene) {
            return true;
        }
        for c in &mut data.chunks {
            c.drop_walk();
        }
        return false;
    }
    let Some((heads, parts)) = layout.cut(&mut out[..words]) else {
        return false;
    };
    let (layout, chunks) = (&layout, &data.chunks);
    let mut jobs: Vec<_> = parts.into_iter().enumerate().collect();
    let per = jobs.len().div_ceil(threads.max(1)).max(1);
    let roots: Option<Vec<(usize, Node8)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = jobs
            .chunks_mut(per)
            .map(|group| {
                scope.spawn(move || {
                    group
                        .iter_mut()
                        .map(|(c, (body, blocks))| {
                            let chunk = &chunks[*c];
                            let form = chunk.walking_form();
                            layout
                                .write_chunk(*c, &form, chunk.tri_count(), body, blocks)
                                .map(|root| (*c, root))
                        })
                        .collect::<Option<Vec<_>>>()
                })
            })
            .collect();
        let mut all = Vec::with_capacity(chunks.len());
        for h in handles {
            // A panic in a builder thread is a bug here, not bad input: pass it on.
            all.extend(h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))?);
        }
        Some(all)
    });
    let Some(roots) = roots else {
        return false;
    };
    let mut root_nodes = vec![Node8::EMPTY; chunks.len()];
    for (c, root) in roots {
        root_nodes[c] = root;
    }
    layout.write_heads(top, &root_nodes, heads);
    let block: Arc<dyn BlockMut> = Arc::from(block);
    // A tree written here from trees that passed their checks passes the check again.
    let Ok(form) = Bvh8::in_block(block, 0, words, u32::MAX) else {
        return false;
    };
    data.flat = Some(FlatTree::new(form, layout.block_chunk(), scene));
    true
}

/// The chunks of one piece of mesh `mesh_id`: one, or more where a tree came out too deep
/// (coincident triangles) and the piece was halved, in the order of its triangles.
fn piece_chunks(
    mesh: &MeshData,
    mesh_id: u32,
    piece: &[u32],
    builder: &mut bvh::Builder,
    remap: &mut Vec<u32>,
    transcode: bool,
) -> Vec<Chunk> {
    let mut out = Vec::new();
    let mut work = vec![piece.to_vec()];
    while let Some(piece) = work.pop() {
        if piece.is_empty() {
            continue;
        }
        let mut wide = builder.build(&chunk::triangle_boxes(mesh, &piece), bvh::MAX_LEAF);
        for t in &mut wide.order {
            *t = piece[*t as usize];
        }
        match chunk::chunk_words_from(mesh, &wide, 0, mesh_id, remap) {
            Some(mut c) => {
                if transcode {
                    c.transcode();
                }
                out.push(c)
            }
            None => {
                let mid = piece.len() / 2;
                work.push(piece[mid..].to_vec());
                work.push(piece[..mid].to_vec());
            }
        }
    }
    out
}

/// Splits meshes into chunks, builds both BVH levels, collects emissive triangles into the
/// light list and cuts textures into tiles. Deterministic.
pub fn prepare(desc: SceneDesc, opts: &PrepareOptions) -> (SceneHeader, MemoryData) {
    prepare_with(desc, opts, None)
}

/// Makes the memory of a block of walking forms: at least the given number of words, zeroed,
/// 64-byte aligned.
pub type MakeBlock<'a> = &'a dyn Fn(usize) -> Box<dyn BlockMut>;

/// As [`prepare`]; with `walks`, every chunk's walking form is built straight into one
/// block that `walks` makes, each at a 64-byte aligned place, and rays walk the chunks there
/// as a render node walks a card's segment. The block can be memory of another kind than
/// the heap: the host maps it in large pages, where random rays through a large scene would
/// otherwise wait on a page walk at nearly every node (a 4 KiB page holds 16 nodes). Built
/// straight there, the forms take no more memory than in the heap. The same rays give the
/// same answers either way.
pub fn prepare_with(
    desc: SceneDesc,
    opts: &PrepareOptions,
    walks: Option<MakeBlock<'_>>,
) -> (SceneHeader, MemoryData) {
    prepare_as(desc, opts, walks.map_or(Walks::Heap, Walks::Block))
}

/// As [`prepare_with`], the chunks' trees then made one tree with the top-level tree
/// ([`MemoryData::flatten`]) and built straight into one block from `make` (or in the heap,
/// where `make` declines with a block too small): no chunk gets a walking form of its own,
/// so the flat tree takes no more memory or time to build than the chunks' forms would.
/// What one process walks. Where the trees do not fit one tree, as [`prepare_with`].
pub fn prepare_flat(
    desc: SceneDesc,
    opts: &PrepareOptions,
    make: MakeBlock<'_>,
) -> (SceneHeader, MemoryData) {
    prepare_as(desc, opts, Walks::Flat(make))
}

/// Where a preparation puts the walking forms.
#[derive(Clone, Copy)]
enum Walks<'a> {
    /// Each chunk's in the heap.
    Heap,
    /// Each chunk's in one block.
    Block(MakeBlock<'a>),
    /// One flat tree in one block.
    Flat(MakeBlock<'a>),
}

fn prepare_as(
    desc: SceneDesc,
    opts: &PrepareOptions,
    walks: Walks<'_>,
) -> (SceneHeader, MemoryData) {
    // Each thread keeps a vertex map as long as the largest mesh: eight bound that memory on
    // a large machine, where reading the file takes longer than building by then.
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get().min(8));
    let mut chunks = build_chunks(&desc.meshes, opts, threads, matches!(walks, Walks::Heap));
    if let Walks::Block(make) = walks {
        walks_in_block(&mut chunks, make, threads);
    }

    // Bounds of everything.
    let mut bounds = Aabb::empty();
    for c in &chunks {
        bounds = bounds.union(&c.bounds());
    }
    let (bmin, bmax) = if chunks.is_empty() {
        (Vec3::ZERO, Vec3::ZERO)
    } else {
        (Vec3::from(bounds.min), Vec3::from(bounds.max))
    };

    // Textures into tiles.
    let mut tiles = Vec::new();
    let mut textures = Vec::new();
    for t in &desc.textures {
        let info = |first_tile: u32, average_linear, average_srgb| TextureInfo {
            name: t.name.clone(),
            width: t.width,
            height: t.height,
            wrap_s: t.wrap_s,
            wrap_t: t.wrap_t,
            filter: t.filter,
            first_tile,
            average_linear,
            average_srgb,
        };
        let made = match t.texels_of {
            // Validated: an earlier texture of the same size, already made.
            Some(of) => {
                let o: &TextureInfo = &textures[of as usize];
                info(o.first_tile, o.average_linear, o.average_srgb)
            }
            None => {
                let (avg_lin, avg_srgb) = texture::averages(&t.rgba);
                let first_tile = tiles.len() as u32;
                tiles.extend(texture::make_tiles(t.width, t.height, &t.rgba));
                info(first_tile, avg_lin, avg_srgb)
            }
        };
        textures.push(made);
    }

    // Emissive triangles become lights, in chunk order.
    let mut lights = desc.lights.clone();
    for c in chunks.iter_mut() {
        let material_id = c.header().material;
        let Some(m) = desc.materials.get(material_id as usize) else {
            continue;
        };
        if !m.is_emissive() {
            continue;
        }
        let base = lights.len() as u32;
        let tex_coord = m.emissive_tex.map_or(0, |t| t.tex_coord);
        let hit = |b: [f32; 3]| crate::triangle::TriHit {
            t: 1.0,
            b0: b[0],
            b1: b[1],
            b2: b[2],
        };
        for tri in 0..c.tri_count() {
            let (v0, v1, v2) = chunk::tri_points(&c.tri_positions()[tri as usize]);
            let uv_at = |b: [f32; 3]| {
                let s = c.surface(tri, &hit(b));
                let uv = if tex_coord == 1 { s.uv1 } else { s.uv0 };
                uv.unwrap_or(Vec2::ZERO)
            };
            lights.push(Light::triangle(
                [Vec3::from(v0), Vec3::from(v1), Vec3::from(v2)],
                [
                    uv_at([1.0, 0.0, 0.0]),
                    uv_at([0.0, 1.0, 0.0]),
                    uv_at([0.0, 0.0, 1.0]),
                ],
                material_id,
                m.double_sided,
            ));
        }
        c.set_light_base(base);
    }

    // A scene "has lights" when it has punctual lights or untextured emitters (area lights).
    // Textured emission (glowing details, screens) alone does not light a scene, so such a
    // scene gets the white environment too.
    let has_lights = !desc.lights.is_empty()
        || chunks.iter().any(|c| {
            desc.materials
                .get(c.header().material as usize)
                .is_some_and(|m| m.is_emissive() && m.emissive_tex.is_none())
        });
    let environment = desc.environment.unwrap_or(if has_lights {
        Environment::default()
    } else {
        Environment::sky()
    });
    let environment = if environment.is_finite() {
        Environment {
            zenith: environment.zenith.max(Vec3::ZERO),
            nadir: environment.nadir.max(Vec3::ZERO),
        }
    } else {
        Environment::default()
    };
    let environment_light = (!environment.is_black()).then(|| {
        lights.push(Light::Environment(environment));
        (lights.len() - 1) as u32
    });

    let chunk_infos: Vec<ChunkInfo> = chunks
        .iter()
        .map(|c| {
            let h = c.header();
            ChunkInfo {
                bounds_min: Vec3::from(h.bounds_min),
                bounds_max: Vec3::from(h.bounds_max),
                tri_count: h.tri_count,
                byte_len: c.byte_len() as u32,
                memory_bytes: c.memory_bytes() as u32,
                material: h.material,
            }
        })
        .collect();
    let boxes: Vec<Aabb> = chunks.iter().map(|c| c.bounds()).collect();
    // One chunk a leaf: a ray tests each chunk's own box before it touches the chunk.
    let top = bvh::build_top(&boxes);

    let mut data = MemoryData {
        chunks,
        tiles,
        flat: None,
    };
    let mut scene = SceneHeader {
        cameras: desc.cameras,
        materials: desc.materials,
        textures,
        lights,
        light_distribution: LightDistribution::default(),
        environment,
        environment_light,
        chunks: chunk_infos,
        tlas: Tlas {
            nodes: top.nodes,
            slots: top.order,
            accel: WalkForm::default(),
        },
        bounds_min: bmin,
        bounds_max: bmax,
        shape_bytes: data.shape_bytes(),
        tile_count: data.tiles.len() as u32,
    };
    scene.tlas.build_accel(&scene.chunks);
    if let Walks::Flat(make) = walks
        && !flat_in_block(&mut data, &scene, make, threads)
    {
        walks_in_block(&mut data.chunks, make, threads);
    }
    let radius = scene.radius();
    let weights: Vec<f64> = scene
        .lights
        .iter()
        .map(|l| l.power(&scene, radius))
        .collect();
    scene.light_distribution = LightDistribution::new(&weights);
    (scene, data)
}

impl SceneHeader {
    /// The camera called `name` ("auto": one framing the whole scene), else the first,
    /// else one framing the whole scene.
    pub fn camera(&self, name: Option<&str>, aspect: f32) -> Result<Camera, SceneError> {
        match name {
            Some("auto") if !self.cameras.iter().any(|c| c.name == "auto") => {
                Ok(Camera::framing(self.bounds_min, self.bounds_max, aspect))
            }
            Some(n) => self
                .cameras
                .iter()
                .find(|c| c.name == n)
                .cloned()
                .ok_or_else(|| SceneError::NoSuchCamera {
                    name: n.to_string(),
                    names: self.cameras.iter().map(|c| c.name.clone()).collect(),
                }),
            None => Ok(self
                .cameras
                .first()
                .cloned()
                .unwrap_or_else(|| Camera::framing(self.bounds_min, self.bounds_max, aspect))),
        }
    }
}

/// Serde for `Vec<T: Pod>` as one byte string: written and read in one piece instead of a
/// call per number, which made encoding a million triangles' description to send it to the
/// first fork node take 41 ms, and decoding it there 40 ms, on the way to the first pixel.
/// The bytes are the elements' in memory, little-endian on every target this builds for.
pub(crate) mod pod_vec {
    use std::marker::PhantomData;

    use bytemuck::Pod;
    use serde::{Deserializer, Serializer, de::Error};

    const _: () = assert!(
        cfg!(target_endian = "little"),
        "scene descriptions travel as little-endian bytes"
    );

    pub fn serialize<S: Serializer, T: Pod>(v: &[T], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(bytemuck::cast_slice(v))
    }

    pub fn deserialize<'de, D: Deserializer<'de>, T: Pod>(d: D) -> Result<Vec<T>, D::Error> {
        d.deserialize_bytes(Elements(PhantomData))
    }

    /// Reads the byte string straight into elements (one copy, aligned for `T`).
    struct Elements<T>(PhantomData<T>);

    impl<T: Pod> Elements<T> {
        fn from_bytes<E: Error>(bytes: &[u8]) -> Result<Vec<T>, E> {
            if !bytes.len().is_multiple_of(size_of::<T>()) {
                return Err(E::custom("byte length is not a whole number of elements"));
            }
            Ok(bytemuck::pod_collect_to_vec(bytes))
        }
    }

    impl<'de, T: Pod> serde::de::Visitor<'de> for Elements<T> {
        type Value = Vec<T>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("bytes")
        }
        fn visit_bytes<E: Error>(self, v: &[u8]) -> Result<Vec<T>, E> {
            Elements::from_bytes(v)
        }
        fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
            let mut v = Vec::new();
            while let Some(b) = seq.next_element::<u8>()? {
                v.push(b);
            }
            Elements::from_bytes(&v)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_description_reads_back_as_it_was_written_and_a_cut_array_is_refused() {
        let cfg = bincode::config::standard();
        let mesh = MeshData {
            positions: vec![Vec3::new(1.0, -2.0, 3.5), Vec3::new(0.0, 1e-30, -7.0)],
            normals: vec![Vec3::Z, Vec3::X],
            uv0: vec![glam::Vec2::new(0.25, 0.5), glam::Vec2::ONE],
            uv1: vec![glam::Vec2::ZERO, glam::Vec2::NEG_ONE],
            tangents: vec![glam::Vec4::W, glam::Vec4::X],
            colors: vec![glam::Vec4::ONE, glam::Vec4::splat(0.5)],
            triangles: vec![[0, 1, 1], [1, 0, u32::MAX]],
            material: 3,
        };
        let bytes = bincode::serde::encode_to_vec(&mesh, cfg).unwrap();
        let (back, used): (MeshData, usize) =
            bincode::serde::decode_from_slice(&bytes, cfg).unwrap();
        assert_eq!((back, used), (mesh, bytes.len()));
        // The positions' byte string one byte short of two elements: refused, not truncated.
        #[derive(serde::Serialize)]
        struct Cut(#[serde(with = "serde_bytes_of")] Vec<u8>);
        mod serde_bytes_of {
            pub fn serialize<S: serde::Serializer>(v: &[u8], s: S) -> Result<S::Ok, S::Error> {
                s.serialize_bytes(v)
            }
        }
        let cut = bincode::serde::encode_to_vec(Cut(vec![0; 23]), cfg).unwrap();
        let e = bincode::serde::decode_from_slice::<MeshData, _>(&cut, cfg).unwrap_err();
        assert!(e.to_string().contains("whole number of elements"), "{e}");
    }

    #[test]
    fn chunks_are_the_same_bytes_and_ids_on_any_number_of_threads() {
        // Meshes of several sizes, in pieces of at most 50 triangles, one of them a stack of
        // the same triangle (a tree too deep for the walk: the piece is halved and rebuilt).
        let grid = |n: u32, z: f32, material: u32| {
            let mut m = MeshData {
                material,
                ..MeshData::default()
            };
            for j in 0..=n {
                for i in 0..=n {
                    let wave = ((i * 7 + j * 3) % 5) as f32 * 0.1;
                    m.positions.push(Vec3::new(i as f32, j as f32, z + wave));
                }
            }
            for j in 0..n {
                for i in 0..n {
                    let a = j * (n + 1) + i;
                    m.triangles.push([a, a + 1, a + n + 2]);
                    m.triangles.push([a, a + n + 2, a + n + 1]);
                }
            }
            m
        };
        let mut stack = grid(1, 0.0, 2);
        stack.triangles = vec![[0, 1, 3]; 300];
        let meshes = vec![grid(20, 0.0, 0), stack, grid(3, 5.0, 1), grid(13, -2.0, 0)];
        let opts = PrepareOptions {
            chunk_triangles: 50,
        };
        let one = build_chunks(&meshes, &opts, 1, true);
        let stacked = one.iter().filter(|c| c.header().mesh_id == 1).count();
        assert!(
            stacked > 300 / 50,
            "the stack's pieces were halved: {stacked} chunks"
        );
        assert!(one.len() > 20, "{} chunks", one.len());
        for (id, c) in one.iter().enumerate() {
            assert_eq!(c.header().chunk_id, id as u32);
        }
        for threads in [2, 3, 8] {
            assert_eq!(
                build_chunks(&meshes, &opts, threads, true),
                one,
                "{threads} threads"
            );
        }
        assert!(build_chunks(&[], &opts, 4, true).is_empty());
    }

    #[test]
    fn walking_forms_built_into_a_block_are_those_built_apart_and_are_walked_there() {
        use crate::region::testing::Lines;
        let opts = PrepareOptions {
            chunk_triangles: 64,
        };
        let (_, apart) = crate::prepare(crate::demo::demo_scene(), &opts);
        assert!(apart.chunks.len() > 4, "{} chunks", apart.chunks.len());
        let made = std::sync::atomic::AtomicUsize::new(0);
        let lines = |words: usize| -> Box<dyn BlockMut> {
            made.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            Box::new(Lines::new(words))
        };
        let (_, together) = prepare_with(crate::demo::demo_scene(), &opts, Some(&lines));
        assert_eq!(made.into_inner(), 1, "one block for the whole scene");
        assert_eq!(together.chunks, apart.chunks);
        for c in &together.chunks {
            assert!(c.accel().nodes.is_shared() && c.accel().leaves.is_shared());
        }
        // A block too small for them (not one the caller should make): each chunk keeps a
        // walking form of its own, the same.
        let short = |words: usize| -> Box<dyn BlockMut> { Box::new(Lines::new(words / 2)) };
        let (_, own) = prepare_with(crate::demo::demo_scene(), &opts, Some(&short));
        assert_eq!(own.chunks, apart.chunks);
        assert!(own.chunks.iter().all(|c| !c.accel().nodes.is_shared()));
    }

    /// Prepared for one process, the scene is one tree built straight into one block (its
    /// chunks without forms of their own), the tree `MemoryData::flatten` makes of the
    /// chunks' forms; in the heap where the block offered is too small; and the header is
    /// the same as a render node's.
    #[test]
    fn a_flat_tree_built_into_a_block_is_the_one_flattened_from_the_chunks() {
        use crate::region::testing::Lines;
        let opts = PrepareOptions {
            chunk_triangles: 64,
        };
        let (header, mut apart) = crate::prepare(crate::demo::demo_scene(), &opts);
        assert!(apart.flatten(&header));
        let want = apart.flat.as_ref().unwrap();
        let lines = |words: usize| -> Box<dyn BlockMut> { Box::new(Lines::new(words)) };
        let short = |words: usize| -> Box<dyn BlockMut> { Box::new(Lines::new(words / 2)) };
        for (make, shared) in [(&lines as MakeBlock<'_>, true), (&short, false)] {
            let (h, data) = prepare_flat(crate::demo::demo_scene(), &opts, make);
            assert_eq!(h, header);
            let got = data.flat.as_ref().expect("a flat tree");
            assert_eq!(got.form.nodes.is_shared(), shared);
            assert_eq!(got.form, want.form);
            assert!(data.chunks.iter().all(|c| c.accel().nodes.is_empty()));
            assert_eq!(data.chunks, apart.chunks);
        }
    }

    #[test]
    fn a_received_triangle_light_must_agree_with_its_corners() {
        let opts = PrepareOptions {
            chunk_triangles: 4096,
        };
        let (mut header, _) = crate::prepare(crate::demo::demo_scene(), &opts);
        header.validate().expect("a prepared header is valid");
        let i = header
            .lights
            .iter()
            .position(|l| matches!(l, Light::Triangle { .. }))
            .expect("the demo scene has an area light");
        if let Light::Triangle { area2, .. } = &mut header.lights[i] {
            *area2 *= 2.0;
        }
        let e = header.validate().unwrap_err().to_string();
        assert!(e.contains("disagrees with its corners"), "{e}");
    }

    /// A texture may sample an earlier texture's texels (one image under two samplers'
    /// settings): prepared, both name the same tiles, and a header from elsewhere may do so
    /// only for an earlier texture of the same size; a description only for an earlier one
    /// of its size that holds texels of its own.
    #[test]
    fn a_texture_may_share_an_earlier_ones_texels_and_tiles() {
        let opts = PrepareOptions {
            chunk_triangles: 4096,
        };
        let mut desc = crate::demo::demo_scene();
        let first = desc.textures[0].clone();
        desc.textures.push(TextureDesc {
            rgba: Vec::new(),
            filter: Filter::Nearest,
            texels_of: Some(0),
            ..first.clone()
        });
        desc.validate().expect("an earlier texture's texels");
        assert_eq!(desc.texels(1), &first.rgba[..]);
        let (header, _) = crate::prepare(desc.clone(), &opts);
        header.validate().expect("a prepared header is valid");
        let (a, b) = (&header.textures[0], &header.textures[1]);
        assert_eq!((a.first_tile, b.first_tile), (0, 0));
        assert_eq!(header.tile_count, a.tile_count(), "tiles made once");
        assert_eq!(b.filter, Filter::Nearest);

        let mut other_size = header.clone();
        other_size.textures[1].width -= 1;
        let e = other_size.validate().unwrap_err().to_string();
        assert!(e.contains("texture 1 starts at tile 0"), "{e}");

        for (what, change) in [("a later texture", 5u32), ("itself", 1)] {
            let mut bad = desc.clone();
            bad.textures[1].texels_of = Some(change);
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains("not an earlier texture"), "{what}: {e}");
        }
        let mut own_too = desc.clone();
        own_too.textures[1].rgba = first.rgba.clone();
        assert!(
            own_too.validate().is_err(),
            "texels both its own and shared"
        );
    }
}
