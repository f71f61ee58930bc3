//! Chunks: the unit of shape data that is cached and moved between nodes.
//!
//! A chunk is a spatially coherent piece of one mesh primitive (at most a configured number
//! of triangles) with its own wide BVH, stored as one flat, position-independent byte block:
//!
//! | section            | type             | count        |
//! |--------------------|------------------|--------------|
//! | header             | [`ChunkHeader`]  | 1            |
//! | tree nodes         | [`WideNode`] (8 x u32) | node_count |
//! | triangle positions | `[f32; 9]`       | tri_count    |
//! | triangle vertices  | `[u32; 3]`       | tri_count    |
//! | normals            | `[f32; 3]`       | vertex_count |
//! | uv0, uv1 (if flag) | `[f32; 2]`       | vertex_count |
//! | tangents (if flag) | `[f32; 4]`       | vertex_count |
//! | colours (if flag)  | `[f32; 4]`       | vertex_count |
//!
//! All fields are little-endian 4-byte words, so the block is valid wherever it lands as long
//! as it sits in 4-byte aligned memory, which [`Chunk`] guarantees by storing words. Triangles
//! are stored in BVH leaf order, so a leaf slot is a triangle index with no indirection.
//! [`Chunk::from_words`] validates bytes from elsewhere once; after that, every access is a
//! cast.

use bytemuck::{Pod, Zeroable};
use glam::{Vec2, Vec3, Vec3A, Vec4};
use obvhs::aabb::Aabb;

use crate::{
    accel::{Bvh8, Closest, WalkFormError, WalkPlace},
    bvh::{self, NodeError, Visit, WideNode},
    ray::RayQuery,
    region::Region,
    triangle::TriHit,
};

pub const CHUNK_MAGIC: u32 = u32::from_le_bytes(*b"MCHK");
pub const CHUNK_VERSION: u32 = 2;

pub const FLAG_UV0: u32 = 1;
pub const FLAG_UV1: u32 = 2;
pub const FLAG_TANGENTS: u32 = 4;
pub const FLAG_COLORS: u32 = 8;
pub const FLAG_NORMALS: u32 = 16;
const KNOWN_FLAGS: u32 = FLAG_UV0 | FLAG_UV1 | FLAG_TANGENTS | FLAG_COLORS | FLAG_NORMALS;

pub const NO_LIGHT: u32 = u32::MAX;

#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
#[repr(C)]
pub struct ChunkHeader {
    pub magic: u32,
    pub version: u32,
    pub chunk_id: u32,
    pub material: u32,
    pub node_count: u32,
    pub tri_count: u32,
    pub vertex_count: u32,
    pub flags: u32,
    /// Index in the scene's light list of this chunk's first triangle, when the material
    /// emits; triangle `i` is light `light_base + i`.
    pub light_base: u32,
    pub mesh_id: u32,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

const HEADER_WORDS: usize = size_of::<ChunkHeader>() / 4;
const NODE_WORDS: usize = size_of::<WideNode>() / 4;

/// Word offsets of each section, derived from the header.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Layout {
    nodes: usize,
    positions: usize,
    vertices: usize,
    normals: usize,
    uv0: usize,
    uv1: usize,
    tangents: usize,
    colors: usize,
    end: usize,
}

impl Layout {
    fn of(h: &ChunkHeader) -> Option<Layout> {
        let tris = h.tri_count as usize;
        let verts = h.vertex_count as usize;
        let mut at = HEADER_WORDS;
        let mut take = |words: usize| -> Option<usize> {
            let start = at;
            at = at.checked_add(words)?;
            Some(start)
        };
        let flag = |f: u32, words: usize| if h.flags & f != 0 { words } else { 0 };
        let nodes = take((h.node_count as usize).checked_mul(NODE_WORDS)?)?;
        let positions = take(tris.checked_mul(9)?)?;
        let vertices = take(tris.checked_mul(3)?)?;
        let normals = take(flag(FLAG_NORMALS, verts.checked_mul(3)?))?;
        let uv0 = take(flag(FLAG_UV0, verts.checked_mul(2)?))?;
        let uv1 = take(flag(FLAG_UV1, verts.checked_mul(2)?))?;
        let tangents = take(flag(FLAG_TANGENTS, verts.checked_mul(4)?))?;
        let colors = take(flag(FLAG_COLORS, verts.checked_mul(4)?))?;
        Some(Layout {
            nodes,
            positions,
            vertices,
            normals,
            uv0,
            uv1,
            tangents,
            colors,
            end: at,
        })
    }
}

