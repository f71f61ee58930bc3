//! The cards' shared-memory segments this render node could map ([`fabric::shm`]): its DMA
//! reads of a card's memory go through the mapping instead of a request and a reply over
//! TCP. A segment is taken only if it opens, maps, has the announced size and carries the
//! announced nonce, which proves the fork node is on this machine (and in this IPC
//! namespace); otherwise the reason is logged and that card stays on TCP. Announcements
//! come in at any time, also while rendering, so the table is read under a lock, once a miss.

use std::{
    collections::HashMap,
    path::Path,
    sync::{Arc, RwLock},
};

use fabric::shm::{self, Segment, ShmError};
use protocol::NodeId;
use renderer::region::Block;

/// A mapped segment, as a block the renderer can walk chunks in place in.
pub struct Mapped(pub Segment);

impl Block for Mapped {
    fn words(&self) -> &[u32] {
        self.0.words()
    }
}

impl std::ops::Deref for Mapped {
    type Target = Segment;

    fn deref(&self) -> &Segment {
        &self.0
    }
}

#[derive(Default)]
pub struct SharedSegments {
    by_card: RwLock<HashMap<NodeId, Known>>,
}

/// A card's mapping, with the name and nonce it was announced with.
#[derive(Clone)]
struct Known {
    name: String,
    nonce: [u32; 4],
    mapped: Arc<Mapped>,
}

impl SharedSegments {
    /// Maps the segment fork node `card` announced; why not, if it cannot be used.
    pub fn add(
        &self,
        card: NodeId,
        name: &str,
        nonce: [u32; 4],
        bytes: u64,
    ) -> Result<(), ShmError> {
        self.add_in(Path::new(shm::SHM_DIR), card, name, nonce, bytes)
    }

    fn add_in(
        &self,
        dir: &Path,
        card: NodeId,
        name: &str,
        nonce: [u32; 4],
        bytes: u64,
    ) -> Result<(), ShmError> {
        // A card's segment can be announced twice (by the fork node that wrote it and by
        // the card's own): mapped once.
        let known = self
            .by_card
            .read()
            .expect("segments lock")
            .get(&card)
            .cloned();
        if known.is_some_and(|k| k.name == name && k.nonce == nonce) {
            return Ok(());
        }
        let segment = Segment::open(dir, name, nonce, bytes)?;
        self.by_card.write().expect("segments lock").insert(
            card,
            Known {
                name: name.to_string(),
                nonce,
                mapped: Arc::new(Mapped(segment)),
            },
        );
        Ok(())
    }

    /// The mapped segment of fork node `card`'s memory, if any.
    pub fn get(&self, card: NodeId) -> Option<Arc<Mapped>> {
        self.by_card
            .read()
            .expect("segments lock")
            .get(&card)
            .map(|k| k.mapped.clone())
    }

    /// How many cards' segments are mapped.
    pub fn count(&self) -> u32 {
        self.by_card.read().expect("segments lock").len() as u32
    }
}

#[cfg(test)]
mod tests {
    use fabric::shm::{Item, Part, Published};
    use protocol::DataId;

    use super::*;

    #[test]
    fn a_segment_with_the_wrong_nonce_or_size_is_refused_and_nothing_is_mapped() {
        let dir = std::env::temp_dir().join(format!("magg-shared-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let words = [5u32; 16];
        let item = Item::whole(DataId::Tile(0), Part::Words, &words);
        let p = Published::create(&dir, 2, &[item]).unwrap();
        let s = SharedSegments::default();
        let mut wrong = p.nonce;
        wrong[0] = !wrong[0];
        let e = s.add_in(&dir, 2, &p.name, wrong, p.bytes).unwrap_err();
        assert!(matches!(e, ShmError::Nonce { .. }), "{e}");
        let e = s
            .add_in(&dir, 2, &p.name, p.nonce, p.bytes - 4)
            .unwrap_err();
        assert!(matches!(e, ShmError::Size { .. }), "{e}");
        assert_eq!(s.count(), 0);
        assert!(s.get(2).is_none(), "refused: this card stays on TCP");
        s.add_in(&dir, 2, &p.name, p.nonce, p.bytes).unwrap();
        assert_eq!(s.count(), 1);
        assert_eq!(s.get(2).unwrap().read(DataId::Tile(0)).unwrap(), &words);
        // Announced again (by the fork node that wrote it, then by the card's own): the
        // mapping made first stays.
        let first = s.get(2).unwrap();
        s.add_in(&dir, 2, &p.name, p.nonce, p.bytes).unwrap();
        assert!(Arc::ptr_eq(&first, &s.get(2).unwrap()), "mapped once");
        drop(p);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
