//! Where shape and texture data come from while rendering.
//!
//! The renderer reads chunks and texture tiles only through [`SceneData`]. In one process
//! the data is all in memory ([`MemoryData`]); on a render node it is a bounded cache that
//! fetches what is missing from the fork node's shared memory. The renderer cannot tell the
//! two apart, which is why an image is the same bytes either way.

use std::ops::Deref;

use crate::{chunk::Chunk, texture::Tile};

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

    fn chunk(&self, id: u32) -> Result<Self::ChunkRef<'_>, DataError>;
    fn tile(&self, id: u32) -> Result<Self::TileRef<'_>, DataError>;
}

/// All shape and texture data in this process's memory.
#[derive(Clone, Debug, Default)]
pub struct MemoryData {
    pub chunks: Vec<Chunk>,
    pub tiles: Vec<Tile>,
}

impl MemoryData {
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
}