/// Why a chunk's bytes were refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ChunkError {
    #[error("chunk is {0} bytes, shorter than its header")]
    TooShort(usize),
    #[error("chunk length {0} is not a multiple of 4")]
    Unaligned(usize),
    #[error("not a chunk (bad magic {0:#x})")]
    BadMagic(u32),
    #[error("chunk format version {0}, expected {CHUNK_VERSION}")]
    BadVersion(u32),
    #[error("chunk has unknown flags {0:#x}")]
    BadFlags(u32),
    #[error("chunk sections need {expected} bytes, the block has {actual}")]
    BadLength { expected: usize, actual: usize },
    #[error("chunk tree: {0}")]
    Nodes(#[from] NodeError),
    #[error("chunk triangle {tri} uses vertex {vertex}, but the chunk has {count}")]
    VertexOutOfRange { tri: usize, vertex: u32, count: u32 },
    #[error("chunk holds a non-finite value")]
    NonFinite,
    #[error("chunk {0}")]
    WalkForm(#[from] WalkFormError),
}

/// Whether every word, read as an `f32`, is finite (its exponent bits not all set). Written
/// as a branch-free OR over blocks so that it runs at memory speed: a render node checks
/// every chunk it reads, and reads most of a scene.
fn all_finite(words: &[u32]) -> bool {
    const EXPONENT: u32 = 0x7f80_0000;
    words.chunks(256).all(|block| {
        block
            .iter()
            .fold(0u32, |bad, &w| bad | u32::from(w & EXPONENT == EXPONENT))
            == 0
    })
}

/// One chunk: its wire layout in 4-byte aligned memory, and the walking form of its tree
/// ([`Bvh8`]) transcoded from it once it was known to be valid.
#[derive(Clone)]
pub struct Chunk {
    words: Region<u32>,
    layout: Layout,
    accel: Bvh8,
}

impl PartialEq for Chunk {
    /// The walking form is derived from the words, so the words decide.
    fn eq(&self, o: &Chunk) -> bool {
        self.words == o.words
    }
}

impl std::fmt::Debug for Chunk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Chunk")
            .field("header", self.header())
            .finish()
    }
}

impl Chunk {
    /// Takes ownership of words received from elsewhere and checks every offset, index and
    /// value once, so that later access can never read out of bounds or loop.
    pub fn from_words(words: Box<[u32]>) -> Result<Chunk, ChunkError> {
        Chunk::from_region(Region::own(words), None)
    }

    /// Checks words as [`Chunk::from_words`] does, wherever they lie (a card's memory mapped
    /// into this process, for one), and transcodes the walking form from them; or, given
    /// `walk`, reads the walking form in place too (checked by [`Bvh8::in_block`]).
    ///
    /// A chunk read in place is checked for what a pass over its header and tree nodes can
    /// see: its layout, header and the tree's shape. Its values (positions, attributes) and
    /// indices (a leaf's triangles, a triangle's vertices) are checked where they are read
    /// instead: a triangle id out of range is never hit, a vertex index out of range reads
    /// NaN (a bad sample, counted in the stats), a value that is not finite makes the samples
    /// that meet it bad. Checking them up front would mean reading the whole chunk before
    /// its first ray, on every render node of the card: on an 86-process cluster that was an
    /// eighth of all the CPU time of a render (and more in faulting the pages in), for data
    /// most rays never touch.
    pub fn from_region(words: Region<u32>, walk: Option<WalkPlace>) -> Result<Chunk, ChunkError> {
        if words.len() < HEADER_WORDS {
            return Err(ChunkError::TooShort(words.len() * 4));
        }
        let header: ChunkHeader =
            *bytemuck::from_bytes(bytemuck::cast_slice(&words[..HEADER_WORDS]));
        if header.magic != CHUNK_MAGIC {
            return Err(ChunkError::BadMagic(header.magic));
        }
        if header.version != CHUNK_VERSION {
            return Err(ChunkError::BadVersion(header.version));
        }
        if header.flags & !KNOWN_FLAGS != 0 {
            return Err(ChunkError::BadFlags(header.flags));
        }
        let layout = Layout::of(&header).ok_or(ChunkError::BadLength {
            expected: usize::MAX,
            actual: words.len() * 4,
        })?;
        if layout.end != words.len() {
            return Err(ChunkError::BadLength {
                expected: layout.end * 4,
                actual: words.len() * 4,
            });
        }
        let chunk = Chunk {
            words,
            layout,
            accel: Bvh8::default(),
        };
        let bounds: [f32; 6] = bytemuck::cast([header.bounds_min, header.bounds_max]);
        if !all_finite(bytemuck::cast_slice(&bounds)) {
            return Err(ChunkError::NonFinite);
        }
        if let Some(w) = walk {
            let accel = Bvh8::in_block(w.block, w.start, w.end, header.tri_count)?;
            return Ok(Chunk { accel, ..chunk });
        }
        if !all_finite(&chunk.words[layout.positions..layout.vertices])
            || !all_finite(&chunk.words[layout.normals..layout.end])
        {
            return Err(ChunkError::NonFinite);
        }
        // The largest index first (a branch-free pass), the culprit only if there is one.
        let indices: &[u32] = bytemuck::cast_slice(chunk.tri_vertices());
        if indices.iter().fold(0, |m, &v| m.max(v)) >= header.vertex_count && !indices.is_empty() {
            let at = indices
                .iter()
                .position(|&v| v >= header.vertex_count)
                .unwrap_or(0);
            return Err(ChunkError::VertexOutOfRange {
                tri: at / 3,
                vertex: indices[at],
                count: header.vertex_count,
            });
        }
        bvh::validate_tree(chunk.nodes(), header.tri_count as usize)?;
        Ok(chunk.transcoded())
    }

    /// Builds the walking form; only ever called on valid words.
    fn transcoded(mut self) -> Chunk {
        self.transcode();
        self
    }

    /// Builds the walking form, in memory of the chunk's own.
    pub(crate) fn transcode(&mut self) {
        self.accel = self.walking_form();
    }

    /// This chunk's walking form, built in memory of its own.
    pub(crate) fn walking_form(&self) -> Bvh8 {
        Bvh8::for_chunk(self.nodes(), self.tri_positions())
    }

