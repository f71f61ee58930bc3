//! A card's shared memory: the scene header, the address table, and the chunks and texture
//! tiles this card holds, kept as the word blocks they travel as, or read from the segment
//! the first fork node wrote for the card. It fills from the first fork node's placement,
//! and is complete once the header and every announced item are here.

use std::{collections::HashMap, sync::Arc};

use fabric::shm::{Part, Segment};
use protocol::{DataId, NodeId, decode_value};
use renderer::SceneHeader;

use crate::ForkNode;

#[derive(Default)]
pub(crate) struct SharedMemory {
    pub scene: Option<Arc<SceneHeader>>,
    /// The header as it travelled (bincode), to pass on to render nodes unchanged.
    pub header_bytes: Option<Arc<Vec<u8>>>,
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
    pub data: HashMap<DataId, Arc<[u32]>>,
    /// This card's share as the segment the first fork node wrote for it, when it came that
    /// way: items are read from the mapping when asked for (those held later, a lost card's
    /// share rebuilt here, are in `data`).
    pub adopted: Option<Segment>,
    /// Walking forms of the chunks held, made when each was checked on arrival (or kept from
    /// the preparation), for the segment ([`ForkNode::publish_segment`]), which takes them:
    /// a chunk is transcoded once on its card, not once to check it and again to publish it.
    pub walks: HashMap<DataId, Vec<u32>>,
    /// Set once the segment took the walking forms: items held later (a lost card's share,
    /// rebuilt here) keep none, as no segment will take them.
    pub walks_taken: bool,
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

    /// The words of item `id`, if this card holds it: kept, or in the adopted segment.
    pub fn item_words(&self, id: DataId) -> Option<&[u32]> {
        let held = self.data.get(&id).map(|w| &w[..]);
        held.or_else(|| self.adopted.as_ref()?.read(id))
    }

    /// Item `id`, if this card holds it, shared where it is kept and copied from a segment.
    pub fn item(&self, id: DataId) -> Option<Arc<[u32]>> {
        let held = self.data.get(&id).cloned();
        held.or_else(|| Some(Arc::from(self.adopted.as_ref()?.read(id)?)))
    }

    /// How many items of the share came as a segment (0 when they came as `Hold`s).
    pub fn adopted_items(&self) -> u32 {
        self.adopted
            .as_ref()
            .map_or(0, |s| s.ids(Part::Words).count() as u32)
    }

    /// Takes `segment`, holding exactly this card's items (checked by the caller), as its
    /// share: the segment has their walking forms already.
    pub fn adopt(&mut self, segment: Segment) {
        self.adopted = Some(segment);
        let count = self.adopted_items();
        self.walks_taken = true;
        self.received += count;
        self.expected = Some(count);
    }

    /// Keeps an item, and a chunk's walking form when it has one; an item sent twice counts
    /// once.
    pub fn store(&mut self, id: DataId, words: Arc<[u32]>, walk: Option<Vec<u32>>) {
        if let Some(walk) = walk.filter(|_| !self.walks_taken) {
            self.walks.insert(id, walk);
        }
        if self.data.insert(id, words).is_none() {
            self.received += 1;
        }
    }
}

