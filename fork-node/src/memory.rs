//! A card's shared memory: the scene header, the address table, and the chunks and texture
//! tiles this card holds, kept as the word blocks they travel as.

use std::{collections::HashMap, sync::Arc};

use protocol::{DataId, NodeId};
use renderer::Scene;

#[derive(Default)]
pub struct SharedMemory {
    pub scene: Option<Arc<Scene>>,
    /// The header as it travelled (bincode), to pass on to render nodes unchanged.
    pub header_bytes: Option<Arc<Vec<u8>>>,
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
    pub data: HashMap<DataId, Arc<[u32]>>,
    /// Items announced as held, and whether all have arrived.
    pub expected: Option<u32>,
    pub received: u32,
}

impl SharedMemory {
    pub fn owner(&self, id: DataId) -> Option<NodeId> {
        match id {
            DataId::Chunk(c) => self.chunk_owner.get(c as usize).copied(),
            DataId::Tile(t) => self.tile_owner.get(t as usize).copied(),
            DataId::Synthetic { .. } => None,
        }
    }

    pub fn complete(&self) -> bool {
        self.scene.is_some() && self.expected == Some(self.received)
    }

    /// Every item of the scene, chunks then tiles.
    pub fn all_ids(&self) -> Vec<DataId> {
        let chunks = (0..self.chunk_owner.len() as u32).map(DataId::Chunk);
        let tiles = (0..self.tile_owner.len() as u32).map(DataId::Tile);
        chunks.chain(tiles).collect()
    }
}