    /// The nodes and blocks of this chunk's walking form, from its tree's shape, without
    /// building it.
    pub(crate) fn walk_counts(&self) -> (usize, usize) {
        (self.nodes().len(), Bvh8::leaf_count(self.nodes()))
    }

    /// How many words this chunk's walking form takes as [`Bvh8::to_words`] writes it, from
    /// its tree's shape, without building it.
    pub(crate) fn walk_words_len(&self) -> usize {
        Bvh8::words_len_for(self.nodes())
    }

    /// Builds the walking form into `out` (as [`Bvh8::to_words`] writes it); false, with
    /// nothing written, if `out` is not its length.
    pub(crate) fn transcode_into(&self, out: &mut [u32]) -> bool {
        let form = self.walking_form();
        if form.words_len() != out.len() {
            return false;
        }
        form.write_words(out);
        true
    }

    /// Walks this chunk's tree where `place` holds it (as [`Bvh8::to_words`] wrote it)
    /// instead of in memory of its own, after checking it as any walking form read in place
    /// is checked; on error the chunk is left as it was.
    pub fn walk_in(&mut self, place: WalkPlace) -> Result<(), WalkFormError> {
        self.accel = Bvh8::in_block(place.block, place.start, place.end, self.tri_count())?;
        Ok(())
    }

    /// Whether the words and walking form lie in a shared block rather than in this
    /// process's own memory.
    pub fn is_shared(&self) -> bool {
        self.words.is_shared()
    }

    /// The tree in the form rays walk.
    #[inline(always)]
    pub fn accel(&self) -> &Bvh8 {
        &self.accel
    }

    /// Drops the walking form, for data whose queries walk every chunk's tree as one
    /// ([`crate::source::MemoryData::flatten`]): the chunk's tree is then empty.
    pub fn drop_walk(&mut self) {
        self.accel = Bvh8::default();
    }

    /// Bytes of a chunk as received (any alignment): copied once into aligned words.
    pub fn from_bytes(bytes: &[u8]) -> Result<Chunk, ChunkError> {
        if !bytes.len().is_multiple_of(4) {
            return Err(ChunkError::Unaligned(bytes.len()));
        }
        let words: Box<[u32]> = bytes
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        Chunk::from_words(words)
    }

    pub fn words(&self) -> &[u32] {
        &self.words
    }