/// Why a scene header cannot go into this card's memory.
#[derive(Debug, thiserror::Error)]
pub(crate) enum HeaderError {
    #[error("undecodable scene header: {0}")]
    Decode(#[from] protocol::DecodeError),
    #[error(transparent)]
    Invalid(#[from] renderer::scene::SceneError),
    #[error("the address table does not match the scene")]
    AddressTable,
}

/// The scene in a header, checked against the address table that came with it.
pub(crate) fn decode_header(
    bytes: &[u8],
    chunk_owner: &[NodeId],
    tile_owner: &[NodeId],
) -> Result<SceneHeader, HeaderError> {
    let scene: SceneHeader = decode_value(bytes)?;
    scene.validate()?;
    if chunk_owner.len() != scene.chunks.len() || tile_owner.len() != scene.tile_count as usize {
        return Err(HeaderError::AddressTable);
    }
    Ok(scene)
}

/// What a received item checked out as.
#[derive(Debug, PartialEq)]
pub(crate) enum Checked {
    Tile,
    /// A chunk, with the walking form its check transcoded.
    Chunk {
        walk: Vec<u32>,
    },
}

/// Whether `words` can be item `id` (render nodes trust what this memory hands them): the
/// words as this memory keeps them, and for a chunk the walking form the check made; `None`
/// if they cannot. A chunk is checked in the words as received and copied once, into what
/// is kept.
pub(crate) fn check_item(id: DataId, words: Box<[u32]>) -> Option<(Arc<[u32]>, Checked)> {
    match id {
        DataId::Chunk(_) => renderer::chunk::Chunk::from_words(words).ok().map(|c| {
            let walk = c.accel().to_words();
            (c.words().into(), Checked::Chunk { walk })
        }),
        DataId::Tile(_) => {
            (words.len() == renderer::texture::TILE_TEXELS).then(|| (words.into(), Checked::Tile))
        }
        DataId::Synthetic { .. } => None,
    }
}

impl ForkNode {
    pub(crate) fn on_header(
        self: &Arc<ForkNode>,
        bytes: Vec<u8>,
        chunk_owner: Vec<NodeId>,
        tile_owner: Vec<NodeId>,
    ) {
        let scene = match decode_header(&bytes, &chunk_owner, &tile_owner) {
            Ok(s) => s,
            Err(e) => {
                tracing::error!("fork node {}: {e}", self.fabric.me());
                return;
            }
        };
        {
            let mut m = self.memory.lock().expect("memory lock");
            m.scene = Some(Arc::new(scene));
            m.header_bytes = Some(Arc::new(bytes));
            m.chunk_owner = chunk_owner;
            m.tile_owner = tile_owner;
        }
        // A header after the first comes when a fork node is lost: one that never answered
        // for its segment will not.
        let f = &self.fabric;
        (self.shares.lock().expect("shares lock")).forget_gone(|n| f.is_alive(n));
        self.maybe_ready();
    }

    pub(crate) fn on_hold(self: &Arc<ForkNode>, id: DataId, words: Box<[u32]>) {
        let (words, walk) = match check_item(id, words) {
            Some((words, Checked::Chunk { walk })) => (words, Some(walk)),
            Some((words, Checked::Tile)) => (words, None),
            None => {
                tracing::error!(
                    "fork node {}: received {id:?} is not valid data; ignored",
                    self.fabric.me()
                );
                return;
            }
        };
        self.store(id, words, walk);
        self.maybe_ready();
    }

    pub(crate) fn store(&self, id: DataId, words: Arc<[u32]>, walk: Option<Vec<u32>>) {
        self.memory
            .lock()
            .expect("memory lock")
            .store(id, words, walk);
    }
}

#[cfg(test)]
mod tests {
    use protocol::encode_value;

    use super::*;

    fn demo() -> SceneHeader {
        let opts = renderer::PrepareOptions {
            chunk_triangles: 64,
        };
        renderer::prepare(renderer::demo::demo_scene(), &opts).0
    }

    #[test]
    fn complete_once_the_header_and_every_announced_item_are_here() {
        let mut m = SharedMemory::default();
        m.store(DataId::Chunk(0), Arc::from(vec![1u32]), None);
        m.expected = Some(2);
        assert!(!m.complete(), "one of two, and no header");
        m.store(DataId::Tile(3), Arc::from(vec![2u32]), None);
        assert!(!m.complete(), "no header");
        m.scene = Some(Arc::new(demo()));
        assert!(m.complete());
    }

    #[test]
    fn an_item_stored_twice_counts_once() {
        let mut m = SharedMemory::default();
        m.store(DataId::Chunk(0), Arc::from(vec![1u32]), None);
        m.store(DataId::Chunk(0), Arc::from(vec![1u32]), Some(vec![7]));
        assert_eq!(m.received, 1);
        assert_eq!(m.walks[&DataId::Chunk(0)], [7]);
        m.walks_taken = true;
        m.walks.clear();
        m.store(DataId::Chunk(1), Arc::from(vec![1u32]), Some(vec![8]));
        assert!(
            m.walks.is_empty(),
            "no walking form kept once the segment took them"
        );
    }

    #[test]
    fn owners_come_from_the_address_table() {
        let m = SharedMemory {
            chunk_owner: vec![1, 2],
            tile_owner: vec![2],
            ..SharedMemory::default()
        };
        assert_eq!(m.owner(DataId::Chunk(1)), Some(2));
        assert_eq!(m.owner(DataId::Tile(0)), Some(2));
        assert_eq!(m.owner(DataId::Chunk(2)), None);
        assert_eq!(m.owner(DataId::Synthetic { bytes: 4 }), None);
        assert_eq!(
            m.all_ids(),
            [DataId::Chunk(0), DataId::Chunk(1), DataId::Tile(0)]
        );
    }

    #[test]
    fn decode_header_checks_the_address_table() {
        let scene = demo();
        let bytes = encode_value(&scene);
        let chunks = vec![1; scene.chunks.len()];
        let tiles = vec![1; scene.tile_count as usize];
        assert!(decode_header(&bytes, &chunks, &tiles).is_ok());
        let err = decode_header(&bytes, &chunks[1..], &tiles).unwrap_err();
        assert!(matches!(err, HeaderError::AddressTable), "{err}");
        let err = decode_header(&[0xff; 8], &[], &[]).unwrap_err();
        assert!(matches!(err, HeaderError::Decode(_)), "{err}");
    }

    #[test]
    fn only_whole_tiles_and_well_formed_chunks_are_held() {
        let check = |id, words: &[u32]| check_item(id, words.into()).map(|(_, c)| c);
        let tile = vec![0u32; renderer::texture::TILE_TEXELS];
        assert_eq!(check(DataId::Tile(0), &tile), Some(Checked::Tile));
        assert_eq!(check(DataId::Tile(0), &tile[1..]), None);
        assert_eq!(check(DataId::Chunk(0), &[1, 2, 3]), None);
        assert_eq!(check(DataId::Synthetic { bytes: 4 }, &[0]), None);
    }

    #[test]
    fn a_chunk_checked_on_arrival_brings_the_walking_form_its_card_publishes() {
        let opts = renderer::PrepareOptions {
            chunk_triangles: 64,
        };
        let (_, data) = renderer::prepare(renderer::demo::demo_scene(), &opts);
        assert!(data.chunks.len() > 1);
        for (i, c) in data.chunks.iter().enumerate() {
            // What the first fork node keeps from its preparation, what another card's
            // check makes, and what a transcoding of the words at publishing made before.
            let kept = c.accel().to_words();
            let (words, checked) = check_item(DataId::Chunk(i as u32), c.words().into()).unwrap();
            assert_eq!(&words[..], c.words(), "chunk {i}");
            let again = renderer::chunk::Chunk::from_words(c.words().into())
                .unwrap()
                .accel()
                .to_words();
            assert_eq!(checked, Checked::Chunk { walk: kept.clone() }, "chunk {i}");
            assert_eq!(kept, again, "chunk {i}");
        }
    }
}
