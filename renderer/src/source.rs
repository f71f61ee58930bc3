//! Where shape and texture data come from while rendering.
//!
//! The renderer reads chunks and texture tiles only through [`SceneData`]. In one process
//! the data is all in memory ([`MemoryData`]); on a render node it is a bounded cache that
//! fetches what is missing from the fork node's shared memory. The renderer cannot tell the
//! two apart, which is why an image is the same bytes either way.

use std::{cell::Cell, ops::Deref};

use crate::{accel::Bvh8, chunk::Chunk, scene::SceneHeader, texture::Tile, trace::SurfaceKind};

/// A chunk or tile could not be had.
#[derive(Debug, Clone, thiserror::Error, PartialEq)]
pub enum DataError {
    #[error("chunk {0} does not exist")]
    NoChunk(u32),
    #[error("texture tile {0} does not exist")]
    NoTile(u32),
    #[error("fetching data failed: {0}")]
    Fetch(String),
    #[error("received data is corrupt: {0}")]
    Corrupt(String),
    #[error("rendering was cancelled")]
    Cancelled,
    /// Only while deferring (see [`Deferral`]): the item is not here, and was not fetched.
    #[error("{0} is not here yet")]
    Missing(Item),
}

/// A chunk or a texture tile, by id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Item {
    Chunk(u32),
    Tile(u32),
}

impl std::fmt::Display for Item {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Item::Chunk(id) => write!(f, "chunk {id}"),
            Item::Tile(id) => write!(f, "texture tile {id}"),
        }
    }
}

/// Data that may have to be fetched, and can instead say at once what it lacks, so that
/// the renderer puts the ray that needs it aside and goes on with others
/// ([`crate::render::render_rect_coherent`]): a render node's cache.
pub trait Deferral {
    /// While on, asking for an item that is not here gives [`DataError::Missing`] instead
    /// of fetching it.
    fn defer(&self, on: bool);
    /// Fetches `item` now (waiting for it) unless it is here already. Items evicted before
    /// may be freed meanwhile: a cache bounded in bytes must free what it evicts while a
    /// long batch of paths goes on, not only when the batch ends.
    ///
    /// # Safety
    /// The caller holds no reference it got from this data (no chunk or tile).
    unsafe fn bring(&self, item: Item) -> Result<(), DataError>;
    /// Marks the passing of time for the least-recently-used order.
    fn tick(&self);
}

/// Implementations need not be shared between threads: a render node gives each rendering
/// thread a reader of its own (`Sync` is asked for where threads share one).
pub trait SceneData {
    type ChunkRef<'a>: Deref<Target = Chunk>
    where
        Self: 'a;
    type TileRef<'a>: Deref<Target = Tile>
    where
        Self: 'a;

    /// Whether asking may give [`DataError::Missing`] (data that defers, [`Deferral`]): the
    /// ray queries' bookkeeping for it is compiled only where it can be needed.
    const MAY_DEFER: bool = false;

    fn chunk(&self, id: u32) -> Result<Self::ChunkRef<'_>, DataError>;
    fn tile(&self, id: u32) -> Result<Self::TileRef<'_>, DataError>;

    /// The whole scene's trees as one, where this data holds every chunk and made it.
    #[inline]
    fn flat(&self) -> Option<&FlatTree> {
        None
    }

    /// Whether this data records the chunks rays enter ([`Touched`]): a query walking
    /// [`SceneData::flat`] asks for no chunk it only walks through, so it tells
    /// [`SceneData::entered`] instead.
    const NOTES_ENTRIES: bool = false;

    /// A query walking [`SceneData::flat`] entered chunk `id`.
    #[inline]
    fn entered(&self, _id: u32) {}
}

/// All shape and texture data in this process's memory.
#[derive(Clone, Debug, Default)]
pub struct MemoryData {
    pub chunks: Vec<Chunk>,
    pub tiles: Vec<Tile>,
    /// Every chunk's tree and the top-level tree as one, when made ([`MemoryData::flatten`]).
    pub flat: Option<FlatTree>,
}