    pub fn as_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.words)
    }

    pub fn byte_len(&self) -> usize {
        self.words.len() * 4
    }

    /// Bytes this chunk takes once it can be walked: its words and its walking form, wherever
    /// they lie (a cache counts a chunk walked in a card's shared memory as one it copied).
    pub fn memory_bytes(&self) -> usize {
        // A chunk whose tree was built into a flat tree (`scene::prepare_flat`) has no form of
        // its own: it counts the one it would have, so the header says the same either way.
        let form = if self.accel.nodes.is_empty() && self.accel.leaves.is_empty() {
            let (nodes, blocks) = self.walk_counts();
            nodes * size_of::<crate::accel::Node8>() + blocks * size_of::<crate::accel::Tri4>()
        } else {
            self.accel.byte_len()
        };
        self.byte_len() + form
    }

    // The accessors below are read on every hit; out of line, each call redid bytemuck's
    // length and alignment checks behind a call (1.1% of a Cornell box sample).
    #[inline(always)]
    pub fn header(&self) -> &ChunkHeader {
        bytemuck::from_bytes(bytemuck::cast_slice(&self.words[..HEADER_WORDS]))
    }

    pub fn nodes(&self) -> &[WideNode] {
        bytemuck::cast_slice(&self.words[self.layout.nodes..self.layout.positions])
    }

    #[inline(always)]
    pub fn tri_positions(&self) -> &[[f32; 9]] {
        bytemuck::cast_slice(&self.words[self.layout.positions..self.layout.vertices])
    }

    #[inline(always)]
    pub fn tri_vertices(&self) -> &[[u32; 3]] {
        bytemuck::cast_slice(&self.words[self.layout.vertices..self.layout.normals])
    }

    #[inline(always)]
    fn section<T: Pod>(&self, start: usize, end: usize) -> &[T] {
        bytemuck::cast_slice(&self.words[start..end])
    }

    pub fn tri_count(&self) -> u32 {
        self.header().tri_count
    }

    /// Closest hit in (0, tmax) within this chunk; `tmax` shrinks to the hit. Equal distances
    /// go to the lower triangle index.
    #[inline]
    pub fn intersect(&self, q: &RayQuery, tmax: &mut f32) -> Option<(u32, TriHit)> {
        self.intersect_with(q, tmax, |_, _| true)
    }

    /// Closest hit in (0, tmax) that `accept` agrees to (alpha-tested surfaces say no where
    /// they are transparent); `tmax` shrinks to the hit.
    #[inline]
    pub fn intersect_with<A: FnMut(u32, &TriHit) -> bool>(
        &self,
        q: &RayQuery,
        tmax: &mut f32,
        accept: A,
    ) -> Option<(u32, TriHit)> {
        let mut best = Closest::new(*tmax);
        if !self.accel.closest(q, 0, &mut best, accept) {
            return None;
        }
        *tmax = best.t;
        best.hit.map(|h| (best.tri, h))
    }

    /// Every triangle hit in (0, tmax), in no particular order, until `f` says stop.
    #[inline]
    pub fn for_each_hit<F: FnMut(u32, TriHit) -> Visit>(&self, q: &RayQuery, tmax: f32, f: F) {
        self.accel.each_hit(q, tmax, f);
    }

    /// Surface attributes of triangle `tri` at barycentrics `hit`, every one the chunk has.
    pub fn surface(&self, tri: u32, hit: &TriHit) -> SurfaceAttributes {
        self.surface_reading(tri, hit, || Reads::ALL)
    }

    /// Surface attributes of triangle `tri` at barycentrics `hit`, leaving out (as `None`)
    /// the optional ones that `reads` says shading will not read; it is asked only when the
    /// chunk has such attributes. Those given are the bits [`Chunk::surface`] gives.
    #[inline]
    pub fn surface_reading(
        &self,
        tri: u32,
        hit: &TriHit,
        reads: impl FnOnce() -> Reads,
    ) -> SurfaceAttributes {
        let h = self.header();
        let reads = if h.flags & (FLAG_UV0 | FLAG_UV1 | FLAG_TANGENTS) != 0 {
            reads()
        } else {
            Reads::ALL
        };
        let l = &self.layout;
        let p = &self.tri_positions()[tri as usize];
        let (v0, v1, v2) = tri_points(p);
        let idx = self.tri_vertices()[tri as usize].map(|i| i as usize);
        let b = [hit.b0, hit.b1, hit.b2];

        // Point and its rounding error bound (pbrt-v4: gamma(7) of the barycentric sum).
        let p = v0 * b[0] + v1 * b[1] + v2 * b[2];
        let p_abs = (v0 * b[0]).abs() + (v1 * b[1]).abs() + (v2 * b[2]).abs();
        let p_error = p_abs * crate::math::gamma(7);

        let ng = (v1 - v0).cross(v2 - v0);
        let area2 = ng.length();
        let ng = if area2 > 0.0 { ng / area2 } else { Vec3A::Z };

        let interp3 = |data: &[[f32; 3]]| -> Vec3 {
            Vec3::from(vertex(data, idx[0])) * b[0]
                + Vec3::from(vertex(data, idx[1])) * b[1]
                + Vec3::from(vertex(data, idx[2])) * b[2]
        };
        let interp4 = |data: &[[f32; 4]]| -> Vec4 {
            Vec4::from(vertex(data, idx[0])) * b[0]
                + Vec4::from(vertex(data, idx[1])) * b[1]
                + Vec4::from(vertex(data, idx[2])) * b[2]
        };

        let ns = if h.flags & FLAG_NORMALS != 0 {
            let n = interp3(self.section(l.normals, l.uv0));
            let len = n.length();
            if len > 1e-12 && len.is_finite() {
                n / len
            } else {
                Vec3::from(ng)
            }
        } else {
            Vec3::from(ng)
        };
        // Texture coordinates serve textures and, with the first set, the tangent frame.
        let uv = reads.uv || reads.frame;
        let uv_of = |flag: u32, start: usize, end: usize| -> Option<[Vec2; 3]> {
            (uv && h.flags & flag != 0).then(|| {
                let data: &[[f32; 2]] = self.section(start, end);
                idx.map(|i| Vec2::from(vertex(data, i)))
            })
        };
        let uv0 = uv_of(FLAG_UV0, l.uv0, l.uv1);
        let uv1 = uv_of(FLAG_UV1, l.uv1, l.tangents);
        let tangent = (reads.frame && h.flags & FLAG_TANGENTS != 0)
            .then(|| interp4(self.section(l.tangents, l.colors)));
        let color = (h.flags & FLAG_COLORS != 0).then(|| interp4(self.section(l.colors, l.end)));

        // dp/du and dp/dv from the first UV set, for normal mapping and texture footprints.
        let dpdu = uv0.filter(|_| reads.frame).and_then(|uv| {
            let duv02 = uv[0] - uv[2];
            let duv12 = uv[1] - uv[2];
            let dp02 = Vec3::from(v0 - v2);
            let dp12 = Vec3::from(v1 - v2);
            let det = duv02.x * duv12.y - duv02.y * duv12.x;
            if det.abs() < 1e-20 {
                return None;
            }
            let inv = 1.0 / det;
            let dpdu = (dp02 * duv12.y - dp12 * duv02.y) * inv;
            let dpdv = (dp12 * duv02.x - dp02 * duv12.x) * inv;
            (dpdu.is_finite() && dpdv.is_finite()).then_some((dpdu, dpdv))
        });

        SurfaceAttributes {
            p,
            p_error,
            ng: Vec3::from(ng),
            ns,
            uv0: uv0.map(|uv| uv[0] * b[0] + uv[1] * b[1] + uv[2] * b[2]),
            uv1: uv1.map(|uv| uv[0] * b[0] + uv[1] * b[1] + uv[2] * b[2]),
            tangent,
            color,
            dpdu,
            area: area2 * 0.5,
            material: h.material,
            light: if h.light_base == NO_LIGHT {
                NO_LIGHT
            } else {
                h.light_base + tri
            },
        }
    }
}

/// Vertex `i` of an attribute array; NaN where `i` is out of range, which only a chunk read
/// in place can have (its vertex indices are checked here, see [`Chunk::from_region`]).
#[inline(always)]
fn vertex<const N: usize>(data: &[[f32; N]], i: usize) -> [f32; N] {
    data.get(i).copied().unwrap_or([f32::NAN; N])
}

