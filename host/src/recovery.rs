//! A lost fork node's share of the scene, rebuilt from the host's copy.
//!
//! The first fork node prepared the scene and spread its chunks and tiles over every card;
//! when a card's fork node dies, the items it held are gone from the cluster. The host still
//! holds the scene description it sent, and preparing a scene is deterministic (the same
//! description and options give the same bytes), so it prepares the scene again, checks
//! that the header is byte for byte the one the cluster renders with, and sends each lost
//! item to a live card, round-robin over the live fork nodes, with the new address table.
//! Items on live cards stay where they are: nothing they hold is sent again, and a render
//! node's cache stays valid (items are named by id, whoever holds them).
//!
//! Render nodes of the lost card are served by the fork node of the nearest live card
//! ([`fabric::Topology::serving_fork`]) as soon as they hear of the loss; their requests
//! for lost items wait at the fork nodes until those items have arrived.

use fabric::Fabric;
use protocol::{DataId, Message, NodeId, bytes_to_words, decode_value, encode_value};
use renderer::{PrepareOptions, SceneDesc};

/// What the host keeps of the scene it sent, to rebuild a lost card's share from.
pub(crate) struct HostCopy {
    /// The scene description as sent to the first fork node.
    pub encoded: Vec<u8>,
    pub chunk_triangles: u32,
    /// The prepared header as the first fork node sent it.
    pub header: Vec<u8>,
    /// Which fork node holds each chunk and each tile now.
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
}

/// Why a lost card's share could not be rebuilt.
#[derive(Debug, thiserror::Error)]
pub enum RebuildError {
    #[error("no fork node is left alive to hold it")]
    NoForkNodeLeft,
    #[error("the host's copy of the scene does not decode: {0}")]
    Decode(#[from] protocol::DecodeError),
    #[error("preparing the scene again failed: {0}")]
    Prepare(String),
    #[error(
        "the scene prepared again differs from the one the cluster renders (preparation is not deterministic here)"
    )]
    Differs,
}

/// Gives every item `owners` places on `lost` to the fork nodes in `live`, round-robin;
/// returns the ids of the items moved.
pub(crate) fn replace_owner(owners: &mut [NodeId], lost: NodeId, live: &[NodeId]) -> Vec<u32> {
    let mut moved = Vec::new();
    if live.is_empty() {
        return moved;
    }
    for (i, owner) in owners.iter_mut().enumerate() {
        if *owner == lost {
            *owner = live[moved.len() % live.len()];
            moved.push(i as u32);
        }
    }
    moved
}

impl HostCopy {
    /// Rebuilds the share of `lost` (already declared dead) on the live fork nodes; returns
    /// how many items moved.
    pub(crate) async fn rebuild(&mut self, f: &Fabric, lost: NodeId) -> Result<u32, RebuildError> {
        let live: Vec<NodeId> = f
            .topology()
            .fork_nodes()
            .into_iter()
            .filter(|&n| f.is_alive(n))
            .collect();
        if live.is_empty() {
            return Err(RebuildError::NoForkNodeLeft);
        }
        let chunks = replace_owner(&mut self.chunk_owner, lost, &live);
        let tiles = replace_owner(&mut self.tile_owner, lost, &live);
        let desc: SceneDesc = decode_value(&self.encoded)?;
        let opts = PrepareOptions {
            chunk_triangles: (self.chunk_triangles as usize).max(1),
        };
        let (scene, data) = tokio::task::spawn_blocking(move || renderer::prepare(desc, &opts))
            .await
            .map_err(|e| RebuildError::Prepare(e.to_string()))?;
        if encode_value(&scene) != self.header {
            return Err(RebuildError::Differs);
        }
        let header_words = bytes_to_words(&self.header);
        let table = Message::Header {
            len: self.header.len() as u64,
            chunk_owner: self.chunk_owner.clone(),
            tile_owner: self.tile_owner.clone(),
        };
        for &fork in &live {
            let hold = |id: DataId, words: Box<[u32]>| {
                let _ = f.send_direct(fork, &Message::Hold { id }, words, 0, 0);
            };
            // The items first, then the table that names this card as their holder, on one
            // connection: a fork node never reads the table before the items are in.
            for &c in chunks
                .iter()
                .filter(|&&c| self.chunk_owner[c as usize] == fork)
            {
                hold(DataId::Chunk(c), data.chunks[c as usize].words().into());
            }
            for &t in tiles
                .iter()
                .filter(|&&t| self.tile_owner[t as usize] == fork)
            {
                hold(DataId::Tile(t), data.tiles[t as usize].texels[..].into());
            }
            let _ = f.send_direct(fork, &table, header_words.clone(), 0, 0);
            let count = self.chunk_owner.iter().filter(|&&o| o == fork).count()
                + self.tile_owner.iter().filter(|&&o| o == fork).count();
            let done = Message::HoldDone {
                count: count as u32,
            };
            let _ = f.send_direct(fork, &done, Box::new([]), 0, 0);
        }
        Ok((chunks.len() + tiles.len()) as u32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lost_fork_nodes_items_go_round_robin_to_the_live_ones() {
        let mut owners = vec![1, 2, 3, 1, 2, 3, 2];
        let moved = replace_owner(&mut owners, 2, &[1, 3]);
        assert_eq!(moved, [1, 4, 6]);
        assert_eq!(owners, [1, 1, 3, 1, 3, 3, 1]);
        // Nothing else moves, and a second loss moves only what the lost one holds.
        let moved = replace_owner(&mut owners, 3, &[1]);
        assert_eq!(moved, [2, 4, 5]);
        assert_eq!(owners, [1; 7]);
    }

    #[test]
    fn with_no_live_fork_node_nothing_moves() {
        let mut owners = vec![1, 1];
        assert!(replace_owner(&mut owners, 1, &[]).is_empty());
        assert_eq!(owners, [1, 1]);
    }

    #[test]
    fn preparing_a_scene_twice_gives_the_same_bytes() {
        // What rebuilding relies on: the header and every chunk and tile come out the same.
        let opts = PrepareOptions {
            chunk_triangles: 64,
        };
        let (h1, d1) = renderer::prepare(renderer::demo::demo_scene(), &opts);
        let (h2, d2) = renderer::prepare(renderer::demo::demo_scene(), &opts);
        assert_eq!(encode_value(&h1), encode_value(&h2));
        assert_eq!(d1.chunks.len(), d2.chunks.len());
        for (a, b) in d1.chunks.iter().zip(&d2.chunks) {
            assert_eq!(a.words(), b.words());
        }
        for (a, b) in d1.tiles.iter().zip(&d2.tiles) {
            assert_eq!(a.texels, b.texels);
        }
    }
}