/// The top-level tree and every chunk's tree as one ([`Bvh8::flatten`]), for data that holds
/// every chunk: a ray walks it as one tree, with no walk of its own per chunk it enters.
#[derive(Clone, Debug)]
pub struct FlatTree {
    pub form: Bvh8,
    /// The chunk of each of the tree's four-triangle blocks.
    block_chunk: Vec<u32>,
    /// How each chunk's surfaces take rays (from its material), looked up at every hit a
    /// query finds, where the two-level walk looked it up at every chunk it entered.
    kinds: Vec<SurfaceKind>,
    /// Whether every chunk takes every hit (no culled back faces, no alpha test): queries
    /// then need not look at a hit's chunk before they take it.
    pub all_solid: bool,
}

impl FlatTree {
    /// The flat tree `form` of `scene`'s chunks, whose blocks belong to `block_chunk`.
    pub(crate) fn new(form: Bvh8, block_chunk: Vec<u32>, scene: &SceneHeader) -> FlatTree {
        let kinds: Vec<SurfaceKind> = (0..scene.chunks.len() as u32)
            .map(|c| crate::trace::surface_kind(scene, c))
            .collect();
        FlatTree {
            form,
            block_chunk,
            all_solid: kinds.iter().all(|&k| k == SurfaceKind::Solid),
            kinds,
        }
    }

    /// The chunk of block `block` of [`FlatTree::form`].
    #[inline(always)]
    pub fn chunk_of(&self, block: usize) -> u32 {
        self.block_chunk.get(block).copied().unwrap_or(u32::MAX)
    }

    /// How chunk `c`'s surfaces take rays.
    #[inline(always)]
    pub(crate) fn kind(&self, c: u32) -> SurfaceKind {
        self.kinds
            .get(c as usize)
            .copied()
            .unwrap_or(SurfaceKind::Solid)
    }
}

impl MemoryData {
    /// Makes the chunks' trees one with the top-level tree of `scene` ([`FlatTree`]), which
    /// every query then walks instead: each chunk's own walking form is dropped, so the data
    /// takes no more memory than before. Where the trees do not fit one tree (see
    /// [`Bvh8::flatten`]) nothing changes and false is returned. (Preparation for one
    /// process builds the same tree straight into its memory: [`crate::prepare_flat`].)
    ///
    /// Data wrapping this data must pass [`SceneData::flat`] on: a query that found no flat
    /// tree would walk chunks that have no tree left.
    pub fn flatten(&mut self, scene: &SceneHeader) -> bool {
        let parts: Vec<_> = self
            .chunks
            .iter()
            .map(|c| (c.accel(), c.tri_count()))
            .collect();
        let Some(flat) = Bvh8::flatten(scene.tlas.accel(), &parts) else {
            return false;
        };
        self.flat = Some(FlatTree::new(flat.form, flat.block_chunk, scene));
        for c in &mut self.chunks {
            c.drop_walk();
        }
        true
    }

    /// Bytes of all chunks: the scene's total shape data, the base of cache percentages.
    pub fn shape_bytes(&self) -> u64 {
        self.chunks.iter().map(|c| c.byte_len() as u64).sum()
    }

    pub fn texture_bytes(&self) -> u64 {
        self.tiles.iter().map(|t| t.as_bytes().len() as u64).sum()
    }
}

impl SceneData for MemoryData {
    type ChunkRef<'a> = &'a Chunk;
    type TileRef<'a> = &'a Tile;

    #[inline]
    fn chunk(&self, id: u32) -> Result<&Chunk, DataError> {
        self.chunks.get(id as usize).ok_or(DataError::NoChunk(id))
    }

    #[inline]
    fn tile(&self, id: u32) -> Result<&Tile, DataError> {
        self.tiles.get(id as usize).ok_or(DataError::NoTile(id))
    }

    #[inline]
    fn flat(&self) -> Option<&FlatTree> {
        self.flat.as_ref()
    }
}

/// Which chunks and texture tiles one thread's rays have touched since it last asked: the
/// per-subscreen records that let a simulator replay a render's data traffic. One bit per
/// id in this thread's own memory, so noting a visit costs an OR, never a lock, an atomic
/// or an allocation.
#[derive(Debug, Default)]
pub struct Touched {
    chunks: Box<[Cell<u64>]>,
    tiles: Box<[Cell<u64>]>,
}

impl Touched {
    pub fn new(chunks: usize, tiles: usize) -> Touched {
        let words = |n: usize| (0..n.div_ceil(64)).map(|_| Cell::new(0)).collect();
        Touched {
            chunks: words(chunks),
            tiles: words(tiles),
        }
    }