#[inline(always)]
pub fn tri_points(p: &[f32; 9]) -> (Vec3A, Vec3A, Vec3A) {
    (
        Vec3A::new(p[0], p[1], p[2]),
        Vec3A::new(p[3], p[4], p[5]),
        Vec3A::new(p[6], p[7], p[8]),
    )
}

/// Which of a hit's optional attributes shading will read ([`Chunk::surface_reading`]):
/// those it will not are not worked out. A Lambertian wall with no textures needs neither.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Reads {
    /// Texture coordinates: some texture is sampled.
    pub uv: bool,
    /// The tangent frame (the interpolated tangent, dp/du and dp/dv): a normal map.
    pub frame: bool,
}

impl Reads {
    pub const ALL: Reads = Reads {
        uv: true,
        frame: true,
    };
}

/// What shading needs to know about a hit point.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceAttributes {
    pub p: Vec3A,
    pub p_error: Vec3A,
    /// Geometric normal, unit, following the triangle's winding (v0, v1, v2 counter-clockwise).
    pub ng: Vec3,
    /// Interpolated shading normal, unit (the geometric one when the mesh has none).
    pub ns: Vec3,
    pub uv0: Option<Vec2>,
    pub uv1: Option<Vec2>,
    pub tangent: Option<Vec4>,
    pub color: Option<Vec4>,
    pub dpdu: Option<(Vec3, Vec3)>,
    pub area: f32,
    pub material: u32,
    pub light: u32,
}

/// A mesh primitive in world space, ready to be cut into chunks. Attribute arrays are either
/// empty or as long as `positions`. In serde each array is one byte string (`pod_vec` in
/// `scene.rs`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeshData {
    #[serde(with = "crate::scene::pod_vec")]
    pub positions: Vec<Vec3>,
    #[serde(with = "crate::scene::pod_vec")]
    pub normals: Vec<Vec3>,
    #[serde(with = "crate::scene::pod_vec")]
    pub uv0: Vec<Vec2>,
    #[serde(with = "crate::scene::pod_vec")]
    pub uv1: Vec<Vec2>,
    #[serde(with = "crate::scene::pod_vec")]
    pub tangents: Vec<Vec4>,
    #[serde(with = "crate::scene::pod_vec")]
    pub colors: Vec<Vec4>,
    #[serde(with = "crate::scene::pod_vec")]
    pub triangles: Vec<[u32; 3]>,
    pub material: u32,
}

/// Cuts `mesh` into spatially coherent pieces of at most `max_tris` triangles: triangles are
/// ordered along a Morton curve of their centroids, then the order is split recursively at
/// the highest bit in which the codes differ (an octree's planes, one axis at a time), so
/// every piece is a box of the octree, or part of one. The octree's cells are cubes (one
/// scale for the three axes): a flat mesh, such as a terrain, is cut into tiles, not into
/// layers of its height that a ray leaving the surface would all cross. Deterministic.
pub fn split_mesh(mesh: &MeshData, max_tris: usize) -> Vec<Vec<u32>> {
    let max_tris = max_tris.max(1);
    let centroid = |t: &[u32; 3]| {
        (mesh.positions[t[0] as usize]
            + mesh.positions[t[1] as usize]
            + mesh.positions[t[2] as usize])
            / 3.0
    };
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for t in &mesh.triangles {
        let c = centroid(t);
        lo = lo.min(c);
        hi = hi.max(c);
    }
    let scale =
        Vec3::splat(((1u32 << 10) - 1) as f32 / (hi - lo).max_element().max(f32::MIN_POSITIVE));
    let codes: Vec<u32> = mesh
        .triangles
        .iter()
        .map(|t| {
            let q = ((centroid(t) - lo) * scale).max(Vec3::ZERO);
            morton3(q.to_array().map(|v| (v as u32).min((1 << 10) - 1)))
        })
        .collect();
    let keyed = radix_sort(&codes);
    let mut out = Vec::new();
    // (start, end, highest bit still to split on)
    let mut work = vec![(0usize, keyed.len(), 29u32)];
    while let Some((start, end, bit)) = work.pop() {
        if end - start <= max_tris {
            out.push(keyed[start..end].iter().map(|k| k.1).collect());
            continue;
        }
        let range = &keyed[start..end];
        // The codes share every bit above `bit`: split where `bit` turns on, else go lower.
        let (mid, next) = match (0..=bit)
            .rev()
            .map(|b| (b, range.partition_point(|k| k.0 & (1u32 << b) == 0)))
            .find(|&(_, m)| m > 0 && m < range.len())
        {
            Some((b, m)) => (start + m, b.saturating_sub(1)),
            // Identical codes: halve.
            None => (start + range.len() / 2, 0),
        };
        // Right first, so pieces come out in curve order.
        work.push((mid, end, next));
        work.push((start, mid, next));
    }
    out
}

/// Interleaves the bits of three 10-bit numbers (x lowest).
fn morton3(c: [u32; 3]) -> u32 {
    let spread = |v: u32| {
        let mut x = v & 0x3ff;
        x = (x | x << 16) & 0x0300_00ff;
        x = (x | x << 8) & 0x0300_f00f;
        x = (x | x << 4) & 0x030c_30c3;
        (x | x << 2) & 0x0924_9249
    };
    spread(c[0]) | spread(c[1]) << 1 | spread(c[2]) << 2
}

