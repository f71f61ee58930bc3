//! This card's memory as real shared memory ([`fabric::shm`]): once the memory is complete,
//! the items it holds are written into a segment, and every render node of the cluster hears
//! of it (this card's directly, other cards' through their own fork node, which passes the
//! announcement on). Render nodes on this machine then read the card's items from the
//! mapping; the rest keep asking over TCP. The segment is removed when the fork node ends
//! (`run`), or by the next fork node to start on this machine if this one was killed.
//!
//! Each chunk goes in twice: its words, and its walking form, transcoded here once for the
//! card instead of once in every render node that reads it. Render nodes walk the chunk in
//! place, so the scene is in this machine's memory once per card rather than once per
//! render node, and a render node's own memory holds only what came over TCP.

use std::{
    path::Path,
    sync::{Arc, Mutex},
};

use fabric::shm::{self, Item, Part, Published};
use protocol::{DataId, Message, NodeId};
use renderer::chunk::Chunk;

use crate::ForkNode;

/// The segment this fork node published, shared with `run` so that it is removed when the
/// role ends even though tasks may still hold the node.
pub(crate) type SegmentSlot = Arc<Mutex<Option<Published>>>;

impl ForkNode {
    /// Publishes this card's memory (once) and announces it to the card's render nodes and
    /// the other fork nodes. Without a shared-memory directory, or if writing fails, nothing
    /// is announced and every render node stays on TCP.
    pub(crate) fn publish_segment(&self, card: &[NodeId]) {
        let f = &self.fabric;
        // Taken whether or not a segment is written, so that none stays held for nothing.
        let mut kept = {
            let mut m = self.memory.lock().expect("memory lock");
            m.walks_taken = true;
            std::mem::take(&mut m.walks)
        };
        let dir = Path::new(shm::SHM_DIR);
        if !dir.is_dir() {
            tracing::info!(
                "fork node {}: no {} here; render nodes read this card over TCP",
                f.me(),
                shm::SHM_DIR
            );
            return;
        }
        let stale = shm::remove_stale(dir);
        if stale > 0 {
            tracing::info!(
                "fork node {}: removed {stale} segments left by fork nodes that died",
                f.me()
            );
        }
        let items: Vec<(DataId, Arc<[u32]>)> = {
            let m = self.memory.lock().expect("memory lock");
            let mut items: Vec<_> = m.data.iter().map(|(id, w)| (*id, w.clone())).collect();
            items.sort_by_key(|(id, _)| match *id {
                DataId::Chunk(c) => (0, c),
                DataId::Tile(t) => (1, t),
                DataId::Synthetic { bytes } => (2, bytes),
            });
            items
        };
        // Each chunk's walking form as its check on arrival made it (or the preparation, on
        // the first fork node); transcoded here only for a chunk held without one.
        let walks: Vec<(DataId, Vec<u32>)> = items
            .iter()
            .filter(|(id, _)| matches!(id, DataId::Chunk(_)))
            .filter_map(|(id, w)| match kept.remove(id) {
                Some(walk) => Some((*id, walk)),
                None => match Chunk::from_words(w[..].into()) {
                    Ok(chunk) => Some((*id, chunk.accel().to_words())),
                    Err(e) => {
                        // Render nodes refuse it as well, whichever way it reaches them.
                        tracing::warn!("fork node {}: {id:?} is not a valid chunk: {e}", f.me());
                        None
                    }
                },
            })
            .collect();
        let refs: Vec<Item> = items
            .iter()
            .map(|(id, w)| Item {
                id: *id,
                part: Part::Words,
                words: &w[..],
            })
            .chain(walks.iter().map(|(id, w)| Item {
                id: *id,
                part: Part::Walk,
                words: w,
            }))
            .collect();
        let published = match Published::create(dir, f.me(), &refs) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!(
                    "fork node {}: {e}; render nodes read this card over TCP",
                    f.me()
                );
                return;
            }
        };
        tracing::debug!(
            "fork node {}: published {} items, {} bytes, as {}",
            f.me(),
            refs.len(),
            published.bytes,
            published.path().display()
        );
        let announce = Message::SharedSegment {
            card: f.me(),
            name: published.name.clone(),
            nonce: published.nonce,
            bytes: published.bytes,
        };
        *self.segment.lock().expect("segment lock") = Some(published);
        let others = f
            .topology()
            .fork_nodes()
            .into_iter()
            .filter(|&n| n != f.me());
        for to in card.iter().copied().chain(others) {
            let _ = f.send_direct(to, &announce, Box::new([]), 0, 0);
        }
    }

    /// Another fork node's announcement: passed on to this card's render nodes, which may
    /// share that fork node's machine too.
    pub(crate) fn relay_segment(&self, from: NodeId, announce: &Message) {
        let f = &self.fabric;
        if !matches!(announce, Message::SharedSegment { card, .. } if *card == from) {
            return;
        }
        for r in self.card_render_nodes() {
            let _ = f.send_direct(r, announce, Box::new([]), 0, 0);
        }
    }
}