    #[inline(always)]
    fn note(bits: &[Cell<u64>], id: u32) {
        // An id past the end is refused by the data itself; it is not worth noting.
        if let Some(w) = bits.get((id >> 6) as usize) {
            w.set(w.get() | 1 << (id & 63));
        }
    }

    fn drain(bits: &[Cell<u64>]) -> Vec<u32> {
        let mut ids = Vec::new();
        for (i, w) in bits.iter().enumerate() {
            let mut b = w.replace(0);
            while b != 0 {
                ids.push(i as u32 * 64 + b.trailing_zeros());
                b &= b - 1;
            }
        }
        ids
    }

    /// The chunk ids and tile ids touched since the last call (ascending), and starts over.
    pub fn take(&self) -> (Vec<u32>, Vec<u32>) {
        (Self::drain(&self.chunks), Self::drain(&self.tiles))
    }

    /// A view of `data` that notes every chunk and tile asked for here.
    pub fn watching<'a, D: SceneData>(&'a self, data: &'a D) -> Noting<'a, D> {
        Noting {
            data,
            touched: self,
        }
    }

    /// As [`Touched::watching`], for data that could defer used where it never does (its
    /// deferral is never turned on): a render node's cache when rays are not made coherent.
    /// Saying so lets the ray queries be compiled without the bookkeeping for paths put
    /// aside, as they are for data in memory.
    pub fn watching_fetched<'a, D: SceneData>(&'a self, data: &'a D) -> Noting<'a, D, false> {
        Noting {
            data,
            touched: self,
        }
    }
}

/// [`SceneData`] that passes every request on and notes its id in a [`Touched`]; it defers
/// as the data it watches does, unless `DEFERS` says the data's deferral is never on.
pub struct Noting<'a, D, const DEFERS: bool = true> {
    data: &'a D,
    touched: &'a Touched,
}

impl<D: SceneData, const DEFERS: bool> SceneData for Noting<'_, D, DEFERS> {
    type ChunkRef<'b>
        = D::ChunkRef<'b>
    where
        Self: 'b;
    type TileRef<'b>
        = D::TileRef<'b>
    where
        Self: 'b;

    const MAY_DEFER: bool = DEFERS && D::MAY_DEFER;

    #[inline(always)]
    fn chunk(&self, id: u32) -> Result<Self::ChunkRef<'_>, DataError> {
        Touched::note(&self.touched.chunks, id);
        let chunk = self.data.chunk(id);
        debug_assert!(
            DEFERS || !matches!(chunk, Err(DataError::Missing(_))),
            "deferred"
        );
        chunk
    }

    #[inline(always)]
    fn flat(&self) -> Option<&FlatTree> {
        self.data.flat()
    }

    const NOTES_ENTRIES: bool = true;

    #[inline(always)]
    fn entered(&self, id: u32) {
        Touched::note(&self.touched.chunks, id);
    }

    #[inline(always)]
    fn tile(&self, id: u32) -> Result<Self::TileRef<'_>, DataError> {
        Touched::note(&self.touched.tiles, id);
        let tile = self.data.tile(id);
        debug_assert!(
            DEFERS || !matches!(tile, Err(DataError::Missing(_))),
            "deferred"
        );
        tile
    }
}

/// Noting data defers as the data it watches does (an item it lacks was noted when asked).
impl<D: SceneData + Deferral> Deferral for Noting<'_, D> {
    fn defer(&self, on: bool) {
        self.data.defer(on);
    }

    unsafe fn bring(&self, item: Item) -> Result<(), DataError> {
        // SAFETY: the caller's promise is passed on.
        unsafe { self.data.bring(item) }
    }

    fn tick(&self) {
        self.data.tick();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn touched_ids_come_back_once_each_and_then_start_over() {
        let data = MemoryData::default();
        let touched = Touched::new(130, 3);
        let view = touched.watching(&data);
        for id in [129, 0, 64, 0, 129, 7] {
            assert!(
                view.chunk(id).is_err(),
                "no data: the request still goes through"
            );
        }
        assert!(view.tile(2).is_err());
        // Past the end: refused by the data, not noted.
        assert!(view.chunk(5000).is_err());
        assert_eq!(touched.take(), (vec![0, 7, 64, 129], vec![2]));
        assert_eq!(touched.take(), (vec![], vec![]));
    }
}