/// (code, index) pairs ordered by code, then index: a stable least-significant-digit radix
/// sort, three passes of ten bits (the codes have thirty).
fn radix_sort(codes: &[u32]) -> Vec<(u32, u32)> {
    let mut a: Vec<(u32, u32)> = codes
        .iter()
        .enumerate()
        .map(|(i, &c)| (c, i as u32))
        .collect();
    let mut b = vec![(0u32, 0u32); a.len()];
    for pass in 0..3 {
        let shift = 10 * pass;
        let mut count = [0usize; 1025];
        for &(c, _) in &a {
            count[((c >> shift) & 0x3ff) as usize + 1] += 1;
        }
        for i in 1..1025 {
            count[i] += count[i - 1];
        }
        for &e in &a {
            let d = ((e.0 >> shift) & 0x3ff) as usize;
            b[count[d]] = e;
            count[d] += 1;
        }
        std::mem::swap(&mut a, &mut b);
    }
    a
}

/// Builds the chunk for the triangles `tris` of `mesh` (with a tree of their own), or `None`
/// when that tree comes out deeper than the walk allows (only degenerate clusters of
/// coincident triangles do that; the caller then splits the piece and tries again).
pub fn build_chunk(mesh: &MeshData, tris: &[u32], chunk_id: u32, mesh_id: u32) -> Option<Chunk> {
    let mut wide = bvh::build(&triangle_boxes(mesh, tris), bvh::MAX_LEAF);
    for t in &mut wide.order {
        *t = tris[*t as usize];
    }
    build_chunk_from(mesh, &wide, chunk_id, mesh_id, &mut Vec::new())
}

/// The box of each of `tris`.
pub fn triangle_boxes(mesh: &MeshData, tris: &[u32]) -> Vec<Aabb> {
    tris.iter()
        .map(|&t| {
            let [a, b, c] =
                mesh.triangles[t as usize].map(|i| Vec3A::from(mesh.positions[i as usize]));
            Aabb::new(a.min(b).min(c), a.max(b).max(c))
        })
        .collect()
}

/// Builds a chunk from its tree, whose leaf order names `mesh`'s triangles; `None` when the
/// tree is deeper than the walk allows. `remap` is scratch space for the vertex numbering
/// (kept between calls for one mesh, so each chunk costs only what it holds).
pub fn build_chunk_from(
    mesh: &MeshData,
    wide: &bvh::WideTree,
    chunk_id: u32,
    mesh_id: u32,
    remap: &mut Vec<u32>,
) -> Option<Chunk> {
    chunk_words_from(mesh, wide, chunk_id, mesh_id, remap).map(Chunk::transcoded)
}

/// As [`build_chunk_from`], without the walking form (for a caller that places it).
pub(crate) fn chunk_words_from(
    mesh: &MeshData,
    wide: &bvh::WideTree,
    chunk_id: u32,
    mesh_id: u32,
    remap: &mut Vec<u32>,
) -> Option<Chunk> {
    if bvh::validate_tree(&wide.nodes, wide.order.len()).is_err() {
        return None;
    }
    let ordered = &wide.order;

    // Chunk-local vertices, first use first.
    if remap.len() < mesh.positions.len() {
        remap.resize(mesh.positions.len(), u32::MAX);
    }
    let mut local_vertices: Vec<u32> = Vec::new();
    let mut tri_vertices = Vec::with_capacity(ordered.len());
    for &t in ordered {
        let idx = mesh.triangles[t as usize].map(|v| {
            let slot = &mut remap[v as usize];
            if *slot == u32::MAX {
                *slot = local_vertices.len() as u32;
                local_vertices.push(v);
            }
            *slot
        });
        tri_vertices.push(idx);
    }
    for &v in &local_vertices {
        remap[v as usize] = u32::MAX;
    }

    let has = |len: usize| len == mesh.positions.len() && len > 0;
    let mut flags = 0;
    if has(mesh.normals.len()) {
        flags |= FLAG_NORMALS;
    }
    if has(mesh.uv0.len()) {
        flags |= FLAG_UV0;
    }
    if has(mesh.uv1.len()) {
        flags |= FLAG_UV1;
    }
    if has(mesh.tangents.len()) {
        flags |= FLAG_TANGENTS;
    }
    if has(mesh.colors.len()) {
        flags |= FLAG_COLORS;
    }

    let mut bounds = Aabb::empty();
    for &v in &local_vertices {
        let p = Vec3A::from(mesh.positions[v as usize]);
        bounds = Aabb::new(bounds.min.min(p), bounds.max.max(p));
    }
    let header = ChunkHeader {
        magic: CHUNK_MAGIC,
        version: CHUNK_VERSION,
        chunk_id,
        material: mesh.material,
        node_count: wide.nodes.len() as u32,
        tri_count: ordered.len() as u32,
        vertex_count: local_vertices.len() as u32,
        flags,
        light_base: NO_LIGHT,
        mesh_id,
        bounds_min: Vec3::from(bounds.min).into(),
        bounds_max: Vec3::from(bounds.max).into(),
    };

    let layout = Layout::of(&header)?;
    // One allocation of the chunk's final size: grown as it was written, it was copied
    // again at each doubling.
    let mut words: Vec<u32> = Vec::with_capacity(layout.end);
    words.extend_from_slice(bytemuck::cast_slice(&[header]));
    words.extend_from_slice(bytemuck::cast_slice(&wide.nodes));
    for &t in ordered {
        let [a, b, c] = mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
        let p = [a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z];
        words.extend_from_slice(bytemuck::cast_slice(&p));
    }
    words.extend_from_slice(bytemuck::cast_slice(&tri_vertices));
    // Each chunk-local vertex's attribute, in local order (no allocation per vertex).
    fn gather<T: bytemuck::Pod>(words: &mut Vec<u32>, local: &[u32], values: &[T]) {
        for &v in local {
            words.extend_from_slice(bytemuck::cast_slice(std::slice::from_ref(
                &values[v as usize],
            )));
        }
    }
    if flags & FLAG_NORMALS != 0 {
        gather(&mut words, &local_vertices, &mesh.normals);
    }
    if flags & FLAG_UV0 != 0 {
        gather(&mut words, &local_vertices, &mesh.uv0);
    }
    if flags & FLAG_UV1 != 0 {
        gather(&mut words, &local_vertices, &mesh.uv1);
    }
    if flags & FLAG_TANGENTS != 0 {
        gather(&mut words, &local_vertices, &mesh.tangents);
    }
    if flags & FLAG_COLORS != 0 {
        gather(&mut words, &local_vertices, &mesh.colors);
    }
    debug_assert_eq!(layout.end, words.len());
    let chunk = Chunk {
        words: words.into(),
        layout,
        accel: Bvh8::default(),
    };
    Some(chunk)
}

impl Chunk {
    /// Sets the chunk's id (done once every chunk of the scene is built, in order).
    pub fn set_chunk_id(&mut self, id: u32) {
        self.header_mut().chunk_id = id;
    }

    /// Sets the light index of the first triangle (done once the scene's light list exists).
    pub fn set_light_base(&mut self, base: u32) {
        self.header_mut().light_base = base;
    }

    /// The header of a chunk being made here (its words are this process's own).
    fn header_mut(&mut self) -> &mut ChunkHeader {
        bytemuck::from_bytes_mut(bytemuck::cast_slice_mut(
            &mut self.words.make_mut()[..HEADER_WORDS],
        ))
    }

    pub fn bounds(&self) -> Aabb {
        let h = self.header();
        Aabb::new(Vec3A::from(h.bounds_min), Vec3A::from(h.bounds_max))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ray::Ray, triangle};

    fn grid_mesh(n: usize) -> MeshData {
        let mut m = MeshData::default();
        for j in 0..=n {
            for i in 0..=n {
                m.positions
                    .push(Vec3::new(i as f32, j as f32, ((i * j) % 3) as f32 * 0.1));
                m.uv0
                    .push(Vec2::new(i as f32 / n as f32, j as f32 / n as f32));
            }
        }
        let w = (n + 1) as u32;
        for j in 0..n as u32 {
            for i in 0..n as u32 {
                let a = j * w + i;
                m.triangles.push([a, a + 1, a + w + 1]);
                m.triangles.push([a, a + w + 1, a + w]);
            }
        }
        m
    }

    #[test]
    fn split_covers_every_triangle_once() {
        let m = grid_mesh(40);
        let pieces = split_mesh(&m, 100);
        let mut seen = vec![0; m.triangles.len()];
        for p in &pieces {
            assert!(p.len() <= 100);
            for &t in p {
                seen[t as usize] += 1;
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
    }

    /// A flat mesh (a terrain) is cut into tiles across its extent, not into layers of its
    /// small height: the pieces' footprints barely overlap (layers would each cover the
    /// footprint of the layer above, and a ray leaving the surface would cross them all).
    #[test]
    fn a_flat_mesh_is_cut_into_tiles_not_layers() {
        let m = grid_mesh(64);
        let pieces = split_mesh(&m, 256);
        assert!(pieces.len() >= 32, "{} pieces", pieces.len());
        let footprint = |tris: &mut dyn Iterator<Item = u32>| {
            let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for t in tris {
                for v in m.triangles[t as usize] {
                    lo = lo.min(m.positions[v as usize]);
                    hi = hi.max(m.positions[v as usize]);
                }
            }
            (hi.x - lo.x) * (hi.y - lo.y)
        };
        let whole = footprint(&mut (0..m.triangles.len() as u32));
        let sum: f32 = pieces
            .iter()
            .map(|p| footprint(&mut p.iter().copied()))
            .sum();
        assert!(
            sum < 1.3 * whole,
            "pieces cover {sum} of a footprint of {whole}"
        );
    }

    #[test]
    fn chunk_round_trips_through_bytes_and_hits_like_brute_force() {
        let m = grid_mesh(20);
        let all: Vec<u32> = (0..m.triangles.len() as u32).collect();
        let chunk = build_chunk(&m, &all, 7, 0).expect("chunk");
        let again = Chunk::from_bytes(chunk.as_bytes()).expect("valid chunk");
        assert_eq!(again, chunk);
        for i in 0..200 {
            let o = Vec3::new(0.37 + i as f32 * 0.09, 0.21 + (i % 13) as f32 * 1.3, 5.0);
            let ray = Ray::infinite(o, Vec3::new(0.05, 0.02, -1.0).normalize());
            let q = RayQuery::new(&ray);
            let mut tmax = f32::INFINITY;
            let got = again.intersect(&q, &mut tmax).map(|(_, h)| h.t);
            let mut brute: Option<f32> = None;
            for p in again.tri_positions() {
                let (a, b, c) = tri_points(p);
                if let Some(h) = triangle::intersect(&q, a, b, c, f32::INFINITY) {
                    brute = Some(brute.map_or(h.t, |t: f32| t.min(h.t)));
                }
            }
            assert_eq!(got, brute, "ray {i}");
        }
    }

    #[test]
    fn a_surface_read_in_part_gives_the_bits_of_the_whole_and_skips_the_rest() {
        let mut m = grid_mesh(4);
        m.normals = m.positions.iter().map(|_| Vec3::Z).collect();
        m.tangents = m
            .positions
            .iter()
            .map(|_| Vec4::new(1.0, 0.0, 0.0, 1.0))
            .collect();
        let all: Vec<u32> = (0..m.triangles.len() as u32).collect();
        let chunk = build_chunk(&m, &all, 3, 0).expect("chunk");
        let bits = |v: Option<Vec2>| v.map(|v| v.to_array().map(f32::to_bits));
        for tri in 0..chunk.tri_count() {
            let hit = TriHit {
                t: 1.0,
                b0: 0.2,
                b1: 0.3,
                b2: 0.5,
            };
            let whole = chunk.surface(tri, &hit);
            assert!(whole.uv0.is_some() && whole.tangent.is_some() && whole.dpdu.is_some());
            for (uv, frame) in [(false, false), (true, false), (false, true), (true, true)] {
                let part = chunk.surface_reading(tri, &hit, || Reads { uv, frame });
                assert_eq!(part.p.to_array(), whole.p.to_array());
                assert_eq!(part.p_error.to_array(), whole.p_error.to_array());
                assert_eq!(part.ng.to_array(), whole.ng.to_array());
                assert_eq!(part.ns.to_array(), whole.ns.to_array());
                assert_eq!(part.light, whole.light);
                let read_uv = uv || frame;
                assert_eq!(bits(part.uv0), bits(whole.uv0).filter(|_| read_uv));
                assert_eq!(part.tangent.is_some(), frame);
                assert_eq!(part.dpdu.is_some(), frame);
                if frame {
                    assert_eq!(part.tangent, whole.tangent);
                    assert_eq!(part.dpdu, whole.dpdu);
                }
            }
        }
        // A chunk with no optional attributes never asks what will be read.
        let plain = grid_mesh(2);
        let plain = MeshData {
            uv0: Vec::new(),
            ..plain
        };
        let all: Vec<u32> = (0..plain.triangles.len() as u32).collect();
        let chunk = build_chunk(&plain, &all, 0, 0).expect("chunk");
        let hit = TriHit {
            t: 1.0,
            b0: 0.3,
            b1: 0.3,
            b2: 0.4,
        };
        let s = chunk.surface_reading(0, &hit, || panic!("asked what is read"));
        assert!(s.uv0.is_none() && s.tangent.is_none() && s.dpdu.is_none());
    }

    #[test]
    fn corrupted_bytes_are_refused_not_trusted() {
        let mut m = grid_mesh(5);
        m.normals = m
            .positions
            .iter()
            .map(|_| Vec3::new(0.0, 0.6, 0.8))
            .collect();
        let all: Vec<u32> = (0..m.triangles.len() as u32).collect();
        let chunk = build_chunk(&m, &all, 0, 0).expect("chunk");
        let bytes = chunk.as_bytes().to_vec();
        assert!(Chunk::from_bytes(&bytes[..bytes.len() - 4]).is_err());
        assert!(Chunk::from_bytes(&bytes[..10]).is_err());
        let mut bad = bytes.clone();
        bad[0] ^= 0xff;
        assert!(matches!(
            Chunk::from_bytes(&bad),
            Err(ChunkError::BadMagic(_))
        ));
        // A vertex index far out of range.
        let mut words: Vec<u32> = chunk.words().to_vec();
        let h = *chunk.header();
        let vert_at = HEADER_WORDS + h.node_count as usize * NODE_WORDS + h.tri_count as usize * 9;
        words[vert_at] = 1_000_000;
        assert!(matches!(
            Chunk::from_words(words.clone().into_boxed_slice()),
            Err(ChunkError::VertexOutOfRange { .. })
        ));

        // Read in place, the same index and a position that is not finite are checked where
        // they are read: the chunk is taken, the surface of the triangle reads NaN texture
        // coordinates (a bad sample) instead of reading out of bounds, the rest is intact.
        words[HEADER_WORDS + h.node_count as usize * NODE_WORDS + 9] = f32::NAN.to_bits();
        let walk = chunk.accel().to_words();
        let (block, places) = crate::region::testing::aligned_block(&[&words, &walk]);
        let [(start, words_end), (walk_start, walk_end)] = places[..] else {
            unreachable!("two parts")
        };
        let place = WalkPlace {
            block: block.clone(),
            start: walk_start,
            end: walk_end,
        };
        let region = Region::in_block(block, start, words_end).expect("in the block");
        let read = Chunk::from_region(region, Some(place)).expect("taken as it lies");
        let hit = TriHit {
            t: 1.0,
            b0: 0.2,
            b1: 0.3,
            b2: 0.5,
        };
        let s = read.surface(0, &hit);
        assert!(s.uv0.is_some_and(|uv| uv.is_nan()));
        assert_eq!(
            s.ns, s.ng,
            "a normal that cannot be read is the geometric one"
        );
        assert_ne!(chunk.surface(0, &hit).ns, s.ng);
        let s = read.surface(1, &hit);
        assert!(s.p.is_nan(), "triangle 1 has a position that is not finite");
        assert_eq!(
            read.surface(2, &hit).uv0.map(|uv| uv.to_array()),
            chunk.surface(2, &hit).uv0.map(|uv| uv.to_array())
        );
    }
}
